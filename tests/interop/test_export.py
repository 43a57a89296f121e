"""`stgs export` of a frame (model dir or packaged tree), the image of an exported frame against the frame's own,
and a file made elsewhere as the static layer of `stgs train` and `stgs synth` (frame, SH, capacity)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from stgs.data import open_dataset
from stgs.interop import gltf, ply
from stgs.interop.files import SEQUENCE_INDEX, read_splats, write_splats
from stgs.interop.frames import frame_splats, open_source
from stgs.interop.splats import from_static, to_static
from stgs.interop.static import fit_similarity, fitted_transform, import_static, transform
from stgs.metrics import psnr
from stgs.model.renderer import FrameRenderer, splat
from stgs.packager import PackConfig, pack
from tests.conftest import run_stgs
from tests.interop.conftest import random_splats

FRAME = 7


def frame_and_render(scene: Path, fmt: str, tmp_path: Path) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(the frame as the player renders it, the exported file as our static layer renders it, that file's values
    rendered directly) from the scene's camera 1, the frame evaluated from that camera."""
    source = open_source(scene)
    cam = open_dataset(scene, "synth").cameras(0)[1]
    k, i = divmod(FRAME, source.gop_size)
    frame = FrameRenderer(source.gop(k), native=False, static=source.static).render(i, cam)
    exported = frame_splats(source, FRAME, cam.center)
    write_splats(tmp_path / f"f.{fmt}", exported)
    imported = to_static(read_splats(tmp_path / f"f.{fmt}"))
    direct = to_static(exported)
    return frame, splat(imported.gaussians(cam.center.float()), cam), splat(direct.gaussians(cam.center.float()), cam)


@pytest.mark.parametrize("fmt", ["ply", "glb"])
def test_an_exported_frame_renders_as_the_frame(scene, tmp_path, fmt):
    frame, image, direct = frame_and_render(scene, fmt, tmp_path)
    assert torch.equal(image, direct)  # the file holds exactly what was exported
    # Against the frame's own float32 image: the INRIA parameterisation (a DC term for the colour, a logit for
    # the opacity) holds most float32 values exactly, not all; what differs is a float32 rounding (docs/INTEROP.md)
    assert psnr(image, frame) > 120
    assert (image - frame).abs().max() < 1e-6


def test_an_spz_frame_renders_within_its_quantisation(scene, tmp_path):
    frame, image, _ = frame_and_render(scene, "spz", tmp_path)
    assert psnr(image, frame) > 42  # 46.0 dB measured: SPZ's 1/16 steps of log-scale dominate (docs/INTEROP.md)


@pytest.mark.parametrize("codec", [ply, gltf], ids=["ply", "glb"])
def test_export_import_export_gives_the_same_bytes(scene, tmp_path, codec):
    source = open_source(scene)
    exported = frame_splats(source, FRAME, source.static.xyz.new_tensor([0.3, -0.2, -4.0]))
    first = codec.encode(exported)
    (tmp_path / "f").write_bytes(first)
    path = tmp_path / f"f.{'glb' if codec is gltf else 'ply'}"
    path.write_bytes(first)
    layer, report = import_static(path)
    assert report["gaussians"] == exported.count and report["padded"] == layer.capacity - exported.count
    again = codec.encode(from_static(layer).select(np.arange(exported.count)))  # the grid's padding left out
    assert again == first


def test_the_cli_exports_a_frame_a_sequence_and_from_a_packaged_tree(scene, tmp_path):
    run = run_stgs("export", str(scene), str(tmp_path / "f.ply"), "--frame", str(FRAME), "--eye", "0,0,-4")
    assert run.returncode == 0, run.stderr
    assert run_stgs("export", str(scene), str(tmp_path / "c.ply"), "--camera", "cam02").returncode == 0
    model_frame = read_splats(tmp_path / "f.ply")
    assert model_frame.count == 10 * 10 + 12 * 12
    run = run_stgs("export", str(scene), str(tmp_path / "seq"), "--frames", "4:9", "--format", "spz", "--quiet")
    assert run.returncode == 0, run.stderr
    index = json.loads((tmp_path / "seq" / SEQUENCE_INDEX).read_text())
    assert [r["frame"] for r in index["files"]] == [4, 5, 6, 7, 8] and index["fps"] == 30.0
    assert all((tmp_path / "seq" / r["file"]).stat().st_size == r["bytes"] for r in index["files"])
    tree = tmp_path / "tree"
    pack(scene, tree, PackConfig(ladder="fixed", qps=(16, 30), codecs=("hevc",), jobs=2), progress=False)
    run = run_stgs("export", str(tree / "manifest.mpd"), str(tmp_path / "t.glb"), "--frame", str(FRAME),
                   "--rep", "qp16", "--eye", "0,0,-4")
    assert run.returncode == 0, run.stderr
    tree_frame = read_splats(tmp_path / "t.glb")
    assert tree_frame.count == model_frame.count
    cam = open_dataset(scene, "synth").cameras(0)[2]
    images = [splat(to_static(f).gaussians(cam.center.float()), cam) for f in (tree_frame, model_frame)]
    assert psnr(*images) > 30  # the same frame through the stream's quantisation (its Gaussians PLAS-sorted)
    bad = run_stgs("export", str(tree), str(tmp_path / "x.ply"), "--rep", "qp99", "--eye", "0,0,0")
    assert bad.returncode == 2 and "qp99" in bad.stderr and not (tmp_path / "x.ply").exists()
    bad = run_stgs("export", str(scene), str(tmp_path / "y.ply"), "--frame", "12")
    assert bad.returncode == 2 and "frames 0..11" in bad.stderr and not (tmp_path / "y.ply").exists()


