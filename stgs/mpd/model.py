"""The MPEG-DASH MPD model: the one place that builds and parses manifest XML.

Dataclasses mirror the subset of ISO/IEC 23009-1 that StreamSTGS uses (a
static MPD, Periods, AdaptationSets with a SegmentTemplate, Representations,
descriptors); `to_xml` builds the document with lxml and `parse_mpd` reads one
back with a hardened parser (no DTDs, no entities, no network). Its XML values (durations, bounded
integers, segment URL templates) and MPDError are in stgs.mpd.values. The StreamSTGS
profile's own descriptors, carried in it, are in stgs.mpd.profile.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lxml import etree

from stgs.errors import MPDError
from stgs.limits import MAX_MPD_BYTES
from stgs.mpd.values import (
    format_duration,
    int_attr,
    optional_int_attr,
    parse_duration,
    required_attr,
    secure_parser,
)

NS = "urn:mpeg:dash:schema:mpd:2011"
PROFILE_LIVE = "urn:mpeg:dash:profile:isoff-live:2011"
"""Segment-template addressing of separate init and media segments."""
PROFILE_STGS = "urn:streamstgs:profile:2026"
"""The StreamSTGS-over-DASH profile (manifests/PROFILE.md)."""


def _q(tag: str) -> str:
    return f"{{{NS}}}{tag}"


@dataclass
class Descriptor:
    """A DASH descriptor (SupplementalProperty, EssentialProperty, Role)."""

    scheme_id_uri: str
    """@schemeIdUri."""
    value: str | None = None
    """@value."""

    def to_element(self, tag: str) -> etree._Element:
        el = etree.Element(_q(tag), schemeIdUri=self.scheme_id_uri)
        if self.value is not None:
            el.set("value", self.value)
        return el

    @classmethod
    def from_element(cls, el: etree._Element) -> Descriptor:
        return cls(required_attr(el, "schemeIdUri"), el.get("value"))

    def fields(self) -> dict[str, str]:
        """@value read as `key=value;key=value` (this profile's descriptors), stripped."""
        out = {}
        for item in (self.value or "").split(";"):
            if "=" in item:
                key, _, val = item.partition("=")
                out[key.strip()] = val.strip()
        return out


@dataclass
class SegmentTemplate:
    """Number-based segment addressing: segment k covers [k - startNumber] * duration."""

    media: str
    """Media URL template ($RepresentationID$, $Number$ with optional %0Nd)."""
    timescale: int
    """Ticks per second."""
    duration: int
    """Segment duration in ticks."""
    start_number: int = 0
    """$Number$ of the first segment."""
    initialization: str | None = None
    """Init segment URL template, if any."""

    def to_element(self) -> etree._Element:
        el = etree.Element(_q("SegmentTemplate"), media=self.media, timescale=str(self.timescale),
                           duration=str(self.duration), startNumber=str(self.start_number))
        if self.initialization is not None:
            el.set("initialization", self.initialization)
        return el

    @classmethod
    def from_element(cls, el: etree._Element) -> SegmentTemplate:
        return cls(required_attr(el, "media"), int_attr(el, "timescale", 1, lo=1), int_attr(el, "duration", lo=1),
                   int_attr(el, "startNumber", 1), el.get("initialization"))

    @property
    def seconds(self) -> float:
        """Segment duration in seconds."""
        return self.duration / self.timescale


@dataclass
class Representation:
    """One encoding of an AdaptationSet's content."""

    id: str
    """@id, also $RepresentationID$."""
    bandwidth: int
    """@bandwidth in bit/s."""
    codecs: str | None = None
    """RFC 6381 codecs string."""
    width: int | None = None
    height: int | None = None
    frame_rate: str | None = None
    """@frameRate, e.g. '31' or '30000/1001'."""
    association_id: list[str] = field(default_factory=list)
    """@associationId: Representations this one is tied to."""
    association_type: list[str] = field(default_factory=list)
    """@associationType: one 4CC per associationId entry."""
    quality_ranking: int | None = None
    """@qualityRanking: lower is better, among the AdaptationSet's Representations."""
    supplemental: list[Descriptor] = field(default_factory=list)
    """SupplementalProperty descriptors."""

    def to_element(self) -> etree._Element:
        el = etree.Element(_q("Representation"), id=self.id, bandwidth=str(self.bandwidth))
        for attr, value in (("qualityRanking", self.quality_ranking), ("codecs", self.codecs),
                            ("width", self.width), ("height", self.height), ("frameRate", self.frame_rate)):
            if value is not None:
                el.set(attr, str(value))
        if self.association_id:
            el.set("associationId", " ".join(self.association_id))
            el.set("associationType", " ".join(self.association_type))
        for d in self.supplemental:
            el.append(d.to_element("SupplementalProperty"))
        return el

    @classmethod
    def from_element(cls, el: etree._Element) -> Representation:
        return cls(required_attr(el, "id"), int_attr(el, "bandwidth"), el.get("codecs"),
                   optional_int_attr(el, "width"), optional_int_attr(el, "height"), el.get("frameRate"),
                   (el.get("associationId") or "").split(), (el.get("associationType") or "").split(),
                   optional_int_attr(el, "qualityRanking"),
                   [Descriptor.from_element(d) for d in el.findall(_q("SupplementalProperty"))])

    def find_descriptor(self, scheme: str) -> Descriptor | None:
        """The first SupplementalProperty with `scheme`, or None."""
        return next((d for d in self.supplemental if d.scheme_id_uri == scheme), None)


@dataclass
class AdaptationSet:
    """A set of interchangeable Representations of one content component."""

    id: int
    content_type: str
    """@contentType, e.g. 'video' or 'application'."""
    mime_type: str
    """@mimeType of every Representation."""
    segment_template: SegmentTemplate
    representations: list[Representation]
    supplemental: list[Descriptor] = field(default_factory=list)
    """SupplementalProperty descriptors."""
    codecs: str | None = None
    segment_alignment: bool = True
    """@segmentAlignment: segment k of every Representation covers the same time."""
    group: int | None = None
    """@group: AdaptationSets of one group are alternatives, a player presents one of them."""

    def to_element(self) -> etree._Element:
        el = etree.Element(_q("AdaptationSet"), id=str(self.id), contentType=self.content_type,
                           mimeType=self.mime_type)
        if self.group is not None:
            el.set("group", str(self.group))
        if self.codecs:
            el.set("codecs", self.codecs)
        el.set("segmentAlignment", "true" if self.segment_alignment else "false")
        el.set("startWithSAP", "1")
        for d in self.supplemental:
            el.append(d.to_element("SupplementalProperty"))
        el.append(self.segment_template.to_element())
        for rep in self.representations:
            el.append(rep.to_element())
        return el

    @classmethod
    def from_element(cls, el: etree._Element) -> AdaptationSet:
        template = el.find(_q("SegmentTemplate"))
        if template is None:
            raise MPDError(f"AdaptationSet {el.get('id')!r} has no SegmentTemplate")
        return cls(int_attr(el, "id"), el.get("contentType") or "", required_attr(el, "mimeType"),
                   SegmentTemplate.from_element(template),
                   [Representation.from_element(r) for r in el.findall(_q("Representation"))],
                   [Descriptor.from_element(d) for d in el.findall(_q("SupplementalProperty"))],
                   el.get("codecs"), el.get("segmentAlignment") == "true",
                   int_attr(el, "group") if el.get("group") is not None else None)

    def has_scheme(self, scheme: str) -> bool:
        return any(d.scheme_id_uri == scheme for d in self.supplemental)

    def descriptor(self, scheme: str) -> Descriptor:
        """The first SupplementalProperty with `scheme`."""
        for d in self.supplemental:
            if d.scheme_id_uri == scheme:
                return d
        raise MPDError(f"AdaptationSet {self.id} has no SupplementalProperty {scheme}")


@dataclass
class Period:
    id: str
    adaptation_sets: list[AdaptationSet]
    start: float = 0.0

    def to_element(self) -> etree._Element:
        el = etree.Element(_q("Period"), id=self.id, start=format_duration(self.start))
        for a in self.adaptation_sets:
            el.append(a.to_element())
        return el

    @classmethod
    def from_element(cls, el: etree._Element) -> Period:
        start = el.get("start")
        return cls(el.get("id") or "", [AdaptationSet.from_element(a) for a in el.findall(_q("AdaptationSet"))],
                   parse_duration(start) if start else 0.0)


@dataclass
class MPD:
    """A static Media Presentation Description."""

    duration: float
    """@mediaPresentationDuration in seconds."""
    min_buffer_time: float
    """@minBufferTime in seconds."""
    periods: list[Period]
    profiles: list[str] = field(default_factory=lambda: [PROFILE_LIVE, PROFILE_STGS])
    base_url: str | None = None
    """A BaseURL element, if any (relative URLs resolve against the MPD's URL)."""

    def to_xml(self) -> bytes:
        root = etree.Element(_q("MPD"), nsmap={None: NS}, type="static",
                             profiles=",".join(self.profiles),
                             mediaPresentationDuration=format_duration(self.duration),
                             minBufferTime=format_duration(self.min_buffer_time))
        if self.base_url:
            etree.SubElement(root, _q("BaseURL")).text = self.base_url
        for p in self.periods:
            root.append(p.to_element())
        return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)

    def adaptation_set(self, scheme: str) -> AdaptationSet:
        """The first AdaptationSet of the first Period marked with `scheme`."""
        found = self.find_adaptation_set(scheme)
        if found is None:
            raise MPDError(f"no AdaptationSet with SupplementalProperty {scheme}")
        return found

    def find_adaptation_set(self, scheme: str) -> AdaptationSet | None:
        """The first AdaptationSet of the first Period marked with `scheme`, or None."""
        found = self.adaptation_sets(scheme)
        return found[0] if found else None

    def adaptation_sets(self, scheme: str) -> list[AdaptationSet]:
        """Every AdaptationSet of the first Period marked with `scheme`, in document order."""
        return [a for a in (self.periods[0].adaptation_sets if self.periods else ()) if a.has_scheme(scheme)]


