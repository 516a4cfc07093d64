"""Checking and normalising evaluation inputs before any engine sees them.

``prepare(gt, detections)`` returns private copies with integer image ids, renumbered GT annotation ids, COCO
defaults filled in (``area = w * h``, ``iscrowd = 0``), and detections of unknown images or categories dropped and
counted (or refused with ``strict=True``). Ordinary inputs take vectorised paths; anything unusual goes record by
record so that an error can name the record.

Detections are kept as columns (numpy arrays); the per-detection COCO dicts that pycocotools needs are built only
when ``PreparedEval.dets`` is first read (the faster-coco-eval path never reads it).

The kept detections are put in one **canonical order** (``canonical_order``): by image and category, then
descending score, then box ``x, y, w, h`` ascending. COCO sorts the detections of each (image, category) by score with a
stable sort, so detections of equal score would otherwise be matched, and cut at ``maxDets``, in the order the
caller happened to list them; in canonical order the result depends only on the set of detections, and both
engines see the same order. For input already in that order (or without equal scores in an image and category)
this is exactly pycocotools' result.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from harness.errors import HarnessError

log = logging.getLogger(__name__)

_INT_RE = re.compile(r"^[+-]?\d+$")


class EvaluationError(HarnessError):
    """Ground truth or detections that cannot be scored (malformed record, unknown id, bad option)."""


def _norm_id(value: Any, where: str) -> int | str:
    """An image or category id as the key it is compared by: ``12``, ``"12"`` and ``12.0`` are all ``12``."""
    if isinstance(value, (bool, np.bool_)):
        raise EvaluationError(f"{where}: id {value!r} is a boolean; use an integer or a string")
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)) and math.isfinite(value) and float(value).is_integer():
        return int(value)
    if isinstance(value, str):
        s = value.strip()
        if _INT_RE.match(s):
            return int(s)
        if s:
            return s
    raise EvaluationError(f"{where}: id {value!r} is neither an integer nor a non-empty string")


def _ids_sha1(ids: Iterable[int | str]) -> str:
    """Hash of the evaluated image ids (integers as ``harness.store.image_ids_hash`` does it)."""
    ids = list(ids)
    if all(isinstance(i, int) for i in ids):
        from harness.store import image_ids_hash

        return image_ids_hash(ids)  # type: ignore[arg-type]
    return hashlib.sha1(",".join(sorted(str(i) for i in ids)).encode()).hexdigest()


def _all_type(values: list, kind: type) -> bool:
    """Every element is exactly of type ``kind`` (a C-speed check for a million-element list)."""
    return set(map(type, values)) <= {kind}


def _box(value: Any, where: str) -> list[float]:
    try:
        box = [float(v) for v in value]
    except (TypeError, ValueError):
        raise EvaluationError(f"{where}: bbox {value!r} is not four numbers [x, y, w, h]") from None
    if len(box) != 4:
        raise EvaluationError(f"{where}: bbox has {len(box)} numbers, expected 4 [x, y, w, h]")
    if not all(math.isfinite(v) for v in box):
        raise EvaluationError(f"{where}: bbox {box} is not finite")
    if box[2] < 0 or box[3] < 0:
        raise EvaluationError(f"{where}: bbox {box} has a negative width or height (COCO boxes are [x, y, w, h])")
    return box


@dataclass
class PreparedEval:
    """Ground truth and detections after checking, with internal integer image ids.

    Detection ``j`` (0-based, in canonical order after dropping unknown images and categories) has the COCO result
    id ``j + 1``; its fields are ``det_columns[...][j]``; ``det_source[j]`` is its index in the caller's list.
    """

    gt: dict[str, Any]
    cat_ids: list[int]  # sorted, as COCOeval orders them
    cat_names: dict[int, str]
    image_keys: list[int | str]  # the caller's ids (normalised), in GT order
    n_gt: dict[int, int]  # non-crowd GT per category id
    n_crowd: int
    crowd_ann_ids: set[int]
    #: the kept detections as arrays: image_id (internal), category_id, score, boxes [N, 4] (float64, checked)
    det_columns: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    #: the GT annotations (``gt["annotations"]`` order) as arrays: image_id, category_id, boxes [G, 4], iscrowd
    gt_columns: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    dropped: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: index of each kept detection in the caller's list (``det_columns`` are in canonical order)
    det_source: np.ndarray | None = None

    @property
    def n_dets(self) -> int:
        return len(self.det_columns[0])

    @cached_property
    def dets(self) -> list[dict[str, Any]]:
        """The kept detections as COCO result dicts (ids 1..N, ``area = w * h``), built on first use."""
        img, cat, score, boxes = self.det_columns
        areas = boxes[:, 2] * boxes[:, 3]
        return [
            {"id": j, "image_id": im, "category_id": c, "bbox": b, "score": sc, "area": ar}
            for j, (im, c, b, sc, ar) in enumerate(
                zip(img.tolist(), cat.tolist(), boxes.tolist(), score.tolist(), areas.tolist()), start=1
            )
        ]


def prepare(gt: Mapping[str, Any], detections: Sequence[Mapping[str, Any]], strict: bool = False) -> PreparedEval:
    """Check and normalise ``gt`` (a COCO dict) and ``detections`` (COCO results); the inputs are not modified."""
    if not isinstance(gt, Mapping):
        raise EvaluationError(f"ground truth must be a COCO dict, got {type(gt).__name__}")
    for key in ("images", "annotations", "categories"):
        if not isinstance(gt.get(key), list):
            raise EvaluationError(f"ground truth: field {key!r} is missing or not a list")
    if detections is None:
        detections = []
    if not isinstance(detections, (list, tuple)):
        raise EvaluationError(f"detections must be a list of COCO result dicts, got {type(detections).__name__}")

    # categories
    cats: list[dict[str, Any]] = []
    cat_names: dict[int, str] = {}
    for i, c in enumerate(gt["categories"]):
        where = f"ground truth categories[{i}]"
        if not isinstance(c, Mapping) or "id" not in c:
            raise EvaluationError(f"{where}: needs an 'id'")
        cid = _norm_id(c["id"], where)
        if not isinstance(cid, int):
            raise EvaluationError(f"{where}: category id {c['id']!r} must be an integer")
        name = str(c.get("name", cid))
        if cid in cat_names:
            raise EvaluationError(f"{where}: duplicate category id {cid}")
        if name in cat_names.values():
            raise EvaluationError(f"{where}: duplicate category name {name!r}")
        cat_names[cid] = name
        cats.append({"id": cid, "name": name})

    # images: internal ids are the caller's integer ids, or 1..N when any id is a non-numeric string
    keys: list[int | str] = []
    for i, im in enumerate(gt["images"]):
        where = f"ground truth images[{i}]"
        if not isinstance(im, Mapping) or "id" not in im:
            raise EvaluationError(f"{where}: needs an 'id'")
        keys.append(_norm_id(im["id"], where))
    if len(set(keys)) != len(keys):
        seen: set = set()
        dup = next(k for k in keys if k in seen or seen.add(k))  # type: ignore[func-returns-value]
        raise EvaluationError(
            f"ground truth images: image id {dup!r} appears more than once (ids 12 and '12' are the same image)"
        )
    all_int = all(isinstance(k, int) for k in keys)
    key_to_internal: dict[int | str, int] = {k: (k if all_int else n + 1) for n, k in enumerate(keys)}  # type: ignore[misc]
    images = []
    for k, im in zip(keys, gt["images"]):
        rec = {"id": key_to_internal[k], "width": im.get("width", 0), "height": im.get("height", 0)}
        images.append(rec)

    # annotations
    anns = _fast_annotations(gt["annotations"], key_to_internal, all_int, cat_names)
    if anns is None:  # something is unusual: the record-by-record path normalises it or names the bad record
        anns = _checked_annotations(gt["annotations"], key_to_internal, cat_names)
    gt_columns = _gt_columns(anns)
    g_cat, g_crowd = gt_columns[1], gt_columns[3]
    cat_sorted = np.asarray(sorted(cat_names), dtype=np.int64)
    per_cat = np.bincount(np.searchsorted(cat_sorted, g_cat[~g_crowd]), minlength=len(cat_sorted))
    n_gt = {cid: 0 for cid in cat_names}
    n_gt.update({int(c): int(k) for c, k in zip(cat_sorted, per_cat)})
    crowd_ids = set((np.flatnonzero(g_crowd) + 1).tolist())  # annotation ids are 1..N in order
    n_crowd = len(crowd_ids)
    notes: list[str] = []
    ignore_without_crowd = sum(1 for a in gt["annotations"] if a.get("ignore") and not a.get("iscrowd"))
    if ignore_without_crowd:
        msg = (
            f"{ignore_without_crowd} GT annotation(s) carry ignore=1 without iscrowd=1; COCO evaluation honours only "
            f"iscrowd, so they are scored as ordinary objects (mark ignore regions with iscrowd=1)"
        )
        log.warning(msg)
        notes.append(msg)

    columns, dropped, source = _prepare_detections(detections, key_to_internal, all_int, cat_names, strict)
    order = canonical_order(*columns)
    columns = tuple(c[order] for c in columns)  # type: ignore[assignment]
    prepared_gt = {
        "info": {"description": "harness evaluation"},
        "images": images,
        "annotations": anns,
        "categories": cats,
    }
    return PreparedEval(
        prepared_gt,
        sorted(cat_names),
        cat_names,
        keys,
        n_gt,
        n_crowd,
        crowd_ids,
        columns,
        gt_columns,
        dropped,
        notes,
        source[order],
    )


def canonical_order(
    image_ids: np.ndarray, category_ids: np.ndarray, scores: np.ndarray, boxes: np.ndarray
) -> np.ndarray:
    """The permutation that puts detections in canonical order: by image id, then category id, then descending
    score, then box ``x, y, w, h`` ascending (detections equal in all of these are interchangeable).

    Three stable sorts give the (image, category, score) order; only runs of equal (image, category, score), usually
    few, are sorted by box."""
    n = len(scores)
    if n < 2:
        return np.arange(n)
    score = np.asarray(scores, dtype=np.float64)
    order = np.argsort(-score, kind="stable")
    order = order[np.argsort(category_ids[order], kind="stable")]
    order = order[np.argsort(image_ids[order], kind="stable")]
    i, c, s = image_ids[order], category_ids[order], score[order]
    tie = (s[1:] == s[:-1]) & (c[1:] == c[:-1]) & (i[1:] == i[:-1])
    if tie.any():
        pos = np.flatnonzero(np.r_[tie, False] | np.r_[False, tie])
        run = np.cumsum(np.r_[True, ~tie])[pos]
        sub = order[pos]
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)[sub]
        order[pos] = sub[np.lexsort((b[:, 3], b[:, 2], b[:, 1], b[:, 0], run))]
    return order


def _gt_columns(anns: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """image_id, category_id, boxes [G, 4] and iscrowd of normalised GT annotations, as arrays."""
    n = len(anns)
    img = np.fromiter((a["image_id"] for a in anns), dtype=np.int64, count=n)
    cat = np.fromiter((a["category_id"] for a in anns), dtype=np.int64, count=n)
    box = np.asarray([a["bbox"] for a in anns], dtype=np.float64).reshape(-1, 4)
    crowd = np.fromiter((a["iscrowd"] for a in anns), dtype=bool, count=n)
    return img, cat, box, crowd


def _fast_annotations(anns_in: list, key_to_internal: dict, all_int: bool, cat_names: dict[int, str]) -> list | None:
    """Vectorised path for ordinary GT (dicts with integer ids and valid boxes); ``None`` when anything is unusual."""
    if not anns_in:
        return []
    try:
        img = [a["image_id"] for a in anns_in]
        cat = [a["category_id"] for a in anns_in]
        box = np.asarray([a["bbox"] for a in anns_in], dtype=np.float64)
        area = np.asarray([a["area"] if "area" in a else np.nan for a in anns_in], dtype=np.float64)
        crowd = [a.get("iscrowd", 0) for a in anns_in]
    except (KeyError, TypeError, ValueError, AttributeError):
        return None
    n = len(anns_in)
    if not (all_int and _all_type(img, int) and _all_type(cat, int)):
        return None
    if box.shape != (n, 4) or not np.isfinite(box).all() or (box[:, 2:] < 0).any():
        return None
    area = np.where(np.isnan(area), box[:, 2] * box[:, 3], area)
    if not np.isfinite(area).all() or (area < 0).any():
        return None
    img_a, cat_a = np.asarray(img, dtype=np.int64), np.asarray(cat, dtype=np.int64)
    if not np.isin(img_a, np.fromiter(key_to_internal, dtype=np.int64)).all():
        return None
    if not np.isin(cat_a, np.fromiter(cat_names, dtype=np.int64)).all():
        return None
    crowd_l = [int(bool(c)) for c in crowd]
    return [
        {"id": j, "image_id": i, "category_id": c, "bbox": b, "area": ar, "iscrowd": cr, "ignore": cr}
        for j, (i, c, b, ar, cr) in enumerate(zip(img, cat, box.tolist(), area.tolist(), crowd_l), start=1)
    ]


def _checked_annotations(anns_in: list, key_to_internal: dict, cat_names: dict[int, str]) -> list[dict[str, Any]]:
    """Record-by-record normalisation of GT annotations; an error names the annotation."""
    anns: list[dict[str, Any]] = []
    for i, a in enumerate(anns_in):
        where = f"ground truth annotations[{i}]" + (
            f" (id {a.get('id')!r})" if isinstance(a, Mapping) and "id" in a else ""
        )
        if not isinstance(a, Mapping):
            raise EvaluationError(f"{where}: not a dict")
        for key in ("image_id", "category_id", "bbox"):
            if key not in a:
                raise EvaluationError(f"{where}: field {key!r} is missing")
        img = _norm_id(a["image_id"], where)
        if img not in key_to_internal:
            raise EvaluationError(f"{where}: image_id {a['image_id']!r} is not in the ground truth's images")
        cid = _norm_id(a["category_id"], where)
        if cid not in cat_names:
            raise EvaluationError(f"{where}: category_id {a['category_id']!r} is not in the ground truth's categories")
        box = _box(a["bbox"], where)
        try:
            area = float(a.get("area", box[2] * box[3]))
        except (TypeError, ValueError):
            area = float("nan")
        if not math.isfinite(area) or area < 0:
            raise EvaluationError(f"{where}: area {a.get('area')!r} is not a finite non-negative number")
        crowd = int(bool(a.get("iscrowd", 0)))
        anns.append(
            {
                "id": len(anns) + 1,
                "image_id": key_to_internal[img],
                "category_id": cid,
                "bbox": box,
                "area": area,
                "iscrowd": crowd,
                "ignore": crowd,
            }
        )
    return anns


def _prepare_detections(
    detections: Sequence[Mapping[str, Any]],
    key_to_internal: dict,
    all_int: bool,
    cat_names: dict[int, str],
    strict: bool,
) -> tuple[tuple, dict[str, int], np.ndarray]:
    """Vectorised checks of COCO results (a million detections take well under a second); returns the kept
    detections as columns (image_id, category_id, score, boxes), the counts of dropped ones and the kept ones'
    indices in ``detections``."""
    n = len(detections)
    dropped = {"unknown_category": 0, "unknown_image": 0}
    if n == 0:
        return (
            (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 4))),
            dropped,
            np.zeros(0, dtype=np.int64),
        )
    try:
        img_raw = [d["image_id"] for d in detections]
        cat_raw = [d["category_id"] for d in detections]
        box_raw = [d["bbox"] for d in detections]
        score_raw = [d["score"] for d in detections]
    except (KeyError, TypeError):
        for i, d in enumerate(detections):
            if not isinstance(d, Mapping):
                raise EvaluationError(f"detections[{i}]: not a dict") from None
            for key in ("image_id", "category_id", "bbox", "score"):
                if key not in d:
                    raise EvaluationError(f"detections[{i}]: field {key!r} is missing") from None
        raise

    # boxes and scores
    boxes = _box_array(box_raw)
    if boxes is None or boxes.shape != (n, 4):
        for i, b in enumerate(box_raw):
            _box(b, f"detections[{i}]")
        raise EvaluationError("detections: every bbox must be four numbers [x, y, w, h]")
    bad = ~np.isfinite(boxes).all(axis=1) | (boxes[:, 2] < 0) | (boxes[:, 3] < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        _box(box_raw[i], f"detections[{i}]")
    scores = None
    if _all_type(score_raw, float):
        scores = np.fromiter(score_raw, dtype=np.float64, count=n)
    else:
        try:
            scores = np.asarray(score_raw, dtype=np.float64)
        except (TypeError, ValueError):
            pass
    if scores is None or scores.shape != (n,) or not np.isfinite(scores).all():
        for i, s in enumerate(score_raw):
            if (
                isinstance(s, (bool, np.bool_))
                or not isinstance(s, (int, float, np.integer, np.floating))
                or not math.isfinite(s)
            ):
                raise EvaluationError(f"detections[{i}]: score {s!r} is not a finite number")
        raise EvaluationError("detections: every score must be a finite number")

    # image ids (fast path: plain Python ints that the GT uses as they are)
    if all_int and _all_type(img_raw, int):
        imgs = np.fromiter(img_raw, dtype=np.int64, count=n)
        known_img = np.isin(imgs, np.fromiter(key_to_internal, dtype=np.int64, count=len(key_to_internal)))
    else:
        imgs = np.zeros(n, dtype=np.int64)
        known_img = np.zeros(n, dtype=bool)
        for i, v in enumerate(img_raw):
            internal = key_to_internal.get(_norm_id(v, f"detections[{i}]"))
            if internal is not None:
                imgs[i] = internal
                known_img[i] = True
    if _all_type(cat_raw, int):
        cats = np.fromiter(cat_raw, dtype=np.int64, count=n)
    else:
        cats = np.zeros(n, dtype=np.int64)
        for i, v in enumerate(cat_raw):
            c = _norm_id(v, f"detections[{i}]")
            cats[i] = c if isinstance(c, int) else -(2**62)
    known_cat = np.isin(cats, np.fromiter(cat_names, dtype=np.int64, count=len(cat_names)))

    n_bad_img = int((~known_img).sum())
    n_bad_cat = int((known_img & ~known_cat).sum())
    if n_bad_img or n_bad_cat:
        parts = []
        if n_bad_img:
            examples = sorted({str(img_raw[i]) for i in np.flatnonzero(~known_img)[:1000]})[:5]
            parts.append(f"{n_bad_img} on images not in the ground truth (e.g. image_id {', '.join(examples)})")
        if n_bad_cat:
            examples = sorted({str(cat_raw[i]) for i in np.flatnonzero(known_img & ~known_cat)[:1000]})[:5]
            parts.append(
                f"{n_bad_cat} of categories not in the ground truth (category_id {', '.join(examples)}; "
                f"detections use category_id = label + 1)"
            )
        msg = f"{n} detections: " + "; ".join(parts)
        if strict:
            raise EvaluationError(msg)
        log.warning("%s: dropped, not scored", msg)
        dropped = {"unknown_category": n_bad_cat, "unknown_image": n_bad_img}
        keep = known_img & known_cat
        return (imgs[keep], cats[keep], scores[keep], boxes[keep]), dropped, np.flatnonzero(keep)
    return (imgs, cats, scores, boxes), dropped, np.arange(n)


def _box_array(box_raw: list) -> np.ndarray | None:
    """``[N, 4]`` float64 array of the boxes, or ``None`` when they are not all four numbers."""
    n = len(box_raw)
    if _all_type(box_raw, list) and set(map(len, box_raw)) == {4}:
        try:  # flat, without numpy's nested-sequence discovery: several times faster for a million boxes
            return np.fromiter(itertools.chain.from_iterable(box_raw), dtype=np.float64, count=4 * n).reshape(n, 4)
        except (TypeError, ValueError):
            pass  # e.g. numbers given as strings: numpy's general conversion below decides
    try:
        return np.asarray(box_raw, dtype=np.float64)
    except (TypeError, ValueError):
        return None
