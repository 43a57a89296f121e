"""Dataset readers: the real Panoptic capture (skips without ../shared), N3DV built here with ffmpeg, synth."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
import torch

from stgs.data import open_dataset, split
from stgs.errors import StgsError
from tests.conftest import PANOPTIC

needs_panoptic = pytest.mark.skipif(not PANOPTIC.is_dir(), reason="../shared/data/panoptic-basketball is absent")


@needs_panoptic
def test_panoptic_shapes_and_cameras():
    ds = open_dataset(PANOPTIC)
    assert ds.name.startswith("panoptic") and ds.num_frames == 150 and len(ds.camera_names) == 27
    assert ds.camera_names[:3] == ["1", "2", "3"]
    cams = ds.cameras(0)
    assert len(cams) == 27 and (cams[0].width, cams[0].height) == (640, 360)
    meta = json.loads((PANOPTIC / "train_meta.json").read_text())
    assert torch.allclose(cams[4].K, torch.tensor(meta["k"][0][4], dtype=torch.float64))
    assert torch.allclose(cams[4].viewmat, torch.tensor(meta["w2c"][0][4], dtype=torch.float64))
    img = ds.image(149, "29")
    assert img.shape == (360, 640, 3) and img.dtype == torch.float32 and img.min() >= 0 and img.max() <= 1
    mask = ds.mask(0, "1")
    assert mask.shape == (360, 640) and mask.dtype == torch.bool and 0.01 < mask.float().mean() < 0.5
    # every camera looks at the middle of the dome: the cameras' centroid is in front of each of them
    centres = torch.stack([c.center for c in cams])
    middle = centres.mean(0)
    for c in cams:
        assert (c.viewmat[:3, :3] @ middle + c.viewmat[:3, 3])[2] > 0
    train, val = split(ds, ["1", "14", "27"])
    assert len(train) == 24 and val == ["1", "14", "27"]


@needs_panoptic
def test_panoptic_bad_layouts_are_clear(tmp_path):
    meta = json.loads((PANOPTIC / "train_meta.json").read_text())
    (tmp_path / "ims").symlink_to(PANOPTIC / "ims")
    meta["k"] = meta["k"][:-1]
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(StgsError, match="must agree"):
        open_dataset(tmp_path)
    meta = json.loads((PANOPTIC / "train_meta.json").read_text())
    meta["fn"][3] = meta["fn"][3][:-1]
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(StgsError, match="camera counts differ"):
        open_dataset(tmp_path)
    meta = json.loads((PANOPTIC / "train_meta.json").read_text())
    meta["fn"][7][2] = "3/999999.jpg"
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(StgsError, match=r"1 frame image\(s\) missing, e\.g\. ims/3/999999\.jpg"):
        open_dataset(tmp_path)


def _n3dv(root, cameras=3, frames=5, size=(64, 48)):
    root.mkdir()
    rows = []
    for i in range(cameras):
        subprocess.run(["ffmpeg", "-loglevel", "error", "-f", "lavfi", "-i",
                        f"testsrc2=size={size[0]}x{size[1]}:rate=30:duration={frames / 30}", "-pix_fmt", "yuv420p",
                        str(root / f"cam{i:02d}.mp4")], check=True)
        # LLFF columns: down, right, back, centre, (h, w, f); camera i at x = i looking down -z (back = +z)
        # down = -y (world y up), right = +x, back = +z; centre (i, 0, 5); full-size h, w and focal 40
        mat = np.array([[0, 1, 0, i, size[1]], [-1, 0, 0, 0, size[0]], [0, 0, 1, 5, 40.0]], dtype=np.float64)
        rows.append(np.concatenate([mat.reshape(-1), [1.0, 10.0]]))
    np.save(root / "poses_bounds.npy", np.stack(rows))
    return root


def test_n3dv_reader_extracts_downscaled_frames(tmp_path):
    root = _n3dv(tmp_path / "scene")
    ds = open_dataset(root, cache=tmp_path / "cache")
    assert ds.camera_names == ["cam00", "cam01", "cam02"] and ds.num_frames == 5
    assert split(ds) == (["cam01", "cam02"], ["cam00"])
    cam = ds.cameras(0)[1]
    assert (cam.width, cam.height) == (32, 24) and cam.K[0, 0] == pytest.approx(20.0)
    assert torch.allclose(cam.center, torch.tensor([1.0, 0.0, 5.0], dtype=torch.float64))
    # OpenCV axes: world -z is in front of the camera, world +x is to the right, world +y is up (negative v)
    p = cam.viewmat[:3, :3] @ torch.tensor([1.5, 0.5, 0.0], dtype=torch.float64) + cam.viewmat[:3, 3]
    assert p[2] > 0 and p[0] > 0 and p[1] < 0
    img = ds.image(4, "cam02")
    assert img.shape == (24, 32, 3) and img.std() > 0.05
    assert not list((tmp_path / "cache").rglob(".cam*"))  # no temp folders left


def test_n3dv_mismatched_cameras_and_garbage_are_clear(tmp_path):
    root = _n3dv(tmp_path / "scene", cameras=2)
    shutil.copy(root / "cam01.mp4", root / "cam02.mp4")
    with pytest.raises(StgsError, match=r"3 cam\*\.mp4 video\(s\) but 2 camera pose\(s\)"):
        open_dataset(root, cache=tmp_path / "cache")
    (root / "cam02.mp4").unlink()
    (root / "cam01.mp4").write_bytes(b"not a video")
    with pytest.raises(StgsError, match="not a readable video"):
        open_dataset(root, cache=tmp_path / "cache")


def test_synth_reader_and_unknown_folders(tmp_path):
    from stgs.synth import SynthConfig, synthesize

    synthesize(SynthConfig(grid_side=4, num_gops=1, gop_size=2, width=16, height=12, num_cameras=3, fit_steps=1),
               tmp_path / "s", progress=False)
    ds = open_dataset(tmp_path / "s")
    assert ds.num_frames == 2 and ds.camera_names == ["cam00", "cam01", "cam02"]
    assert split(ds) == (["cam00", "cam01"], ["cam02"])
    assert ds.image(1, "cam01").shape == (12, 16, 3) and ds.mask(0, "cam00").shape == (12, 16)
    shutil.rmtree(tmp_path / "s" / "gt" / "masks")  # a scene written before synth wrote masks
    assert ds.mask(0, "cam00") is None
    with pytest.raises(StgsError, match="not a dataset"):
        open_dataset(tmp_path)
    with pytest.raises(StgsError, match=r"no camera\(s\) \['nope'\]"):
        split(ds, ["nope"])


def test_views_are_checked_from_their_headers_before_anything_trains(tmp_path):
    """A ground-truth image of another size or a missing one, in the last frame: one line from check_views, and
    from `stgs train` before it writes anything."""
    import cv2

    from stgs.synth import SynthConfig, synthesize
    from tests.conftest import run_stgs

    synthesize(SynthConfig(grid_side=4, num_gops=2, gop_size=4, width=16, height=12, num_cameras=3, fit_steps=1),
               tmp_path / "s", progress=False)
    ds = open_dataset(tmp_path / "s")
    ds.check_views(list(range(8)), ds.camera_names)  # as written: all present, all 16x12
    late = tmp_path / "s" / "gt" / "cam01" / "00007.png"
    cv2.imwrite(str(late), np.zeros((24, 32, 3), np.uint8))
    with pytest.raises(StgsError, match=r"1 of \d+ image\(s\) are missing or of another size, e\.g\. "
                                        r"gt/cam01/00007\.png is 32x24, expected 16x12"):
        ds.check_views(list(range(8)), ds.camera_names)
    ds.check_views(list(range(7)), ds.camera_names)  # the views a run would not train are not its business
    result = run_stgs("train", str(tmp_path / "s"), str(tmp_path / "out"), "--budget", "quick", "--gop-size", "4",
                      "--quiet")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"stgs: {tmp_path / 's'}: 1 of 48 image(s) are missing or of "
                                                  "another size, e.g. gt/cam01/00007.png is 32x24, expected 16x12"]
    assert not (tmp_path / "out").exists()
    late.unlink()
    with pytest.raises(StgsError, match=r"gt/cam01/00007\.png is missing or not a readable image"):
        ds.check_views(list(range(8)), ds.camera_names)


@needs_panoptic
def test_panoptic_views_of_another_size_are_found_from_the_headers(tmp_path):
    import cv2

    (tmp_path / "ims").mkdir()
    for cam in (PANOPTIC / "ims").iterdir():
        if cam.name != "3":
            (tmp_path / "ims" / cam.name).symlink_to(cam)
    (tmp_path / "ims" / "3").mkdir()
    for image in (PANOPTIC / "ims" / "3").iterdir():
        (tmp_path / "ims" / "3" / image.name).symlink_to(image)
    odd = tmp_path / "ims" / "3" / "000120.jpg"
    odd.unlink()
    cv2.imwrite(str(odd), np.zeros((180, 320, 3), np.uint8))
    shutil.copy(PANOPTIC / "train_meta.json", tmp_path / "train_meta.json")
    ds = open_dataset(tmp_path)  # no seg/: images only
    ds.check_views(list(range(120)), ds.camera_names)
    with pytest.raises(StgsError, match=r"1 of 4050 image\(s\) .* e\.g\. ims/3/000120\.jpg is 320x180, expected "
                                        r"640x360"):
        ds.check_views(list(range(150)), ds.camera_names)
