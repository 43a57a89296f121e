"""Validate MPDs against the ISO/IEC 23009-1 XML schema, offline.

The schema imports the W3C xlink and xml schemas by URL; a resolver maps
those URLs to local copies kept beside DASH-MPD.xsd, and the parser never
touches the network.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from lxml import etree

W3C_FILES = {
    "http://www.w3.org/XML/2008/06/xlink.xsd": "xlink.xsd",
    "http://www.w3.org/1999/xlink.xsd": "xlink.xsd",
    "http://www.w3.org/2001/xml.xsd": "xml.xsd",
    "http://www.w3.org/2009/01/xml.xsd": "xml.xsd",
}


class _LocalW3C(etree.Resolver):
    def __init__(self, folder: Path):
        super().__init__()
        self.folder = folder

    def resolve(self, url, pubid, context):
        name = W3C_FILES.get(url)
        if name is not None:
            return self.resolve_filename(str(self.folder / name), context)
        return None


@lru_cache(maxsize=4)
def load_schema(xsd_path: Path) -> etree.XMLSchema:
    """The compiled DASH MPD schema at xsd_path (xlink.xsd and xml.xsd beside it)."""
    xsd_path = Path(xsd_path)
    parser = etree.XMLParser(load_dtd=True, resolve_entities=True, no_network=True)
    parser.resolvers.add(_LocalW3C(xsd_path.parent))
    return etree.XMLSchema(etree.parse(str(xsd_path), parser))


def schema_errors(mpd_xml: bytes, xsd_path: Path) -> list[str]:
    """Validation errors of an MPD document (empty when it is valid)."""
    schema = load_schema(Path(xsd_path))
    doc = etree.fromstring(mpd_xml, etree.XMLParser(resolve_entities=False, no_network=True))
    if schema.validate(doc):
        return []
    return [f"line {e.line}: {e.message}" for e in schema.error_log]
