"""COCO JSON validation shared by every COCO-based dataset adapter (``m3t``, ``coco-rgbt``, ``rgbt-tiny``).

``read_coco(path, hint)`` reads one COCO detection file and checks it the same way for every adapter:

* **The file**: missing, a folder, empty, invalid JSON (with line and column), not an object, or ``images`` /
  ``categories`` / ``annotations`` not lists: a ``DataError`` naming the file (``hint`` says where to name another).
* **Ids** are read by the rule of the evaluation (``harness.evaluation.inputs``): ``12``, ``"12"`` and ``12.0`` are
  the same id. Image ids that are non-numeric strings (``"a_001"``) are numbered 1..N in the order of ``images[]``,
  as the evaluation numbers them, and the original id is kept (``CocoImage.original_id``). A boolean, an empty or a
  fractional id is an error naming the record. Category ids must be integers (or numeric strings).
* **Duplicates**: two images with the same id (``12`` and ``"12"`` included), one file listed twice, two categories
  with the same id or the same name: a ``DataError`` naming both records. They stop the preparation before anything
  is cached.
* **Annotations that cannot be used** (unknown image or category id, malformed box, duplicate annotation id) are
  returned as ``issues`` (``(where, reason)``, reasons starting with ``annotation``): the adapter reports them as
  counted skips, and the preparation's plausibility guard (``harness.input_guard``) stops unless the risk is
  accepted, because a dropped box leaves an unlabelled object that training learns as background.

``box_reading(boxes)`` is the adapters' check of the box convention: COCO ``bbox`` is ``[x, y, width, height]``;
boxes written as corners (``x1, y1, x2, y2``) or with ``y`` first reach past the frame's edge when read as COCO,
and fit inside it read the way they were written.

The adapters add their own fields on top (``CocoImage.entry`` is the raw record): the M3T's ``project`` and
``date_captured``, coco-rgbt's ``thermal_file_name``, ``group`` and ``homography``.
"""

from __future__ import annotations

import math
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from harness.errors import DataError

_INT_RE = re.compile(r"^[+-]?\d+$")
#: How many examples a message about many records quotes.
EXAMPLES = 3


