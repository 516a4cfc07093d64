"""Helpers shared by the adapters of public datasets that ship 8-bit thermal images (RGBT-Tiny, M3FD, LLVIP,
FLIR-aligned) and by coco-rgbt.

Small pure functions: read an image with explicit flags, turn an 8-bit thermal image into one channel, clip boxes
to the frame, resolve the dataset root, check plugin options, hash file stats into a fingerprint. What the sources
themselves share (counted drops, strict mode, one sample loop) is in ``adapters.datasets._paired``.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from harness.api import AlignedSample
from harness.errors import ConfigError, DataError

#: Largest per-pixel difference between the three channels of a JPEG-decoded grey image that still counts as
#: grey (chroma rounding of a grey JPEG stays within a few levels).
GREY_TOLERANCE = 8


class ImageReadError(DataError):
    """An image file exists but cannot be decoded (truncated, not an image)."""


def read_image(path: Path, flags: int) -> np.ndarray:
    """Decode ``path`` with OpenCV ``flags`` (works for non-ASCII paths); raise ``ImageReadError`` naming it."""
    import cv2

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise ImageReadError(f"{path}: cannot read ({exc.strerror})") from None
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise ImageReadError(f"{path}: not a decodable image (truncated or wrong format)")
    return img


def read_rgb(path: Path) -> np.ndarray:
    """A visible image as uint8 HxWx3 in R, G, B order (8-bit, alpha dropped, grey promoted)."""
    import cv2

    img = read_image(path, cv2.IMREAD_COLOR)
    if img.dtype != np.uint8:  # pragma: no cover - IMREAD_COLOR always gives 8 bits
        raise ImageReadError(f"{path}: expected an 8-bit image, got {img.dtype}")
    return np.ascontiguousarray(img[:, :, ::-1])


def read_thermal8(path: Path) -> tuple[np.ndarray, bool]:
    """An 8-bit thermal image as uint8 HxW, and whether it had to be converted from colour.

    Thermal JPEG/PNG files are grey images often stored with three identical channels. Those are read as one
    channel exactly. A file whose channels really differ (a false-colour palette) is converted to luminance and
    reported (``True``): luminance of a palette is not monotonic in temperature, so the caller should say so.
    """
    import cv2

    img = read_image(path, cv2.IMREAD_UNCHANGED)
    if img.dtype == np.uint16:
        raise ImageReadError(f"{path}: 16-bit thermal image; this dataset adapter expects 8-bit thermal frames")
    if img.dtype != np.uint8:
        raise ImageReadError(f"{path}: unsupported thermal pixel type {img.dtype}")
    if img.ndim == 2:
        return np.ascontiguousarray(img), False
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if img.shape[2] == 1:
        return np.ascontiguousarray(img[:, :, 0]), False
    spread = int((img.max(axis=2).astype(np.int16) - img.min(axis=2).astype(np.int16)).max())
    if spread <= GREY_TOLERANCE:
        return np.ascontiguousarray(img[:, :, 1]), False
    return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY), True


@dataclass
class BoxStats:
    """What happened while one dataset's samples were brought into the prepared format: boxes kept, clipped to the
    frame, dropped (no area inside the frame, crowd), thermal images converted from colour, images with no label
    file."""

    kept: int = 0
    clipped: int = 0
    degenerate: int = 0
    crowd: int = 0
    colour: int = 0
    unlabelled: int = 0

    def add(self, other: "BoxStats") -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    def note(self) -> str:
        """The prepare-report line about the boxes (kept, clipped, dropped for want of area)."""
        return (
            f"boxes: {self.kept} kept, {self.clipped} clipped to the frame, "
            f"{self.degenerate} dropped with no area inside the frame"
        )


def clip_boxes(xyxy: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Clip xyxy boxes to ``[0, width] x [0, height]``.

    Returns the clipped boxes (float32 Nx4), a keep mask (boxes with positive width and height after clipping)
    and how many kept boxes were changed by the clipping.
    """
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    clipped = xyxy.copy()
    clipped[:, [0, 2]] = clipped[:, [0, 2]].clip(0, width)
    clipped[:, [1, 3]] = clipped[:, [1, 3]].clip(0, height)
    keep = (clipped[:, 2] > clipped[:, 0]) & (clipped[:, 3] > clipped[:, 1])
    changed = int((np.abs(clipped - xyxy).max(axis=1) > 0)[keep].sum()) if len(xyxy) else 0
    return clipped.astype(np.float32), keep, changed


def clip_to_frame(
    xyxy: np.ndarray, labels: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, BoxStats]:
    """``clip_boxes``, then only the boxes that keep an area: contiguous boxes (float32 Nx4) and their labels, and
    what happened to them (kept, clipped, degenerate)."""
    boxes, keep, clipped = clip_boxes(xyxy, width, height)
    stats = BoxStats(kept=int(keep.sum()), clipped=clipped, degenerate=int((~keep).sum()))
    return np.ascontiguousarray(boxes[keep]), np.ascontiguousarray(np.asarray(labels)[keep]), stats


