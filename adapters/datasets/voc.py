"""One Pascal-VOC reader for every dataset that ships VOC XML annotations (M3FD, LLVIP, the FLIR-aligned release).

**The pixel convention.** VOC XMLs written by the VOC devkit and by labelImg (the tool M3FD and LLVIP were labelled
with) give ``<bndbox>`` in **1-based, inclusive pixel indices**: the top-left pixel of the image is ``(1, 1)`` and a
box covering the whole ``W x H`` image is ``xmin=1, ymin=1, xmax=W, ymax=H``. The harness's boxes are continuous
0-based corners (the COCO frame: the whole image is ``[0, 0, W, H]``). The conversion is therefore::

    x1 = xmin - 1,   y1 = ymin - 1,   x2 = xmax,   y2 = ymax          (convention "one-based", the default)

which is what the VOC evaluation and Detectron2's VOC reader do. Reading the numbers as 0-based corners instead
cuts one pixel off every box's left and top edge, which matters on boxes a few pixels wide. Files known to be
written as 0-based continuous corners (for example by a COCO-to-VOC converter) are read as written with the
convention ``"zero-based"`` (the ``voc_convention`` option of the adapters).

**Float coordinates** are accepted (some converters write ``12.5``) and converted by the same rule, as Detectron2
does; they are counted so the prepare report can say how many there were.

**``<difficult>``.** The VOC evaluation leaves difficult objects out of the score (a detection on one is neither a
true nor a false positive). The harness's samples have no ignore regions, so a difficult box is left out of both the
training targets and the ground truth that is scored (``difficult="drop"``, the default; a detection on it then
counts as a false positive, which the report's note states), or treated as an ordinary object
(``difficult="keep"``). Every conversion is summed up in ``VocStats`` and written to the prepare report.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from adapters.datasets._eightbit import option_choice
from adapters.datasets._paired import SkipPair
from harness.errors import DataError

CONVENTIONS = ("one-based", "zero-based")
DIFFICULT = ("drop", "keep")
#: The spellings of each convention that the ``voc_convention`` option accepts.
_CONVENTION_NAMES = {
    "one-based": ("one-based", "1", "1-based", "voc", "labelimg"),
    "zero-based": ("zero-based", "0", "0-based", "continuous"),
}


@dataclass(frozen=True)
class VocObject:
    """One ``<object>`` as written: its name, ``<bndbox>`` numbers and ``<difficult>`` flag."""

    name: str
    xmin: float
    ymin: float
    xmax: float
    ymax: float
    difficult: bool = False

    @property
    def has_float(self) -> bool:
        return any(v != int(v) for v in (self.xmin, self.ymin, self.xmax, self.ymax))


@dataclass
class VocAnnotation:
    """A parsed VOC XML: ``<size>`` (``None`` when absent or empty) and the objects in file order."""

    width: int | None
    height: int | None
    objects: list[VocObject]


def normalise_convention(dataset: str, value: object) -> str:
    expected = "one-based (VOC/labelImg, default) or zero-based (0-based corners taken as written)"
    return option_choice(dataset, "voc_convention", value, _CONVENTION_NAMES, expected)


def normalise_difficult(dataset: str, value: object) -> str:
    expected = "drop (left out of training and scoring, default) or keep (an ordinary object)"
    return option_choice(dataset, "difficult", value, {d: (d,) for d in DIFFICULT}, expected)


def parse_voc(path: Path) -> VocAnnotation:
    """Read a Pascal-VOC XML; a malformed file or field is a ``DataError`` naming the file (and line/column)."""
    try:
        tree = ET.parse(path)
    except ET.ParseError as exc:
        line, col = exc.position
        raise DataError(f"{path}: malformed XML at line {line} column {col + 1}") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    root = tree.getroot()

    def number(node: ET.Element | None, tag: str, where: str) -> float:
        text = node.findtext(tag) if node is not None else None
        try:
            value = float(str(text).strip())
        except ValueError:
            raise DataError(f"{path}: {where}: <{tag}> must be a number, got {text!r}") from None
        if not math.isfinite(value):
            raise DataError(f"{path}: {where}: <{tag}> is not finite")
        return value

    size = root.find("size")
    width = height = None
    if size is not None and size.findtext("width") not in (None, "") and size.findtext("height") not in (None, ""):
        width, height = int(number(size, "width", "<size>")), int(number(size, "height", "<size>"))
    objects = []
    for i, obj in enumerate(root.findall("object")):
        name = (obj.findtext("name") or "").strip()
        box = obj.find("bndbox")
        where = f"object {i} ({name or 'no name'})"
        if box is None:
            raise DataError(f"{path}: {where}: no <bndbox>")
        flag = (obj.findtext("difficult") or "0").strip()
        if flag not in ("0", "1", "0.0", "1.0", "true", "false", "True", "False"):
            raise DataError(f"{path}: {where}: <difficult> must be 0 or 1, got {flag!r}")
        coords = [number(box, t, where) for t in ("xmin", "ymin", "xmax", "ymax")]
        objects.append(VocObject(name, *coords, difficult=flag in ("1", "1.0", "true", "True")))
    return VocAnnotation(width, height, objects)


def read_known(path: Path, names: Sequence[str], expected: str) -> VocAnnotation:
    """``parse_voc``, where every object must be one of ``names`` (lower case; the file's names are matched without
    case and surrounding spaces). A malformed file or another class is a ``SkipPair`` of the file (``expected``
    ends the message: "'dog' is not <expected>")."""
    try:
        ann = parse_voc(path)
    except DataError as exc:
        raise SkipPair(f"malformed annotation: {exc}", path) from None
    unknown = sorted({o.name for o in ann.objects if o.name.strip().lower() not in names})
    if unknown:
        raise SkipPair(f"unknown class: {', '.join(map(repr, unknown))} is not {expected}", path)
    return ann


def check_size(ann: VocAnnotation, path: Path, width: int, height: int) -> None:
    """A ``<size>`` other than the images' is a ``SkipPair`` of the file (an absent or zero size is not checked)."""
    if ann.width and ann.height and (ann.width, ann.height) != (width, height):
        raise SkipPair(f"size mismatch: <size> says {ann.width}x{ann.height}, images are {width}x{height}", path)


