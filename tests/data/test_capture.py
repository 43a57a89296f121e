"""Calibrated captures: COLMAP models (binary, text) beside per-frame folders, per-camera folders and per-camera
videos, and nerfstudio's transforms.json, each read back to the synthetic capture they were written from; our COLMAP
reader against pycolmap's; undistortion; `stgs inspect`; bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from stgs.camera import Camera, rig_focus, rig_size
from stgs.cli import main
from stgs.data import open_dataset, split
from stgs.data.colmap import read_model
from stgs.data.frames import write_png
from stgs.data.inspect import inspect_dataset
from stgs.data.synth import SynthReader
from stgs.data.units import REFERENCE_SIZE, scale_view, world_scale
from stgs.metrics import psnr
from stgs.synth import SynthConfig
from stgs.synth.generate import ground_truth_cameras
from stgs.train.seeding import initial_points
from tests.conftest import PANOPTIC, run_stgs
from tests.data.captures import MOVING, TEXTURED, ground_truth, write_capture, write_colmap

LAYOUTS = [("frames", True, "colmap-frames"), ("frames", False, "colmap-frames"), ("images", True, "colmap-images"),
           ("videos", True, "colmap-videos"), ("nerfstudio", True, "nerfstudio")]


@pytest.fixture(scope="module")
def truth(tmp_path_factory) -> SynthReader:
    return ground_truth(tmp_path_factory.mktemp("capture") / "truth")


@pytest.mark.parametrize("layout,binary,kind", LAYOUTS,
                         ids=["frames-bin", "frames-txt", "images", "videos", "nerfstudio"])
def test_a_capture_reads_back_to_the_same_cameras_and_pixels(truth, tmp_path, layout, binary, kind):
    root = write_capture(truth, tmp_path / "cap", layout, binary)
    ds = open_dataset(root, cache=tmp_path / "cache")
    assert ds.name.startswith(kind) and ds.num_frames == truth.num_frames
    assert ds.camera_names == truth.camera_names
    for f in (0, truth.num_frames - 1):
        for mine, theirs in zip(ds.cameras(f), truth.cameras(f), strict=True):
            assert mine.name == theirs.name and (mine.width, mine.height) == (theirs.width, theirs.height)
            assert torch.allclose(mine.K, theirs.K.double(), rtol=0, atol=1e-6)
            assert torch.allclose(mine.viewmat, theirs.viewmat.double(), rtol=0, atol=1e-9)
            assert np.array_equal(ds.pixels(f, mine.name), truth.pixels(f, theirs.name))  # lossless files
    ds.check_views(list(range(ds.num_frames)), ds.camera_names)


def test_the_per_frame_layout_holds_out_cam00_and_takes_any_camera_by_name(truth, tmp_path):
    ds = open_dataset(write_capture(truth, tmp_path / "cap", "frames"))
    assert split(ds) == (truth.camera_names[1:], ["cam00"])
    assert split(ds, ["cam02", "cam04"])[1] == ["cam02", "cam04"]
    nerf = open_dataset(write_capture(truth, tmp_path / "ns", "nerfstudio"))
    assert split(nerf, ["cam03"])[1] == ["cam03"] and split(nerf)[1] == []


def test_the_per_frame_layout_takes_its_model_from_the_top_too(truth, tmp_path):
    root = write_capture(truth, tmp_path / "cap", "frames")
    (root / "sparse").mkdir()
    (root / "frame000000" / "sparse" / "0").rename(root / "sparse" / "0")
    ds = open_dataset(root)
    assert ds.models[0].path == root / "sparse" / "0"
    assert torch.allclose(ds.cameras(3)[1].viewmat, truth.cameras(3)[1].viewmat.double(), atol=1e-9)


def test_a_capture_of_image_files_takes_its_frame_rate_from_the_command_line(truth, tmp_path):
    root = write_capture(truth, tmp_path / "cap", "frames")
    assert open_dataset(root).fps == 30.0 and open_dataset(root, fps=25.0).fps == 25.0
    run = run_stgs("inspect", str(root), "--fps", "25", "--json")
    assert run.returncode == 0 and json.loads(run.stdout)["fps"] == 25.0
    assert open_dataset(write_capture(truth, tmp_path / "v", "videos")).fps == 30.0  # the videos say it
    bad = run_stgs("train", str(truth.root), str(tmp_path / "out"), "--fps", "25")
    assert bad.returncode == 2 and "says its own frame rate" in bad.stderr and not (tmp_path / "out").exists()


def test_per_frame_models_give_each_frame_its_own_cameras(truth, tmp_path):
    root = write_capture(truth, tmp_path / "cap", "frames", per_frame=True)
    ds = open_dataset(root)
    assert len(ds.models) == truth.num_frames
    assert inspect_dataset(root)["calibration"] == "changes between frames"
    for f in range(truth.num_frames):
        moved = ds.cameras(f)[2].center - truth.cameras(f)[2].center.double()
        assert torch.allclose(moved, torch.tensor([0.01 * f, 0, 0], dtype=torch.float64), atol=1e-9)


def test_our_colmap_reader_agrees_with_pycolmap(truth, tmp_path):
    points = np.random.default_rng(1).normal(size=(40, 3))
    for binary in (True, False):
        root = write_capture(truth, tmp_path / f"cap{binary}", "images", binary, "OPENCV",
                             (-0.05, 0.01, 1e-3, -5e-4), points)
        ours, theirs = read_model(root / "sparse" / "0"), pycolmap.Reconstruction(str(root / "sparse" / "0"))
        assert sorted(ours.cameras) == sorted(theirs.cameras)
        for cid, cam in theirs.cameras.items():
            mine = ours.cameras[cid]
            assert mine.model == cam.model.name and (mine.width, mine.height) == (cam.width, cam.height)
            assert np.allclose([mine.fx, mine.fy, mine.cx, mine.cy, *mine.coefficients], cam.params, atol=0)
        assert sorted(i.name for i in ours.images) == sorted(i.name for i in theirs.images.values())
        for image in ours.images:
            ref = theirs.images[image.image_id]
            assert image.name == ref.name and image.camera_id == ref.camera_id
            assert np.allclose(image.viewmat()[:3], ref.cam_from_world().matrix(), atol=1e-12)
        xyz = np.array([p.xyz for p in theirs.points3D.values()])
        rgb = np.array([p.color for p in theirs.points3D.values()])
        order, mine_order = np.lexsort(xyz.T), np.lexsort(ours.points.T)
        assert np.allclose(ours.points[mine_order], xyz[order], atol=1e-12)
        assert np.array_equal(ours.colours[mine_order], rgb[order])


def test_points3d_seed_training(truth, tmp_path):
    points = np.random.default_rng(2).normal(scale=0.3, size=(300, 3))
    ds = open_dataset(write_capture(truth, tmp_path / "cap", "frames", points=points))
    xyz, rgb = ds.points(0)
    assert xyz.shape == (300, 3) and rgb.min() >= 0 and rgb.max() <= 1
    assert ds.points(1) is None  # the one model is frame 0's
    init = initial_points(ds, ds.camera_names, [0], 500, torch.Generator().manual_seed(0))
    assert init.triangulated == 300
    assert torch.allclose(init.points[:300].double().sort(0).values,
                          torch.from_numpy(points).float().double().sort(0).values)


@pytest.mark.parametrize("model,coefficients,floor", [
    ("SIMPLE_RADIAL", (-0.08,), 35.0),
    ("RADIAL", (-0.08, 0.02), 35.0),
    ("OPENCV", (-0.08, 0.02, 1e-3, -5e-4), 35.0),
    ("FULL_OPENCV", (-0.08, 0.02, 1e-3, -5e-4, 0.01, 0.0, 0.0, 0.0), 35.0),
    ("OPENCV_FISHEYE", (0.05, -0.01, 0.002, -0.001), 33.0),
])
def test_a_distorted_capture_reads_back_undistorted(tmp_path, model, coefficients, floor):
    truth = ground_truth(tmp_path / "truth", TEXTURED)
    root = write_capture(truth, tmp_path / "cap", "frames", model=model, coefficients=coefficients)
    ds = open_dataset(root, cache=tmp_path / "cache")
    name = ds.camera_names[1]
    assert torch.allclose(ds.cameras(0)[1].K, truth.cameras(0)[1].K.double(), atol=1e-9)
    # Distorting and undistorting resample twice (bilinear), and the corners the lens pushes out of the frame come
    # back black: the undistorted view is the pinhole one within the stated PSNR (docs/CAPTURE.md, "Distortion"),
    # far nearer than the distorted frame is.
    pinhole = truth.image(0, name)
    undistorted = psnr(ds.image(0, name), pinhole)
    distorted = psnr(torch.from_numpy(ds.intrinsics(name).distort(truth.pixels(0, name))).float() / 255, pinhole)
    assert undistorted > floor and undistorted > distorted + 10
    assert len(list((tmp_path / "cache" / "undistorted").iterdir())) == 1  # once, into the cache
    assert np.array_equal(open_dataset(root, cache=tmp_path / "cache").pixels(0, name), ds.pixels(0, name))


@pytest.mark.parametrize("model,coefficients", [
    ("SIMPLE_PINHOLE", ()), ("PINHOLE", ()), ("SIMPLE_RADIAL", (-0.08,)), ("RADIAL", (-0.08, 0.02)),
    ("OPENCV", (-0.08, 0.02, 1e-3, -5e-4)), ("FULL_OPENCV", (-0.08, 0.02, 1e-3, -5e-4, 0.01, 0.0, 0.0, 0.0)),
    ("OPENCV_FISHEYE", (0.05, -0.01, 0.002, -0.001)),
])
def test_a_lens_given_as_json_projects_as_colmap_projects_it_at_any_frame_size(model, coefficients):
    from stgs.data.distortion import Intrinsics

    fy = 380.0 if model in ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE") else 400.0
    lens = Intrinsics.from_json({"model": model, "width": 640, "height": 360, "fx": 400.0, "fy": fy, "cx": 321.5,
                                 "cy": 178.25, "coefficients": list(coefficients)})
    assert Intrinsics.from_json(lens.to_json()) == lens
    point = np.array([[0.3, -0.2, 1.0], [-0.5, 0.25, 2.0]])
    full = pycolmap.Camera(model=model, width=640, height=360, params=lens.colmap_params())
    assert full.verify_params() and full.params_info.count(",") + 1 == len(lens.colmap_params())
    # Half the resolution (COLMAP's convention: the image's edges at 0 and W) projects every point to half the
    # pixel coordinates, distortion included.
    half = lens.resized(320, 180)
    small = pycolmap.Camera(model=model, width=320, height=180, params=half.colmap_params())
    assert np.allclose(small.img_from_cam(point), full.img_from_cam(point) / 2, atol=1e-9)
    with pytest.raises(ValueError, match="another aspect ratio"):
        lens.resized(320, 320)


@pytest.mark.parametrize("change,message", [
    ({"model": "THIN_PRISM_FISHEYE"}, "model is not supported"),
    ({"fx": -1.0, "fy": -1.0}, "focal lengths must be positive"),
    ({"fy": 401.0}, "one focal length"),
    ({"coefficients": [0.1, 0.2]}, "takes 1 coefficients"),
    ({"coefficients": [float("nan")]}, "must be finite"),
    ({"width": "wide"}, "must be integers"),
    ({"cx": None}, "numbers"),
])
def test_a_bad_lens_is_an_error_naming_what_is_wrong(change, message):
    from stgs.data.distortion import Intrinsics

    good = {"model": "SIMPLE_RADIAL", "width": 640, "height": 360, "fx": 400.0, "fy": 400.0, "cx": 320.0,
            "cy": 180.0, "coefficients": [0.01]}
    with pytest.raises(ValueError, match=message):
        Intrinsics.from_json({**good, **change})
    with pytest.raises(ValueError, match="needs the field 'cy'"):
        Intrinsics.from_json({k: v for k, v in good.items() if k != "cy"})


def test_inspect_reports_the_capture_and_draws_the_rig(truth, tmp_path):
    root = write_capture(truth, tmp_path / "cap", "frames", model="OPENCV", coefficients=(-0.05, 0.0, 0.0, 0.0))
    run = run_stgs("inspect", str(root), "--json")
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    assert report["kind"] == "colmap-frames" and report["frames"] == truth.num_frames
    assert report["camera_count"] == 5 and report["holdout"] == ["cam00"] and report["problems"] == []
    assert report["calibration"] == "the same for every frame"
    assert report["distorted_cameras"] == truth.camera_names and report["resolutions"] == ["64x48"]
    focus, radius = rig_focus(truth.cameras(0))
    assert report["rig"]["radius"] == pytest.approx(radius) and np.allclose(report["rig"]["centre"], focus)
    centres = torch.stack([c.center for c in truth.cameras(0)])
    assert np.allclose(report["rig"]["span"], float((centres.max(0).values - centres.min(0).values).norm()))
    run = run_stgs("inspect", str(root), "--plot", str(tmp_path / "rig.png"))
    assert run.returncode == 0 and "colmap-frames" in run.stdout and "OPENCV -0.05" in run.stdout
    assert (tmp_path / "rig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _rewrite_model(path: Path, old: str, new: str) -> None:
    path.write_text(path.read_text().replace(old, new))


BAD = {
    "truncated images.bin": ("frames", lambda r: _truncate(r / "frame000000/sparse/0/images.bin"), "images.bin"),
    "unknown camera model": ("images-txt", lambda r: _rewrite_model(r / "sparse/0/cameras.txt", "PINHOLE", "FOV"),
                             "FOV"),
    "missing image": ("frames", lambda r: (r / "frame000002/images/cam03.png").unlink(), "lacks cam03"),
    "camera without frames": ("images", lambda r: shutil.rmtree(r / "images" / "cam01"),
                              "image 'cam01/000000.png' (camera cam01) has no frames"),
    "frame counts differ": ("images", lambda r: (r / "images/cam02/000003.png").unlink(),
                            "camera cam02 has 3 frames, cam00 has 4"),
    "transforms without cameras": ("nerfstudio", lambda r: _rewrite_model(
        r / "transforms.json", '"camera": "cam', '"label": "cam'), "cannot tell which camera took each image"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_captures_are_one_line_and_write_nothing(truth, tmp_path, capsys, case):
    layout, spoil, message = BAD[case]
    binary = not layout.endswith("-txt")
    root = write_capture(truth, tmp_path / "cap", layout.removesuffix("-txt"), binary)
    if case == "transforms without cameras":  # and the images all in one folder: nothing says the camera
        doc = json.loads((root / "transforms.json").read_text())
        for i, frame in enumerate(doc["frames"]):
            flat = f"images/{i:05d}.png"
            (root / frame["file_path"]).rename(root / flat)
            frame["file_path"] = flat
        (root / "transforms.json").write_text(json.dumps(doc))
    spoil(root)
    for args in (["inspect", str(root)], ["train", str(root), str(tmp_path / "out")]):
        code = main(args)  # the command itself, in this process (a subprocess costs seconds of imports each)
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("stgs: ") and message in lines[0], (case, err)
    assert not (tmp_path / "out").exists()


def test_world_scale_keeps_a_rig_of_the_reference_size_and_brings_any_other_to_it():
    cams = ground_truth_cameras(SynthConfig(num_cameras=6))
    assert world_scale(cams) == 1.0  # the synthetic orbit: trained as it always was
    for factor in (0.01, 0.5, 1.5, 100.0):
        scaled = [scale_view(c, factor) for c in cams]
        expected = 1.0 if 1 / np.sqrt(2) <= REFERENCE_SIZE / rig_size(scaled) < np.sqrt(2) else \
            REFERENCE_SIZE / rig_size(scaled)
        assert world_scale(scaled) == expected
        if expected != 1.0:
            assert rig_size([scale_view(c, expected) for c in scaled]) == pytest.approx(REFERENCE_SIZE, rel=1e-12)
    assert world_scale([cams[0], cams[0]]) == 1.0  # cameras at one point have no size to go by


def test_a_capture_in_centimetres_or_in_hectometres_trains_to_the_same_model(tmp_path):
    """Part of what training does is not invariant to the unit of length (the deformation field's offsets, the
    near planes), and training is chaotic: a capture scaled by 0.01 trained to 14.5 dB held out where the same one
    at 100 gave 21.0 (docs/CAPTURE.md, "Units"). Read in the trainer's unit (stgs.data.units) both train to the
    same bits."""
    from safetensors.torch import load_file

    from stgs.evaluate import evaluate
    from stgs.train import budget, train

    truth = ground_truth(tmp_path / "truth", MOVING)
    psnrs, tensors = {}, {}
    for factor in (0.01, 100.0):
        cap = write_capture(truth, tmp_path / f"cap{factor}", "frames", scale=factor)
        out = tmp_path / f"m{factor}"
        train(cap, out, budget("quick", gop_size=6, max_gops=1, grid_side=12, holdout=["cam07"]), progress=False)
        meta = json.loads((out / "model.json").read_text())
        assert meta["extra"]["world_scale"] == pytest.approx(REFERENCE_SIZE / rig_size(
            open_dataset(cap).cameras(0)), rel=1e-12)
        model_cams = [Camera.from_json(c) for c in json.loads((out / "cameras.json").read_text())["cameras"]]
        assert rig_size(model_cams) == pytest.approx(REFERENCE_SIZE, rel=1e-9)  # the model's frame
        tensors[factor] = load_file(str(out / "gop_0000.safetensors"))
        evaluation = evaluate(out, cap, tmp_path / f"e{factor}", progress=False, lpips_net=None)
        psnrs[factor] = evaluation["streams"]["uncompressed"]["psnr"]
    assert abs(psnrs[0.01] - psnrs[100.0]) < 0.1, psnrs
    assert all(torch.equal(tensors[0.01][k], tensors[100.0][k]) for k in tensors[0.01])


@pytest.mark.skipif(not PANOPTIC.is_dir(), reason="../shared/data/panoptic-basketball is absent")
def test_panoptic_written_as_a_colmap_capture_trains_as_the_panoptic_reader_reads_it(tmp_path):
    """Panoptic's first frames written as per-frame folders (with its masks) and a COLMAP model: the same pixels
    and masks, the cameras to 1e-9, and a short training bit for bit the one the Panoptic reader gives once its
    rotations are what COLMAP can hold (quaternions: Panoptic's matrices are orthonormal to 1.4e-10 only, and that
    difference alone moves a quick training's held-out PSNR by up to a dB either way: docs/CAPTURE.md)."""
    from safetensors.torch import load_file

    from stgs.evaluate import evaluate
    from stgs.train import budget, train

    frames, held_out = 6, ["1", "14", "27"]
    panoptic = open_dataset(PANOPTIC)
    cap = tmp_path / "cap"
    for f in range(frames):
        for name in panoptic.camera_names:
            write_png(cap / f"frame{f:06d}" / "images" / f"{name}.png", panoptic.pixels(f, name))
            write_png(cap / f"frame{f:06d}" / "masks" / f"{name}.png",
                      np.repeat(panoptic.mask(f, name).numpy()[..., None], 3, 2).astype(np.uint8) * 255)
    write_colmap(cap / "frame000000" / "sparse" / "0", panoptic.cameras(0), [f"{c}.png" for c in
                                                                             panoptic.camera_names])
    colmap = open_dataset(cap)
    assert colmap.name.startswith("colmap-frames") and colmap.camera_names == panoptic.camera_names
    for mine, theirs in zip(colmap.cameras(0), panoptic.cameras(0), strict=True):
        assert torch.equal(mine.K, theirs.K) and torch.allclose(mine.viewmat, theirs.viewmat, rtol=0, atol=1e-9)
    for f in (0, frames - 1):
        for name in panoptic.camera_names[::5]:
            assert np.array_equal(colmap.pixels(f, name), panoptic.pixels(f, name))
            assert torch.equal(colmap.mask(f, name), panoptic.mask(f, name))
    # The same frames through the Panoptic reader, its w2c as the COLMAP model holds them.
    same = tmp_path / "panoptic"
    same.mkdir()
    meta = json.loads((PANOPTIC / "train_meta.json").read_text())
    meta = {k: v[:frames] if isinstance(v, list) else v for k, v in meta.items()}
    meta["w2c"] = [[c.viewmat.tolist() for c in colmap.cameras(f)] for f in range(frames)]
    (same / "train_meta.json").write_text(json.dumps(meta))
    (same / "ims").symlink_to(PANOPTIC / "ims")
    (same / "seg").symlink_to(PANOPTIC / "seg")
    results = {}
    for name, source in (("colmap", cap), ("panoptic", same)):
        out = tmp_path / f"m_{name}"
        train(source, out, budget("quick", gop_size=frames, max_gops=1, holdout=held_out, scale=0.25,
                                  coarse_iterations=300, iterations=200), progress=False)
        psnr_held_out = evaluate(out, source, tmp_path / f"e_{name}", progress=False,
                                 lpips_net=None)["streams"]["uncompressed"]["psnr"]
        results[name] = (psnr_held_out, load_file(str(out / "gop_0000.safetensors")))
    assert results["colmap"][0] == results["panoptic"][0] and results["colmap"][0] > 15
    assert all(torch.equal(results["colmap"][1][k], results["panoptic"][1][k]) for k in results["colmap"][1])


@pytest.mark.parametrize("kind,message", [("colmap-frames", "no frame folders"), ("colmap-images", "no images/"),
                                          ("colmap-videos", "no videos/"), ("nerfstudio", "not a readable")])
def test_a_layout_named_on_the_command_line_that_is_not_there_is_one_line(tmp_path, capsys, kind, message):
    code = main(["inspect", str(tmp_path), "--kind", kind])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message in err, err