def test_a_degree_1_export_fits_the_view_dependent_colour_over_the_cameras(scene):
    source = open_source(scene)
    cams = open_dataset(scene, "synth").cameras(0)
    centres = [c.center for c in cams]
    k, i = divmod(FRAME, source.gop_size)
    renderer = FrameRenderer(source.gop(k), native=False, static=source.static)
    flat = to_static(frame_splats(source, FRAME, cams[0].center))
    fitted = to_static(frame_splats(source, FRAME, cams[0].center, 1, centres))
    score = lambda layer: np.mean([psnr(splat(layer.gaussians(c.center.float()), c), renderer.render(i, c))  # noqa
                                   for c in cams[1:]])
    assert fitted.sh_degree == 1 and score(fitted) > score(flat)


def test_a_transform_is_fitted_from_the_cameras_a_file_was_trained_with(scene, tmp_path):
    cams = open_dataset(scene, "synth").cameras(0)
    angle = 0.7
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    theirs = np.eye(4)
    theirs[:3, :3], theirs[:3, 3] = 2.5 * rot, [1.0, -2.0, 0.5]  # our frame to theirs
    centres = [{"img_name": f"{c.name}.png", "position": (theirs[:3, :3] @ c.center.double().numpy()
                                                          + theirs[:3, 3]).tolist()} for c in cams]
    (tmp_path / "cameras.json").write_text(json.dumps(centres))
    from stgs.interop.static import read_camera_centres

    matrix, how = fitted_transform(read_camera_centres(tmp_path / "cameras.json"), cams, "test")
    assert np.allclose(matrix, np.linalg.inv(theirs), atol=1e-9) and "6 camera centres" in how
    s = random_splats(64, 1)
    back = transform(transform(s, theirs), matrix)
    assert np.allclose(back.means, s.means, atol=1e-5) and np.allclose(back.log_scales, s.log_scales, atol=1e-5)
    assert np.allclose(back.sh, s.sh, atol=1e-5)
    q0, q1 = (q / np.linalg.norm(q, axis=1, keepdims=True) for q in (s.quats, back.quats))
    assert np.allclose(np.abs((q0 * q1).sum(1)), 1, atol=1e-5)
    assert fit_similarity(np.eye(3), np.eye(3))[1] < 1e-12


def test_train_and_synth_take_a_static_layer_from_a_file(scene, tmp_path):
    source = open_source(scene)
    write_splats(tmp_path / "bg.ply", from_static(source.static))
    out = tmp_path / "trained"
    run = run_stgs("train", str(scene), str(out), "--static-from", str(tmp_path / "bg.ply"), "--gop-size", "6",
                   "--gops", "1", "--grid-side", "6", "--iterations", "10", "--no-aux", "--quiet", "--no-migrate")
    assert run.returncode == 0, run.stderr
    report = json.loads((out / "train_report.json").read_text())["static_import"]
    assert report["grid_side"] == 10 and report["padded"] == 0 and report["transform_source"].startswith("identity")
    static = load_file(str(out / "static.safetensors"))
    assert torch.equal(static["xyz"], source.static.xyz) and torch.equal(static["log_scale"], source.static.log_scale)
    refined = tmp_path / "refined"
    run = run_stgs("train", str(scene), str(refined), "--static-from", str(tmp_path / "bg.ply"), "--gop-size", "6",
                   "--gops", "1", "--grid-side", "6", "--iterations", "5", "--static-refine", "8", "--no-aux",
                   "--quiet")
    assert run.returncode == 0, run.stderr
    assert "static layer from" in run.stdout and "grid of side 10" in run.stdout
    assert not torch.equal(load_file(str(refined / "static.safetensors"))["xyz"], source.static.xyz)
    bad = run_stgs("train", str(scene), str(tmp_path / "x"), "--static-from", str(tmp_path / "bg.ply"),
                   "--layers", "single")
    assert bad.returncode == 2 and "--layers single" in bad.stderr
    synth = tmp_path / "synth"
    run = run_stgs("synth", str(synth), "--grid-side", "6", "--gops", "1", "--gop-size", "4", "--width", "32",
                   "--height", "24", "--cameras", "3", "--effects", "rigid", "--fit-steps", "5",
                   "--static-from", str(tmp_path / "bg.ply"), "--quiet")
    assert run.returncode == 0, run.stderr
    layer = load_file(str(synth / "static.safetensors"))
    assert torch.equal(layer["xyz"], source.static.xyz)
