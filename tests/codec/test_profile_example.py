"""manifests/example.mpd, example-layered.mpd and example-still.mpd: valid DASH, and a StreamSTGS profile the parsers
accept."""

from __future__ import annotations

from pathlib import Path

import pytest

from stgs.mpd.model import PROFILE_STGS, parse_mpd
from stgs.mpd.profile import FEATURE_SCHEME, KEYFRAME_SCHEME
from tests.conftest import SHARED

EXAMPLE = Path(__file__).resolve().parents[2] / "manifests" / "example.mpd"
LAYERED = EXAMPLE.with_name("example-layered.mpd")
STILL = EXAMPLE.with_name("example-still.mpd")


@pytest.mark.parametrize("example", [EXAMPLE, LAYERED, STILL], ids=["format1", "layered", "still"])
def test_example_validates_against_the_schema(example):
    xsd = SHARED / "dash" / "DASH-MPD.xsd"
    if not xsd.is_file():
        pytest.skip("../shared/dash is absent")
    from stgs.mpd.schema import schema_errors

    assert schema_errors(example.read_bytes(), xsd) == []


def test_layered_example_parses_with_its_static_layer():
    from stgs.client.manifest import Presentation

    pres = Presentation.parse(LAYERED.read_bytes(), "http://example.org/scene/manifest.mpd")
    assert pres.static.capacity == 1024 and pres.static.sh_degree == 0 and pres.shape.capacity == 4096
    assert pres.static_url() == "http://example.org/scene/v-9bf733199119/static/layer.stgl"
    assert Presentation.parse(EXAMPLE.read_bytes(), "http://example.org/manifest.mpd").static is None


def test_still_example_parses_as_a_still_scene():
    from stgs.client.manifest import StillPresentation, open_presentation

    pres = open_presentation(STILL.read_bytes(), "http://example.org/still/manifest.mpd")
    assert isinstance(pres, StillPresentation) and pres.static.capacity == 576 and pres.mpd.duration == 1
    assert pres.static_url() == "http://example.org/still/v-8b3785a5d4bd/static/layer.stgl"
    assert not isinstance(open_presentation(LAYERED.read_bytes(), "http://example.org/manifest.mpd"),
                          StillPresentation)


def test_example_parses_as_the_profile():
    mpd = parse_mpd(EXAMPLE.read_bytes())
    assert PROFILE_STGS in mpd.profiles
    kf = mpd.adaptation_set(KEYFRAME_SCHEME)
    assert kf.representations[0].id == "keyframes"
    assert "grid_side=32" in kf.supplemental[0].value
    hevc, av1 = mpd.adaptation_sets(FEATURE_SCHEME)
    assert [r.id for r in hevc.representations] == ["qp16", "qp20", "qp24", "qp28", "qp32"]
    assert [r.id for r in av1.representations] == ["av1q12", "av1q19", "av1q27", "av1q35", "av1q43"]
    assert hevc.group == av1.group == 2 and all(r.codecs == "av01.0.00M.10" for r in av1.representations)
    from stgs.client.manifest import Presentation

    for codec, first in (("auto", "qp"), ("hevc", "qp"), ("av1", "av1q")):
        pres = Presentation.parse(EXAMPLE.read_bytes(), "http://example.org/manifest.mpd", codec)
        assert all(r.rep_id.startswith(first) for r in pres.ladder) and len(pres.ladder) == 5
