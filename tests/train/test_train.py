"""`stgs train` / `stgs eval` on a synthetic scene with the quick budget; initial points on Panoptic."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from stgs.cli.model import gop_sizes_covering
from stgs.data import open_dataset, split
from stgs.errors import StgsError
from stgs.metrics import psnr
from stgs.model.store import load_model
from stgs.synth import SynthConfig, synthesize
from stgs.train import DivergedError, budget, train
from stgs.train import losses as loss_module
from tests.conftest import run_stgs as stgs
from tests.train.conftest import PANOPTIC, mask_hits

SCENE = SynthConfig(grid_side=16, num_gops=1, gop_size=6, width=96, height=72, num_cameras=8, fit_steps=30)
TINY = {"gop_size": 6, "grid_side": 16, "max_gops": 1}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("train") / "scene"
    synthesize(SCENE, out, progress=False)
    return out


@pytest.fixture(scope="module")
def trained(scene, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("train") / "model"
    report = train(scene, out, budget("quick", **TINY), progress=False)
    return out, report


def mean_colour_psnr(scene: Path) -> float:
    """PSNR on the held-out camera of predicting every pixel as the mean colour of the training images."""
    ds = open_dataset(scene)
    train_cams, val = split(ds)
    frames = range(SCENE.gop_size)
    mean = torch.stack([ds.image(f, c) for f in frames for c in train_cams]).mean((0, 1, 2))
    values = []
    for f in frames:
        truth = ds.image(f, val[0])
        values.append(psnr(mean.expand_as(truth), truth))
    return sum(values) / len(values)


def test_quick_training_learns_the_scene(scene, trained):
    out, report = trained
    gop = report["gops"][0]
    curve = gop["curve"]
    assert curve[-1]["loss"] < curve[0]["loss"]  # the loss falls
    baseline = mean_colour_psnr(scene)
    assert gop["val_psnr"] > baseline + 6.0, (gop["val_psnr"], baseline)  # measured: 27.1 vs 15.6 dB
    assert 0 < curve[0]["val_ssim"] < gop["val_ssim"] <= 1  # SSIM on the held-out camera improves too
    seconds = [point["seconds"] for point in curve]
    assert seconds == sorted(seconds) and seconds[-1] <= gop["seconds"]
    meta, gops = load_model(out)
    assert meta.shape.capacity == 256 and meta.num_gops == 1 and meta.extra["validation_cameras"] == ["cam07"]
    assert all(torch.isfinite(p).all() for p in gops[0].parameters())
    cams = json.loads((out / "cameras.json").read_text())
    assert [c["name"] for c in cams["cameras"]] == [f"cam{i:02d}" for i in range(8)]


@pytest.mark.parametrize("switch", ["--no-aux", "--no-dynamic-density", "--no-temporal-reg", "--no-relocate",
                                    "--no-camera-colour"])
def test_every_component_switch_runs(scene, tmp_path, switch):
    out = tmp_path / "model"
    result = stgs("train", str(scene), str(out), "--gops", "1", "--gop-size", "6", "--grid-side", "16",
                  "--iterations", "12", "--coarse-iterations", "5", "--quiet", switch)
    assert result.returncode == 0, result.stderr
    config = json.loads((out / "model.json").read_text())["extra"]["config"]
    field, off = {"--no-aux": ("aux", False), "--no-dynamic-density": ("dynamic", False),
                  "--no-temporal-reg": ("temporal_weight", 0.0), "--no-relocate": ("relocate", False),
                  "--no-camera-colour": ("camera_colour", False)}[switch]
    assert config[field] == off
    report = json.loads((out / "train_report.json").read_text())
    assert ("camera_colour" in report) == (switch != "--no-camera-colour")


def test_same_seed_same_model_and_resume_matches(scene, tmp_path, monkeypatch):
    cfg = budget("quick", **TINY, coarse_iterations=10, iterations=30, checkpoint_every=10, threads=2)
    train(scene, tmp_path / "a", cfg, progress=False)
    train(scene, tmp_path / "b", cfg, progress=False)
    a = (tmp_path / "a" / "gop_0000.safetensors").read_bytes()
    assert a == (tmp_path / "b" / "gop_0000.safetensors").read_bytes()
    # interrupt the third run at iteration 25, then resume from its checkpoint at 20
    real = loss_module.opacity_l1
    calls = {"n": 0}

    def interrupt(x):
        calls["n"] += 1
        if calls["n"] == 26:
            raise KeyboardInterrupt
        return real(x)

    monkeypatch.setattr(loss_module, "opacity_l1", interrupt)
    with pytest.raises(KeyboardInterrupt):
        train(scene, tmp_path / "c", cfg, progress=False)
    assert not (tmp_path / "c" / "model.json").exists()
    monkeypatch.setattr(loss_module, "opacity_l1", real)
    train(scene, tmp_path / "c", cfg, progress=False, resume=True)
    assert (tmp_path / "c" / "gop_0000.safetensors").read_bytes() == a
    # the resumed run reports the points the interrupted one triangulated
    report_a, report_c = (json.loads((tmp_path / d / "train_report.json").read_text()) for d in ("a", "c"))
    assert report_c["triangulated_points"] == report_a["triangulated_points"] is not None
    assert report_c["background_points"] == report_a["background_points"]


def test_a_non_finite_loss_stops_with_the_last_checkpoint_kept(scene, tmp_path, monkeypatch):
    real = loss_module.opacity_l1
    calls = {"n": 0}

    def poisoned(x):
        calls["n"] += 1
        return real(x) * (math.nan if calls["n"] >= 15 else 1.0)

    monkeypatch.setattr(loss_module, "opacity_l1", poisoned)
    cfg = budget("quick", **TINY, coarse_iterations=5, iterations=30, checkpoint_every=10)
    with pytest.raises(DivergedError, match=r"loss became nan at iteration 14.*last good checkpoint"):
        train(scene, tmp_path / "m", cfg, progress=False)
    assert (tmp_path / "m" / ".train" / "gop_0000.safetensors").is_file()
    assert not (tmp_path / "m" / "model.json").exists()


def test_eval_uncompressed_and_packaged(scene, trained, tmp_path, monkeypatch):
    from stgs.packager import PackConfig, pack

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty-cache"))  # no LPIPS weights here
    model, _ = trained
    stats = pack(model, tmp_path / "dash", PackConfig(ladder="fixed", qps=(16, 32), av1_qps=(19,), jobs=2),
                 progress=False)
    result = stgs("eval", str(model), str(scene), "--dash", str(tmp_path / "dash"), "--out", str(tmp_path / "ev"),
                  "--quiet")
    assert result.returncode == 0, result.stderr
    doc = json.loads((tmp_path / "ev" / "eval.json").read_text())
    streams = doc["streams"]
    assert set(streams) == {"uncompressed", "qp16", "qp32", "av1q19"}  # every Representation of both sets
    assert len(streams["uncompressed"]["gops"][0]["frames"]) == SCENE.gop_size  # every frame, one held-out camera
    assert streams["uncompressed"]["psnr"] >= streams["qp16"]["psnr"] - 0.5 >= streams["qp32"]["psnr"] - 1.0
    assert streams["av1q19"]["psnr"] >= streams["qp32"]["psnr"] - 1.0
    assert 0 < streams["qp32"]["ssim"] <= 1
    # the packer's quality per rung is eval's against the uncompressed model, at the held-out cameras, on a sample
    # of the frames
    assert stats["quality_views"]["source"] == "held-out"
    assert stats["quality_views"]["cameras"] == doc["validation_cameras"]
    for rep in ("qp16", "qp32", "av1q19"):
        assert abs(stats["representations"][rep]["mean_render_psnr"] - streams[rep]["render_psnr"]) <= 0.1, rep
    assert streams["qp16"]["render_psnr"] > streams["qp32"]["render_psnr"]
    assert "render_psnr" not in streams["uncompressed"]
    # against the capture, a rung's error adds to the model's own held-out error (the training report's)
    held_out = json.loads((model / "train_report.json").read_text())["gops"][0]["val_psnr"]
    truth = {rep: stats["representations"][rep]["mean_truth_psnr"] for rep in ("qp16", "qp32", "av1q19")}
    assert held_out > truth["qp16"] > held_out - 0.5 and truth["qp16"] > truth["qp32"]
    assert stats["ladders"]["hevc"]["measure"] == "truth_psnr"
    assert doc["lpips"]["computed"] is False and "lpips" not in streams["qp32"]
    assert str(tmp_path / "empty-cache") in doc["lpips"]["reason"] and "LPIPS not computed" in result.stdout
    assert (tmp_path / "ev" / "eval_grid.png").stat().st_size > 1000


def test_eval_adds_lpips_where_its_weights_are_local(scene, trained, tmp_path, monkeypatch):
    from stgs.evaluate import evaluate
    from tests.test_lpips import place_random_backbone

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    place_random_backbone(tmp_path / "torch")
    doc = evaluate(trained[0], scene, tmp_path / "ev", stride=2, progress=False)
    assert doc["lpips"] == {"net": "alex", "computed": True, "version": "0.1",
                            "backbone": str(tmp_path / "torch" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth")}
    stream = doc["streams"]["uncompressed"]
    rows = stream["gops"][0]["frames"]
    assert len(rows) == 3 and all(0 < r["lpips"] < 2 for r in rows)
    assert stream["lpips"] == pytest.approx(sum(r["lpips"] for r in rows) / 3)
    off = evaluate(trained[0], scene, tmp_path / "ev", stride=2, progress=False, lpips_net=None)
    assert off["lpips"] is None and "lpips" not in off["streams"]["uncompressed"]


def test_bench_train_tables_and_plot(trained, tmp_path):
    model, report = trained
    result = stgs("bench", "train", "--runs", str(model), "--plot", str(tmp_path / "curves.png"))
    assert result.returncode == 0, result.stderr
    label = "quick: all components, 256 Gaussians"  # TINY's grid_side 16 is not the quick budget's 24
    rows = [line for line in result.stdout.splitlines() if line.startswith(f"| {label} | 0 |")]
    curve = report["gops"][0]["curve"]
    assert len(rows) == len(curve) + 1  # one row per curve point, then the GOP's final numbers
    assert rows[-1].split("|")[6].strip() == f"{report['gops'][0]['val_psnr']:.2f}"
    assert (tmp_path / "curves.png").stat().st_size > 1000
    for args, message in [((), "needs --runs"), (("--runs", str(tmp_path)), "no train_report.json")]:
        bad = stgs("bench", "train", *args)
        assert bad.returncode == 2 and message in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_bad_training_input_is_one_line(scene, tmp_path):
    for args, message in [(("--holdout", "cam09"), "no camera(s) ['cam09']"),
                          (("--gop-size", "50"), "do not fill one GOP of 50"),
                          (("--scale", "2"), "scale must be in (0, 1]")]:
        result = stgs("train", str(scene), str(tmp_path / "o"), "--quiet", *args)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1 and message in lines[0], result.stderr
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")
    result = stgs("train", str(scene), str(tmp_path / "full"), "--gop-size", "6", "--quiet")
    assert result.returncode == 2 and "not a model dir" in result.stderr


def test_frames_after_the_last_whole_gop_are_reported(scene, trained, tmp_path):
    assert budget("quick", gop_size=4).untrained_tail(6) == (4, 5)
    assert budget("quick", gop_size=2, start_frame=1).untrained_tail(6) == (5, 5)
    assert budget("quick", gop_size=6).untrained_tail(6) is None  # the GOPs cover the span
    assert budget("quick", gop_size=2, max_gops=1).untrained_tail(5) is None  # fewer GOPs asked for
    assert budget("quick", gop_size=50).untrained_tail(6) is None  # not one GOP: the trainer's own error
    assert trained[1]["untrained_tail"] is None and trained[1]["frames"] == SCENE.gop_size
    assert gop_sizes_covering(150, 60) == [50, 75] and gop_sizes_covering(97, 60) == [97]
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")  # the run stops at the output check, after the note
    result = stgs("train", str(scene), str(tmp_path / "full"), "--gop-size", "4", "--quiet")
    note, error = result.stderr.strip().splitlines()
    assert note == ("stgs: note: frames 4-5 do not fill a GOP of 4 and are not trained; --gop-size 3 or "
                    "--gop-size 6 would cover all 6")
    assert result.returncode == 2 and "not a model dir" in error


def _foreground_shares(ds, cams, frame: int, pts: torch.Tensor) -> list[float]:
    """Per camera, the share of points that land inside its foreground mask at `frame`."""
    return [float(share) for share in mask_hits(ds, cams, [frame], pts)[1].mean(1)]


def test_triangulated_points_land_in_the_foreground(panoptic_frame0):
    from stgs.train.triangulate import triangulate

    ds, cams = panoptic_frame0
    pts, colors = triangulate(cams, [ds.image(0, c.name) for c in cams], [ds.mask(0, c.name) for c in cams])
    assert len(pts) >= 100 and colors.shape == pts.shape
    fractions = _foreground_shares(ds, cams, 0, pts)
    assert np.median(fractions) > 0.7 and sum(f > 0.5 for f in fractions) >= 0.75 * len(cams), fractions


def test_initial_points_seed_the_people_at_every_triangulated_time(panoptic_frame0):
    from stgs.train.seeding import initial_points

    ds, cams = panoptic_frame0
    names = [c.name for c in cams]
    first = initial_points(ds, names, [0], 4096, torch.Generator().manual_seed(0))
    both = initial_points(ds, names, [0, 48], 4096, torch.Generator().manual_seed(0))
    assert both.triangulated > first.triangulated
    seeded = both.points[:both.triangulated]
    late = seeded[first.triangulated:]  # triangulated at frame 48
    assert np.median(_foreground_shares(ds, cams, 48, late)) > 0.7
    # The players moved: frame 0's points miss where they stand at frame 48, frame 48's points do not.
    assert np.median(_foreground_shares(ds, cams, 48, first.points[:first.triangulated])) < 0.5


def test_eval_splits_psnr_by_the_foreground_masks(panoptic_frame0, tmp_path):
    from stgs.camera import rig_focus
    from stgs.evaluate import evaluate
    from stgs.model.gop import GOPModel, GOPShape
    from stgs.model.store import save_model

    ds, cams = panoptic_frame0
    focus, _ = rig_focus(cams)
    gen = torch.Generator().manual_seed(3)
    model = GOPModel(GOPShape(256, gop_size=60))
    with torch.no_grad():  # a cloud of visible blobs around the action
        model.xyz.copy_(focus.float() + torch.randn(256, 3, generator=gen) * 0.6)
        model.log_scale.fill_(-2.5)
        model.opacity_logit.fill_(0.0)
        model.color.copy_(torch.rand(256, 3, generator=gen))
    save_model(tmp_path / "m", [model], ds.fps, {"validation_cameras": ["1", "14"], "start_frame": 0})
    doc = evaluate(tmp_path / "m", PANOPTIC, tmp_path / "m", stride=30, progress=False)
    rows = doc["streams"]["uncompressed"]["gops"][0]["frames"]
    assert len(rows) == 4  # frames 0 and 30, cameras 1 and 14
    for row in rows:
        share = float(ds.mask(row["frame"], row["camera"]).float().mean())
        assert 0.01 < share < 0.5
        # The two regions' squared errors add up to the whole image's.
        mse = {k: 10 ** (-row[k] / 10) for k in ("psnr", "psnr_foreground", "psnr_background")}
        assert mse["psnr"] == pytest.approx(share * mse["psnr_foreground"] + (1 - share) * mse["psnr_background"],
                                            rel=1e-6)
    stream = doc["streams"]["uncompressed"]
    assert stream["psnr_foreground"] == pytest.approx(sum(r["psnr_foreground"] for r in rows) / 4)


def test_region_psnr_scales_the_mask_to_the_render():
    from stgs.evaluate import region_psnr

    truth = torch.zeros(2, 2, 3)
    image = torch.tensor([[[0.1] * 3, [0.2] * 3], [[0.3] * 3, [0.4] * 3]])
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[:2] = True  # the top half at twice the render's size
    top = torch.tensor([[True, True], [False, False]])
    assert region_psnr(image, truth, mask) == {"psnr_foreground": pytest.approx(psnr(image, truth, mask=top)),
                                               "psnr_background": pytest.approx(psnr(image, truth, mask=~top))}
    assert region_psnr(image, truth, None) == {}
    assert region_psnr(image, truth, torch.zeros(2, 2, dtype=torch.bool))["psnr_foreground"] is None


def test_init_frames_spread_over_the_span():
    from stgs.picks import spread

    assert spread(list(range(60)), 6) == [0, 12, 24, 35, 47, 59]
    assert spread(list(range(10, 70)), 1) == [10]
    assert spread([3, 4], 6) == [3, 4]
    with pytest.raises(StgsError, match="init_frames"):
        budget("quick", init_frames=0)


def test_background_shell_points_cover_the_walls_and_floor_in_the_image_colours(panoptic_frame0):
    from stgs.train.triangulate import background_shell_points, ground_height, in_view, rig_sphere, triangulate

    ds, cams = panoptic_frame0
    images = [ds.image(0, c.name) for c in cams]
    centre, radius = rig_sphere(cams)
    assert 2.5 < radius < 3.0  # the dome's cameras sit on a sphere of about 2.75 units
    tri, _ = triangulate(cams, images, [ds.mask(0, c.name) for c in cams])
    down, floor = ground_height(cams, tri)
    pts, colors = background_shell_points(cams, images, 500, torch.Generator().manual_seed(0), (down, floor))
    assert pts.shape == colors.shape == (500, 3)
    p = pts.double()
    on_wall = ((p - centre).norm(dim=1) / radius - 1.04).abs() <= 0.04 + 1e-5
    on_floor = ((p @ down) - floor).abs() < 1e-4
    assert (on_wall | on_floor).all() and on_floor.sum() > 50 and on_wall.sum() > 50
    assert (p @ down <= floor + 1e-4).all()  # nothing below the floor
    cam_centres = torch.stack([c.center for c in cams])
    assert torch.cdist(p, cam_centres).min() > 0.3 * radius - 1e-5  # none beside a camera
    seen_by = sum(in_view(cam, pts.double().numpy())[1].astype(int) for cam in cams)
    assert (seen_by >= 1).all()
    # Coloured from the pictures: the dome's grey walls and floor, not random colours.
    wall = torch.stack([img.reshape(-1, 3).median(0).values for img in images]).median(0).values
    assert (colors.median(0).values - wall).abs().max() < 0.15, (colors.median(0).values, wall)
    assert colors.std(0).max() < 0.25


def _cameras_at(eyes, target) -> list:
    from stgs.camera import Camera, intrinsics, look_at

    return [Camera(str(i), intrinsics(64, 48, 60.0), look_at(tuple(e), target), 64, 48) for i, e in enumerate(eyes)]


def test_rig_sphere_fits_a_dome_and_falls_back_for_a_ring():
    from stgs.camera import rig_focus, surrounds
    from stgs.train.triangulate import rig_sphere

    gen = torch.Generator().manual_seed(1)
    centre = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    d = torch.randn(12, 3, generator=gen, dtype=torch.float64)
    d[:, 1] = -d[:, 1].abs()  # the upper half, like a dome
    eyes = centre + 3.0 * d / d.norm(dim=1, keepdim=True)
    dome = _cameras_at(eyes.tolist(), (0.5, -0.5, 2.0))
    got_centre, got_radius = rig_sphere(dome)
    assert torch.allclose(got_centre, centre, atol=1e-9) and abs(got_radius - 3.0) < 1e-9
    assert surrounds(dome)
    angles = torch.linspace(0, 2 * math.pi, 9)[:-1]
    ring = _cameras_at([(2 * math.cos(a), 0.5, 2 * math.sin(a)) for a in angles], (0.0, 0.0, 0.0))
    focus, rig = rig_focus(ring)
    ring_centre, ring_radius = rig_sphere(ring)  # a flat ring fits no one sphere
    assert torch.equal(ring_centre, focus) and ring_radius == rig
    assert surrounds(ring)
    forward = _cameras_at([(x, 0.0, -4.0) for x in (-1.0, -0.5, 0.0, 0.5, 1.0)], (0.0, 0.0, 0.0))
    assert not surrounds(forward)  # side by side, looking the same way: no walls around them


def test_times_with_too_few_triangulated_points_fall_back_to_random_points(scene):
    from stgs.train.seeding import initial_points
    from stgs.train.triangulate import MIN_TRIANGULATED, triangulate

    ds = open_dataset(scene)
    names, _ = split(ds)
    frames = list(range(SCENE.gop_size))
    per_frame = []
    for f in frames:
        cams = [c for c in ds.cameras(f) if c.name in names]
        per_frame.append(len(triangulate(cams, [ds.image(f, c.name) for c in cams], [None] * len(cams))[0]))
    # Each time of the tiny synthetic scene yields a few points, together more than the minimum (measured:
    # 6 to 17 each, 69 in all): pooled, they drew every seeded copy around a few blobs (held out 21.6 dB
    # against 27.1 from random points).
    assert all(0 < n < MIN_TRIANGULATED for n in per_frame) and sum(per_frame) >= MIN_TRIANGULATED
    init = initial_points(ds, names, frames, 256, torch.Generator().manual_seed(0))
    assert init.triangulated == 0 and not init.anchored.any() and torch.isfinite(init.points).all()


def test_background_share_is_validated_and_splits_the_capacity(scene):
    from stgs.model.gop import GOPModel, GOPShape
    from stgs.train.seeding import init_canonical, initial_points

    with pytest.raises(StgsError, match="background_share"):
        budget("quick", background_share=1.0)
    ds = open_dataset(scene)
    names, _ = split(ds)
    init = initial_points(ds, names, [0], 256, torch.Generator().manual_seed(0), background_share=0.25)
    assert init.points.shape == init.colors.shape == (256, 3) and torch.isfinite(init.points).all()
    assert init.background == 64  # a quarter of the capacity; the rest inside the rig as before
    assert init.anchored[:64].all()
    assert int(init.anchored.sum()) == 64 + min(init.triangulated, 192)
    model = GOPModel(GOPShape(256))
    init_canonical(model, init)
    opacity = torch.sigmoid(model.opacity_logit.detach())
    assert torch.allclose(opacity[init.anchored], torch.tensor(0.1)) and torch.allclose(
        opacity[~init.anchored], torch.tensor(0.02))  # filler starts faint


def test_training_keeps_opacity_in_the_streams_range_and_parks_dead_slots(scene, trained, tmp_path):
    from stgs.codec.attributes import OPACITY_LOGIT_RANGE, SPECS, dequantize, encode_attributes
    from stgs.model.gop import GOPModel
    from stgs.train.ops import Optimizer, prune
    from stgs.train.trainer import Trainer

    lo, hi = OPACITY_LOGIT_RANGE
    trainer = Trainer(scene, tmp_path / "m", budget("quick", **TINY), progress=False)
    model = GOPModel(trainer.shape)
    opt = Optimizer(model, trainer.cfg, trainer.extent, None)
    with torch.no_grad():
        model.opacity_logit.fill_(lo + 0.5)
        model.opacity_logit[:3] = hi - 0.5
    for it in range(20):  # a loss that drives every opacity towards 0 and a few towards 1
        trainer.step(opt, model.opacity_logit.sum() * 100 - model.opacity_logit[:3].sum() * 200, "test", it, model)
    assert model.opacity_logit.min().item() == lo and model.opacity_logit.max().item() == hi

    accum = torch.stack([torch.full((256,), 0.5), torch.ones(256)])
    accum[0, :10] = 0.001  # ten slots stayed dead over the GOP
    with torch.no_grad():
        model.opacity_logit.fill_(1.0)
        model.log_scale.copy_(torch.linspace(-6, -2, 256 * 3).reshape(256, 3))
    assert prune(model, accum, trainer.cfg.dead_opacity) == 10
    assert (model.opacity_logit[:10] == lo).all() and (model.opacity_logit[10:] == 1.0).all()
    live_min = torch.linspace(-6, -2, 256 * 3).reshape(256, 3)[10:].amin(0)
    assert torch.equal(model.log_scale[:10], live_min.expand(10, 3))

    # The trained model packs its opacities to within half a quantisation step: the clip changes nothing.
    trained_model = load_model(trained[0])[1][0]
    logits = trained_model.opacity_logit.detach()
    assert lo <= logits.min() and logits.max() <= hi
    spec = next(s for s in SPECS if s.name == "opacity")
    codes, rng = encode_attributes(trained_model, 16)["opacity"]
    step = (hi - lo) / (spec.levels - 1)
    assert (dequantize(spec, codes, rng).reshape(-1) - logits).abs().max() <= step / 2 + 1e-6