def to_xyxy(objects: list[VocObject], convention: str = "one-based") -> np.ndarray:
    """The objects' boxes as 0-based continuous corners ``[x1, y1, x2, y2]`` (float64 Nx4), see the module doc."""
    xyxy = np.array([[o.xmin, o.ymin, o.xmax, o.ymax] for o in objects], dtype=np.float64).reshape(-1, 4)
    if convention == "one-based":
        xyxy[:, :2] -= 1.0
    elif convention != "zero-based":
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    return xyxy


@dataclass
class VocStats:
    """What the VOC reader did over a whole dataset (written to the prepare report)."""

    convention: str = "one-based"
    difficult_mode: str = "drop"
    boxes: int = 0
    difficult: int = 0
    floats: int = 0

    def add(self, objects: list[VocObject]) -> None:
        self.boxes += len(objects)
        self.difficult += sum(o.difficult for o in objects)
        self.floats += sum(o.has_float for o in objects)

    def targets(self, ann: VocAnnotation, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Count ``ann``'s objects, leave out the difficult ones when they are dropped, and return the boxes as
        0-based corners (float64 Nx4) and the labels (the index in ``names`` of each lower-cased name)."""
        self.add(ann.objects)
        objects = [o for o in ann.objects if not (o.difficult and self.difficult_mode == "drop")]
        labels = np.array([list(names).index(o.name.strip().lower()) for o in objects], dtype=np.int64)
        return to_xyxy(objects, self.convention), labels

    def note(self) -> str:
        if self.convention == "one-based":
            rule = (
                "VOC boxes read as 1-based inclusive pixel indices (VOC/labelImg) and converted to 0-based "
                "corners (xmin - 1, ymin - 1, xmax, ymax)"
            )
        else:
            rule = "VOC boxes read as 0-based corners, as written (voc_convention: zero-based)"
        if self.difficult_mode == "drop":
            diff = (
                f"{self.difficult} difficult box(es) left out of training targets and scoring "
                f"(a detection on one counts as a false positive)"
            )
        else:
            diff = f"{self.difficult} difficult box(es) kept as ordinary objects (difficult: keep)"
        return f"{rule}; {self.boxes} boxes read, {self.floats} with fractional coordinates; {diff}"
