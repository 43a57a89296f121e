"""`stgs prepare` on real footage files: a synthetic rig's views as one MP4 per camera, started at different
frames, with a shared click track (PyAV writes and reads them, pycolmap calibrates, OpenCV undistorts)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from stgs.cli import main
from stgs.data import open_dataset
from stgs.prepare import output
from stgs.prepare.calibrate import calibration_frames, rig_errors
from stgs.prepare.sync import audio_lag, parse_offsets
from stgs.synth import SynthConfig
from tests.prepare.footage import (
    rig_cameras,
    synthetic_rig,
    textured_backdrop,
    write_footage,
    write_rig_footage,
)

LATE = {"cam01": 2, "cam03": 1, "cam05": 3}
"""Frames some cameras started after the others."""
CAMERAS = 10


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    root = tmp_path_factory.mktemp("rig")
    backdrop = textured_backdrop(root / "backdrop.ply")
    cfg = SynthConfig(grid_side=16, num_gops=1, gop_size=8, width=480, height=360,
                      effects=("rigid", "static_background"), static_grid_side=174, static_from=str(backdrop))
    truth = synthetic_rig(root / "truth", cfg, rig_cameras(CAMERAS, 120.0, cfg.width, cfg.height))
    videos = write_rig_footage(truth, root / "videos", LATE)
    return root, truth, videos


@pytest.fixture(scope="module")
def prepared(rig):
    root = rig[0]
    out = root / "capture"
    assert main(["prepare", str(root / "videos"), str(out), "--calib-frames", "2",
                 "--quiet"]) == 0
    return out


def test_audio_offsets_are_found_exactly_and_the_common_span_trimmed(rig, prepared):
    _, truth, _ = rig
    report = json.loads((prepared / "prepare_report.json").read_text())
    offsets = {o["camera"]: o for o in report["sync"]["offsets"]}
    assert {k: v["frames"] for k, v in offsets.items()} == {c: LATE.get(c, 0) for c in truth.camera_names}
    assert all(o["source"] == "audio" and o["confidence"] >= 2 for k, o in offsets.items() if k != "cam00")
    span = report["span"]
    assert span["frames"] == truth.num_frames - max(LATE.values())
    # Every camera's first kept frame shows the scene's frame 3 (the latest start).
    assert {k: v + LATE.get(k, 0) for k, v in span["first_frame"].items()} == {c: 3 for c in truth.camera_names}


def test_the_prepared_capture_reads_back_calibrated_and_upright(rig, prepared):
    _, truth, _ = rig
    ds = open_dataset(prepared)
    assert ds.name.startswith("colmap-frames") and ds.camera_names == truth.camera_names
    assert ds.num_frames == truth.num_frames - max(LATE.values())
    report = json.loads((prepared / "prepare_report.json").read_text())
    cal = report["calibration"]
    assert cal["registered"] == cal["total"] == CAMERAS and cal["points"] > 100
    assert set(cal["tracks"]) == set(truth.camera_names) and min(cal["tracks"].values()) > 20
    # +Y up and the rig's radius as stated.
    cams = ds.cameras(0)
    centres = torch.stack([c.center for c in cams])
    assert float((centres - centres.mean(0)).norm(dim=1).mean()) == pytest.approx(3.2, rel=1e-9)
    up = -torch.stack([c.viewmat[1, :3] for c in cams]).mean(0)
    assert float(up[1] / up.norm()) == pytest.approx(1.0, abs=1e-9)
    # Camera error after a similarity fit to the truth, lenses fitted: within 0.2° and 0.5 % of the rig's radius.
    rotations, centres_pct = _camera_errors(cams, truth)
    assert np.median(rotations) < 0.2 and np.median(centres_pct) < 0.5
    assert max(rotations) < 0.5 and max(centres_pct) < 1.0


def _camera_errors(cams, truth) -> tuple[list[float], list[float]]:
    errors = rig_errors({c.name: c.viewmat.numpy() for c in cams},
                        {c.name: c.viewmat.double().numpy() for c in truth.cameras(0)})
    return [e[0] for e in errors.values()], [e[1] for e in errors.values()]


def _lens_json(camera) -> dict:
    K = camera.K.double()
    return {"model": "PINHOLE", "width": camera.width, "height": camera.height, "fx": float(K[0, 0]),
            "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def test_known_lenses_are_kept_and_only_the_poses_solved(rig, tmp_path):
    root, truth, _ = rig
    lens = truth.cameras(0)[0]
    # The lens as calibrated at twice the footage's resolution: it is scaled to the frames.
    doubled = {**_lens_json(lens), "width": 2 * lens.width, "height": 2 * lens.height}
    doubled.update({k: 2 * doubled[k] for k in ("fx", "fy", "cx", "cy")})
    (tmp_path / "lens.json").write_text(json.dumps({"lens": doubled}))
    out = tmp_path / "capture"
    assert main(["prepare", str(root / "videos"), str(out), "--calib-frames", "2", "--intrinsics",
                 str(tmp_path / "lens.json"), "--quiet"]) == 0
    report = json.loads((out / "prepare_report.json").read_text())["calibration"]
    assert set(report["lenses"].values()) == {"given"}
    assert all(v == {**_lens_json(lens), "coefficients": []} for v in report["intrinsics"].values())
    ds = open_dataset(out)
    cams = ds.cameras(0)
    assert all(torch.equal(c.K.double(), lens.K.double()) for c in cams)
    # A pinhole lens: nothing is resampled, and the pixels are the scene's (H.264 at QP 0 in 4:4:4: rounding only),
    # from its frame 3 (the latest camera's start).
    view = ds.pixels(0, "cam02").astype(np.int16)
    assert np.abs(view - truth.pixels(3, "cam02").astype(np.int16)).mean() < 1.0
    rotations, centres_pct = _camera_errors(cams, truth)
    assert np.median(rotations) < 0.2 and np.median(centres_pct) < 0.5


def test_a_prepared_capture_trains_as_the_scene_read_directly(rig, tmp_path):
    """Within 0.5 dB of held-out PSNR. Training is chaotic (one seed moves a run by about half a
    dB here), so each side is the mean of seeds 0-2."""
    from stgs.evaluate import evaluate
    from stgs.train import budget, train

    _, truth, _ = rig
    write_rig_footage(truth, tmp_path / "videos", {}, audio=False)  # every camera from the scene's first frame
    capture = tmp_path / "capture"
    assert main(["prepare", str(tmp_path / "videos"), str(capture), "--sync", "index", "--calib-frames", "2",
                 "--quiet"]) == 0
    means = {}
    for side, source in (("direct", truth.root), ("prepared", capture)):
        psnrs = []
        for seed in range(3):
            out = tmp_path / f"{side}{seed}"
            train(source, out, budget("quick", gop_size=8, max_gops=1, holdout=["cam04"], scale=0.5,
                                      coarse_iterations=300, iterations=200, seed=seed), progress=False)
            evaluation = evaluate(out, source, tmp_path / f"eval-{side}{seed}", progress=False, lpips_net=None)
            psnrs.append(evaluation["streams"]["uncompressed"]["psnr"])
        means[side] = float(np.mean(psnrs))
    assert abs(means["prepared"] - means["direct"]) < 0.5, means


def test_the_videos_layout_holds_the_same_frames(rig, prepared, tmp_path):
    root, _, _ = rig
    out = tmp_path / "as_videos"
    assert main(["prepare", str(root / "videos"), str(out), "--layout", "videos", "--sync", "index", "--offsets",
                 ",".join(f"{k}={v}" for k, v in LATE.items()), "--calib-frames", "2", "--quiet"]) == 0
    frames, videos = open_dataset(prepared), open_dataset(out, cache=tmp_path / "cache")
    assert videos.name.startswith("colmap-videos") and videos.num_frames == frames.num_frames
    for f in (0, frames.num_frames - 1):
        for cam in ("cam00", "cam05"):
            assert np.array_equal(videos.pixels(f, cam), frames.pixels(f, cam))


def test_audio_lag_is_found_to_the_sample():
    rng = np.random.default_rng(1)
    reference = rng.normal(0, 1, 20000)
    assert audio_lag(reference, reference[137:], 40)[0] == 137
    assert audio_lag(reference[137:], reference, 40)[0] == -137


def test_offsets_and_calibration_frames_parse_and_spread():
    assert parse_offsets("cam01=2, cam3=-1") == {"cam01": 2, "cam3": -1}
    with pytest.raises(ValueError, match="'cam01' is not camera=frames"):
        parse_offsets("cam01")
    assert calibration_frames(90, 3) == [15, 45, 75]
    assert calibration_frames(2, 5) == [0, 1]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("stgs: ") and "\n" not in err and "Traceback" not in err, err
    return err


def _still(rgb_seed: int, count: int = 3, size: tuple[int, int] = (64, 48)) -> list[np.ndarray]:
    rng = np.random.default_rng(rgb_seed)
    return [rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8) for _ in range(count)]


@pytest.mark.parametrize("case", ["not_a_video", "rates_differ", "audio_missing", "no_overlap", "short",
                                  "offset_unknown", "lens_camera_unknown", "lens_aspect", "lens_not_json"])
def test_unusable_footage_is_one_line_and_writes_nothing(tmp_path, capsys, case):
    videos = tmp_path / "videos"
    args = ["--quiet"]
    for i in range(3):
        audio = None if case == "audio_missing" and i == 2 else np.zeros(48000, np.float32)
        write_footage(videos / f"cam{i}.mkv", _still(i), 25 if case == "rates_differ" and i == 1 else 30, audio,
                      codec="ffv1")
    expected = {"rates_differ": "frame rates differ: cam1 (25.000 fps)",
                "audio_missing": "camera cam2 has no audio track",
                "no_overlap": "COLMAP registered 0 of 3 cameras",
                "short": "10.0 s asked from 0.0 s, but the common span holds 0.10 s",
                "offset_unknown": "offset given for 'cam9'",
                "not_a_video": "not a readable video",
                "lens_camera_unknown": "camera 'cam9' is not in the footage",
                "lens_aspect": "a lens calibrated at 64x64 does not fit 64x48 frames",
                "lens_not_json": "cannot be read as JSON"}[case]
    if case == "not_a_video":
        (videos / "cam1.mkv").write_text("this is not a video\n")
    lens = {"model": "PINHOLE", "width": 64, "height": 64 if case == "lens_aspect" else 48, "fx": 50.0,
            "fy": 50.0, "cx": 32.0, "cy": 24.0}
    lenses = tmp_path / "lenses.json"
    lenses.write_text("{" if case == "lens_not_json" else json.dumps(
        {"cameras": {"cam9": lens}} if case == "lens_camera_unknown" else {"lens": lens}))
    if case.startswith("lens_"):
        args += ["--intrinsics", str(lenses), "--sync", "index"]
    args += {"audio_missing": ["--sync", "audio"], "short": ["--sync", "index", "--seconds", "10"],
             "no_overlap": ["--sync", "index"],
             "offset_unknown": ["--offsets", "cam9=3"]}.get(case, [])
    out = tmp_path / "out"
    assert main(["prepare", str(videos), str(out), *args]) == 2
    assert expected in _one_line(capsys)
    assert not out.exists() and not output.staging_dir(out).exists()


def test_a_killed_run_resumes_and_finishes_whole(rig, prepared, tmp_path, monkeypatch, capsys):
    root, _, _ = rig
    out = tmp_path / "capture"
    base = ["prepare", str(root / "videos"), str(out), "--calib-frames", "2", "--quiet"]
    written = []
    real = output.write_png

    def dies_after_twelve(path, rgb):
        if len(written) == 12:
            raise KeyboardInterrupt
        written.append(path)
        real(path, rgb)

    monkeypatch.setattr(output, "write_png", dies_after_twelve)
    assert main(base) == 130
    assert _one_line(capsys) == "stgs: interrupted"
    stage = output.staging_dir(out)
    assert not out.exists() and stage.is_dir() and (stage / output.STATE).is_file()
    assert main(base) == 2 and "--resume" in _one_line(capsys)
    monkeypatch.setattr(output, "write_png", real)
    assert main([*base, "--resume"]) == 0
    assert out.is_dir() and not stage.exists() and not (out / output.STATE).exists()
    again, first = open_dataset(out), open_dataset(prepared)
    assert again.num_frames == first.num_frames and again.camera_names == first.camera_names
    for f in range(again.num_frames):
        assert np.array_equal(again.pixels(f, "cam00"), first.pixels(f, "cam00"))
    hidden = [p for p in out.rglob(".*")]
    assert hidden == [], hidden


def test_rotated_footage_is_turned_upright(tmp_path):
    from stgs.prepare.footage import probe, read_frames

    frames = _still(5, count=2)
    path = write_footage(tmp_path / "cam0.mkv", frames, 30, rotation=90, codec="ffv1")
    footage = probe(path)
    assert (footage.rotation, footage.width, footage.height) == (90, 48, 64)
    got = dict(read_frames(footage, 0, 2))
    assert np.array_equal(got[1], np.rot90(frames[1]))


def test_json_report_names_every_stage(prepared):
    report = json.loads((prepared / "prepare_report.json").read_text())
    assert {"footage", "fps", "sync", "span", "calibration", "layout", "frames_bytes", "capture_bytes",
            "timings"} <= set(report)
    calibration = report["calibration"]
    assert calibration["mean_reprojection_error_px"] < 2.0
    assert set(calibration["lenses"].values()) == {"fitted"} and calibration["camera_model"] == "SIMPLE_RADIAL"
    assert 1 <= calibration["refine_rounds"] <= 4 and calibration["observations_dropped"] > 0
    assert calibration["pairs_ruled_out_by_lenses"] == 0  # none given
    assert Path(report["footage"][0]["path"]).name == "cam00.mp4"
