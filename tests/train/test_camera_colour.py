"""The training cameras' colour responses (stgs.train.camera_colour): learnt beside the scene in the base stage,
applied to every stage's drawn images, never shipped."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from stgs.train import budget
from stgs.train.camera_colour import CameraColour, as_recorded
from stgs.train.images import tensor_views
from stgs.train.run import stage_views
from stgs.train.trainer import Trainer
from tests.train.conftest import LAYERED

TINT = torch.tensor([0.75, 1.0, 1.25])
"""The colour response given to one training camera of the synthetic scene."""


def test_the_identity_at_the_start_and_zero_mean_over_the_cameras():
    colour = CameraColour(4)
    image = torch.rand(6, 5, 3)
    assert torch.equal(colour(image, 2), image)
    with torch.no_grad():
        colour.log_gain.copy_(torch.randn(4, 3))
        colour.offset.copy_(torch.randn(4, 3) * 0.1)
    gains, offsets = colour.centred()
    assert torch.allclose(gains.mean(0), torch.zeros(3), atol=1e-6)
    assert torch.allclose(offsets.mean(0), torch.zeros(3), atol=1e-6)
    expected = image * torch.exp(gains[1]) + offsets[1]
    assert torch.allclose(colour(image, 1), expected)
    assert torch.equal(as_recorded(colour, image, 1), colour(image, 1)) and as_recorded(None, image, 1) is image
    # Shifting every camera alike changes nothing: the scene keeps the average camera's colour.
    with torch.no_grad():
        colour.log_gain.add_(0.3)
        colour.offset.sub_(0.05)
    assert torch.allclose(colour(image, 1), expected, atol=1e-6)
    summary = colour.summary(["a", "b", "c", "d"])
    assert list(summary) == ["a", "b", "c", "d"] and len(summary["b"]) == 6
    assert summary["b"][:3] == pytest.approx(torch.exp(gains[1]).tolist(), abs=1e-4)


def test_gradients_reach_the_image_and_the_colours_and_stay_finite_at_extremes():
    colour = CameraColour(3)
    with torch.no_grad():
        colour.log_gain[0] = torch.tensor([40.0, -40.0, 0.0])
    image = torch.full((4, 4, 3), 0.5, requires_grad=True)
    out = colour(image, 0)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(image.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in colour.parameters())
    with pytest.raises(ValueError, match="at least one camera"):
        CameraColour(0)


def test_stage_a_learns_the_colour_of_a_tinted_camera(layered_scene, tmp_path):
    """One training camera of the synthetic scene records every channel scaled by TINT: stage A's learnt gains
    for it move that way against the others', and the untinted cameras stay near the identity. Without
    camera colours there are none."""
    cfg = budget("quick", **LAYERED, coarse_iterations=600)
    trainer = Trainer(layered_scene, tmp_path / "m", cfg, progress=False)
    plain_views, _ = stage_views(trainer, [0, 2, 4])
    images = torch.stack([torch.stack([torch.from_numpy(plain_views.source.decoded(f, c))
                                       for c in range(len(plain_views.cameras))]) for f in range(3)])
    tinted = 1
    images[:, tinted] = (images[:, tinted].float() * TINT).round().clamp(0, 255).to(torch.uint8)
    views = tensor_views(plain_views.cameras, plain_views.frames, images)
    trainer.stage_a(views)
    gains = torch.exp(trainer.colour.centred()[0])
    others = torch.cat([gains[:tinted], gains[tinted + 1:]])
    relative = gains[tinted] / others.mean(0)
    # Measured: (0.92, 1.05, 1.15) (the offsets take part of the tint: -0.05 red, +0.02 blue); the untinted
    # cameras' gains 0.91-1.06.
    assert relative[0] < 0.96 and relative[2] > 1.06 and relative[2] - relative[0] > 0.15, relative
    assert abs(relative[1] - 1) < relative[2] - relative[0], relative  # green moves least
    assert (others - 1).abs().max() < 0.15, others
    assert not trainer.colour.log_gain.requires_grad, "frozen after the base stage"
    plain = Trainer(layered_scene, tmp_path / "p", dataclasses.replace(cfg, camera_colour=False), progress=False)
    plain.stage_a(tensor_views(plain_views.cameras, plain_views.frames, images))
    assert plain.colour is None