def pair_sample(
    image_id: int,
    rgb: np.ndarray,
    ir8: np.ndarray,
    xyxy: np.ndarray,
    labels: np.ndarray,
    group: str,
    meta: dict[str, Any],
) -> tuple[AlignedSample, BoxStats]:
    """One pair of a release with 8-bit thermal images as an ``AlignedSample`` (no temperature map), its boxes
    clipped to the thermal frame by ``clip_to_frame``, whose counts come back beside it."""
    h, w = ir8.shape
    boxes, labels, stats = clip_to_frame(xyxy, labels, w, h)
    sample = AlignedSample(
        image_id=image_id, rgb=rgb, thermal=None, ir8=ir8, boxes=boxes, labels=labels, group=group, meta=meta
    )
    return sample, stats


def xywh_to_xyxy(xywh: np.ndarray) -> np.ndarray:
    """COCO ``[x, y, w, h]`` (top-left corner) to ``[x1, y1, x2, y2]``."""
    b = np.asarray(xywh, dtype=np.float64).reshape(-1, 4)
    return np.concatenate([b[:, :2], b[:, :2] + b[:, 2:]], axis=1)


def resolve_root(root: str | os.PathLike | None, env: str, dataset: str, must_contain: Iterable[str]) -> Path:
    """The dataset folder: ``root`` when given, else ``$env``; it must exist and contain ``must_contain``."""
    if root is None or str(root) == "":
        value = os.environ.get(env)
        if not value:
            raise DataError(
                f"dataset {dataset!r}: no data folder given; pass --set dataset.root=/path/to/{dataset} "
                f"or set the environment variable {env}"
            )
        root = value
    path = Path(root).expanduser()
    if not path.is_dir():
        raise DataError(f"dataset {dataset!r}: data folder {path} does not exist (from dataset.root or {env})")
    missing = [m for m in must_contain if not (path / m).exists()]
    if missing:
        found = sorted(p.name for p in path.iterdir())[:12]
        raise DataError(
            f"dataset {dataset!r}: {path} is not the dataset folder: missing {', '.join(missing)} "
            f"(found: {', '.join(found) or 'nothing'}); point dataset.root or {env} at the folder that holds them"
        )
    return path


def find_release_root(
    root: str | os.PathLike | None, env: str, dataset: str, names: Iterable[str], layouts: Iterable[Iterable[str]]
) -> Path:
    """The release folder: ``root`` (else ``$env``) itself or one of the folders ``names`` inside it, the first that
    holds every sub-folder of one of ``layouts``; otherwise a ``DataError`` naming what the first layout misses."""
    path = resolve_root(root, env, dataset, ())
    needs = [tuple(need) for need in layouts]
    for folder in (path, *(path / n for n in names)):
        if any(all((folder / d).is_dir() for d in need) for need in needs):
            return folder
    return resolve_root(path, env, dataset, needs[0])  # raises, naming what is missing


def check_strict(dataset: str, strict: Any) -> bool:
    """The ``strict`` option: true or false, nothing else."""
    if not isinstance(strict, bool):
        raise ConfigError(f"dataset {dataset!r}: option 'strict' must be true or false, got {strict!r}")
    return strict


def option_choice(dataset: str, name: str, value: Any, names: Mapping[str, Sequence[str]], expected: str) -> str:
    """The choice that ``value`` of option ``name`` spells: ``names`` maps each choice to its spellings, compared in
    lower case without outer spaces; any other value is a ``ConfigError`` saying the option must be ``expected``."""
    key = str(value).strip().lower()
    for choice, spellings in names.items():
        if key in spellings:
            return choice
    raise ConfigError(f"dataset {dataset!r}: option {name!r} must be {expected}, got {value!r}")


def positive_int(dataset: str, name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < 1:
        raise ConfigError(f"dataset {dataset!r}: option {name!r} must be a positive integer, got {value!r}")
    return int(value)


def source_parts(dataset: str, version: int, root: Path, *options: Any) -> list[Any]:
    """The first parts of a source fingerprint: the dataset, its adapter's version, the resolved root and the
    values of the options that change the samples."""
    return [dataset, version, str(root.resolve()), *options]


def stat_digest(parts: Iterable[Any]) -> str:
    """SHA-1 of the string forms of ``parts`` (file stats, option values): a source fingerprint."""
    h = hashlib.sha1()
    for p in parts:
        h.update(str(p).encode("utf-8", "surrogateescape"))
        h.update(b"\0")
    return h.hexdigest()


def file_stat(path: Path) -> tuple[int, int] | None:
    """``(size, mtime_ns)`` of ``path`` or ``None`` when it does not exist."""
    try:
        st = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        return None
    return st.st_size, st.st_mtime_ns
