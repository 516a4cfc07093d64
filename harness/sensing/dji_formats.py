"""Which DJI R-JPEG layout a file uses, and what the decoder does with each (``docs/sensing.md``, camera table).

DJI's Thermal SDK picks a reader by the EXIF camera model, and an APP4 segment that starts ``FF D2 D1 FF``
followed by an ASCII tag (``iirp``, ``hirp``, ``girp``) overrides that choice. The layouts:

=========  =====================================================  ===========================================
format     cameras (EXIF ``Model``)                               decoded here
=========  =====================================================  ===========================================
``iirp``   M3T, M30T, M3TD, ZH20N, H30T, M4T,                     raw14 = APP3 word >> 2; blackbody and DJI's
           MAVIC2-ENTERPRISE-ADVANCED (APP4 without the tag)      correction (``dji_correction``)
``dirp``   ZH20T (class D: calibration block ``AA 55 12``)        raw as stored; the curve map (``dji_dirp``)
``hirp``   M3TD / M4T with newer firmware                         raw as stored; temperatures: converter only
``girp``   some M30T captures                                     raw as stored; temperatures: converter only
``dirp-g`` Zenmuse XT S (class G: raw in APP4)                    raw as stored; temperatures: converter only
=========  =====================================================  ===========================================

Anything else (FLIR-style XT2 files, an unknown tag) is refused with the camera model and the format named. A
refusal names both ways on: DJI's own SDK through the converter route (``dji_converter``), and, where one exists,
the labelled approximate route (``dji_approximate``).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from harness.errors import DataError
from harness.sensing import dji_dirp

APP4_MAGIC = b"\xff\xd2\xd1\xff"
#: EXIF models whose R-JPEGs use the iirp layout (used when APP4 carries no format tag).
IIRP_MODELS = ("M3T", "M30T", "M3TD", "ZH20N", "H30T", "M4T", "MAVIC2-ENTERPRISE-ADVANCED")
#: the formats whose temperatures are decoded
DECODED = ("iirp", "dirp")
#: why a format is refused (completes "... is not decoded: <reason>")
REFUSED = {
    "hirp": "its temperatures come from DJI's integer measurement core (MicroTA), driven by the camera's "
    "calibration in the APP5 'HIDR' container, which this decoder does not implement",
    "girp": "its gray-to-temperature curves are built into DJI's SDK, not stored in the file",
    "dirp-g": "the Zenmuse XT S layout (class G: 'Plug' block in APP2, curve in APP3, raw in APP4) is not implemented",
}
CONVERTER_HINT = (
    "decode it with DJI's own Thermal SDK: --converter dji_irp (sensing.radiometry.converter: "
    "dji_irp), or give the temperature file DJI's SDK wrote (.tif/.npy with its sidecar)"
)
APPROXIMATE_HINT = "or accept approximate temperatures: --approximate (sensing.radiometry.approximate: true)"


class UnsupportedFormat(DataError):
    """A DJI R-JPEG layout whose temperatures are not decoded; the message names the camera and the format."""


def detect(app4: bytes | None, model: str) -> str:
    """The layout of a file from its first APP4 payload and EXIF model: ``iirp``, ``dirp``, ``dirp-g``, a tag
    read from APP4 (``hirp``, ``girp``, ...), ``""`` for a model DJI's SDK has no reader for."""
    if app4 is not None and len(app4) > 0x20 and app4.startswith(APP4_MAGIC):
        tag = app4[4:12].split(b"\x00", 1)[0].decode("latin-1").strip()
        if tag:
            return tag
    if app4 is not None and dji_dirp.is_dirp_block(app4):
        return "dirp"
    upper = model.upper()
    if upper in dji_dirp.DIRP_MODELS:
        return "dirp"
    if upper == "XT S":
        return "dirp-g"
    if not model or upper in IIRP_MODELS:
        return "iirp"
    return ""


def camera_text(model: str) -> str:
    return f"camera {model!r}" if model else "an unnamed camera (no EXIF model)"


def options_text(approximation: object | None, why_not: str = "") -> str:
    """The two ways on, for a refusal: the converter, and the approximate route with its bound (or why there is
    none). ``approximation``: a ``dji_approximate.Approximation`` or ``None``."""
    if approximation is None:
        return f"{CONVERTER_HINT}; no approximate route exists for it{' (' + why_not + ')' if why_not else ''}"
    top = max(b for _, b in approximation.bands)  # type: ignore[attr-defined]
    return (
        f"{CONVERTER_HINT}; {APPROXIMATE_HINT}, measured within {top:g} C of DJI's SDK or better ({approximation.name})"  # type: ignore[attr-defined]
    )


