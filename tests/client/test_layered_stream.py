"""A layered (format-2) scene streamed end to end: pack -> real server on loopback -> play.

The static layer is one segment of its own AdaptationSet, fetched once per playback before the first GOP
(whatever the start GOP); per-GOP segments carry the dynamic layer only (manifests/PROFILE.md)."""

from __future__ import annotations

import json
import subprocess

import cv2
import pytest
import torch

from stgs.client import PlaybackError, PlayConfig, play
from stgs.client.config import ViewSpec
from stgs.client.manifest import Presentation
from stgs.codec.static import StaticSegmentError, decode_static, encode_static
from stgs.metrics import psnr
from stgs.model.renderer import FrameRenderer
from stgs.model.store import load_model, load_static, read_meta
from stgs.mpd.model import parse_mpd
from stgs.mpd.profile import FEATURE_SCHEME, KEYFRAME_SCHEME, STATIC_SCHEME
from stgs.packager import MANIFEST, STATS, PackConfig, pack
from stgs.server.catalogue import catalogue
from stgs.synth import SynthConfig, load_ground_truth, synthesize
from stgs.tree import STATIC_EXTENSION
from tests.client.conftest import QUICK, copy_tree, serving
from tests.conftest import SHARED
from tests.conftest import run_stgs as stgs

LAYERED = SynthConfig(grid_side=12, num_gops=6, gop_size=4, fps=8.0, width=64, height=48, num_cameras=2,
                      fit_steps=60, effects=["rigid", "nonrigid", "color", "static_background"], static_grid_side=20)
XSD = SHARED / "dash" / "DASH-MPD.xsd"


@pytest.fixture(scope="module")
def layered(tmp_path_factory):
    base = tmp_path_factory.mktemp("layered")
    synthesize(LAYERED, base / "model", progress=False)
    stats = pack(base / "model", base / "dash", PackConfig(ladder="fixed",
                                                           qps=(16, 32), av1_qps=(16, 41), jobs=2), progress=False)
    return base, stats


def static_segment(root):
    return next(root.rglob(f"*{STATIC_EXTENSION}"))


def test_mpd_has_four_adaptation_sets_and_stays_valid(layered):
    base, stats = layered
    data = (base / "dash" / MANIFEST).read_bytes()
    mpd = parse_mpd(data)
    sets = mpd.periods[0].adaptation_sets
    assert len(sets) == 4 and sets[0].has_scheme(STATIC_SCHEME)  # static, keyframes, HEVC and AV1 features
    static = mpd.adaptation_set(STATIC_SCHEME)
    assert static.descriptor(STATIC_SCHEME).fields() == {"version": "1", "capacity": "400", "grid_side": "20",
                                                         "sh_degree": "0"}
    # One segment for the whole Period.
    assert static.segment_template.seconds == pytest.approx(mpd.duration)
    assert stats["static"]["bytes"] == static_segment(base / "dash").stat().st_size
    # The per-GOP sets describe the dynamic layer only.
    assert mpd.adaptation_set(KEYFRAME_SCHEME).descriptor(KEYFRAME_SCHEME).fields()["capacity"] == "144"
    assert all(r.width == 48 for a in mpd.adaptation_sets(FEATURE_SCHEME) for r in a.representations)
    if XSD.is_file():
        from stgs.mpd.schema import schema_errors

        assert schema_errors(data, XSD) == []
    probe = subprocess.run(["ffprobe", "-v", "error", "-show_entries", "stream=codec_name,width", "-of", "json",
                            str(base / "dash" / MANIFEST)], capture_output=True, text=True, check=True)
    streams = json.loads(probe.stdout)["streams"]
    assert [(s["codec_name"], s["width"]) for s in streams] == [("hevc", 48)] * 2 + [("av1", 48)] * 2


