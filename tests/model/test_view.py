"""The frame path's guard band: Gaussians far outside the image are not drawn (stgs.model.renderer)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from stgs.camera import Camera, intrinsics, look_at
from stgs.model.gop import Gaussians, GOPModel, GOPShape
from stgs.model.renderer import GUARD_BAND, NEAR_CLIP, FrameRenderer, in_guard_band, splat
from stgs.native.library import available
from stgs.render import rasterize

W, H = 64, 48
CAM = Camera("c", intrinsics(W, H, 60.0), look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0)), W, H)


def point_at_pixel(u: float, v: float, depth: float) -> torch.Tensor:
    """The world point that projects to pixel (u, v) at camera depth `depth`."""
    K, view = CAM.K, CAM.viewmat
    cam = torch.tensor([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], dtype=torch.float64)
    return view[:3, :3].T @ (cam - view[:3, 3])


def test_guard_band_edges_in_both_axes():
    half_w, half_h = W / 2, H / 2
    inside_x = point_at_pixel(W / 2 + (GUARD_BAND - 0.01) * half_w, H / 2, 2.0)
    outside_x = point_at_pixel(W / 2 + (GUARD_BAND + 0.01) * half_w, H / 2, 2.0)
    inside_y = point_at_pixel(W / 2, H / 2 - (GUARD_BAND - 0.01) * half_h, 5.0)
    outside_y = point_at_pixel(W / 2, H / 2 - (GUARD_BAND + 0.01) * half_h, 5.0)
    means = torch.stack([inside_x, outside_x, inside_y, outside_y, point_at_pixel(W / 2, H / 2, 1.0)])
    assert in_guard_band(means, CAM).tolist() == [True, False, True, False, True]
    assert in_guard_band(means.float(), CAM).tolist() == [True, False, True, False, True]


def test_near_clip():
    means = torch.stack([point_at_pixel(W / 2, H / 2, NEAR_CLIP * 0.9), point_at_pixel(W / 2, H / 2, NEAR_CLIP * 1.1),
                         point_at_pixel(W / 2, H / 2, -1.0)])
    assert in_guard_band(means, CAM).tolist() == [False, True, False]


def test_a_gaussian_at_the_lens_does_not_black_out_the_frame():
    """A dome's other cameras are part of the scene; rendered from a held-out camera, the housing it sits in
    would fill the image."""
    housing = point_at_pixel(W / 2, H / 2, 0.05)
    far = point_at_pixel(W / 2, H / 2, 3.0)
    g = Gaussians(torch.stack([housing, far]).float(), torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(2, 4),
                  torch.tensor([[0.05] * 3, [0.5] * 3]), torch.ones(2),
                  torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    raw = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, CAM.viewmat.float(), CAM.K.float(), W, H)
    assert raw.max() < 0.05  # black: the housing hides everything
    assert splat(g, CAM)[H // 2, W // 2].min() > 0.9  # the frame path sees past it


def grazing_gaussian(dtype=torch.float32) -> Gaussians:
    """One large opaque Gaussian close to the camera, seen at a grazing angle: its mean projects 40 image
    widths to the right of the image."""
    mean = point_at_pixel(W / 2 + 40 * W, H / 2, 0.05)
    return Gaussians(mean[None].to(dtype), torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype),
                     torch.full((1, 3), 0.3, dtype=dtype), torch.ones(1, dtype=dtype),
                     torch.tensor([[1.0, 0.5, 0.25]], dtype=dtype))


def test_a_grazing_gaussian_veils_the_raw_splat_but_not_the_frame_path():
    g = grazing_gaussian()
    raw = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, CAM.viewmat.float(), CAM.K.float(), W, H)
    covered = (raw.sum(-1) > 0.1).float().mean()
    assert covered > 0.5  # the EWA footprint of a mean far outside the image reaches across it
    assert splat(g, CAM).abs().max() == 0  # the frame path leaves it out


def test_splat_gradients_reach_kept_gaussians_only():
    near = point_at_pixel(W / 2, H / 2, 2.0)
    g = grazing_gaussian(torch.float64)
    means = torch.cat([g.means, near[None]]).requires_grad_(True)
    opacities = torch.tensor([1.0, 0.8], dtype=torch.float64, requires_grad=True)
    colors = torch.tensor([[1.0, 0.5, 0.25], [0.2, 0.9, 0.4]], dtype=torch.float64, requires_grad=True)
    both = Gaussians(means, g.quats.expand(2, 4), torch.tensor([[0.3] * 3, [0.1] * 3], dtype=torch.float64),
                     opacities, colors)
    image = splat(both, CAM)
    image.sum().backward()
    assert torch.isfinite(means.grad).all() and torch.isfinite(opacities.grad).all()
    assert opacities.grad[0] == 0 and colors.grad[0].abs().max() == 0
    assert opacities.grad[1] != 0 and colors.grad[1].abs().min() > 0


@pytest.mark.skipif(not available(), reason="needs the native build")
@pytest.mark.parametrize("precision", ["fp32", "bf16", "int16"])
def test_the_native_deformation_applies_the_same_guard_band(precision):
    from stgs.model.native_deform import runnable_precisions

    if precision not in runnable_precisions():
        pytest.skip(f"the {precision} deformation cannot run on this CPU")
    half_w, half_h = W / 2, H / 2
    points = [point_at_pixel(W / 2 + (GUARD_BAND - 0.01) * half_w, H / 2, 2.0),
              point_at_pixel(W / 2 + (GUARD_BAND + 0.01) * half_w, H / 2, 2.0),
              point_at_pixel(W / 2, H / 2 - (GUARD_BAND - 0.01) * half_h, 5.0),
              point_at_pixel(W / 2, H / 2 - (GUARD_BAND + 0.01) * half_h, 5.0),
              point_at_pixel(W / 2, H / 2, NEAR_CLIP * 0.9), point_at_pixel(W / 2, H / 2, NEAR_CLIP * 1.1)]
    model = GOPModel(GOPShape(capacity=len(points), gop_size=4))
    with torch.no_grad():
        for p in model.field.parameters():
            p.zero_()  # deformed = canonical
        model.xyz.copy_(torch.stack(points).float())
        model.log_scale.fill_(-1.0)  # large enough to reach the image from anywhere here
        model.opacity_logit.fill_(4.0)
    renderer = FrameRenderer(model, native=True, precision=precision)
    drawn = renderer.gaussians(1, CAM).opacities > 0
    assert renderer.guarded and drawn.tolist() == in_guard_band(model.xyz, CAM).tolist() == [
        True, False, True, False, False, True]


@pytest.mark.skipif(not available(), reason="needs the native build")
def test_a_kept_backdrop_draws_and_differentiates_as_the_splat_of_both_layers():
    """splat_over: the static layer kept per camera (static_backdrops) against its Gaussians splatted with the
    moving ones; the guard band applies to the moving layer in both (a grazing Gaussian is not drawn)."""
    from stgs.model.renderer import splat_over, static_backdrops, static_view
    from tests.model.test_gop import random_model
    from tests.model.test_layers import random_static

    static = random_static(400, seed=3)
    model = random_model(n=64, gop_size=4, seed=4)
    (kept,) = static_backdrops(static, [CAM])
    plain = static_view(static, CAM)
    weights = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
    results = []
    for backdrop in (kept, plain):
        model.zero_grad(set_to_none=True)
        fields = [f.name for f in dataclasses.fields(Gaussians)]
        grazing = Gaussians(*(getattr(grazing_gaussian(), f).clone().requires_grad_() for f in fields))
        d = model.deform(1, CAM.center.float())
        g = Gaussians(*(torch.cat([getattr(d, f), getattr(grazing, f)]) for f in fields))
        image = splat_over(backdrop, g, CAM)
        (image * weights).sum().backward()
        results.append((image.detach(), model.color.grad.clone(), model.xyz.grad.clone(), grazing.colors.grad))
    (image, color, xyz, veil), (want_image, want_color, want_xyz, want_veil) = results
    torch.testing.assert_close(image, want_image, atol=1e-5, rtol=0)
    torch.testing.assert_close(color, want_color, atol=1e-4, rtol=1e-3)
    torch.testing.assert_close(xyz, want_xyz, atol=1e-3, rtol=1e-2)
    assert color.abs().sum() > 0 and veil.abs().max() == 0 and want_veil.abs().max() == 0
