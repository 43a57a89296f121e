"""`stgs pack` end to end on a synthetic scene, with real ffmpeg/ffprobe and OpenImageIO."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from stgs.metrics import psnr
from stgs.mpd.model import parse_mpd
from stgs.mpd.profile import FEATURE_SCHEME, KEYFRAME_QUANT_SCHEME, KEYFRAME_SCHEME
from stgs.packager import MANIFEST, STATS, PackConfig, pack
from stgs.synth import SynthConfig, synthesize
from stgs.tree import expand_template
from tests.conftest import LOOP_FILTERS_OFF, SHARED, loop_filter_flags
from tests.conftest import run_stgs as stgs

SCENE = SynthConfig(grid_side=16, num_gops=2, gop_size=6, width=64, height=48, num_cameras=2, fit_steps=200)
QPS = (16, 20, 24, 28, 32)
AV1_QPS = (12, 19, 27, 35, 43)
XSD = SHARED / "dash" / "DASH-MPD.xsd"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("pack") / "scene"
    synthesize(SCENE, out, progress=False)
    return out


@pytest.fixture(scope="module")
def packed(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("pack") / "dash"
    stats = pack(scene, out, PackConfig(ladder="fixed", qps=QPS, av1_qps=AV1_QPS, jobs=2), progress=False)
    return out, stats


def feature_sets(mpd):
    """{codec name: AdaptationSet} of a parsed MPD's feature sets."""
    from stgs.mpd.profile import feature_set_codec

    return {feature_set_codec(a): a for a in mpd.adaptation_sets(FEATURE_SCHEME)}


def tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_mpd_validates_against_the_dash_schema(packed):
    if not XSD.is_file():
        pytest.skip("../shared/dash is absent")
    from stgs.mpd.schema import schema_errors

    out, _ = packed
    assert schema_errors((out / MANIFEST).read_bytes(), XSD) == []


def test_mpd_follows_the_profile(packed):
    out, stats = packed
    mpd = parse_mpd((out / MANIFEST).read_bytes())
    assert len(mpd.periods) == 1 and mpd.duration == pytest.approx(2 * 6 / 30.0)
    kf = mpd.adaptation_set(KEYFRAME_SCHEME)
    sets = feature_sets(mpd)
    assert list(sets) == ["hevc", "av1"] and sets["hevc"].group == sets["av1"].group is not None
    assert [r.id for r in sets["hevc"].representations] == [f"qp{q}" for q in QPS]
    assert [r.id for r in sets["av1"].representations] == [f"av1q{c}" for c in AV1_QPS]
    assert sets["hevc"].descriptor(FEATURE_SCHEME).fields()["bits"] == "12"
    assert sets["av1"].descriptor(FEATURE_SCHEME).fields()["bits"] == "10"
    for codec, video in sets.items():
        assert kf.segment_template.start_number == video.segment_template.start_number == 0
        assert kf.segment_template.seconds == pytest.approx(0.2) == video.segment_template.seconds
        for rep in video.representations:
            prefix = "hvc1.4." if codec == "hevc" else "av01.0."
            assert rep.codecs.startswith(prefix) and rep.association_id == ["keyframes"]
            assert rep.bandwidth == stats["representations"][rep.id]["bandwidth"]
            assert stats["representations"][rep.id]["codec"] == codec
            for k in range(2):
                seg = out / expand_template(video.segment_template.media, rep.id, k)
                assert seg.is_file()
                assert rep.bandwidth >= seg.stat().st_size * 8 / 0.2  # the largest segment fits
    for k in range(2):
        assert (out / expand_template(kf.segment_template.media, "keyframes", k)).is_file()


def test_ffprobe_lists_one_video_stream_per_rung_of_both_sets(packed):
    out, _ = packed
    probe = subprocess.run(["ffprobe", "-v", "error", "-show_entries", "stream=codec_name,width,pix_fmt",
                            "-of", "json", str(out / MANIFEST)], capture_output=True, text=True, check=True)
    streams = json.loads(probe.stdout)["streams"]
    assert [(s["codec_name"], s["pix_fmt"]) for s in streams] == (
        [("hevc", "gray12le")] * len(QPS) + [("av1", "yuv420p10le")] * len(AV1_QPS))
    assert all(s["width"] == 64 for s in streams)


