"""JPEG container plumbing for radiometric files: marker segments and a small EXIF (TIFF) reader/writer.

Only what the sensing pipeline needs, written against the JPEG (ITU T.81) and EXIF 2.3 (TIFF 6.0) layouts:

* ``read_segments(data)`` walks the marker segments from SOI up to the first SOS and finds the end of the main
  image's entropy-coded data (its EOI); anything cut short is a ``DataError`` rather than a partial result.
* ``parse_exif(payload)`` reads IFD0 and the EXIF sub-IFD of an APP1 ``Exif`` payload into ``{tag name: value}``.
* ``build_exif(tags)`` writes the inverse: a little-endian TIFF with the tags the harness writes into synthetic
  files (make, model, capture time, focal length, image size).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Mapping

from harness.errors import DataError

SOI, EOI, SOS = 0xD8, 0xD9, 0xDA
APP0, APP1, APP2, APP3, APP4, APP5 = 0xE0, 0xE1, 0xE2, 0xE3, 0xE4, 0xE5
SOF_MARKERS = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
#: The largest payload one marker segment can carry (the 16-bit length counts itself).
MAX_SEGMENT_PAYLOAD = 65533
TRUNCATED_PICTURE = "truncated JPEG: the picture data has no end-of-image marker; the file was cut short"


@dataclass(frozen=True)
class Segment:
    """One marker segment: the marker byte, the file offset of its 0xFF, and its payload (without the length)."""

    marker: int
    offset: int
    payload: bytes


@dataclass(frozen=True)
class JpegLayout:
    """The header segments of a JPEG up to its first SOS, the frame size, and where the main image ends."""

    segments: tuple[Segment, ...]
    width: int
    height: int
    components: int
    end: int  # offset just past the main image's EOI marker
    complete: bool = True  # False when read with ``require_eoi=False`` and the picture has no EOI

    def check_complete(self, name: str | Path) -> None:
        """The ``DataError`` ``read_segments(require_eoi=True)`` raises, when the picture has no end marker."""
        if not self.complete:
            raise DataError(f"{name}: {TRUNCATED_PICTURE}")

    def payloads(self, marker: int) -> list[bytes]:
        return [s.payload for s in self.segments if s.marker == marker]


def read_segments(data: bytes, name: str | Path = "<bytes>", require_eoi: bool = True) -> JpegLayout:
    """Walk ``data``'s marker segments (SOI ... SOS) and locate the main image's EOI.

    Raises ``DataError`` naming ``name`` when the bytes are not a JPEG, a segment runs past the end of the file
    (a file cut in the middle of a segment), no frame header or scan is found, or (``require_eoi``) the
    entropy-coded data of the main image has no end-of-image marker (a file cut inside the picture).
    """
    n = len(data)
    if n == 0:
        raise DataError(f"{name}: empty file (0 bytes): nothing was copied into it; copy it again from the card")
    if 2 <= n < 4 and data[0] == 0xFF and data[1] == SOI:
        raise DataError(
            f"{name}: truncated JPEG: the file holds only {n} bytes ({data.hex(' ')}), the start-of-image marker and "
            "nothing after it; pass an R-JPEG straight from the camera"
        )
    if n < 4 or data[0] != 0xFF or data[1] != SOI:
        head = data[:8].hex(" ")
        raise DataError(
            f"{name}: not a JPEG file (starts with {head}, expected ff d8); pass an R-JPEG straight from the camera"
        )
    segments: list[Segment] = []
    width = height = components = 0
    i = 2
    while True:
        if i >= n:
            raise DataError(f"{name}: truncated JPEG: the file ends at byte {n} before the image data (no SOS marker)")
        if data[i] != 0xFF:
            raise DataError(f"{name}: corrupt JPEG: expected a marker at byte {i}, found 0x{data[i]:02x}")
        while i < n and data[i] == 0xFF:  # fill bytes
            i += 1
        if i >= n:
            raise DataError(f"{name}: truncated JPEG: the file ends inside a marker at byte {n}")
        marker = data[i]
        start = i - 1
        i += 1
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # TEM, RSTn: no length
            continue
        if marker == EOI:
            raise DataError(f"{name}: JPEG ends (EOI at byte {start}) before any image data")
        if i + 2 > n:
            raise DataError(
                f"{name}: truncated JPEG: the file ends inside the length of segment 0x{marker:02x} at byte {start}"
            )
        length = struct.unpack(">H", data[i : i + 2])[0]
        if length < 2:
            raise DataError(f"{name}: corrupt JPEG: segment 0x{marker:02x} at byte {start} has length {length}")
        end = i + length
        if end > n:
            raise DataError(
                f"{name}: truncated JPEG: segment 0x{marker:02x} at byte {start} declares {length - 2} bytes but the "
                f"file ends after {n - i - 2}; the file was cut short (copy it again from the card)"
            )
        payload = bytes(data[i + 2 : end])
        segments.append(Segment(marker, start, payload))
        if marker in SOF_MARKERS and len(payload) >= 6:
            height, width = struct.unpack(">HH", payload[1:5])
            components = payload[5]
        i = end
        if marker == SOS:
            break
    if not width or not height:
        raise DataError(f"{name}: corrupt JPEG: no frame header (SOF) before the scan")
    eoi = _find_eoi(data, i)
    complete = eoi >= 0
    if not complete:
        if require_eoi:
            raise DataError(f"{name}: {TRUNCATED_PICTURE}")
        eoi = n - 2
    return JpegLayout(tuple(segments), int(width), int(height), int(components), eoi + 2, complete)


def _find_eoi(data: bytes, start: int) -> int:
    """Offset of the EOI that ends the entropy-coded data starting at ``start`` (or -1).

    Inside entropy-coded data a 0xFF byte is followed by 0x00 (stuffing) or a restart marker, so the first
    0xFF followed by anything else is the next marker; for a baseline single-scan image that is EOI. Progressive
    images have further scans (SOS, DHT) before EOI, which the loop steps over.
    """
    j = start
    n = len(data)
    while True:
        j = data.find(b"\xff", j)
        if j < 0 or j + 1 >= n:
            return -1
        nxt = data[j + 1]
        if nxt == 0x00 or nxt == 0xFF or 0xD0 <= nxt <= 0xD7:
            j += 1 if nxt == 0xFF else 2
            continue
        if nxt == EOI:
            return j
        if j + 4 > n:  # another segment (progressive scans, DHT between scans): skip it
            return -1
        j += 2 + struct.unpack(">H", data[j + 2 : j + 4])[0]


def segment(marker: int, payload: bytes) -> bytes:
    """Encode one marker segment (``payload`` at most ``MAX_SEGMENT_PAYLOAD`` bytes)."""
    if len(payload) > MAX_SEGMENT_PAYLOAD:
        raise ValueError(f"segment payload of {len(payload)} bytes exceeds {MAX_SEGMENT_PAYLOAD}")
    return bytes((0xFF, marker)) + struct.pack(">H", len(payload) + 2) + payload


# ---------------------------------------------------------------------------------------------- EXIF
#: tag id -> (name, which IFD it belongs to when written)
EXIF_TAGS: dict[int, tuple[str, str]] = {
    0x010E: ("ImageDescription", "ifd0"),
    0x010F: ("Make", "ifd0"),
    0x0110: ("Model", "ifd0"),
    0x0112: ("Orientation", "ifd0"),
    0x0100: ("ImageWidth", "ifd0"),
    0x0101: ("ImageLength", "ifd0"),
    0x0131: ("Software", "ifd0"),
    0x0132: ("DateTime", "ifd0"),
    0x829A: ("ExposureTime", "exif"),
    0x829D: ("FNumber", "exif"),
    0x9003: ("DateTimeOriginal", "exif"),
    0x9004: ("DateTimeDigitized", "exif"),
    0x9291: ("SubSecTimeOriginal", "exif"),
    0x920A: ("FocalLength", "exif"),
    0xA002: ("ExifImageWidth", "exif"),
    0xA003: ("ExifImageHeight", "exif"),
    0xA405: ("FocalLengthIn35mmFilm", "exif"),
    0xA420: ("ImageUniqueID", "exif"),
}
#: tags of the GPS IFD (IFD0's ``GPSInfo`` pointer): latitude and longitude as three rationals (degrees, minutes,
#: seconds) with their hemisphere in the ``*Ref`` tag (``N``/``S``, ``E``/``W``), altitude in metres with
#: ``GPSAltitudeRef`` 1 below sea level
GPS_TAGS: dict[int, str] = {
    0x0001: "GPSLatitudeRef",
    0x0002: "GPSLatitude",
    0x0003: "GPSLongitudeRef",
    0x0004: "GPSLongitude",
    0x0005: "GPSAltitudeRef",
    0x0006: "GPSAltitude",
}
_NAME_TO_TAG = {name: tag for tag, (name, _) in EXIF_TAGS.items()}
_GPS_NAME_TO_TAG = {name: tag for tag, name in GPS_TAGS.items()}
_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 7: 1, 9: 4, 10: 8, 11: 4, 12: 8}
_EXIF_POINTER = 0x8769
_GPS_POINTER = 0x8825


def parse_exif(payload: bytes) -> dict[str, Any]:
    """Known tags of an APP1 payload (``b"Exif\\0\\0"`` + TIFF) as ``{name: value}``; empty when not EXIF. The GPS
    IFD's tags (``GPS_TAGS``) are included under their names.

    ASCII values come back as ``str``, single numbers as ``int``/``float`` (rationals divided out), lists for
    multi-valued tags. Malformed offsets end the walk quietly: EXIF is provenance, never worth refusing a file.
    """
    if not payload.startswith(b"Exif\x00\x00") or len(payload) < 14:
        return {}
    tiff = payload[6:]
    order = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if order is None:
        return {}
    out: dict[str, Any] = {}
    try:
        (ifd0,) = struct.unpack(order + "I", tiff[4:8])
        pointers = _read_ifd(tiff, ifd0, order, out)
        if pointers.get(_EXIF_POINTER):
            _read_ifd(tiff, pointers[_EXIF_POINTER], order, out)
        if pointers.get(_GPS_POINTER):
            _read_ifd(tiff, pointers[_GPS_POINTER], order, out, gps=True)
    except (struct.error, IndexError, UnicodeDecodeError):
        pass
    return out


def _read_ifd(tiff: bytes, offset: int, order: str, out: dict[str, Any], gps: bool = False) -> dict[int, int]:
    """Read one IFD's known tags into ``out`` (``gps``: the GPS IFD's); return its EXIF and GPS IFD pointers."""
    (count,) = struct.unpack(order + "H", tiff[offset : offset + 2])
    pointers: dict[int, int] = {}
    for k in range(count):
        e = offset + 2 + 12 * k
        tag, typ, num = struct.unpack(order + "HHI", tiff[e : e + 8])
        size = _TYPE_SIZE.get(typ, 0) * num
        if size == 0:
            continue
        if size <= 4:
            raw = tiff[e + 8 : e + 8 + size]
        else:
            (ptr,) = struct.unpack(order + "I", tiff[e + 8 : e + 12])
            raw = tiff[ptr : ptr + size]
            if len(raw) < size:
                continue
        if gps:
            if tag in GPS_TAGS:
                out[GPS_TAGS[tag]] = _decode_value(raw, typ, num, order)
            continue
        if tag in (_EXIF_POINTER, _GPS_POINTER):
            (pointers[tag],) = struct.unpack(order + "I", raw[:4])
            continue
        if tag not in EXIF_TAGS:
            continue
        out[EXIF_TAGS[tag][0]] = _decode_value(raw, typ, num, order)
    return pointers


def _decode_value(raw: bytes, typ: int, num: int, order: str) -> Any:
    if typ == 2:
        return raw.split(b"\x00", 1)[0].decode("latin-1").strip()
    if typ in (1, 7):
        vals: list[Any] = list(raw)
    elif typ in (3, 4, 9):
        fmt = {3: "H", 4: "I", 9: "i"}[typ]
        vals = list(struct.unpack(order + fmt * num, raw))
    elif typ in (5, 10):
        fmt = "I" if typ == 5 else "i"
        pairs = struct.unpack(order + fmt * (2 * num), raw)
        vals = [a / b if b else float("nan") for a, b in zip(pairs[::2], pairs[1::2])]
    elif typ in (11, 12):
        vals = list(struct.unpack(order + ("f" if typ == 11 else "d") * num, raw))
    else:  # pragma: no cover - types filtered by _TYPE_SIZE
        return None
    return vals[0] if num == 1 else vals


def _rational(value: float, den: int) -> tuple[int, int]:
    return int(round(float(value) * den)), den


def build_exif(tags: Mapping[str, Any]) -> bytes:
    """An APP1 payload (``Exif\\0\\0`` + little-endian TIFF) holding ``tags`` (names from ``EXIF_TAGS`` and
    ``GPS_TAGS``).

    Strings are written as ASCII, ``FocalLength``/``FNumber``/``ExposureTime`` as rationals (1/1000 steps), the
    rest as SHORT or LONG. ``DateTimeOriginal`` may be a ``datetime``. GPS tags as EXIF stores them:
    ``GPSLatitude``/``GPSLongitude`` as (degrees, minutes, seconds) rationals (seconds in 1e-6 steps),
    ``GPSAltitude`` a rational (1/1000 m), ``GPSAltitudeRef`` a byte, the ``*Ref`` letters ASCII.
    """
    ifds: dict[str, list[tuple[int, int, int, bytes]]] = {"ifd0": [], "exif": [], "gps": []}
    for name, value in tags.items():
        if name in _GPS_NAME_TO_TAG:
            tag = _GPS_NAME_TO_TAG[name]
            if name in ("GPSLatitudeRef", "GPSLongitudeRef"):
                ifds["gps"].append((tag, 2, 2, str(value)[:1].encode("ascii") + b"\x00"))
            elif name == "GPSAltitudeRef":
                ifds["gps"].append((tag, 1, 1, bytes([int(value)])))
            elif name == "GPSAltitude":
                ifds["gps"].append((tag, 5, 1, struct.pack("<II", *_rational(value, 1000))))
            else:
                d, m, sec = (float(v) for v in value)
                parts = (*_rational(d, 1), *_rational(m, 1), *_rational(sec, 1_000_000))
                ifds["gps"].append((tag, 5, 3, struct.pack("<6I", *parts)))
            continue
        if name not in _NAME_TO_TAG:
            known = sorted([*_NAME_TO_TAG, *_GPS_NAME_TO_TAG])
            raise DataError(f"EXIF tag {name!r} cannot be written; known tags: {', '.join(known)}")
        tag = _NAME_TO_TAG[name]
        where = EXIF_TAGS[tag][1]
        if isinstance(value, datetime):
            value = value.strftime("%Y:%m:%d %H:%M:%S")
        if isinstance(value, str):
            data = value.encode("ascii", "replace") + b"\x00"
            ifds[where].append((tag, 2, len(data), data))
        elif name in ("FocalLength", "FNumber", "ExposureTime"):
            num, den = int(round(float(value) * 1000)), 1000
            ifds[where].append((tag, 5, 1, struct.pack("<II", num, den)))
        elif name in ("Orientation", "FocalLengthIn35mmFilm"):
            ifds[where].append((tag, 3, 1, struct.pack("<H", int(value))))
        else:
            ifds[where].append((tag, 4, 1, struct.pack("<I", int(value))))

    def layout(entries: list[tuple[int, int, int, bytes]], start: int) -> tuple[bytes, bytes]:
        """An IFD at ``start`` holding ``entries`` (tag order) and its data area, which follows it."""
        data_start = start + 2 + 12 * len(entries) + 4
        head, area = [], b""
        for tag, typ, num, data in sorted(entries):
            if len(data) <= 4:
                head.append(struct.pack("<HHI", tag, typ, num) + data.ljust(4, b"\x00"))
            else:
                head.append(struct.pack("<HHII", tag, typ, num, data_start + len(area)))
                area += data + (b"\x00" if len(data) % 2 else b"")
        return struct.pack("<H", len(entries)) + b"".join(head) + struct.pack("<I", 0), area

    # IFD0 at offset 8, then its data area; the EXIF and GPS IFDs IFD0 points at follow, each with its data area
    subs = [(ptr, ifds[k]) for ptr, k in ((_EXIF_POINTER, "exif"), (_GPS_POINTER, "gps")) if ifds[k]]
    entries0 = list(ifds["ifd0"]) + [(ptr, 4, 1, b"\x00\x00\x00\x00") for ptr, _ in subs]
    ifd0, area0 = layout(entries0, 8)
    offset = 8 + len(ifd0) + len(area0)
    blocks, pointers = [], {}
    for ptr, entries in subs:
        pointers[ptr] = offset
        ifd, area = layout(entries, offset)
        blocks.append(ifd + area)
        offset += len(ifd) + len(area)
    entries0 = list(ifds["ifd0"]) + [(ptr, 4, 1, struct.pack("<I", pointers[ptr])) for ptr, _ in subs]
    ifd0, area0 = layout(entries0, 8)
    tiff = b"II*\x00" + struct.pack("<I", 8) + ifd0 + area0 + b"".join(blocks)
    return b"Exif\x00\x00" + tiff


def parse_exif_datetime(value: Any, subsec: Any = None) -> datetime | None:
    """EXIF ``YYYY:MM:DD HH:MM:SS`` (+ optional sub-seconds) as a naive ``datetime``; ``None`` when unparsable."""
    if isinstance(value, datetime):
        return value
    if not isinstance(value, str):
        return None
    text = value.strip().replace("-", ":").replace("T", " ")
    for fmt in ("%Y:%m:%d %H:%M:%S", "%Y:%m:%d %H:%M:%S.%f"):
        try:
            dt = datetime.strptime(text, fmt)
            break
        except ValueError:
            continue
    else:
        return None
    if subsec is not None and str(subsec).strip().isdigit() and not dt.microsecond:
        digits = str(subsec).strip()[:6].ljust(6, "0")
        dt = dt.replace(microsecond=int(digits))
    return dt


def read_exif(path: str | Path) -> dict[str, Any]:
    """EXIF of a JPEG file (empty dict when it has none); a non-JPEG or cut file is a ``DataError``."""
    path = Path(path)
    data = _read_bytes(path)
    layout = read_segments(data, path, require_eoi=False)
    for payload in layout.payloads(APP1):
        exif = parse_exif(payload)
        if exif:
            return exif
    return {}


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise DataError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise DataError(f"{path}: is a folder, expected a file") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
