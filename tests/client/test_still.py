"""A still scene end to end: a capture of one frame -> `stgs train` (stage A alone) -> `stgs pack` (the static layer
alone) -> the real server on loopback -> `stgs play` (one frame per view, no clock), and the catalogue's entry
(manifests/PROFILE.md, "A still scene")."""

from __future__ import annotations

import json
import shutil

import av
import cv2
import pytest
import torch

from stgs.camera import read_scene_cameras
from stgs.client import PlaybackError, PlayConfig, play
from stgs.client.config import ViewSpec
from stgs.client.manifest import Presentation, StillPresentation, open_presentation
from stgs.errors import FieldError, MPDError, StgsError
from stgs.fsio import to_uint8
from stgs.metrics import psnr
from stgs.model.renderer import render_still
from stgs.model.store import load_model, load_static, read_meta, save_model
from stgs.mpd.model import parse_mpd
from stgs.mpd.profile import KEYFRAME_SCHEME, STATIC_SCHEME
from stgs.packaged import packaged_static
from stgs.packager import MANIFEST, STATS
from stgs.server.catalogue import catalogue
from stgs.train import budget
from stgs.train.trainer import Trainer
from stgs.tree import MODEL_META, SCENE, STATIC_EXTENSION
from tests.client.conftest import serving
from tests.conftest import SHARED, STILL_CAMERA, run_stgs

XSD = SHARED / "dash" / "DASH-MPD.xsd"


def tree(still_scene):
    return still_scene / "tree" / "still"


def test_one_frame_trains_a_still_model_dir(still_scene):
    inspected = run_stgs("inspect", str(still_scene / "capture"))
    assert inspected.returncode == 0 and "frames: 1 at 30 fps (0.03 s): a still scene" in inspected.stdout
    assert "one frame: training a still scene (--layers still)" in (still_scene / "train.stderr").read_text()
    doc = json.loads((still_scene / "model" / MODEL_META).read_text())
    assert doc["version"] == 2 and doc["gops"] == [] and doc["static"]["capacity"] == 24 ** 2
    meta, gops = load_model(still_scene / "model")
    assert meta.still and gops == [] and meta.num_frames == 0
    layer = load_static(still_scene / "model", meta)
    cam = next(c for c in read_scene_cameras(still_scene / "model") if c.name == STILL_CAMERA)
    truth = cv2.cvtColor(cv2.imread(str(next((still_scene / "capture").rglob(f"{STILL_CAMERA}.png")))),
                         cv2.COLOR_BGR2RGB)
    held_out = psnr(render_still(layer, cam).clamp(0, 1), torch.from_numpy(truth).float() / 255)
    report = json.loads((still_scene / "model" / "train_report.json").read_text())
    assert report["still"] and report["gops"] == [] and report["validation_cameras"] == [STILL_CAMERA]
    assert report["val_psnr"] == pytest.approx(held_out, abs=0.01) and held_out > 15  # the capture, not noise


def test_a_one_frame_capture_is_refused_as_gops_and_a_still_needs_its_layer(still_scene, tmp_path):
    with pytest.raises(FieldError, match="layers = still") as err:
        Trainer(still_scene / "capture", tmp_path / "out", budget("quick", layers="layered"), progress=False)
    assert err.value.field == "layers"
    result = run_stgs("train", str(still_scene / "capture"), str(tmp_path / "out"), "--layers", "single")
    assert result.returncode != 0 and result.stderr.count("\n") == 1 and "--layers" in result.stderr
    assert not (tmp_path / "out").exists()
    meta = read_meta(still_scene / "model")
    with pytest.raises(ValueError, match="still"):
        save_model(tmp_path / "bad", [], meta.fps)  # neither a GOP nor a static layer
    doc = json.loads((still_scene / "model" / MODEL_META).read_text())
    del doc["static"]
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / MODEL_META).write_text(json.dumps(doc))
    with pytest.raises(StgsError, match="empty only beside a static layer"):
        read_meta(tmp_path / "bad")


def test_the_still_tree_holds_the_static_layer_alone(still_scene):
    root = tree(still_scene)
    data = (root / MANIFEST).read_bytes()
    mpd = parse_mpd(data)
    [only] = mpd.periods[0].adaptation_sets
    assert only.has_scheme(STATIC_SCHEME) and mpd.find_adaptation_set(KEYFRAME_SCHEME) is None
    assert mpd.duration == 1 and only.segment_template.seconds == 1
    segment = next(root.rglob(f"*{STATIC_EXTENSION}"))
    assert only.representations[0].bandwidth == segment.stat().st_size * 8
    assert {p.suffix for p in root.rglob("*") if p.is_file()} == {".mpd", ".json", ".webp", STATIC_EXTENSION}
    stats = json.loads((root / STATS).read_text())
    assert stats["still"] and stats["gops"] == [] and stats["static"]["bytes"] == segment.stat().st_size
    assert stats["static"]["render_psnr"] > 40  # the segment's quantisation against the trained layer
    assert stats["quality_views"]["cameras"] == [STILL_CAMERA]
    scene = json.loads((root / SCENE).read_text())
    assert scene["title"] == "A still rig shot" and scene["poster_view"] == {"camera": "cam00", "frame": 0}
    assert cv2.imread(str(root / scene["poster"])).shape == (72, 96, 3)
    if XSD.is_file():
        from stgs.mpd.schema import schema_errors

        assert schema_errors(data, XSD) == []
    pres = open_presentation(data, "http://x/still/manifest.mpd")
    assert isinstance(pres, StillPresentation) and pres.static.capacity == 24 ** 2
    assert pres.static_url() == f"http://x/still/{segment.relative_to(root)}"
    with pytest.raises(MPDError, match="keyframe"):
        Presentation(mpd, "http://x/still/manifest.mpd")  # a player of GOPs says what it lacks
    entry = catalogue(root.parent)[0]
    assert entry["still"] and entry["gaussians"] == 24 ** 2 and entry["rungs"] == 0 and entry["codecs"] == []


