"""Where a capture was taken: GPS and attitude from the XMP packet DJI writes into every JPEG, else EXIF GPS.

DJI stores them as attributes (or elements) of the ``drone-dji`` namespace (``http://www.dji.com/drone-dji/1.0/``)
in an APP1 segment that starts with ``http://ns.adobe.com/xap/1.0/\\0``: ``GpsLatitude``, ``GpsLongitude`` (degrees,
WGS84; some firmware spells it ``GpsLongtitude``, and both are read), ``AbsoluteAltitude`` and ``RelativeAltitude``
(m, written with a sign, ``+103.45``), ``GimbalYawDegree``, ``GimbalPitchDegree``, ``GimbalRollDegree`` and
``FlightYawDegree`` (degrees). exiftool reads the same fields as ``XMP-drone-dji:*`` (``GPSLongtitude`` for the
second spelling). A field a file lacks, or whose text is not a finite number, is missing (``None``), never 0.

A capture whose XMP (of the wide image, else of the thermal one) has no latitude and longitude takes them, and the
absolute altitude, from the EXIF GPS tags instead (degrees, minutes and seconds with their ``N``/``S``, ``E``/``W``
reference; altitude negative with ``GPSAltitudeRef`` 1), as exiftool's ``-n`` composite ``GPSLatitude``,
``GPSLongitude`` and ``GPSAltitude`` read them. ``Position.gps_source`` says which: ``xmp``, ``exif`` or ``None``.

``add_xmp`` writes such a packet into a JPEG and ``add_exif_gps`` the EXIF GPS tags (the synthetic flights of the
tests and benchmarks).
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import asdict, dataclass, replace
from typing import Any, Mapping
from xml.etree import ElementTree

from harness.sensing import jpeg

XMP_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"
DJI_NS = "http://www.dji.com/drone-dji/1.0/"
#: our field -> DJI's XMP name
FIELDS = {
    "lat": "GpsLatitude",
    "lon": "GpsLongitude",
    "alt_abs": "AbsoluteAltitude",
    "alt_rel": "RelativeAltitude",
    "gimbal_yaw": "GimbalYawDegree",
    "gimbal_pitch": "GimbalPitchDegree",
    "gimbal_roll": "GimbalRollDegree",
    "flight_yaw": "FlightYawDegree",
}
#: our field -> the XMP names read, first found wins (DJI firmware of some models writes ``GpsLongtitude``, sic)
READ_NAMES = {**{ours: (dji,) for ours, dji in FIELDS.items()}, "lon": ("GpsLongitude", "GpsLongtitude")}
#: where a capture's latitude and longitude came from
GPS_SOURCES = ("xmp", "exif")


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
    #: where ``lat``/``lon`` came from: ``xmp`` (DJI's XMP), ``exif`` (the EXIF GPS tags) or None (nowhere)
    gps_source: str | None = None

    @property
    def has_gps(self) -> bool:
        return self.lat is not None and self.lon is not None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def merged(self, other: "Position") -> "Position":
        """This position with its missing fields taken from ``other``; latitude, longitude and their source go
        together (from ``other`` only when this one has no GPS and ``other`` has)."""
        mine, theirs = self.to_dict(), other.to_dict()
        out = {k: mine[k] if mine[k] is not None else theirs[k] for k in mine}
        if not self.has_gps:
            gps = theirs if other.has_gps else {"lat": self.lat, "lon": self.lon, "gps_source": None}
            out.update(lat=gps["lat"], lon=gps["lon"], gps_source=gps["gps_source"])
        return Position(**out)


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
    return [p[len(XMP_HEADER) :] for p in layout.payloads(jpeg.APP1) if p.startswith(XMP_HEADER)]


def _dji_values(packet: bytes) -> dict[str, str]:
    """``{DJI name: text}`` of every drone-dji attribute or element of one XMP packet."""
    text = packet.decode("utf-8", "replace")
    start, end = text.find("<x:xmpmeta"), text.rfind("</x:xmpmeta>")
    body = text[start : end + len("</x:xmpmeta>")] if start >= 0 and end > start else text
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
                out.setdefault(key[len(prefix) :], value)
        if el.tag.startswith(prefix) and el.text and el.text.strip():
            out.setdefault(el.tag[len(prefix) :], el.text)
    return out


def xmp_position(data: bytes, name: str = "<bytes>", layout: jpeg.JpegLayout | None = None) -> Position:
    """The position in the DJI XMP of a JPEG's bytes (all ``None`` when it carries none)."""
    values: dict[str, str] = {}
    for packet in xmp_packets(data, name, layout):
        for key, value in _dji_values(packet).items():
            values.setdefault(key, value)
    found: dict[str, Any] = {}
    for ours, names in READ_NAMES.items():
        found[ours] = next((v for v in (_number(values.get(n)) for n in names) if v is not None), None)
    pos = Position(**found)
    return replace(pos, gps_source="xmp") if pos.has_gps else pos


def _degrees(value: Any, ref: Any, negative: str) -> float | None:
    """EXIF (degrees, minutes, seconds) with its hemisphere letter, as exiftool's composite tag computes it
    (``d + (m + s / 60) / 60``, negative for ``S``/``W``); None without the reference letter, as exiftool."""
    parts = list(value) if isinstance(value, (list, tuple)) else [value]
    if not parts or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in parts):
        return None
    if not isinstance(ref, str) or ref.strip()[:1].upper() not in ("N", "S", "E", "W"):
        return None
    d, m, s = (list(map(float, parts)) + [0.0, 0.0])[:3]
    deg = d + (m + s / 60) / 60
    return -deg if ref.strip()[:1].upper() == negative else deg


