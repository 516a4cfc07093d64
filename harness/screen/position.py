"""Where a capture was taken: GPS and attitude from the XMP packet DJI writes into every JPEG.

DJI stores them as attributes (or elements) of the ``drone-dji`` namespace (``http://www.dji.com/drone-dji/1.0/``)
in an APP1 segment that starts with ``http://ns.adobe.com/xap/1.0/\\0``: ``GpsLatitude``, ``GpsLongitude`` (degrees,
WGS84), ``AbsoluteAltitude`` and ``RelativeAltitude`` (m, written with a sign, ``+103.45``), ``GimbalYawDegree``,
``GimbalPitchDegree``, ``GimbalRollDegree`` and ``FlightYawDegree`` (degrees). exiftool reads the same fields as
``XMP-drone-dji:*``. A field a file lacks, or whose text is not a finite number, is missing (``None``), never 0.

``add_xmp`` writes such a packet into a JPEG (the synthetic flights of the tests and benchmarks).
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import asdict, dataclass
from typing import Any, Mapping
from xml.etree import ElementTree

from harness.sensing import jpeg

XMP_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"
DJI_NS = "http://www.dji.com/drone-dji/1.0/"
#: our field -> DJI's XMP name
FIELDS = {
    "lat": "GpsLatitude", "lon": "GpsLongitude", "alt_abs": "AbsoluteAltitude", "alt_rel": "RelativeAltitude",
    "gimbal_yaw": "GimbalYawDegree", "gimbal_pitch": "GimbalPitchDegree", "gimbal_roll": "GimbalRollDegree",
    "flight_yaw": "FlightYawDegree",
}


@dataclass(frozen=True)
class Position:
    """GPS (degrees, metres) and attitude (degrees) of one capture; ``None`` where the file does not say."""

    lat: float | None = None
    lon: float | None = None
    alt_abs: float | None = None
    alt_rel: float | None = None
    gimbal_yaw: float | None = None
    gimbal_pitch: float | None = None
    gimbal_roll: float | None = None
    flight_yaw: float | None = None

    @property
    def has_gps(self) -> bool:
        return self.lat is not None and self.lon is not None

    def to_dict(self) -> dict[str, float | None]:
        return asdict(self)

    def merged(self, other: "Position") -> "Position":
        """This position with its missing fields taken from ``other``."""
        mine, theirs = self.to_dict(), other.to_dict()
        return Position(**{k: mine[k] if mine[k] is not None else theirs[k] for k in mine})


def _number(text: str | None) -> float | None:
    if text is None:
        return None
    try:
        value = float(text.strip())
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def xmp_packets(data: bytes, name: str = "<bytes>", layout: jpeg.JpegLayout | None = None) -> list[bytes]:
    """The XMP packets in a JPEG's header segments (``DataError`` when ``data`` is not a JPEG); ``layout``: the
    file's ``jpeg.read_segments`` when already read."""
    if layout is None:
        layout = jpeg.read_segments(data, name, require_eoi=False)
    return [p[len(XMP_HEADER):] for p in layout.payloads(jpeg.APP1) if p.startswith(XMP_HEADER)]


def _dji_values(packet: bytes) -> dict[str, str]:
    """``{DJI name: text}`` of every drone-dji attribute or element of one XMP packet."""
    text = packet.decode("utf-8", "replace")
    start, end = text.find("<x:xmpmeta"), text.rfind("</x:xmpmeta>")
    body = text[start:end + len("</x:xmpmeta>")] if start >= 0 and end > start else text
    prefix = "{" + DJI_NS + "}"
    out: dict[str, str] = {}
    try:
        root = ElementTree.fromstring(body)
    except ElementTree.ParseError:  # not well-formed: read the attributes as text
        for key, value in re.findall(r"drone-dji:(\w+)\s*=\s*\"([^\"]*)\"", body):
            out.setdefault(key, value)
        return out
    for el in root.iter():
        for key, value in el.attrib.items():
            if key.startswith(prefix):
                out.setdefault(key[len(prefix):], value)
        if el.tag.startswith(prefix) and el.text and el.text.strip():
            out.setdefault(el.tag[len(prefix):], el.text)
    return out


def read_position(data: bytes, name: str = "<bytes>", layout: jpeg.JpegLayout | None = None) -> Position:
    """The capture's position from the XMP of a JPEG's bytes (all ``None`` when it carries none); ``layout``: the
    file's ``jpeg.read_segments`` when already read."""
    values: dict[str, str] = {}
    for packet in xmp_packets(data, name, layout):
        for key, value in _dji_values(packet).items():
            values.setdefault(key, value)
    return Position(**{ours: _number(values.get(dji)) for ours, dji in FIELDS.items()})


# ------------------------------------------------------------------------------------------------ writing
def xmp_packet(values: Mapping[str, Any], model: str = "M3T") -> bytes:
    """An XMP packet in DJI's layout with ``values`` (our field names, see ``FIELDS``) as drone-dji attributes."""
    attrs = []
    for ours, dji in FIELDS.items():
        v = values.get(ours)
        if v is None:
            continue
        if ours in ("lat", "lon"):
            text = f"{float(v):.8f}"
        elif ours.startswith("alt"):
            text = f"{float(v):+.3f}"
        else:
            text = f"{float(v):+.2f}"
        attrs.append(f'   drone-dji:{dji}="{text}"')
    body = "\n".join(attrs)
    xml = (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        '  <rdf:Description rdf:about="DJI Meta Data"\n'
        '    xmlns:tiff="http://ns.adobe.com/tiff/1.0/"\n'
        f'    xmlns:drone-dji="{DJI_NS}"\n'
        f'   tiff:Make="DJI"\n   tiff:Model="{model}"\n{body}>\n'
        '  </rdf:Description>\n </rdf:RDF>\n</x:xmpmeta>\n<?xpacket end="w"?>'
    )
    return xml.encode("utf-8")


def add_xmp(data: bytes, values: Mapping[str, Any], model: str = "M3T") -> bytes:
    """``data`` (a JPEG) with a DJI XMP segment holding ``values`` inserted after its leading APP0/APP1 segments."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG")
    i = 2
    while i + 4 <= len(data) and data[i] == 0xFF and data[i + 1] in (jpeg.APP0, jpeg.APP1):
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        i += 2 + length
    return data[:i] + jpeg.segment(jpeg.APP1, XMP_HEADER + xmp_packet(values, model)) + data[i:]