def test_static_segment_round_trips_the_layer(layered):
    base, _ = layered
    meta = read_meta(base / "model")
    original = load_static(base / "model", meta)
    data = static_segment(base / "dash").read_bytes()
    decoded = decode_static(data, meta.static.capacity, 0, len(data))
    # Same Gaussians (PLAS-sorted: in another order), each within position's quantisation step of one original,
    # and every original matched once.
    distance = torch.cdist(decoded.xyz.detach(), original.xyz.detach(), compute_mode="donot_use_mm_for_euclid_dist")
    nearest = distance.min(dim=1)
    assert nearest.values.max() < 1e-3 and len(set(nearest.indices.tolist())) == 400
    with pytest.raises(StaticSegmentError, match="capacity"):
        decode_static(data, 361, 0, len(data))
    with pytest.raises(StaticSegmentError, match="limit"):
        decode_static(data, 400, 0, len(data) - 1)
    with pytest.raises(StaticSegmentError):
        decode_static(data[: len(data) // 2], 400, 0, len(data))


def test_sh1_static_layer_round_trips():
    from stgs.model.static import StaticLayer

    layer = StaticLayer(64, sh_degree=1)
    with torch.no_grad():
        for p in layer.parameters():
            p.uniform_(-1, 1)
    data = encode_static(layer)
    decoded = decode_static(data, 64, 1, len(data))
    assert torch.allclose(decoded.sh1, layer.sh1, atol=2 / (1 << 16) * 2)
    with pytest.raises(StaticSegmentError, match="sh_degree"):
        decode_static(data, 64, 0, len(data))


def test_stats_render_psnr_is_the_composites(layered):
    _, stats = layered
    # The composite of the decoded static layer and the QP-16 dynamic layer stays close to the model.
    assert stats["representations"]["qp16"]["mean_render_psnr"] > 40
    assert stats["representations"]["qp16"]["mean_render_psnr"] > stats["representations"]["qp32"]["mean_render_psnr"]


async def test_streamed_layered_frames_match_the_uncompressed_composite(layered, tmp_path):
    base, _ = layered
    frames = tmp_path / "frames"
    async with serving(base / "dash") as url:
        log = await play(PlayConfig(url, qp=16, view=ViewSpec(camera="cam00"), out=frames, download=QUICK))
    assert log["error"] is None and log["gops_played"] == LAYERED.num_gops
    meta, gops = load_model(base / "model")
    static = load_static(base / "model", meta)
    cam = next(c for c in load_ground_truth(base / "model")[1] if c.name == "cam00")
    values = []
    for png in sorted(frames.glob("*.png")):
        f = int(png.stem)
        local = FrameRenderer(gops[f // LAYERED.gop_size], static=static).render(f % LAYERED.gop_size, cam)
        streamed = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
        values.append(psnr(torch.from_numpy(streamed).float() / 255, local.clamp(0, 1)))
    assert len(values) == LAYERED.num_gops * LAYERED.gop_size and min(values) >= 40.0, values
    # Without the static layer the frames would lack the backdrop: the composite is what was drawn.
    alone = FrameRenderer(gops[0]).render(0, cam).clamp(0, 1)
    first = cv2.cvtColor(cv2.imread(str(frames / "00000.png")), cv2.COLOR_BGR2RGB)
    assert psnr(torch.from_numpy(first).float() / 255, alone) < min(values) - 5


def static_requests(log: dict) -> list[dict]:
    return [r for g in log["gops"] for r in g["requests"] if r["kind"] == "static"]


async def test_static_layer_is_fetched_once_and_first_whatever_the_start_gop(layered):
    base, stats = layered
    async with serving(base / "dash") as url:
        log = await play(PlayConfig(url, start_s=5 * LAYERED.gop_size / LAYERED.fps - 0.01, abr="dynamic",
                                    download=QUICK, view=ViewSpec(width=32, height=24)))
    assert log["error"] is None and [g["index"] for g in log["gops"]] == [4, 5]
    assert len(static_requests(log)) == 1 and log["static_bytes"] == stats["static"]["bytes"]
    first = log["gops"][0]
    assert first["requests"][0]["kind"] == "static" and first["static_decode_s"] > 0
    assert log["gops"][1]["static_bytes"] == 0
    assert log["bytes"] == sum(g["keyframe_bytes"] + g["feature_bytes"] + g["init_bytes"] for g in log["gops"]) \
        + stats["static"]["bytes"]


@pytest.mark.parametrize("damage", ["missing", "corrupt"])
async def test_missing_or_corrupt_static_segment_is_one_clear_error(layered, tmp_path, damage):
    root = copy_tree(layered[0], tmp_path)
    seg = static_segment(root)
    if damage == "missing":
        seg.unlink()
    else:
        data = bytearray(seg.read_bytes())
        data[len(data) // 2:] = bytes(len(data) - len(data) // 2)
        seg.write_bytes(bytes(data))
    async with serving(root) as url:
        with pytest.raises(PlaybackError, match="static layer") as info:
            await play(PlayConfig(url, qp=32, download=QUICK, view=ViewSpec(width=32, height=24)))
    assert "\n" not in str(info.value)


def test_presentation_checks_the_static_descriptor(layered):
    base, _ = layered
    data = (base / "dash" / MANIFEST).read_bytes()
    pres = Presentation.parse(data, "http://h/s/manifest.mpd")
    assert pres.static.capacity == 400 and pres.static_url().startswith("http://h/s/v-")
    assert pres.static_url().endswith(STATIC_EXTENSION)
    for bad, match in ((b"grid_side=20", b"grid_side=19"), (b"sh_degree=0", b"sh_degree=2"),
                       (b"static:2026\" value=\"version=1", b"static:2026\" value=\"version=9")):
        with pytest.raises(ValueError, match="static-layer descriptor"):
            Presentation.parse(data.replace(bad, match), "http://h/s/manifest.mpd")


def test_catalogue_lists_both_formats(layered, scene, tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    (root / "one").symlink_to(scene / "dash")
    (root / "two").symlink_to(layered[0] / "dash")
    listed = {s["name"]: s for s in catalogue(root)}
    assert listed["one"]["format"] == 1 and listed["one"]["static"] is None
    assert listed["two"]["format"] == 2
    assert listed["two"]["static"]["capacity"] == 400 and listed["two"]["static"]["bandwidth"] > 0


def test_stats_of_format1_trees_have_no_static_entry(scene):
    assert "static" not in json.loads((scene / "dash" / STATS).read_text())


def test_a_scenario_compares_format1_and_format2_trees_in_one_report(layered, scene, tmp_path):
    (tmp_path / "s.toml").write_text(f'scene = "{layered[0] / "dash"}"\ncompare = ["{scene / "dash"}"]\n'
                                     'abr = "throughput"\n[effects]\nbandwidth = { kbps = 20000 }\n')
    out = tmp_path / "out"
    result = stgs("sim", str(tmp_path / "s.toml"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    rows = json.loads((out / "s.summary.json").read_text())
    assert [(r["format"], r["static_bytes"] > 0) for r in rows] == [(2, True), (1, False)]
    table = (out / "s.summary.md").read_text()
    for folder, fmt in ((layered[0], 2), (scene, 1)):
        assert f"| {folder.name}/dash (format {fmt}): throughput (sim) |" in table
    # Over a folder of traces too: each tree once per trace, one batch report.
    traces = tmp_path / "traces"
    traces.mkdir()
    (traces / "slow.csv").write_text("time_s,bandwidth_kbps\n0,800\n1,1200\n")
    result = stgs("sim", str(tmp_path / "s.toml"), "--traces", str(traces), "--out", str(out))
    assert result.returncode == 0, result.stderr
    rows = json.loads((out / "s.batch.json").read_text())
    assert sorted((r["format"], r["trace"]) for r in rows) == [(1, "slow.csv"), (2, "slow.csv")]
    assert f"| {layered[0].name}/dash (format 2): throughput (sim) | 1 |" in result.stdout


async def test_the_server_serves_the_static_segment_as_an_immutable_segment(layered):
    import aiohttp

    base, stats = layered
    rel = static_segment(base / "dash").relative_to(base / "dash")
    async with serving(base / "dash") as url, aiohttp.ClientSession() as session:
        async with session.get(url.replace("manifest.mpd", str(rel))) as resp:
            body = await resp.read()
            assert resp.status == 200 and len(body) == stats["static"]["bytes"]
            assert resp.headers["Content-Type"] == "application/vnd.streamstgs.static"
            assert "immutable" in resp.headers["Cache-Control"]
        async with session.get(url.replace("manifest.mpd", "scenes")) as resp:
            listed = (await resp.json())["scenes"]
    assert [s["format"] for s in listed] == [2]


def test_init_and_any_single_dynamic_segment_decode_alone(layered):
    from stgs.codec.video import decode_segment

    base, _ = layered
    rep = base / "dash" / next((base / "dash").glob("v-*")).name / "features" / "qp16"
    frames = decode_segment((rep / "init.mp4").read_bytes(), (rep / "seg_00004.m4s").read_bytes(),
                            LAYERED.gop_size + 2, 48, 48)
    assert frames.shape == (LAYERED.gop_size + 2, 48, 48)


def test_eval_of_a_layered_tree_draws_the_trees_static_layer(layered, tmp_path, monkeypatch):
    from stgs.evaluate import evaluate

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty-cache"))
    base, _ = layered
    doc = evaluate(base / "model", base / "model", tmp_path / "ev", dash=base / "dash", holdout=["cam01"],
                   stride=2, progress=False, lpips_net=None)
    streams = doc["streams"]
    assert set(streams) == {"uncompressed", "qp16", "qp32", "av1q16", "av1q41"} and doc["format"] == 2
    assert streams["uncompressed"]["psnr"] > streams["qp16"]["psnr"] > streams["qp32"]["psnr"] and \
        streams["qp16"]["psnr"] > 40
    # The packaged streams draw the tree's static layer: without it the backdrop is missing.
    import stgs.evaluate

    monkeypatch.setattr(stgs.evaluate, "packaged_static", lambda dash: None)
    alone = evaluate(base / "model", base / "model", tmp_path / "ev2", dash=base / "dash", holdout=["cam01"],
                     stride=2, progress=False, lpips_net=None)["streams"]
    assert alone["qp16"]["psnr"] < streams["qp16"]["psnr"] - 10
