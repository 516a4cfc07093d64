"""How a prepared dataset stores its pixels: the cache forms, the lossless codecs of the compact form and source
references.

Forms (``manifest.json`` key ``form``; a manifest without it is ``raw``):

``raw``
    every channel uncompressed and memory-mapped (``rgb.u8``, ``ir8.u8``, ``thermal.f32``, ``enc/*.u8``).
``compact`` (the default)
    each sample's channels compressed losslessly, back to back in ``rgb.pack``, ``ir8.pack``, ``thermal.pack``
    (offsets in ``samples.json``):

    * 8-bit images (RGB, 8-bit thermal, encodings): with the optional ``zstandard`` package (extra
      ``fast-cache``), each row's left-neighbour differences compressed with zstd level 1 (``zstd``); without it,
      PNG at compression level 1 through OpenCV (``png``). Measured on 640x512 RGB: both about half of the raw
      bytes, ``zstd`` decodes about three times faster; lossless WebP is a third smaller but decodes no faster than
      PNG and is about ten times slower to write; zlib without the difference filter is larger. The codec is
      recorded in the manifest (``codec``).
    * temperatures: the float32 map as an index image into the frame's table of distinct values (its bit
      patterns, sorted, so the index grows with temperature): a radiometric frame holds at most a few thousand
      distinct values (the sensor's integer counts through one calibration curve), so the indices are the source's
      own integers up to the table's order and the round trip is exact bit for bit (NaN payloads included). A
      frame with more than 65,536 distinct values is stored as byte-shuffled zlib float32, still exact.
    * an 8-bit sample whose pixels are exactly what the harness's reader decodes from the dataset's own files
      (a dataset without a sensing stage: RGBT-Tiny, M3FD, ...) is not copied at all: the record names the files
      (relative to the dataset folder) and a digest of the decoded pixels, checked the first time a process loads
      the sample (``harness cache verify`` checks all), so a changed or re-encoded source file is an error naming
      it rather than different samples.

Loading is transparent: ``PreparedDataset[i]`` returns the same arrays in every form.
"""

from __future__ import annotations

import hashlib
import zlib
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from harness.errors import DataError

#: Version of the folder layout (``manifest.json`` ``schema``); a cache of another schema is prepared again.
PREPARED_SCHEMA = 1
FORMS = ("compact", "raw")
DEFAULT_FORM = "compact"
ENV_FORM = "HARNESS_CACHE_FORM"
PNG_LEVEL = 1
ZSTD_LEVEL = 1
U8_CODECS = ("png", "zstd")


def default_u8_codec() -> str:
    """``zstd`` when the ``zstandard`` package is installed, else ``png``."""
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return "png"
    return "zstd"


def zstd_module(where: str) -> Any:
    try:
        import zstandard
    except ImportError:
        raise DataError(
            f"{where}: this prepared dataset is compressed with zstd; `pip install zstandard` (extra "
            f"rgbt-harness[fast-cache]) or prepare it again without"
        ) from None
    return zstandard


def check_form(form: str) -> str:
    if form not in FORMS:
        raise DataError(f"unknown cache form {form!r}; choose one of {', '.join(FORMS)}")
    return form


# ------------------------------------------------------------------------------------------------ 8-bit images
def encode_u8(img: np.ndarray, codec: str = "png") -> bytes:
    """Lossless ``png`` or ``zstd`` bytes of a uint8 HxW or HxWx3 (channel order kept as stored)."""
    import cv2

    if codec == "zstd":
        img = np.ascontiguousarray(img)
        delta = np.diff(img, axis=1, prepend=np.zeros_like(img[:, :1]))
        return zstd_module("zstd").ZstdCompressor(level=ZSTD_LEVEL).compress(delta.tobytes())

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 PNG
        raise DataError("PNG encoding failed")
    return buf.tobytes()


def decode_u8(data: np.ndarray | bytes, shape: tuple[int, ...], where: str, codec: str = "png") -> np.ndarray:
    import cv2

    if codec == "zstd":
        z = zstd_module(where)
        try:
            flat = np.frombuffer(z.ZstdDecompressor().decompress(np.ascontiguousarray(data).data), np.uint8)
            return np.cumsum(flat.reshape(shape), axis=1, dtype=np.uint8)
        except (z.ZstdError, ValueError) as exc:
            raise DataError(f"{where}: damaged compressed image ({exc}); prepare again") from None

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.shape != shape:
        got = None if img is None else img.shape
        raise DataError(f"{where}: damaged compressed image (decoded {got}, expected {shape}); prepare again")
    return img