@pytest.mark.parametrize("rep,gop", [("qp16", 0), ("qp20", 1), ("qp32", 1), ("av1q12", 0), ("av1q27", 1),
                                     ("av1q43", 1)])
def test_any_single_segment_decodes_alone_bit_exactly_in_ffmpeg(packed, tmp_path, rep, gop):
    """Debian's ffmpeg (libdav1d for AV1) decodes init + one segment to exactly our decoder's frames."""
    from stgs.codec.video import AV1, HEVC, decode_segment

    out, _ = packed
    mpd = parse_mpd((out / MANIFEST).read_bytes())
    codec = AV1 if rep.startswith("av1") else HEVC
    st = feature_sets(mpd)[codec.name].segment_template
    init = (out / expand_template(st.initialization, rep)).read_bytes()
    media = (out / expand_template(st.media, rep, gop)).read_bytes()
    joined = tmp_path / "alone.mp4"
    joined.write_bytes(init + media)
    decoder = ["-c:v", "libdav1d"] if codec is AV1 else []
    raw = subprocess.run(["ffmpeg", "-v", "error", *decoder, "-i", str(joined), "-f", "rawvideo", "-pix_fmt",
                          codec.pixel_format, "-"], capture_output=True, check=True).stdout
    num_features = SCENE.gop_size + 3 - 1
    picture = 64 * 64 * 2 * (3 if codec is AV1 else 2) // 2  # 4:2:0 adds two quarter planes
    assert len(raw) == num_features * picture  # exactly E frames
    theirs = np.frombuffer(raw, np.uint16).reshape(num_features, -1)[:, :64 * 64].reshape(num_features, 64, 64)
    ours = decode_segment(init, media, num_features, 64, 64, codec=codec)
    assert np.array_equal(theirs, ours)
    assert ours.max() <= (1 << codec.bits) - 1


@pytest.mark.parametrize("ladder", [[f"qp{q}" for q in QPS], [f"av1q{c}" for c in AV1_QPS]])
def test_rate_and_distortion_fall_with_qp(packed, ladder):
    _, stats = packed
    for gop in stats["gops"]:
        reps = [gop["representations"][rep] for rep in ladder]
        sizes = [r["bytes"] for r in reps]
        psnrs = [r["feature_psnr"] for r in reps]
        assert sizes == sorted(sizes, reverse=True) and len(set(sizes)) == len(sizes)
        assert psnrs == sorted(psnrs, reverse=True) and len(set(psnrs)) == len(psnrs)


def test_rendered_views_at_qp20_and_av1q19_are_faithful(packed):
    _, stats = packed
    for gop in stats["gops"]:
        assert gop["representations"]["qp20"]["render_psnr"] >= 40.0
        assert gop["representations"]["av1q19"]["render_psnr"] >= 40.0


def test_repack_is_byte_identical_and_resume_completes(scene, packed, tmp_path):
    out, _ = packed
    again = tmp_path / "again"
    pack(scene, again, PackConfig(ladder="fixed", qps=QPS, av1_qps=AV1_QPS, jobs=1), progress=False)
    assert tree_digest(again) == tree_digest(out)
    for seg in (next(again.rglob("qp*/seg_00001.m4s")), next(again.rglob("av1q*/seg_00001.m4s"))):
        seg.unlink()
    pack(scene, again, PackConfig(ladder="fixed", qps=QPS, av1_qps=AV1_QPS, resume=True), progress=False)
    assert tree_digest(again) == tree_digest(out)


