"""Synthetic scenes: only the named effects are simulated, and the fitted model is faithful."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from stgs.codec.features import feature_ranges, quantize_features, tile_frames
from stgs.codec.video import VideoTiming, encode_gop
from stgs.data import open_dataset
from stgs.errors import FieldError, StgsError
from stgs.model.gop import GOPShape
from stgs.model.store import load_model, load_static, read_meta
from stgs.synth import SynthConfig, config_from_toml, synthesize
from stgs.synth.config import DEFAULT_EFFECTS
from stgs.synth.fit import feature_roughness, fit_gop
from stgs.synth.scene import ProceduralScene

TINY = SynthConfig(grid_side=16, num_gops=2, gop_size=6, width=48, height=36, num_cameras=2,
                   fit_steps=150, fidelity_stride=3)


def frames_differ(a, b, field, sl):
    return not torch.allclose(getattr(a, field)[sl], getattr(b, field)[sl])


def test_no_effect_means_a_static_scene():
    scene = ProceduralScene(400, ())
    a, b = scene.at(0.0), scene.at(1.3)
    for field in ("means", "quats", "log_scales", "opacities", "base_colors"):
        assert torch.equal(getattr(a, field), getattr(b, field)), field
    cam1, cam2 = torch.tensor([0.0, 1.0, 3.0]), torch.tensor([3.0, 1.0, 0.0])
    assert torch.equal(a.colors(cam1), a.colors(cam2))


@pytest.mark.parametrize("effect,field,obj", [("rigid", "means", "ring"), ("rigid", "quats", "ring"),
                                              ("nonrigid", "means", "blob"),
                                              ("color", "base_colors", "blob"),
                                              ("appear", "opacities", "sparks")])
def test_each_effect_animates_only_its_part(effect, field, obj):
    scene = ProceduralScene(400, (effect,))
    a, b = scene.at(0.2), scene.at(1.1)
    assert frames_differ(a, b, field, scene.slices[obj])
    for other, sl in scene.slices.items():
        if other != obj:
            assert not frames_differ(a, b, field, sl), (effect, other)
    for f in {"means", "quats", "log_scales", "opacities", "base_colors"} - {field}:
        if not (effect == "rigid" and f in ("means", "quats")):
            assert not frames_differ(a, b, f, slice(None)), (effect, f)


def test_view_dependent_colour_only_when_named():
    cam1, cam2 = torch.tensor([0.0, 1.0, 3.0]), torch.tensor([0.0, 1.0, -3.0])
    plain = ProceduralScene(400, ("rigid",)).at(0.0)
    assert torch.equal(plain.colors(cam1), plain.colors(cam2))
    scene = ProceduralScene(400, ("view_dependent",))
    vd = scene.at(0.0)
    ring = scene.slices["ring"]
    assert not torch.allclose(vd.colors(cam1)[ring], vd.colors(cam2)[ring])
    assert torch.equal(vd.colors(cam1)[scene.slices["blob"]], vd.colors(cam2)[scene.slices["blob"]])


def test_unused_slots_are_transparent():
    scene = ProceduralScene(1000, DEFAULT_EFFECTS)
    assert scene.unused.stop - scene.unused.start > 0
    for t in (0.0, 0.7):
        assert (scene.at(t).opacities[scene.unused] == 0).all()


def test_unknown_effect_is_rejected():
    with pytest.raises(ValueError, match="unknown effect"):
        ProceduralScene(100, ("rigid", "explode"))
    with pytest.raises(StgsError, match="unknown effect"):
        dataclasses.replace(TINY, effects=("explode",)).validate()


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "scene"
    report = synthesize(TINY, out, progress=False)
    return out, report


def test_synth_writes_a_faithful_model_dir(tiny_scene):
    out, report = tiny_scene
    meta, _gops = load_model(out)
    assert meta.num_gops == 2 and meta.shape.capacity == 256 and meta.shape.gop_size == 6
    assert meta.extra["generator"] == "stgs.synth"
    assert meta.extra["config"]["effects"] == list(DEFAULT_EFFECTS)
    cams = json.loads((out / "gt" / "cameras.json").read_text())
    assert cams["num_frames"] == 12 and len(cams["cameras"]) == 2
    assert len(list((out / "gt" / "cam00").glob("*.png"))) == 12
    assert report.fidelity_views == 2 * 2 * 2
    assert report.fidelity_psnr > 35.0, report
    for fit in report.fit:
        assert fit["position_rmse"] < 0.01 and fit["opacity_rmse"] < 0.05
    saved = json.loads((out / "synth_report.json").read_text())
    assert saved["fidelity_psnr"] == pytest.approx(report.fidelity_psnr)


def test_synth_refuses_to_clobber_a_foreign_folder(tmp_path):
    target = tmp_path / "precious"
    target.mkdir()
    (target / "thesis.txt").write_text("do not delete")
    with pytest.raises(StgsError, match="refusing to overwrite"):
        synthesize(dataclasses.replace(TINY, num_gops=1, fit_steps=1), target, progress=False)
    assert (target / "thesis.txt").read_text() == "do not delete"
    assert [p.name for p in tmp_path.iterdir()] == ["precious"], "no staging folder left behind"


def test_a_duration_becomes_whole_gops():
    cfg = SynthConfig(gop_size=60, fps=30.0)
    assert cfg.gops_for_seconds(60) == 30  # one minute: 1,800 frames
    assert cfg.gops_for_seconds(5) == 3  # 150 frames: the last GOP runs past the capture's end
    assert SynthConfig(gop_size=30, fps=30.0).gops_for_seconds(2.0) == 2
    assert SynthConfig(gop_size=6, fps=12.0).gops_for_seconds(0.1) == 1
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(FieldError, match="seconds"):
            cfg.gops_for_seconds(bad)


def test_config_from_toml(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('grid_side = 8\neffects = ["rigid"]\n')
    cfg = config_from_toml(path)
    assert cfg.grid_side == 8 and cfg.effects == ("rigid",)
    path.write_text("grid_sid = 8\n")
    with pytest.raises(StgsError, match="unknown key"):
        config_from_toml(path)


def test_static_background_is_a_static_layer_drawn_behind_the_objects(tmp_path):
    cfg = dataclasses.replace(TINY, num_gops=1, effects=(*DEFAULT_EFFECTS, "static_background"), static_grid_side=8,
                              width=64, height=48)
    report = synthesize(cfg, tmp_path / "layered", progress=False)
    meta = read_meta(tmp_path / "layered")
    static = load_static(tmp_path / "layered", meta)
    assert meta.version == 2 and static is not None and static.capacity == 64
    assert report.fidelity_psnr > 30.0
    scene = ProceduralScene(256, cfg.effects, cfg.seed, 64)
    a, b = scene.static, ProceduralScene(256, cfg.effects, cfg.seed, 64).static
    assert torch.equal(a.means, b.means)  # seeded
    # Static in truth: the backdrop is one TruthFrame for every time; and the images need it.
    ds = open_dataset(tmp_path / "layered")
    cam = ds.camera_names[0]
    mask = ds.mask(3, cam)
    image = ds.image(3, cam)
    assert mask is not None and 0.01 < mask.float().mean() < 0.6
    background = image[~mask]
    assert (background.std(0) > 0.05).all(), "the backdrop is textured, not a flat colour"
    without = synthesize(dataclasses.replace(cfg, effects=DEFAULT_EFFECTS), tmp_path / "plain", progress=False)
    assert without.fidelity_views == report.fidelity_views
    assert read_meta(tmp_path / "plain").version == 1
    assert (open_dataset(tmp_path / "plain").image(3, cam)[~mask] - background).abs().mean() > 0.05


def test_static_background_needs_its_capacity():
    with pytest.raises(ValueError, match="static_capacity"):
        ProceduralScene(256, ("static_background",))


def test_feature_roughness_is_grid_and_time_neighbour_differences():
    # (E=2, S²=4, C=1) on a 2x2 grid: frame 0 = [[0, 1], [0, 1]], frame 1 = frame 0 + 2.
    frame = torch.tensor([0.0, 1.0, 0.0, 1.0]).reshape(4, 1)
    features = torch.stack([frame, frame + 2])
    # Right neighbours differ by 1 from the first column, by 0 (itself) from the last: mean 1/2; lower ones by
    # 0: the grid term is (1/2 + 0) / 2. The time term is 2² = 4.
    assert feature_roughness(features, 2).item() == pytest.approx(0.25 + 4.0)
    assert feature_roughness(features[:1], 2).item() == pytest.approx(0.25)
    # Anchors: slot 0 alone differs by 1 from its right neighbour and 0 from its lower one.
    assert feature_roughness(features, 2, torch.tensor([0])).item() == pytest.approx(0.5 + 4.0)


@pytest.mark.parametrize("frames", [1, 5])
def test_whole_grid_roughness_equals_the_gathered_one_over_every_slot(frames):
    """The fit's whole-grid roughness (slices, a hand-written gradient) against the gathered one with every
    slot as an anchor (autograd through indexing): the same value and the same gradient."""
    torch.manual_seed(4)
    side = 7
    features = torch.randn(frames, side * side, 3, dtype=torch.float64) * torch.linspace(0.1, 3, 3,
                                                                                        dtype=torch.float64)
    gathered = features.clone().requires_grad_()
    sliced = features.clone().requires_grad_()
    want = feature_roughness(gathered, side, torch.randperm(side * side))
    got = feature_roughness(sliced, side)
    (2.5 * want).backward()
    (2.5 * got).backward()
    assert got.item() == pytest.approx(want.item(), rel=1e-12)
    torch.testing.assert_close(sliced.grad, gathered.grad, rtol=1e-12, atol=1e-15)
    assert sliced.grad.abs().max() > 0


def test_roughness_needs_a_square_grid():
    with pytest.raises(ValueError, match="not a 3 x 3 grid"):
        feature_roughness(torch.zeros(2, 8, 4), 3)


def test_smooth_features_cost_fewer_bits_at_the_same_fidelity():
    """The roughness term is what makes a fitted GOP's feature video cheap: the same scene fitted with and
    without it, its features encoded by x265 at one QP."""
    scene = ProceduralScene(256, DEFAULT_EFFECTS, seed=3)
    shape = GOPShape(capacity=256, gop_size=6, window=3)
    times = [i / 30 for i in range(6)]
    rough = fit_gop(scene, times, shape, steps=150, seed=1, smoothness=0.0)
    smooth = fit_gop(scene, times, shape, steps=150, seed=1, smoothness=0.3)
    assert smooth.position_rmse < 0.01 and smooth.opacity_rmse < 0.05 and smooth.color_rmse < 0.05, smooth
    timing = VideoTiming.for_gop(shape.num_features, shape.gop_size, 30.0)

    def video_bytes(result):
        feats = result.model.features.detach()
        frames = tile_frames(quantize_features(feats, feature_ranges(feats)), 16).numpy().astype(np.uint16)
        return len(encode_gop(frames, 24, timing, preset="ultrafast"))

    ratio = video_bytes(smooth) / video_bytes(rough)
    assert ratio < 0.8, ratio


@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf")])
def test_feature_smoothness_must_be_a_finite_non_negative_weight(value):
    with pytest.raises(StgsError, match="feature_smoothness"):
        dataclasses.replace(TINY, feature_smoothness=value).validate()