def refusal(path: str | Path, fmt: str, model: str) -> UnsupportedFormat:
    """The error for a file whose layout is not decoded, naming the camera model, the format and the ways on."""
    camera = camera_text(model)
    if fmt == "":
        return UnsupportedFormat(
            f"{path}: {camera} does not write a DJI R-JPEG layout this decoder knows; decoded: iirp "
            f"({', '.join(IIRP_MODELS)}) and dirp ({', '.join(dji_dirp.DIRP_MODELS)}); a converter of your own "
            "can be named with --converter 'COMMAND {input} {output}'"
        )
    reason = REFUSED.get(fmt, "the format is not known")
    why = "the temperatures need DJI's own code" if fmt in REFUSED else ""
    return UnsupportedFormat(
        f"{path}: {camera}, DJI R-JPEG format {fmt!r}: temperatures are not decoded: "
        f"{reason}; {options_text(None, why)}"
    )


# ---------------------------------------------------------------------------------------------- hirp fields
#: where a hirp APP4 payload keeps its measurement parameters (a block of little-endian fields)
HIRP_PARAMS_AT = 0x48


def hirp_params(app4: bytes) -> dict[str, float]:
    """The measurement parameters a hirp APP4 payload states: ``emissivity`` (uint16 Q13 at +0x10), ``distance``
    (int32 Q13, m, +0x14), ``reflected`` (int32 Q13, C, +0x18, used when bit 0 of +0x1C is set, else the ambient
    temperature stands in for it, as DJI's SDK reports), ``ambient`` (int32, milli-C, +0x28), ``humidity``
    (int32, thousandths of %, +0x2C); offsets from ``HIRP_PARAMS_AT``. Empty when the block is too short."""
    b = HIRP_PARAMS_AT
    if len(app4) < b + 0x30:
        return {}
    emissivity = struct.unpack_from("<H", app4, b + 0x10)[0] / 8192.0
    distance = struct.unpack_from("<i", app4, b + 0x14)[0] / 8192.0
    reflected = struct.unpack_from("<i", app4, b + 0x18)[0] / 8192.0
    flags = struct.unpack_from("<H", app4, b + 0x1C)[0]
    ambient = struct.unpack_from("<i", app4, b + 0x28)[0] / 1000.0
    humidity = struct.unpack_from("<i", app4, b + 0x2C)[0] / 1000.0
    return {
        "emissivity": round(emissivity, 6),
        "distance": round(distance, 6),
        "humidity": round(humidity, 4),
        "reflected": round(reflected if flags & 1 else ambient, 4),
        "ambient": round(ambient, 4),
    }


def original_raw(words: np.ndarray, fmt: str) -> np.ndarray:
    """The SDK's ``dirp_get_original_raw`` from the APP3 words: ``word >> 2`` for iirp (14-bit counts stored
    shifted left by 2), the words as stored for the other layouts."""
    words = np.asarray(words, dtype=np.uint16)
    return (words >> 2).astype(np.uint16) if fmt == "iirp" else words.copy()


def frame_words(layout: object, fmt: str, model: str, path: str | Path) -> np.ndarray:
    """The stored 16-bit radiometric words of a file, ``H x W``: APP3 (APP4 for the XT S, class G), shaped by the
    iirp APP4 header's width and height when it states them (the M30T's 1280x1024 pictures carry a 640x512 frame),
    else by the picture's size. A payload that fits neither is a ``DataError`` naming the file."""
    from harness.sensing import jpeg

    app4 = layout.payloads(jpeg.APP4)  # type: ignore[attr-defined]
    raw = b"".join(layout.payloads(jpeg.APP4 if fmt == "dirp-g" else jpeg.APP3))  # type: ignore[attr-defined]
    w, h = layout.width, layout.height  # type: ignore[attr-defined]
    if fmt == "iirp" and app4 and app4[0].startswith(APP4_MAGIC) and len(app4[0]) >= 0xA1:
        aw, ah = struct.unpack_from("<HH", app4[0], 0x9D)
        if aw and ah and aw * ah * 2 == len(raw):
            w, h = aw, ah
    if len(raw) != w * h * 2:
        where = "APP4" if fmt == "dirp-g" else "APP3"
        raise DataError(
            f"{path}: radiometric payload ({where}) holds {len(raw)} bytes, expected {w * h * 2} for "
            f"{w}x{h} 16-bit words ({model or 'unnamed camera'}, format {fmt or 'unknown'!r})"
        )
    return np.frombuffer(raw, dtype="<u2").reshape(h, w)


def read_original_raw(path: str | Path) -> tuple[str, str, np.ndarray]:
    """(format, EXIF model, ``dirp_get_original_raw``) of any DJI R-JPEG, including the layouts whose
    temperatures are not decoded (hirp, girp, XT S); a file without the payload of its frame is a ``DataError``."""
    from harness.sensing import jpeg

    path = Path(path)
    layout = jpeg.read_segments(jpeg._read_bytes(path), path, require_eoi=False)
    exif: dict = {}
    for payload in layout.payloads(jpeg.APP1):
        exif = jpeg.parse_exif(payload)
        if exif:
            break
    model = str(exif.get("Model") or "").strip()
    app4 = layout.payloads(jpeg.APP4)
    fmt = detect(app4[0] if app4 else None, model)
    return fmt, model, original_raw(frame_words(layout, fmt, model, path), fmt)