def test_an_av1_only_tree_has_one_feature_set_and_the_same_av1_bytes(scene, packed, tmp_path):
    out, _ = packed
    alone = tmp_path / "av1"
    stats = pack(scene, alone, PackConfig(ladder="fixed", codecs=("av1",), av1_qps=AV1_QPS, jobs=2), progress=False)
    mpd = parse_mpd((alone / MANIFEST).read_bytes())
    sets = feature_sets(mpd)
    assert list(sets) == ["av1"] and sets["av1"].group is None
    assert sorted(stats["representations"]) == sorted(f"av1q{c}" for c in AV1_QPS)
    both = {Path(*Path(p).parts[1:]): d for p, d in tree_digest(out).items() if "/av1q" in p}
    assert both and {Path(*Path(p).parts[1:]): d for p, d in tree_digest(alone).items() if "/av1q" in p} == both


def test_interrupted_pack_leaves_no_manifest(scene, tmp_path, monkeypatch):
    import stgs.packager.segments as pack_module

    calls = {"n": 0}
    real = pack_module.encode_gop

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(pack_module, "encode_gop", failing)
    out = tmp_path / "dash"
    with pytest.raises(KeyboardInterrupt):
        pack(scene, out, PackConfig(ladder="fixed", qps=QPS, jobs=1), progress=False)
    assert not (out / MANIFEST).exists() and not (out / STATS).exists()
    assert not [p for p in out.rglob(".*") if p.name != ".pack-state.json"], "temp files left behind"


def test_a_pack_killed_at_its_first_segment_resumes(scene, packed, tmp_path, monkeypatch):
    """Outputs used to come before the first state file: a run killed there left a tree --resume refused."""
    import stgs.packager.segments as pack_module

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pack_module, "encode_gop", killed)
    out = tmp_path / "dash"
    with pytest.raises(KeyboardInterrupt):
        pack(scene, out, PackConfig(ladder="fixed", qps=QPS, jobs=1), progress=False)
    assert list(out.rglob("*.stgk")) and (out / ".pack-state.json").is_file()
    monkeypatch.undo()
    pack(scene, out, PackConfig(ladder="fixed", qps=QPS, jobs=2, resume=True), progress=False)
    assert tree_digest(out) == tree_digest(packed[0])


def test_a_gop_file_changed_in_place_changes_the_pack_id(scene, packed, tmp_path):
    def nudge(d: Path) -> None:
        tensors = load_file(str(d / "gop_0001.safetensors"))
        tensors["features"][0, 0, 0] += 0.5
        save_file(tensors, str(d / "gop_0001.safetensors"))

    model = corrupt_copy(scene, tmp_path, nudge)  # model.json untouched
    out = tmp_path / "dash"
    stats = pack(model, out, PackConfig(ladder="fixed", qps=QPS, jobs=2), progress=False)
    assert stats["pack_id"] != packed[1]["pack_id"]
    assert {p.name for p in out.glob("v-*")} == {f"v-{stats['pack_id']}"}


@pytest.mark.parametrize("manifest", [b"<MPD xmlns='urn:mpeg:dash:schema:mpd:2011'/>", b"not even xml"])
def test_a_folder_with_someone_elses_manifest_is_not_overwritten(scene, tmp_path, manifest):
    out = tmp_path / "site"
    out.mkdir()
    (out / "manifest.mpd").write_bytes(manifest)
    (out / "index.html").write_text("their page")
    result = stgs("pack", str(scene), str(out), "--qps", "20", "--quiet")
    assert result.returncode == 2 and "not a tree stgs pack wrote" in result.stderr
    assert sorted(p.name for p in out.iterdir()) == ["index.html", "manifest.mpd"]
    assert (out / "manifest.mpd").read_bytes() == manifest


def test_different_input_gets_new_segment_names(scene, packed, tmp_path):
    out, _ = packed
    other = tmp_path / "other"
    pack(scene, other, PackConfig(ladder="fixed", qps=(20,), jobs=2), progress=False)
    names = {p.relative_to(other).parts[0] for p in other.iterdir()}
    assert not names & {p.relative_to(out).parts[0] for p in out.iterdir() if p.name.startswith("v-")}


