"""Which DJI R-JPEG layout a file uses, and what the decoder does with each (``docs/sensing.md``, camera table).

DJI's Thermal SDK picks a reader by the EXIF camera model, and an APP4 segment that starts ``FF D2 D1 FF``
followed by an ASCII tag (``iirp``, ``hirp``, ``girp``) overrides that choice. The layouts:

=========  =====================================================  ===========================================
format     cameras (EXIF ``Model``)                               decoded here
=========  =====================================================  ===========================================
``iirp``   M3T, M30T, M3TD, ZH20N, H30T, M4T,                     raw14 = APP3 word >> 2; blackbody and DJI's
           MAVIC2-ENTERPRISE-ADVANCED (APP4 without the tag)      correction (``dji_correction``)
``dirp``   ZH20T (class D: calibration block ``AA 55 12``)        raw as stored; the curve map (``dji_dirp``)
``hirp``   M3TD / M4T with newer firmware                         raw as stored; temperatures refused
``girp``   some M30T captures                                     refused
=========  =====================================================  ===========================================

Anything else (Zenmuse XT S, FLIR-style XT2 files, an unknown tag) is refused with the camera model and the
format named.
"""

from __future__ import annotations

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
    "dirp-g": "the Zenmuse XT S layout (class G: 'Plug' block in APP2, curve in APP3, raw in APP4) is not "
              "implemented",
}
WORKAROUND = ("convert it with the DJI Thermal SDK (dirp_measure_ex) and give the decoded temperature file "
              "(.tif/.png/.npy with its sidecar) instead")


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


def refusal(path: str | Path, fmt: str, model: str) -> UnsupportedFormat:
    """The error for a file whose layout is not decoded, naming the camera model and the format."""
    camera = f"camera {model!r}" if model else "an unnamed camera (no EXIF model)"
    if fmt == "":
        return UnsupportedFormat(
            f"{path}: {camera} does not write a DJI R-JPEG layout this decoder knows; decoded: iirp "
            f"({', '.join(IIRP_MODELS)}) and dirp ({', '.join(dji_dirp.DIRP_MODELS)})")
    reason = REFUSED.get(fmt, "the format is not known")
    return UnsupportedFormat(f"{path}: {camera}, DJI R-JPEG format {fmt!r}: temperatures are not decoded: "
                             f"{reason}; {WORKAROUND}")


def original_raw(words: np.ndarray, fmt: str) -> np.ndarray:
    """The SDK's ``dirp_get_original_raw`` from the APP3 words: ``word >> 2`` for iirp (14-bit counts stored
    shifted left by 2), the words as stored for the other layouts."""
    words = np.asarray(words, dtype=np.uint16)
    return (words >> 2).astype(np.uint16) if fmt == "iirp" else words.copy()


def read_original_raw(path: str | Path) -> tuple[str, str, np.ndarray]:
    """(format, EXIF model, ``dirp_get_original_raw``) of any DJI R-JPEG, including the layouts whose
    temperatures are refused (hirp, girp); a file without the APP3 payload of its frame is a ``DataError``."""
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
    raw = b"".join(layout.payloads(jpeg.APP3))
    w, h = layout.width, layout.height
    if len(raw) != w * h * 2:
        raise DataError(f"{path}: radiometric payload (APP3) holds {len(raw)} bytes, expected {w * h * 2} for "
                        f"{w}x{h} 16-bit words ({model or 'unnamed camera'}, format {fmt or 'unknown'!r})")
    return fmt, model, original_raw(np.frombuffer(raw, dtype="<u2").reshape(h, w), fmt)