def exif_position(data: bytes, name: str = "<bytes>", layout: jpeg.JpegLayout | None = None) -> Position:
    """Latitude, longitude and altitude from a JPEG's EXIF GPS tags (``gps_source="exif"``; all ``None`` without
    them)."""
    if layout is None:
        layout = jpeg.read_segments(data, name, require_eoi=False)
    exif: dict[str, Any] = {}
    for payload in layout.payloads(jpeg.APP1):
        exif = jpeg.parse_exif(payload)
        if exif:
            break
    lat = _degrees(exif.get("GPSLatitude"), exif.get("GPSLatitudeRef"), "S")
    lon = _degrees(exif.get("GPSLongitude"), exif.get("GPSLongitudeRef"), "W")
    alt = exif.get("GPSAltitude")
    alt_abs = None
    if isinstance(alt, (int, float)) and math.isfinite(alt):
        alt_abs = -float(alt) if exif.get("GPSAltitudeRef") == 1 else float(alt)
    if lat is None or lon is None:
        return Position()  # an altitude without a position is of no use, and would look like one
    return Position(lat=lat, lon=lon, alt_abs=alt_abs, gps_source="exif")


def read_position(
    data: bytes, name: str = "<bytes>", layout: jpeg.JpegLayout | None = None, exif: bool = True
) -> Position:
    """The capture's position from the XMP of a JPEG's bytes, else (``exif``) its latitude, longitude and altitude
    from the EXIF GPS tags; all ``None`` when it carries neither. ``layout``: the file's ``jpeg.read_segments``
    when already read."""
    if layout is None:
        layout = jpeg.read_segments(data, name, require_eoi=False)
    pos = xmp_position(data, name, layout)
    return pos.merged(exif_position(data, name, layout)) if exif and not pos.has_gps else pos


def capture_position(
    rgb: tuple[bytes, str, jpeg.JpegLayout | None], thermal: tuple[bytes, str, jpeg.JpegLayout | None] | None
) -> Position:
    """A capture's position: the XMP of its wide image, what that lacks from the XMP of its thermal image, and
    latitude, longitude and altitude from the EXIF GPS of the wide image, else the thermal one, when neither XMP has
    them. ``rgb``, ``thermal``: (bytes, name, layout) of each JPEG (``thermal`` None when it is no JPEG)."""
    files = [rgb] + ([thermal] if thermal is not None else [])
    pos = Position()
    for data, name, layout in files:
        pos = pos.merged(xmp_position(data, name, layout))
    for data, name, layout in files:
        if pos.has_gps:
            break
        pos = pos.merged(exif_position(data, name, layout))
    return pos


# ------------------------------------------------------------------------------------------------ writing
def xmp_packet(values: Mapping[str, Any], model: str = "M3T", longitude: str = "GpsLongitude") -> bytes:
    """An XMP packet in DJI's layout with ``values`` (our field names, see ``FIELDS``) as drone-dji attributes;
    ``longitude``: the longitude's name (``GpsLongtitude`` as some DJI firmware spells it)."""
    attrs = []
    for ours, dji in {**FIELDS, "lon": longitude}.items():
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


def add_xmp(data: bytes, values: Mapping[str, Any], model: str = "M3T", longitude: str = "GpsLongitude") -> bytes:
    """``data`` (a JPEG) with a DJI XMP segment holding ``values`` inserted after its leading APP0/APP1 segments
    (``longitude``: see ``xmp_packet``)."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG")
    i = 2
    while i + 4 <= len(data) and data[i] == 0xFF and data[i + 1] in (jpeg.APP0, jpeg.APP1):
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        i += 2 + length
    return data[:i] + jpeg.segment(jpeg.APP1, XMP_HEADER + xmp_packet(values, model, longitude)) + data[i:]


def add_exif_gps(data: bytes, lat: float, lon: float, alt: float | None = None) -> bytes:
    """``data`` (a JPEG) with the EXIF GPS tags of ``lat``/``lon`` (degrees, signed) and ``alt`` (m): its EXIF
    segment rewritten with them (the tags ``jpeg.EXIF_TAGS`` knows kept), or one added after SOI."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG")
    tags: dict[str, Any] = {}

    def dms(value: float) -> tuple[float, float, float]:
        a = abs(float(value))
        d = math.floor(a)
        m = math.floor((a - d) * 60)
        return float(d), float(m), round(((a - d) * 60 - m) * 60, 6)

    tags.update(
        GPSLatitudeRef="S" if lat < 0 else "N",
        GPSLatitude=dms(lat),
        GPSLongitudeRef="W" if lon < 0 else "E",
        GPSLongitude=dms(lon),
    )
    if alt is not None:
        tags.update(GPSAltitudeRef=1 if alt < 0 else 0, GPSAltitude=abs(float(alt)))
    layout = jpeg.read_segments(data, require_eoi=False)
    for seg in layout.segments:
        if seg.marker == jpeg.APP1 and seg.payload.startswith(b"Exif\x00\x00"):
            old = {k: v for k, v in jpeg.parse_exif(seg.payload).items() if not k.startswith("GPS")}
            new = jpeg.segment(jpeg.APP1, jpeg.build_exif({**old, **tags}))
            end = seg.offset + 4 + len(seg.payload)
            return data[: seg.offset] + new + data[end:]
    return data[:2] + jpeg.segment(jpeg.APP1, jpeg.build_exif(tags)) + data[2:]