def test_no_loop_filters_reaches_every_segment(scene, tmp_path):
    out = tmp_path / "dash"
    result = stgs("pack", str(scene), str(out), "--qps", "20", "--no-loop-filters", "--quiet")
    assert result.returncode == 0, result.stderr
    ladders = json.loads((out / STATS).read_text())["ladders"]  # --qps alone: a fixed ladder
    assert {c: (d["mode"], [x["representation"] for x in d["candidates"]]) for c, d in ladders.items()} == \
        {"hevc": ("fixed", ["qp20"]), "av1": ("fixed", [f"av1q{c}" for c in reversed(AV1_QPS)])}
    video = parse_mpd((out / MANIFEST).read_bytes()).adaptation_set(FEATURE_SCHEME)
    init = (out / video.segment_template.initialization.replace("$RepresentationID$", "qp20")).read_bytes()
    for k in range(SCENE.num_gops):
        media = (out / expand_template(video.segment_template.media, "qp20", k)).read_bytes()
        flags = loop_filter_flags(init + media, tmp_path / f"{k}.mp4")
        assert flags == LOOP_FILTERS_OFF


def corrupt_copy(scene: Path, tmp_path: Path, edit) -> Path:
    import shutil

    dst = tmp_path / "model"
    shutil.copytree(scene, dst)
    edit(dst)
    return dst


def nan_features(d: Path) -> None:
    tensors = load_file(str(d / "gop_0001.safetensors"))
    tensors["features"][0, 0, 0] = float("nan")
    save_file(tensors, str(d / "gop_0001.safetensors"))


def non_square(d: Path) -> None:
    doc = json.loads((d / "model.json").read_text())
    doc["capacity"] = 255
    (d / "model.json").write_text(json.dumps(doc))


@pytest.mark.parametrize("case,message", [
    ("missing", "not a model dir"),
    ("garbage", "not valid JSON"),
    ("non-square", "is not a square"),
    ("nan", "NaN or Inf"),
    ("unwritable", ""),
])
def test_bad_input_is_one_line_and_writes_nothing(scene, tmp_path, case, message):
    model = {"missing": lambda: tmp_path / "nowhere",
             "garbage": lambda: corrupt_copy(scene, tmp_path, lambda d: (d / "model.json").write_text("{")),
             "non-square": lambda: corrupt_copy(scene, tmp_path, non_square),
             "nan": lambda: corrupt_copy(scene, tmp_path, nan_features),
             "unwritable": lambda: scene}[case]()
    if case == "unwritable":
        (tmp_path / "file").write_text("x")
        out = tmp_path / "file" / "dash"
    else:
        out = tmp_path / "dash"
    result = stgs("pack", str(model), str(out), "--qps", "20", "--quiet")
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stgs: ") and message in lines[0]
    assert "Traceback" not in result.stderr
    assert not (out / MANIFEST).exists()
    if case != "nan":  # the NaN sits in GOP 1: GOP 0's segments may exist, never a manifest
        assert not out.exists() or not any(out.rglob("*.m4s"))


def test_pack_cli_rejects_bad_options(scene, tmp_path):
    result = stgs("pack", str(scene), str(tmp_path / "o"), "--qps", "20,99")
    assert result.returncode == 2 and "--qps" in result.stderr
    result = stgs("pack", str(scene), str(tmp_path / "o"), "--codecs", "vp9")
    assert result.returncode == 2 and "--codecs" in result.stderr and "hevc, av1" in result.stderr
    result = stgs("pack", str(scene), str(tmp_path / "o"), "--av1-qps", "0")
    assert result.returncode == 2 and "--av1-qps" in result.stderr and "1..63" in result.stderr
    result = stgs("pack", str(scene), str(tmp_path / "o"), "--ladder", "best")
    assert result.returncode == 2 and "--ladder" in result.stderr and "auto" in result.stderr
    assert not (tmp_path / "o").exists()


