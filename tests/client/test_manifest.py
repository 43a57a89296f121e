"""The client's view of an MPD: scheme lookup, descriptor caps, URL resolution."""

from __future__ import annotations

from pathlib import Path

import pytest

from stgs.client.manifest import Presentation
from stgs.errors import MPDError
from stgs.limits import MAX_CAPACITY

EXAMPLE = (Path(__file__).resolve().parents[2] / "manifests" / "example.mpd").read_bytes()


def test_example_resolves_every_segment_url_against_the_mpd_url():
    p = Presentation.parse(EXAMPLE, "http://cdn.example/scenes/a/manifest.mpd?token=1")
    assert p.shape.capacity == 1024 and p.grid_side == 32 and p.shape.gop_size == 30 and p.fps == 30
    assert p.num_gops == 2 and p.segment_seconds == 1.0
    assert [r.qp for r in p.ladder] == [32, 28, 24, 20, 16]  # ascending bandwidth, the HEVC set's
    assert [r.rep_id for r in Presentation.parse(EXAMPLE, "http://h/m.mpd", "av1").ladder] == [
        "av1q43", "av1q35", "av1q27", "av1q19", "av1q12"]
    version = "v-e849cc0b184d"
    assert p.keyframe_url(1) == f"http://cdn.example/scenes/a/{version}/keyframes/gop_00001.stgk"
    assert p.init_url("qp20") == f"http://cdn.example/scenes/a/{version}/features/qp20/init.mp4"
    assert p.media_url("qp20", 0) == f"http://cdn.example/scenes/a/{version}/features/qp20/seg_00000.m4s"
    assert p.sibling_url("stats.json") == "http://cdn.example/scenes/a/stats.json"
    with pytest.raises(MPDError, match="GOP 2 is outside"):
        p.media_url("qp20", 2)


@pytest.mark.parametrize("base,expected", [
    ("https://other.example/store/", "https://other.example/store/"),
    ("../shared/", "http://cdn.example/scenes/shared/"),
])
def test_base_url(base, expected):
    mpd = EXAMPLE.replace(b'<Period id="0"', f"<BaseURL>{base}</BaseURL>\n  <Period id=\"0\"".encode())
    p = Presentation.parse(mpd, "http://cdn.example/scenes/a/manifest.mpd")
    assert p.keyframe_url(0).startswith(expected + "v-")


@pytest.mark.parametrize("gops,gop_size,fps", [(2, 4, 30.0), (3, 7, 29.97), (5, 60, 30.0), (1, 2, 240.0)])
def test_gop_count_survives_millisecond_durations(gops, gop_size, fps):
    from stgs.mpd.values import format_duration

    ticks = round(gop_size / fps * 90000)
    mpd = (EXAMPLE.replace(b'mediaPresentationDuration="PT2S"',
                           f'mediaPresentationDuration="{format_duration(gops * gop_size / fps)}"'.encode())
           .replace(b'timescale="1024" duration="1024"', f'timescale="90000" duration="{ticks}"'.encode()))
    assert Presentation.parse(mpd, "http://h/m.mpd").num_gops == gops


def test_start_time_maps_to_its_gop():
    p = Presentation.parse(EXAMPLE, "http://h/m.mpd")
    assert [p.gop_at(t) for t in (0, 0.99, 1.0, 1.5, 99)] == [0, 0, 1, 1, 1]


def test_segment_caps_follow_bandwidth():
    p = Presentation.parse(EXAMPLE, "http://h/m.mpd")
    assert p.max_media_bytes("qp16") > 751936 / 8  # one second at @bandwidth, with slack
    assert p.max_media_bytes("qp16") < 751936 / 8 * 1.5
    with pytest.raises(MPDError, match="no feature Representation 'qp99'"):
        p.max_media_bytes("qp99")


@pytest.mark.parametrize("edit,message", [
    ((b"urn:streamstgs:profile:2026", b"urn:other:profile"), "not a StreamSTGS manifest"),
    ((b"urn:streamstgs:keyframe:2026", b"urn:other:keyframe"), "no AdaptationSet with SupplementalProperty"),
    ((b"capacity=1024;grid_side=32", f"capacity={MAX_CAPACITY * 4};grid_side=4096".encode()), "client limit"),
    ((b"grid_side=32", b"grid_side=31"), "does not match capacity"),
    ((b"gop_size=30", b"gop_size=x"), "lacks an integer gop_size"),
    ((b"version=1;capacity=1024", b"version=2;capacity=1024"), "keyframe descriptor version '2' is not supported"),
    ((b"window=3", b"window=0"), r"keyframe descriptor window=0 is outside 1\.\."),
    ((b"fps=30", b"fps=nan"), "keyframe descriptor fps=nan is outside"),
    ((b";fps=30", b""), "keyframe descriptor lacks fps"),
    ((b'type="static"', b'type="dynamic"'), "only static"),
    ((b"<MPD ", b"<NotMPD "), "not well-formed"),
    # numeric edge cases: each was a ZeroDivisionError, OverflowError or ValueError traceback
    ((b'timescale="1024"', b'timescale="0"'), r"SegmentTemplate@timescale is 0, outside 1\.\.4294967295"),
    ((b'duration="1024"', b'duration="0"'), r"SegmentTemplate@duration is 0, outside 1\.\."),
    ((b'mediaPresentationDuration="PT2S"', b'mediaPresentationDuration="PT' + b"9" * 400 + b'S"'),
     "unsupported duration"),
    ((b'mediaPresentationDuration="PT2S"', b'mediaPresentationDuration="P' + b"9" * 5000 + b'D"'),
     "unsupported duration"),
    ((b'mediaPresentationDuration="PT2S"', b'mediaPresentationDuration="P999999999D"'), "over the .*-second limit"),
    ((b'bandwidth="751936"', b'bandwidth="' + b"9" * 400 + b'"'), "not an integer of at most 20 digits"),
    ((b'bandwidth="751936"', b'bandwidth="99999999999"'), r"Representation@bandwidth is 99999999999, outside"),
    ((b'bandwidth="751936"', b'bandwidth="-5"'), r"Representation@bandwidth is -5, outside"),
    # the feature sets: a codec this client does not play, a depth that is not the codec's, two sets of one codec
    ((b'codecs="av01.0.00M.10" width="128" height="128" frameRate="32" associationId="keyframes" '
      b'associationType="cdsc"/>\n    </AdaptationSet>', b'codecs="vp09.02.10.12" width="128" height="128" '
      b'frameRate="32"/>\n    </AdaptationSet>'), "is not one codec this client plays"),
    ((b"bits=10", b"bits=11"), "this client dequantises 12 or 10-bit codes"),
    ((b"bits=10", b"bits=12"), "av1 carries 10-bit codes, its descriptor says bits=12"),
    ((b"tiles=4x4;channels=16;bits=10", b"tiles=2x8;channels=16;bits=10"), "is not the 4x4 tiling"),
    ((b'codecs="av01.0.00M.10"', b'codecs="hvc1.4.10.L30.99.C8"'), "hevc carries 12-bit codes, its descriptor says "
                                                                    "bits=10"),
])
def test_refuses_what_is_not_this_profile(edit, message):
    with pytest.raises(MPDError, match=message):
        Presentation.parse(EXAMPLE.replace(*edit), "http://h/m.mpd")