def parse_mpd(data: bytes) -> MPD:
    """Parse a static MPD (bounded size, hardened parser)."""
    if len(data) > MAX_MPD_BYTES:
        raise MPDError(f"manifest is {len(data)} bytes, over the {MAX_MPD_BYTES}-byte limit")
    try:
        root = etree.fromstring(data, secure_parser())
    except etree.XMLSyntaxError as exc:
        raise MPDError(f"manifest is not well-formed XML ({exc})") from exc
    if root.tag != _q("MPD"):
        raise MPDError("not an MPEG-DASH MPD (root element is not MPD in the DASH namespace)")
    if root.get("type", "static") != "static":
        raise MPDError("only static MPDs are supported")
    base = root.find(_q("BaseURL"))
    return MPD(parse_duration(required_attr(root, "mediaPresentationDuration")),
               parse_duration(required_attr(root, "minBufferTime")),
               [Period.from_element(p) for p in root.findall(_q("Period"))],
               (root.get("profiles") or "").split(","),
               base.text.strip() if base is not None and base.text else None)


def read_mpd(path: Path) -> MPD:
    """Parse the MPD file at `path`, reading no more of it than parse_mpd accepts."""
    with open(path, "rb") as f:
        return parse_mpd(f.read(MAX_MPD_BYTES + 1))