def test_defaults_and_what_names_the_output():
    from stgs.codec.video import AV1, HEVC

    cfg = PackConfig()
    assert cfg.ladder == "auto" and cfg.preset == "medium" and cfg.sort and cfg.codecs == ("hevc", "av1")
    assert cfg.loop_filters and cfg.av1_preset == "8"
    assert cfg.points(HEVC) == HEVC.candidates and cfg.points(AV1) == AV1.candidates
    fixed = dataclasses.replace(cfg, ladder="fixed")
    assert fixed.points(HEVC) == QPS and fixed.points(AV1) == AV1_QPS
    assert dataclasses.replace(fixed, qps=(20,)).encodes() == [(HEVC, 20), *((AV1, q) for q in AV1_QPS)]
    assert fixed.digest_fields() != cfg.digest_fields()
    assert dataclasses.replace(cfg, rules=dataclasses.replace(cfg.rules, min_ratio=2.0)).digest_fields() \
        != cfg.digest_fields()
    assert dataclasses.replace(cfg, codecs=("hevc",)).digest_fields() != cfg.digest_fields()
    assert dataclasses.replace(cfg, av1_qps=(20,)).digest_fields() != cfg.digest_fields()
    assert dataclasses.replace(cfg, sort=False).digest_fields() != cfg.digest_fields()
    assert dataclasses.replace(cfg, loop_filters=False).digest_fields() != cfg.digest_fields()
    assert dataclasses.replace(cfg, jobs=7, resume=True).digest_fields() == cfg.digest_fields()


def test_published_files_are_world_readable(packed):
    out, _ = packed
    for path in out.rglob("*"):
        mode = path.stat().st_mode & 0o777
        assert mode & 0o444 == 0o444, f"{path} is {oct(mode)}: a static server of another user cannot read it"


def test_scene_cameras_are_published_beside_the_mpd(scene, packed):
    from stgs.camera import Camera
    from stgs.synth import load_ground_truth
    from stgs.tree import CAMERAS, CAMERAS_FORMAT

    out, _ = packed
    doc = json.loads((out / CAMERAS).read_text())
    assert doc["format"] == CAMERAS_FORMAT and doc["version"] == 1
    published = [Camera.from_json(c) for c in doc["cameras"]]
    truth = load_ground_truth(scene)[1]
    assert [c.name for c in published] == [c.name for c in truth]
    assert all((a.viewmat == b.viewmat).all() and (a.K == b.K).all() for a, b in zip(published, truth, strict=True))