def coco_id(value: Any) -> int | str | None:
    """An id as the evaluation compares it: ``12``, ``"12"`` and ``12.0`` are ``12``; a non-numeric string is kept;
    anything else (a boolean, an empty string, a fraction, a list) is ``None``."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return int(value) if math.isfinite(value) and value.is_integer() else None
    if isinstance(value, str):
        s = value.strip()
        if _INT_RE.match(s):
            return int(s)
        return s or None
    return None


@dataclass
class CocoImage:
    """One ``images[]`` entry: its id (an integer, see the module docstring), file and size as written."""

    id: int
    file_name: str
    width: int | None
    height: int | None
    entry: dict[str, Any]
    original_id: Any = None


@dataclass
class CocoAnnotation:
    """One usable annotation: ids resolved (``id`` is ``None`` when the record has none), ``bbox`` ``[x, y, w, h]``
    four finite numbers with ``w, h > 0``."""

    id: Any
    image_id: int
    category_id: int
    bbox: list[float]
    entry: dict[str, Any]


@dataclass
class CocoFile:
    """A checked COCO file: images in file order, categories ``{id: name}`` in file order, usable annotations, and
    the annotations that cannot be used as ``issues`` ``(where, reason)``."""

    path: Path
    images: list[CocoImage]
    categories: dict[int, str]
    annotations: list[CocoAnnotation]
    issues: list[tuple[str, str]] = field(default_factory=list)
    renumbered: bool = False
    #: the file's top-level object (for the adapter's own keys)
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    def by_image(self) -> dict[int, list[CocoAnnotation]]:
        out: dict[int, list[CocoAnnotation]] = defaultdict(list)
        for a in self.annotations:
            out[a.image_id].append(a)
        return out


def load_coco_json(path: Path, hint: str = "") -> dict[str, Any]:
    """The file's top-level object, with ``images`` and ``categories`` lists and an ``annotations`` list (``[]`` when
    absent); every problem is a ``DataError`` naming the file."""
    from harness.io import read_json

    tail = f"; {hint}" if hint else ""
    if not path.exists():
        raise DataError(f"{path}: annotation file not found{tail}")
    if path.is_dir():
        raise DataError(f"{path}: is a folder, not a COCO JSON file{tail}")
    if not path.read_bytes().strip():
        raise DataError(
            f"{path}: annotation file is empty; expected a COCO JSON object with 'images', "
            "'annotations' and 'categories'"
        )
    coco = read_json(path)
    if not isinstance(coco, dict):
        raise DataError(f"{path}: expected a COCO JSON object, got a {type(coco).__name__}")
    for key in ("images", "categories"):
        if not isinstance(coco.get(key), list):
            raise DataError(f"{path}: COCO key {key!r} is missing or not a list")
    if not isinstance(coco.setdefault("annotations", []), list):
        raise DataError(f"{path}: COCO key 'annotations' is not a list")
    return coco


def _size(value: Any) -> int | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return int(value)


def read_categories(path: Path, coco: dict[str, Any]) -> dict[int, str]:
    """``{id: name}`` in file order; a category without an integer id or a name, or a duplicate id or name, is a
    ``DataError`` naming the file."""
    cats: dict[int, str] = {}
    for i, cat in enumerate(coco["categories"]):
        cid = coco_id(cat.get("id")) if isinstance(cat, dict) else None
        name = cat.get("name") if isinstance(cat, dict) else None
        if not isinstance(cid, int) or not isinstance(name, str) or not name.strip():
            raise DataError(
                f"{path}: categories[{i}]: every category needs an integer 'id' and a non-empty 'name', "
                f"got {str(cat)[:120]}"
            )
        if cid in cats:
            raise DataError(f"{path}: duplicate category id {cid} ({cats[cid]!r} and {name!r})")
        if name in cats.values():
            raise DataError(f"{path}: category name {name!r} is used by two category ids")
        cats[cid] = name
    return cats


def read_images(path: Path, coco: dict[str, Any]) -> tuple[list[CocoImage], bool]:
    """The images in file order with integer ids (non-numeric string ids numbered 1..N, see the module docstring)
    and whether they were renumbered; malformed and duplicate entries are ``DataError``s naming both records."""
    keys: list[int | str] = []
    for i, entry in enumerate(coco["images"]):
        if not isinstance(entry, dict) or "id" not in entry or "file_name" not in entry:
            raise DataError(f"{path}: images[{i}]: every image needs 'id' and 'file_name', got {str(entry)[:120]}")
        key = coco_id(entry["id"])
        if key is None:
            raise DataError(
                f"{path}: images[{i}] ({entry['file_name']}): image id {entry['id']!r} is neither an "
                f"integer nor a non-empty string"
            )
        keys.append(key)
    renumber = not all(isinstance(k, int) for k in keys)
    images: list[CocoImage] = []
    by_id: dict[int | str, CocoImage] = {}
    by_name: dict[str, CocoImage] = {}
    for n, (key, entry) in enumerate(zip(keys, coco["images"])):
        fname = str(entry["file_name"])
        if key in by_id:
            first = by_id[key]
            raise DataError(
                f"{path}: duplicate image id {key!r} ({first.file_name!r} and {fname!r}); image ids must "
                f'be unique (12, "12" and 12.0 are the same id)'
            )
        if fname in by_name:
            raise DataError(
                f"{path}: file {fname!r} is listed twice (image ids {by_name[fname].original_id!r} and {entry['id']!r})"
            )
        image = CocoImage(
            n + 1 if renumber else int(key),
            fname,
            _size(entry.get("width")),
            _size(entry.get("height")),
            entry,
            entry["id"],
        )
        by_id[key] = by_name[fname] = image
        images.append(image)
    return images, renumber


def read_coco(path: Path, hint: str = "") -> CocoFile:
    """Read and check a COCO detection file (see the module docstring)."""
    coco = load_coco_json(path, hint)
    cats = read_categories(path, coco)
    images, renumbered = read_images(path, coco)
    internal = {coco_id(im.original_id): im.id for im in images}
    issues: list[tuple[str, str]] = []
    anns: list[CocoAnnotation] = []
    seen: dict[Any, Any] = {}
    for i, ann in enumerate(coco["annotations"]):
        aid = ann.get("id", f"[{i}]") if isinstance(ann, dict) else f"[{i}]"
        where = f"{path.name}#annotation={aid}"
        if not isinstance(ann, dict):
            issues.append((where, "annotation malformed: not an object"))
            continue
        if "id" in ann:
            key = coco_id(ann["id"])
            if key in seen:
                issues.append(
                    (
                        where,
                        f"annotation with a duplicate id: {ann['id']!r} is used twice (image ids "
                        f"{seen[key]!r} and {ann.get('image_id')!r})",
                    )
                )
                continue
            seen[key] = ann.get("image_id")
        image_id = internal.get(coco_id(ann.get("image_id")))
        if image_id is None:
            issues.append((where, f"annotation for an unknown image id: {ann.get('image_id')!r}"))
            continue
        cid = coco_id(ann.get("category_id"))
        if cid not in cats:
            known = ", ".join(f"{k} {v}" for k, v in cats.items())
            issues.append(
                (
                    where,
                    f"annotation with an unknown category id: {ann.get('category_id')!r} (the categories are {known})",
                )
            )
            continue
        box = parse_bbox(ann.get("bbox"))
        if box is None:
            issues.append(
                (where, f"annotation box malformed: {str(ann.get('bbox'))[:80]} (expected [x, y, w, h] with w, h > 0)")
            )
            continue
        aid_key = coco_id(ann["id"]) if "id" in ann else None
        anns.append(CocoAnnotation(aid_key, image_id, int(cid), box, ann))  # type: ignore[arg-type]
    return CocoFile(path, images, cats, anns, issues, renumbered, coco)


def parse_bbox(value: Any) -> list[float] | None:
    """``[x, y, w, h]`` as four finite floats with ``w, h > 0`` (numbers written as strings are read, as the
    evaluation reads them), or ``None``."""
    if not isinstance(value, (list, tuple)) or len(value) != 4 or any(isinstance(v, bool) for v in value):
        return None
    try:
        box = [float(v) for v in value]
    except (TypeError, ValueError):
        return None
    if not all(math.isfinite(v) for v in box) or box[2] <= 0 or box[3] <= 0:
        return None
    return box


#: ``box_reading``: the share (and count) of boxes reaching past the frame as given above which another reading that
#: fits them all is the finding
PAST_EDGE_SHARE = 0.1
PAST_EDGE_MIN = 3
#: how far past the edge (px) a box may reach before it counts (rounding at the border)
EDGE_TOL = 1.0
#: the readings ``box_reading`` tries: name, [x, y, w, h] of a written box
_READINGS = (
    ("x1, y1, x2, y2 (corners)", lambda b: (b[0], b[1], b[2] - b[0], b[3] - b[1])),
    ("y, x, h, w (y first)", lambda b: (b[1], b[0], b[3], b[2])),
)


def _past_edge(x: float, y: float, w: float, h: float, width: int, height: int) -> bool:
    return w <= 0 or h <= 0 or x < -EDGE_TOL or y < -EDGE_TOL or x + w > width + EDGE_TOL or y + h > height + EDGE_TOL


def box_reading(boxes: list[tuple[list[float], int, int]]) -> str | None:
    """``(bbox [x, y, w, h] as written, frame width, frame height)`` of every annotation: a sentence saying what was
    seen when at least ``PAST_EDGE_SHARE`` (and ``PAST_EDGE_MIN``) of them reach past the frame read as COCO
    ``[x, y, w, h]`` and another reading (corners, ``y`` first) fits every one inside; ``None`` otherwise."""
    n = len(boxes)
    given = sum(_past_edge(*b, w, h) for b, w, h in boxes)
    if n == 0 or given < max(PAST_EDGE_MIN, PAST_EDGE_SHARE * n):
        return None
    for name, read in _READINGS:
        if not any(_past_edge(*read(b), w, h) for b, w, h in boxes):
            return (
                f"{given} of {n} boxes reach past their frame's edge read as COCO [x, y, width, height], none read "
                f"as {name}: the bbox values look written as {name.split(' (')[0]}; write [x, y, width, height] "
                f"(top-left corner, size) in the thermal frame's pixels"
            )
    return None
