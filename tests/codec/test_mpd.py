"""The MPD model: durations, templates, round trips, hostile input."""

from __future__ import annotations

import pytest

from stgs.mpd.model import (
    MPD,
    AdaptationSet,
    Descriptor,
    MPDError,
    Period,
    Representation,
    SegmentTemplate,
    parse_mpd,
)
from stgs.mpd.profile import KEYFRAME_SCHEME
from stgs.mpd.values import format_duration, parse_duration
from stgs.tree import expand_template


@pytest.mark.parametrize("seconds,text", [(0, "PT0S"), (2, "PT2S"), (2.5, "PT2.5S"), (61.25, "PT1M1.25S"),
                                          (3723, "PT1H2M3S")])
def test_durations_round_trip(seconds, text):
    assert format_duration(seconds) == text
    assert parse_duration(text) == pytest.approx(seconds)


def test_duration_errors():
    for bad in ("", "P", "PT", "2S", "P1Y"):
        with pytest.raises(MPDError):
            parse_duration(bad)
    with pytest.raises(ValueError):
        format_duration(-1)


@pytest.mark.parametrize("template,rep,number,want", [
    ("v/$RepresentationID$/seg_$Number%05d$.m4s", "qp20", 7, "v/qp20/seg_00007.m4s"),
    ("$RepresentationID$/$Number$.m4s", "a", 123, "a/123.m4s"),
    ("cost$$/$Number%03d$", "a", 5, "cost$/005"),
])
def test_expand_template(template, rep, number, want):
    assert expand_template(template, rep, number) == want


def test_expand_template_rejects_unknown_identifiers():
    with pytest.raises(MPDError, match="unsupported"):
        expand_template("$Time$.m4s", "a", 1)
    with pytest.raises(MPDError, match="format tag"):
        expand_template("$Number%5x$.m4s", "a", 1)


def test_number_width_is_capped():
    """$Number%0999999999d$ once took the player to 7.2 GB; a 20-digit width was an OverflowError."""
    assert expand_template("$Number%032d$", "a", 7) == "0" * 31 + "7"
    for tag in ("%033d", "%0999999999d", "%099999999999999999999d"):
        with pytest.raises(MPDError, match="over the limit"):
            expand_template(f"$Number{tag}$", "a", 1)


def sample_mpd() -> MPD:
    kf = AdaptationSet(1, "application", "application/vnd.streamstgs.keyframe",
                       SegmentTemplate("k/$Number%05d$.stgk", 1000, 2000, 0),
                       [Representation("keyframes", 800_000)], [Descriptor(KEYFRAME_SCHEME, "version=1")])
    video = AdaptationSet(2, "video", "video/mp4",
                          SegmentTemplate("f/$RepresentationID$/$Number$.m4s", 1000, 2000, 0,
                                          "f/$RepresentationID$/init.mp4"),
                          [Representation("qp20", 1_000_000, "hvc1.4.10.L30.99.C8", 128, 128, "31",
                                          ["keyframes"], ["cdsc"])])
    return MPD(4.0, 2.0, [Period("0", [kf, video])])


def test_round_trip():
    mpd = sample_mpd()
    back = parse_mpd(mpd.to_xml())
    assert back == mpd
    assert back.adaptation_set(KEYFRAME_SCHEME).representations[0].id == "keyframes"
    assert back.periods[0].adaptation_sets[1].segment_template.seconds == 2.0


def test_parse_rejects_hostile_or_foreign_documents():
    xxe = (b'<?xml version="1.0"?><!DOCTYPE MPD [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
           b'<MPD xmlns="urn:mpeg:dash:schema:mpd:2011" mediaPresentationDuration="PT1S" minBufferTime="PT1S">'
           b'<BaseURL>&x;</BaseURL></MPD>')
    mpd = parse_mpd(xxe)
    assert mpd.base_url is None or "root:" not in mpd.base_url  # the entity is never expanded
    with pytest.raises(MPDError, match="not an MPEG-DASH MPD"):
        parse_mpd(b"<html/>")
    with pytest.raises(MPDError, match="well-formed"):
        parse_mpd(b"<MPD")
    with pytest.raises(MPDError, match="limit"):
        parse_mpd(b" " * (2 << 20))
    dynamic = sample_mpd().to_xml().replace(b'type="static"', b'type="dynamic"')
    with pytest.raises(MPDError, match="static"):
        parse_mpd(dynamic)


def test_template_number_width_is_capped():
    assert expand_template("seg_$Number%032d$.m4s", "r", 7) == f"seg_{7:032d}.m4s"
    for width in ("033", "0999999999", "099999999999999999999"):
        with pytest.raises(MPDError, match="over the limit"):
            expand_template(f"seg_$Number%{width}d$.m4s", "r", 7)


def test_the_quality_descriptor_round_trips_and_refuses_what_is_not_a_db_figure():
    from stgs.mpd.profile import QUALITY_SCHEME, QualityDescriptor

    def rep(value: str | None) -> Representation:
        extra = [] if value is None else [Descriptor(QUALITY_SCHEME, value)]
        return Representation("qp20", 1000, quality_ranking=2, supplemental=extra)

    written = rep(QualityDescriptor(44.8434, 26.7054).value)
    parsed = parse_mpd(MPD(1.0, 1.0, [Period("0", [AdaptationSet(
        2, "video", "video/mp4", SegmentTemplate("$RepresentationID$/$Number$.m4s", 1, 1), [written])])])
        .to_xml()).periods[0].adaptation_sets[0].representations[0]
    assert parsed.quality_ranking == 2
    assert QualityDescriptor.parse(parsed) == QualityDescriptor(44.84, 26.71)
    assert QualityDescriptor.parse(rep("render_psnr=31.5")) == QualityDescriptor(31.5, None)
    assert QualityDescriptor.parse(rep(None)) is None  # a tree written before the descriptor
    for bad in ("render_psnr=nan", "render_psnr=1e3", "render_psnr=-1", "render_psnr=100", "truth_psnr=30",
                "render_psnr=30;truth_psnr=inf"):
        with pytest.raises(MPDError, match="quality descriptor of Representation qp20"):
            QualityDescriptor.parse(rep(bad))