def test_the_scene_face_has_a_poster_from_the_first_camera_mid_first_gop(scene, packed):
    """scene.json names the model dir as the title and a WebP poster: the uncompressed model's middle frame of GOP 0
    at the first scene camera, within the WebP's loss."""
    import cv2

    from stgs.model.renderer import FrameRenderer
    from stgs.model.store import load_gop, read_meta
    from stgs.synth import load_ground_truth
    from stgs.tree import SCENE as SCENE_DOC
    from stgs.tree import SCENE_FORMAT

    out, _ = packed
    doc = json.loads((out / SCENE_DOC).read_text())
    assert doc["format"] == SCENE_FORMAT and doc["title"] == scene.name and doc["description"] == ""
    assert doc["poster"].endswith("/poster.webp") and doc["poster"].startswith("v-")
    cam = load_ground_truth(scene)[1][0]
    assert doc["poster_view"] == {"camera": cam.name, "frame": SCENE.gop_size // 2}
    poster = cv2.cvtColor(cv2.imread(str(out / doc["poster"])), cv2.COLOR_BGR2RGB)
    assert poster.shape == (cam.height, cam.width, 3)
    meta = read_meta(scene)
    truth = FrameRenderer(load_gop(scene, meta, 0)).render(SCENE.gop_size // 2, cam).clamp(0, 1).numpy() * 255
    assert psnr(torch.from_numpy(poster / 255.0), torch.from_numpy(truth / 255.0)) > 30


def test_a_title_and_description_are_kept_as_given_and_a_bad_one_is_one_line(scene, tmp_path):
    from stgs.tree import SCENE as SCENE_DOC

    title, description = "Court <b>one</b> & \"two\"", "Line one\nline <script>two</script>"
    result = stgs("pack", str(scene), str(tmp_path / "o"), "--quiet", "--ladder", "fixed", "--qps", "32",
                  "--codecs", "hevc", "--title", title, "--description", description, "--no-poster")
    assert result.returncode == 0, result.stderr
    doc = json.loads((tmp_path / "o" / SCENE_DOC).read_text())
    assert (doc["title"], doc["description"], doc["poster"]) == (title, description, None)
    assert not list((tmp_path / "o").rglob("*.webp"))
    for args, message in [(("--title", " "), "blank"), (("--title", "x" * 201), "at most 200"),
                          (("--description", "a\x07b"), "control characters")]:
        bad = stgs("pack", str(scene), str(tmp_path / "bad"), "--quiet", *args)
        lines = bad.stderr.strip().splitlines()
        assert bad.returncode == 2 and len(lines) == 1 and args[0] in lines[0] and message in lines[0], bad.stderr
        assert not (tmp_path / "bad").exists()


@pytest.fixture(scope="module")
def auto_packed(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("pack") / "auto"
    result = stgs("pack", str(scene), str(out), "--quiet", "--jobs", "2")
    assert result.returncode == 0, result.stderr
    return out, json.loads((out / STATS).read_text()), result.stdout


def test_the_auto_ladder_keeps_rungs_on_the_hull_and_says_why(auto_packed):
    from stgs.codec.video import AV1, HEVC
    from stgs.mpd.profile import QualityDescriptor

    out, stats, summary = auto_packed
    mpd = parse_mpd((out / MANIFEST).read_bytes())
    for codec in (HEVC, AV1):
        ladder = stats["ladders"][codec.name]
        assert ladder["mode"] == "auto" and set(ladder["rules"]) == {"min_gain_db", "top_gain_db", "min_ratio"}
        keyframe_reps = ["keyframes", *(f"keyframes-{name}" for name in ("fine", "coarse"))]
        assert sorted((c["features"], c["keyframes"]) for c in ladder["candidates"]) == \
            sorted((codec.rep_id(q), kf) for q in codec.candidates for kf in keyframe_reps)
        kept = [c for c in ladder["candidates"] if c["kept"]]
        assert kept and all(c["reason"] for c in ladder["candidates"])
        # the ladder compares what the rungs differ by: bytes above the cheapest keyframes
        cheapest = min(c["total_bytes"] - c["bytes"] for c in ladder["candidates"])
        for below, above in itertools.pairwise(kept):  # ascending bytes, rising quality, spaced
            assert above["total_bytes"] - cheapest >= 1.5 * (below["total_bytes"] - cheapest)
            assert above["render_psnr"] - below["render_psnr"] >= 0.1
        reps = feature_sets(mpd)[codec.name].representations
        assert sorted(r.id for r in reps) == sorted(c["features"] for c in kept) == \
            sorted(r for r in stats["representations"] if r.startswith(codec.rep_id(0)[:-1]))
        paired = {c["features"]: c["keyframes"] for c in kept}
        for rep in reps:
            assert rep.association_id == [paired[rep.id]]
            assert stats["representations"][rep.id]["keyframes"] == paired[rep.id]
            assert QualityDescriptor.parse(rep).render_psnr == pytest.approx(
                stats["representations"][rep.id]["mean_render_psnr"], abs=0.005)
            kept_pair = next(c for c in kept if c["features"] == rep.id)
            assert kept_pair["render_psnr"] == pytest.approx(
                stats["representations"][rep.id]["mean_render_psnr"], abs=0.005)
        assert sorted(r.quality_ranking for r in reps) == list(range(1, len(reps) + 1))
        best = min(reps, key=lambda r: r.quality_ranking)
        assert stats["representations"][best.id]["mean_render_psnr"] == max(
            stats["representations"][r.id]["mean_render_psnr"] for r in reps)
        for c in ladder["candidates"]:
            if not c["kept"]:
                assert f"{c['representation']}  dropped: " in summary
        for rep in {c["features"] for c in ladder["candidates"]} - set(paired):  # no segments of a non-rung
            assert not list(out.rglob(f"features/{rep}"))
    keyframe_set = mpd.adaptation_set(KEYFRAME_SCHEME)
    used = {r.association_id[0] for a in feature_sets(mpd).values() for r in a.representations}
    assert keyframe_set.representations[0].id == "keyframes"
    for rep in keyframe_set.representations:  # a lossy keyframe Representation is there when a rung plays it
        assert (rep.id == "keyframes") == (rep.find_descriptor(KEYFRAME_QUANT_SCHEME) is None)
        assert rep.id == "keyframes" or rep.id in used
        assert stats["keyframe_representations"].get(rep.id, {}).get("quant") == \
            (None if rep.id == "keyframes" else rep.find_descriptor(KEYFRAME_QUANT_SCHEME).value)
    folders = {p.parent.name for p in out.rglob("gop_*.stgk")}
    assert folders == {r.id for r in keyframe_set.representations}
    assert "rendered PSNR against the uncompressed model at 2 sample camera(s)" in summary
    assert stats["quality_views"]["source"] == "sample" and stats["quality_views"]["sizes"] == [[64, 48]] * 2


def test_the_auto_ladder_mpd_is_schema_valid_and_repacks_byte_identically(scene, auto_packed, tmp_path):
    out, _, _ = auto_packed
    if XSD.is_file():
        from stgs.mpd.schema import schema_errors

        assert schema_errors((out / MANIFEST).read_bytes(), XSD) == []
    again = tmp_path / "again"
    pack(scene, again, PackConfig(jobs=1), progress=False)
    assert tree_digest(again) == tree_digest(out)


def test_a_scene_every_rung_renders_the_same_gets_one_rung_per_codec(tmp_path):
    """A GOP that is pure static layer: its dynamic Gaussians are invisible, so every rung draws the same image."""
    from stgs.model.store import load_gop, read_meta, save_gop

    scene = tmp_path / "layered"
    synthesize(dataclasses.replace(SCENE, num_gops=1, fit_steps=20, effects=("rigid", "static_background"),
                                   static_grid_side=12), scene, progress=False)
    meta = read_meta(scene)
    gop = load_gop(scene, meta, 0)
    with torch.no_grad():
        gop.opacity_logit.fill_(-40.0)
    save_gop(gop, scene / meta.gop_files[0], meta.version)
    out = tmp_path / "dash"
    stats = pack(scene, out, PackConfig(jobs=2, keyframe_rungs=()), progress=False)  # the lossless keyframe only
    for codec in ("hevc", "av1"):
        candidates = stats["ladders"][codec]["candidates"]
        psnrs = [c["render_psnr"] for c in candidates]
        assert max(psnrs) - min(psnrs) < 0.05  # under the top rule: the static layer's quantisation is in all alike
        kept = [c for c in candidates if c["kept"]]
        assert len(kept) == 1 and kept[0]["bytes"] == min(c["bytes"] for c in candidates)
    assert len(stats["representations"]) == 2 and "static" in stats
    paired = tmp_path / "paired"  # with keyframe rungs (the default) the pure static GOP still packs a valid tree
    paired_stats = pack(scene, paired, PackConfig(jobs=2, codecs=("av1",)), progress=False)
    assert paired_stats["representations"] and set(paired_stats.get("keyframe_representations", {})) <= {
        "keyframes-fine", "keyframes-coarse"}
    if XSD.is_file():
        from stgs.mpd.schema import schema_errors

        for tree in (out, paired):
            assert schema_errors((tree / MANIFEST).read_bytes(), XSD) == []


def test_a_ladder_of_one_point_is_a_valid_tree(scene, tmp_path):
    out = tmp_path / "one"
    stats = pack(scene, out, PackConfig(qps=(24,), codecs=("hevc",), jobs=2), progress=False)  # auto, one candidate
    assert list(stats["representations"]) == ["qp24"]
    assert [c["features"] for c in stats["ladders"]["hevc"]["candidates"] if c["kept"]] == ["qp24"]
    if XSD.is_file():
        from stgs.mpd.schema import schema_errors

        assert schema_errors((out / MANIFEST).read_bytes(), XSD) == []