def test_two_feature_sets_of_one_codec_are_refused():
    mpd = EXAMPLE.replace(b'codecs="av01.0.00M.10"', b'codecs="hvc1.4.10.L30.99.C8"').replace(b"bits=10", b"bits=12")
    with pytest.raises(MPDError, match=r"two feature AdaptationSets \(2, 3\) of one codec, hevc"):
        Presentation.parse(mpd, "http://h/m.mpd")


COARSE = "position=8;scale=4;rotation=4;opacity=3;color=6;field=4"


def paired_example(quant: str = COARSE, names: str = "keyframes-coarse") -> bytes:
    """example.mpd with a lossy keyframe Representation that the two lowest HEVC rungs play with."""
    lossy = (f'<Representation id="keyframes-coarse" bandwidth="200000"><SupplementalProperty '
             f'schemeIdUri="urn:streamstgs:keyframe-quant:2026" value="{quant}"/></Representation>')
    mpd = EXAMPLE.replace(b"v-e849cc0b184d/keyframes/gop_", b"v-e849cc0b184d/$RepresentationID$/gop_")
    mpd = mpd.replace(b'<Representation id="keyframes" bandwidth="780016"/>',
                          b'<Representation id="keyframes" bandwidth="780016"/>' + lossy.encode())
    mpd = mpd.replace(b'"qp28" bandwidth="186776" codecs="hvc1.4.10.L30.99.C8" width="128" height="128" '
                      b'frameRate="32" associationId="keyframes"',
                      b'"qp28" bandwidth="186776" codecs="hvc1.4.10.L30.99.C8" width="128" height="128" '
                      b'frameRate="32" associationId="' + names.encode() + b'"')
    return mpd.replace(b'"qp32" bandwidth="102872" codecs="hvc1.4.10.L30.99.C8" width="128" height="128" '
                       b'frameRate="32" associationId="keyframes"',
                       b'"qp32" bandwidth="102872" codecs="hvc1.4.10.L30.99.C8" width="128" height="128" '
                       b'frameRate="32" associationId="keyframes-coarse"')


def test_a_rung_plays_with_the_keyframe_representation_it_names():
    from stgs.codec.quant import KEYFRAME_RUNGS, LOSSLESS

    p = Presentation.parse(paired_example(), "http://h/s/manifest.mpd")
    assert [(r.rep_id, r.keyframe_rep) for r in p.ladder] == [
        ("qp32", "keyframes-coarse"), ("qp28", "keyframes-coarse"), ("qp24", "keyframes"), ("qp20", "keyframes"),
        ("qp16", "keyframes")]
    assert p.keyframe_quants == {"keyframes": LOSSLESS, "keyframes-coarse": KEYFRAME_RUNGS["coarse"]}
    assert p.keyframe_url(1, "keyframes-coarse") == "http://h/s/v-e849cc0b184d/keyframes-coarse/gop_00001.stgk"
    assert p.keyframe_url(1) == "http://h/s/v-e849cc0b184d/keyframes/gop_00001.stgk"
    assert p.max_keyframe_bytes("keyframes-coarse") < p.max_keyframe_bytes()
    # a rule weighs each rung's features plus its keyframes beyond the cheapest
    assert p.abr_bandwidths() == [102872, 186776, 314432 + 580016, 502592 + 580016, 751936 + 580016]
    with pytest.raises(MPDError, match="no keyframe Representation"):
        p.keyframe_url(0, "keyframes-fine")


@pytest.mark.parametrize("quant,names,match", [
    ("position=17;scale=4;rotation=4;opacity=3;color=6;field=4", "keyframes-coarse", "position"),
    ("bits=8", "keyframes-coarse", "quant"),
    (COARSE, "keyframes-fine", "must name one keyframe Representation"),
    (COARSE, "keyframes keyframes-coarse", "must name one keyframe Representation"),
])
def test_a_bad_keyframe_pairing_is_refused(quant, names, match):
    with pytest.raises(MPDError, match=match):
        Presentation.parse(paired_example(quant, names), "http://h/m.mpd")