async def test_stgs_play_shows_the_still_from_a_scene_camera_and_a_path(still_scene, tmp_path):
    root = tree(still_scene)
    layer = packaged_static(root)
    cameras = {c.name: c for c in read_scene_cameras(root)}
    path = tmp_path / "path.json"
    path.write_text(json.dumps([cameras[n].to_json() for n in ("cam01", "cam02", "cam03")]))
    async with serving(root) as url:
        log = await play(PlayConfig(url, view=ViewSpec(camera=STILL_CAMERA), out=tmp_path / "one",
                                    log=tmp_path / "one.json"))
        await play(PlayConfig(url, view=ViewSpec(path=str(path)), out=tmp_path / "three"))
        await play(PlayConfig(url, out=tmp_path / "orbit.mp4"))
    assert log["still"] and log["frames"] == 1 and log["error"] is None
    assert log["static_bytes"] == next(root.rglob(f"*{STATIC_EXTENSION}")).stat().st_size
    assert json.loads((tmp_path / "one.json").read_text())["frames"] == 1
    for folder, names in (("one", [STILL_CAMERA]), ("three", ["cam01", "cam02", "cam03"])):
        assert sorted(p.name for p in (tmp_path / folder).iterdir()) == [f"{j:05d}.png" for j in range(len(names))]
        for j, name in enumerate(names):  # the frame the packaged layer renders, to the byte
            shown = cv2.cvtColor(cv2.imread(str(tmp_path / folder / f"{j:05d}.png")), cv2.COLOR_BGR2RGB)
            assert (shown == to_uint8(render_still(layer, cameras[name]))).all()
    with av.open(str(tmp_path / "orbit.mp4")) as video:
        assert sum(1 for _ in video.decode(video=0)) == 1


async def test_a_corrupt_still_segment_ends_with_one_error_and_no_output(still_scene, tmp_path):
    root = shutil.copytree(tree(still_scene), tmp_path / "still")
    segment = next(root.rglob(f"*{STATIC_EXTENSION}"))
    data = bytearray(segment.read_bytes())
    data[len(data) // 2:] = bytes(len(data) - len(data) // 2)
    segment.write_bytes(bytes(data))
    async with serving(root) as url:
        with pytest.raises(PlaybackError, match=r"^static layer: "):
            await play(PlayConfig(url, view=ViewSpec(camera=STILL_CAMERA), out=tmp_path / "frames.mp4"))
    assert not list(tmp_path.glob("*.mp4")) and not list(tmp_path.glob(".frames*"))


def test_a_still_exports_evaluates_and_comes_back_in_through_static_from(still_scene, tmp_path):
    """The still's layer out as a PLY (from the model dir and from the tree), scored on its held-out camera, and that
    PLY brought back in as a still (`--static-from` on the one-frame capture) scores the same."""
    model, root = still_scene / "model", tree(still_scene)
    for source in (model, root):
        result = run_stgs("export", str(source), str(tmp_path / f"{source.name}.ply"))
        assert result.returncode == 0, result.stderr
        assert f"frame 0 of {source}" in result.stdout and f"{24 ** 2} Gaussians" in result.stdout
    result = run_stgs("eval", str(model), str(still_scene / "capture"), "--dash", str(root), "--out",
                      str(tmp_path / "eval"), "--lpips", "off")
    assert result.returncode == 0, result.stderr
    scores = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert scores["gaussians"] == {"static": 24 ** 2, "dynamic": 0}
    assert set(scores["streams"]) == {"uncompressed", "static"}
    assert scores["streams"]["static"]["render_psnr"] > 40  # the tree's layer against the trained one
    report = json.loads((model / "train_report.json").read_text())
    assert scores["streams"]["uncompressed"]["psnr"] == pytest.approx(report["val_psnr"], abs=1e-3)
    result = run_stgs("train", str(still_scene / "capture"), str(tmp_path / "back"), "--static-from",
                      str(tmp_path / "model.ply"), "--quiet")
    assert result.returncode == 0, result.stderr
    back = json.loads((tmp_path / "back" / "train_report.json").read_text())
    assert back["still"] and back["static_import"]["gaussians"] == 24 ** 2
    assert back["val_psnr"] == pytest.approx(report["val_psnr"], abs=0.05)