# ------------------------------------------------------------------------------------------------ temperatures
def encode_f32(t: np.ndarray) -> bytes:
    """Exact float32 map -> bytes: ``b"P" + n + table(zlib) + uint16 PNG index`` or ``b"Z" + shuffled zlib``."""
    bits = np.ascontiguousarray(t, dtype=np.float32).view(np.uint32)
    table, index = np.unique(bits, return_inverse=True)
    if len(table) <= 65536:
        import cv2

        order = np.argsort(table.view(np.float32), kind="stable")  # index grows with temperature (NaN last)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        idx = rank[index.reshape(bits.shape)].astype(np.uint16)
        ok, png = cv2.imencode(".png", idx, [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
        tab = zlib.compress(table[order].astype("<u4").tobytes(), 6)
        return b"P" + len(tab).to_bytes(4, "little") + tab + png.tobytes()
    shuffled = bits.astype("<u4").view(np.uint8).reshape(-1, 4).T.tobytes()
    return b"Z" + zlib.compress(shuffled, 1)


def decode_f32(data: np.ndarray | bytes, shape: tuple[int, int], where: str) -> np.ndarray:
    buf = np.frombuffer(data, np.uint8).data
    try:
        kind = bytes(buf[:1])
        if kind == b"P":
            import cv2

            n = int.from_bytes(buf[1:5], "little")
            table = np.frombuffer(zlib.decompress(buf[5 : 5 + n]), "<u4").astype(np.uint32)
            idx = cv2.imdecode(np.frombuffer(buf[5 + n :], np.uint8), cv2.IMREAD_UNCHANGED)
            if idx is None or idx.shape != shape or idx.dtype != np.uint16:
                raise ValueError("index image")
            return table[idx].view(np.float32)
        if kind == b"Z":
            raw = np.frombuffer(zlib.decompress(buf[1:]), np.uint8).reshape(4, -1).T
            return np.ascontiguousarray(raw).view("<u4").astype(np.uint32).view(np.float32).reshape(shape)
        raise ValueError(f"kind {kind!r}")
    except (ValueError, IndexError, zlib.error) as exc:
        raise DataError(f"{where}: damaged compressed temperatures ({exc}); prepare again") from None


# ------------------------------------------------------------------------------------------------ references
def pixel_digest(img: np.ndarray) -> str:
    """Digest of decoded pixels (shape, dtype and bytes)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{img.dtype.str}{img.shape}".encode())
    h.update(np.ascontiguousarray(img).data)
    return h.hexdigest()


def read_rgb_file(path: Path) -> np.ndarray | None:
    """A visible image file as uint8 HxWx3 RGB (None when it is not readable)."""
    import cv2

    try:
        data = np.fromfile(path, np.uint8)
    except OSError:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    return None if img is None else np.ascontiguousarray(img[:, :, ::-1])


#: How an 8-bit thermal file becomes one channel: as stored (grey), its middle channel, or luminance.
IR8_MODES = ("grey", "g", "luma")


def read_ir8_file(path: Path, mode: str) -> np.ndarray | None:
    import cv2

    try:
        data = np.fromfile(path, np.uint8)
    except OSError:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None or img.dtype != np.uint8:
        return None
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if mode == "grey":
        return np.ascontiguousarray(img) if img.ndim == 2 else None
    if img.ndim != 3:
        return None
    if mode == "g":
        return np.ascontiguousarray(img[:, :, 1])
    return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)


def find_reference(sample: Any, bases: Sequence[Path], files: tuple[Any, Any] | None = None) -> dict[str, Any] | None:
    """The source files holding exactly ``sample``'s RGB and 8-bit thermal pixels, or None.

    ``files``: (rgb, thermal) paths named by the dataset (``source.pixel_files(sample)``); otherwise the sample's
    ``meta["rgb_file"]`` and ``meta["file_name"]`` are looked up under each of ``bases``. Only an exact match of
    the decoded pixels is a reference.
    """
    if sample.thermal is not None:
        return None
    if files is None:
        meta = sample.meta if isinstance(sample.meta, dict) else {}
        rgb_name, ir_name = meta.get("rgb_file"), meta.get("file_name")
        if not isinstance(rgb_name, str) or not isinstance(ir_name, str):
            return None
        candidates = [(b, b / rgb_name, b / ir_name) for b in bases]
    else:
        candidates = [(b, Path(files[0]), Path(files[1])) for b in bases]
    for b, rgb_path, ir_path in candidates:
        if not (rgb_path.is_file() and ir_path.is_file()):
            continue
        rgb = read_rgb_file(rgb_path)
        if rgb is None or not np.array_equal(rgb, sample.rgb):
            continue
        for mode in IR8_MODES:
            ir8 = read_ir8_file(ir_path, mode)
            if ir8 is not None and np.array_equal(ir8, sample.ir8):
                try:
                    rel = (
                        rgb_path.resolve().relative_to(b.resolve()).as_posix(),
                        ir_path.resolve().relative_to(b.resolve()).as_posix(),
                    )
                except ValueError:  # not under this folder: perhaps under the next one
                    break
                return {
                    "base": b,
                    "rgb": rel[0],
                    "ir8": rel[1],
                    "ir8_mode": mode,
                    "digest": {"rgb": pixel_digest(sample.rgb), "ir8": pixel_digest(sample.ir8)},
                    "bytes": rgb_path.stat().st_size + ir_path.stat().st_size,
                }
        if files is None:
            break  # the pixels differ from the named files: compress them instead
    return None


def load_reference(
    base: Path, ref: dict[str, Any], shape: tuple[int, int], verify: bool, channels: Sequence[str] = ("rgb", "ir8")
) -> list[np.ndarray]:
    """The referenced files' pixels (``channels`` of ``rgb``, ``ir8``); ``verify`` compares them with the recorded
    digests. A missing, unreadable or changed file is a ``DataError`` naming it."""
    out = []
    for name in channels:
        path = base / ref[name]
        img = read_rgb_file(path) if name == "rgb" else read_ir8_file(path, ref["ir8_mode"])
        want = (*shape, 3) if name == "rgb" else shape
        if img is None:
            raise DataError(
                f"{path}: source file of a prepared sample is missing or unreadable; restore it or "
                f"prepare again (`harness prepare --force`)"
            )
        if img.shape != want or (verify and pixel_digest(img) != ref["digest"][name]):
            raise DataError(
                f"{path}: source file changed since it was prepared (decoded pixels differ from the "
                f"recorded digest); restore it or prepare again (`harness prepare --force`)"
            )
        out.append(img)
    return out
