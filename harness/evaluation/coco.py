"""COCO box AP for every detector and dataset: one code path, two engines, checked inputs.

``evaluate(gt, detections)`` scores COCO-format detections against COCO ground truth exactly as pycocotools
defines AP (IoU thresholds 0.50:0.05:0.95, 101 recall points, at most 100 detections per image and category,
crowd GT ignored, area ranges on the GT ``area`` field). The default engine is faster-coco-eval (C++, identical
statistics); ``engine="pycocotools"`` runs the reference implementation.

Before either engine sees them, the inputs are checked and normalised, because pycocotools crashes or silently
drops on several ordinary cases:

* no detections at all: scored (AP 0 for every category with GT), not an ``IndexError``;
* images without GT: kept in the evaluated set; detections on them are false positives;
* categories without GT: AP is ``null`` for them and they are left out of every mean;
* detections of a category or an image the GT does not know: dropped, counted in
  ``metrics.dropped_detections`` and logged as a warning (``strict=True`` makes them an error);
* image ids given as ``12``, ``"12"`` or ``12.0`` are the same image; non-numeric string ids are allowed;
* GT annotation ids are renumbered 1..N (pycocotools treats a matched GT id of 0 as "unmatched");
* malformed boxes, scores or ids are an ``EvaluationError`` naming the record.

The result has the ``support``, ``metrics`` and ``per_category`` sections of ``metrics.json``
(``harness/store.py``); definitions are in ``docs/evaluation.md``.
"""

from __future__ import annotations

import contextlib
import copy
import gc
import hashlib
import io
import logging
import math
import re
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from harness.errors import HarnessError
from harness.evaluation.operating_point import OPERATING_POINT, max_f1_operating_point
from harness.evaluation.safit import ANCHORS, SAFIT_C, TINY_AREA_RANGES, safit_xywh

log = logging.getLogger(__name__)

ENGINES = ("faster-coco-eval", "pycocotools")
MATCHINGS = ("iou", "safit")
#: The 12 numbers of ``COCOeval.summarize()`` for boxes, in order.
COCO_STAT_NAMES = ("AP", "AP50", "AP75", "APs", "APm", "APl", "AR1", "AR10", "AR100", "ARs", "ARm", "ARl")
_INT_RE = re.compile(r"^[+-]?\d+$")


class EvaluationError(HarnessError):
    """Ground truth or detections that cannot be scored (malformed record, unknown id, bad option)."""


# ----------------------------------------------------------------------------------------------- input checks
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
    """Ground truth and detections after checking, with internal integer image ids."""

    gt: dict[str, Any]
    dets: list[dict[str, Any]]
    cat_ids: list[int]  # sorted, as COCOeval orders them
    cat_names: dict[int, str]
    image_keys: list[int | str]  # the caller's ids (normalised), in GT order
    n_gt: dict[int, int]  # non-crowd GT per category id
    n_crowd: int
    crowd_ann_ids: set[int]
    #: the kept detections as arrays, in ``dets`` order: image_id (internal), category_id, score
    det_columns: tuple[np.ndarray, np.ndarray, np.ndarray]
    dropped: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


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
        raise EvaluationError(f"ground truth images: image id {dup!r} appears more than once (ids 12 and '12' are the same image)")
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
    n_gt = {cid: 0 for cid in cat_names}
    crowd_ids: set[int] = set()
    for a in anns:
        if a["iscrowd"]:
            crowd_ids.add(a["id"])
        else:
            n_gt[a["category_id"]] += 1
    n_crowd = len(crowd_ids)
    notes: list[str] = []
    ignore_without_crowd = sum(1 for a in gt["annotations"] if a.get("ignore") and not a.get("iscrowd"))
    if ignore_without_crowd:
        msg = (f"{ignore_without_crowd} GT annotation(s) carry ignore=1 without iscrowd=1; COCO evaluation honours only "
               f"iscrowd, so they are scored as ordinary objects (mark ignore regions with iscrowd=1)")
        log.warning(msg)
        notes.append(msg)

    dets, columns, dropped = _prepare_detections(detections, key_to_internal, all_int, cat_names, strict)
    prepared_gt = {"info": {"description": "harness evaluation"}, "images": images, "annotations": anns, "categories": cats}
    return PreparedEval(prepared_gt, dets, sorted(cat_names), cat_names, keys, n_gt, n_crowd, crowd_ids, columns,
                        dropped, notes)


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
    if not (all_int and all(type(v) is int for v in img) and all(type(v) is int for v in cat)):
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
    return [{"id": j, "image_id": i, "category_id": c, "bbox": b, "area": ar, "iscrowd": cr}
            for j, (i, c, b, ar, cr) in enumerate(zip(img, cat, box.tolist(), area.tolist(), crowd_l), start=1)]


def _checked_annotations(anns_in: list, key_to_internal: dict, cat_names: dict[int, str]) -> list[dict[str, Any]]:
    """Record-by-record normalisation of GT annotations; an error names the annotation."""
    anns: list[dict[str, Any]] = []
    for i, a in enumerate(anns_in):
        where = f"ground truth annotations[{i}]" + (f" (id {a.get('id')!r})" if isinstance(a, Mapping) and "id" in a else "")
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
        anns.append({"id": len(anns) + 1, "image_id": key_to_internal[img], "category_id": cid, "bbox": box,
                     "area": area, "iscrowd": int(bool(a.get("iscrowd", 0)))})
    return anns


def _prepare_detections(detections: Sequence[Mapping[str, Any]], key_to_internal: dict, all_int: bool,
                        cat_names: dict[int, str], strict: bool) -> tuple[list[dict[str, Any]], tuple, dict[str, int]]:
    """Vectorised checks of COCO results (a million detections take about a second)."""
    n = len(detections)
    dropped = {"unknown_category": 0, "unknown_image": 0}
    if n == 0:
        return [], (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)), dropped
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
    try:
        boxes = np.asarray(box_raw, dtype=np.float64)
    except (TypeError, ValueError):
        boxes = None
    if boxes is None or boxes.shape != (n, 4):
        for i, b in enumerate(box_raw):
            _box(b, f"detections[{i}]")
        raise EvaluationError("detections: every bbox must be four numbers [x, y, w, h]")
    bad = ~np.isfinite(boxes).all(axis=1) | (boxes[:, 2] < 0) | (boxes[:, 3] < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        _box(box_raw[i], f"detections[{i}]")
    try:
        scores = np.asarray(score_raw, dtype=np.float64)
    except (TypeError, ValueError):
        scores = None
    if scores is None or scores.shape != (n,) or not np.isfinite(scores).all():
        for i, s in enumerate(score_raw):
            if isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, float, np.integer, np.floating)) or not math.isfinite(s):
                raise EvaluationError(f"detections[{i}]: score {s!r} is not a finite number")
        raise EvaluationError("detections: every score must be a finite number")

    # image ids (fast path: plain Python ints that the GT uses as they are)
    if all_int and all(type(v) is int for v in img_raw):
        imgs = np.asarray(img_raw, dtype=np.int64)
        known_img = np.isin(imgs, np.fromiter(key_to_internal, dtype=np.int64, count=len(key_to_internal)))
    else:
        imgs = np.zeros(n, dtype=np.int64)
        known_img = np.zeros(n, dtype=bool)
        for i, v in enumerate(img_raw):
            internal = key_to_internal.get(_norm_id(v, f"detections[{i}]"))
            if internal is not None:
                imgs[i] = internal
                known_img[i] = True
    if all(type(v) is int for v in cat_raw):
        cats = np.asarray(cat_raw, dtype=np.int64)
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
            parts.append(f"{n_bad_cat} of categories not in the ground truth (category_id {', '.join(examples)}; "
                         f"detections use category_id = label + 1)")
        msg = f"{n} detections: " + "; ".join(parts)
        if strict:
            raise EvaluationError(msg)
        log.warning("%s: dropped, not scored", msg)
        dropped = {"unknown_category": n_bad_cat, "unknown_image": n_bad_img}
    keep_mask = known_img & known_cat
    areas = boxes[:, 2] * boxes[:, 3]
    # the caller's bbox lists are shared (read-only) rather than copied when they are plain lists
    box_rows = box_raw if all(type(b) is list for b in box_raw) else boxes.tolist()
    cols = (imgs.tolist(), cats.tolist(), box_rows, scores.tolist(), areas.tolist())
    if not keep_mask.all():
        idx = np.flatnonzero(keep_mask).tolist()
        cols = tuple([c[i] for i in idx] for c in cols)  # type: ignore[assignment]
    dets = [{"id": j, "image_id": im, "category_id": c, "bbox": b, "score": sc, "area": ar}
            for j, (im, c, b, sc, ar) in enumerate(zip(*cols), start=1)]
    columns = (imgs[keep_mask], cats[keep_mask], scores[keep_mask])
    return dets, columns, dropped


# ----------------------------------------------------------------------------------------------- engines
@dataclass
class EngineResult:
    stats: list[float]  # the 12 COCO stats (-1 where undefined)
    precision: np.ndarray  # [T, R, K, A, M] as COCOeval.eval["precision"]
    iou_thrs: np.ndarray
    area_labels: list[str]
    #: for the operating point: evaluated, non-ignored detections at IoU 0.50, area "all", maxDets 100
    op_scores: np.ndarray | None = None
    op_cat_index: np.ndarray | None = None
    op_is_tp: np.ndarray | None = None


@contextlib.contextmanager
def _gc_paused() -> Any:
    """Pause the cyclic garbage collector (reference counting still frees everything); restore it afterwards."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def _silent(*_: Any, **__: Any) -> None:
    return None


def _sorted_topk(dt: list[dict[str, Any]], max_det: int) -> list[dict[str, Any]]:
    inds = np.argsort([-d["score"] for d in dt], kind="mergesort")
    return [dt[i] for i in inds[:max_det]]


def _safit_matrix(gt: list[dict[str, Any]], dt: list[dict[str, Any]], max_det: int, anchor: str) -> Any:
    if len(gt) == 0 or len(dt) == 0:
        return []
    dt = _sorted_topk(dt, max_det)
    g = np.array([o["bbox"] for o in gt], dtype=np.float64)
    d = np.array([o["bbox"] for o in dt], dtype=np.float64)
    crowd = np.array([bool(o.get("iscrowd", 0)) for o in gt])
    return safit_xywh(d, g, crowd, SAFIT_C, anchor)  # type: ignore[arg-type]


def _faster_eval_class(matching: str, anchor: str) -> type:
    from faster_coco_eval.core.faster_eval_api import COCOeval_faster

    if matching == "iou":
        return COCOeval_faster

    class SAFitEvalFaster(COCOeval_faster):  # type: ignore[misc, valid-type]
        def computeIoU(self, imgId: int, catId: int) -> Any:  # noqa: N802 (COCOeval's name)
            p = self.params
            cat = [catId] if p.useCats else p.catIds
            gt = self.gt_dataset.get_instances([imgId], cat, bool(p.useCats))[0][0]
            dt = self.dt_dataset.get_instances([imgId], cat, bool(p.useCats))[0][0]
            return _safit_matrix(gt, dt, p.maxDets[-1], anchor)

    return SAFitEvalFaster


def _pycoco_eval_class(matching: str, anchor: str) -> type:
    from pycocotools.cocoeval import COCOeval

    if matching == "iou":
        return COCOeval

    class SAFitEvalPycoco(COCOeval):  # type: ignore[misc, valid-type]
        def computeIoU(self, imgId: int, catId: int) -> Any:  # noqa: N802
            p = self.params
            if p.useCats:
                gt, dt = self._gts[imgId, catId], self._dts[imgId, catId]
            else:
                gt = [o for c in p.catIds for o in self._gts[imgId, c]]
                dt = [o for c in p.catIds for o in self._dts[imgId, c]]
            return _safit_matrix(gt, dt, p.maxDets[-1], anchor)

    return SAFitEvalPycoco


def run_engine(prep: PreparedEval, engine: str = "faster-coco-eval", matching: str = "iou", anchor: str = "center",
               area_ranges: Mapping[str, tuple[float, float]] | None = None, operating_point: bool = True) -> EngineResult:
    """Run one engine on prepared inputs. ``area_ranges`` replaces COCO's small/medium/large (first must be 'all')."""
    if engine not in ENGINES:
        raise EvaluationError(f"unknown evaluation engine {engine!r}; use one of {', '.join(ENGINES)} (config eval.engine)")
    if matching not in MATCHINGS:
        raise EvaluationError(f"unknown matching {matching!r}; use one of {', '.join(MATCHINGS)} (config eval.matching)")
    if anchor not in ANCHORS:
        raise EvaluationError(f"unknown SAFit NWD anchor {anchor!r}; use one of {', '.join(ANCHORS)} (config eval.safit_anchor)")
    if engine == "faster-coco-eval":
        return _run_faster(prep, matching, anchor, area_ranges, operating_point)
    return _run_pycocotools(prep, matching, anchor, area_ranges, operating_point)


def _run_faster(prep: PreparedEval, matching: str, anchor: str, area_ranges: Mapping[str, tuple[float, float]] | None,
                want_op: bool) -> EngineResult:
    from faster_coco_eval.core.coco import COCO

    gt = COCO(prep.gt, print_function=_silent)
    dt = COCO({"images": prep.gt["images"], "categories": prep.gt["categories"], "annotations": prep.dets},
              print_function=_silent)
    ranges = None
    if area_ranges is not None:
        ranges = {k: list(v) for k, v in area_ranges.items() if k != "all"}
    cls = _faster_eval_class(matching, anchor)
    ev = cls(gt, dt, iouType="bbox", print_function=_silent, ranges=ranges)
    ev.params.imgIds = [im["id"] for im in prep.gt["images"]]
    ev.params.catIds = list(prep.cat_ids)
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    result = EngineResult(list(map(float, ev.stats[:12])), np.asarray(ev.eval["precision"]),
                          np.asarray(ev.params.iouThrs), list(ev.params.areaRngLbl))
    if want_op:
        try:
            matches = _faster_matches_at_50(ev)
        except (AttributeError, TypeError, RuntimeError, KeyError) as exc:  # faster-coco-eval internals changed
            log.debug("faster-coco-eval C++ matching unavailable (%s); matching in Python", exc)
            matches = _python_matches_at_50(ev)
        _fill_operating_inputs(result, prep, matches)
    return result


def _faster_matches_at_50(ev: Any) -> dict[int, int]:
    """COCO's own matching at IoU 0.50, area 'all', last maxDets: detection id -> GT id.

    faster-coco-eval's ``eval["matched"]`` is the union over all thresholds and area ranges, so the C++ image
    evaluation is re-run once on the already computed IoU matrices with only that threshold and area range.
    """
    import faster_coco_eval.faster_eval_api_cpp as _C

    p = ev.params
    ious = [[ev.ious[i, c] for c in p.catIds] for i in p.imgIds]
    all_range = [list(p.areaRng[0])]
    evals = _C.COCOevalEvaluateImages(all_range, p.maxDets[-1], [0.5], ious, ev.gt_dataset, ev.dt_dataset,
                                      p.imgIds, p.catIds, bool(p.useCats))
    params = copy.deepcopy(ev._paramsEval)
    params.iouThrs = np.array([0.5])
    params.areaRng = all_range
    params.areaRngLbl = ["all"]
    params.maxDets = [p.maxDets[-1]]
    acc = _C.COCOevalAccumulate(params, evals)
    out: dict[int, int] = {}
    for key in acc["matched"]:
        d, g = key.split("_", 1)
        out[int(d)] = int(g)
    return out


def _python_matches_at_50(ev: Any) -> dict[int, int]:
    """COCOeval.evaluateImg's greedy matching at IoU 0.50, area 'all', on faster-coco-eval's IoU matrices."""
    p = ev.params
    out: dict[int, int] = {}
    thr = min(0.5, 1 - 1e-10)
    for img in p.imgIds:
        for cat in p.catIds:
            ious = ev.ious.get((img, cat))
            if ious is None or len(ious) == 0:
                continue
            gts = ev.gt_dataset.get_instances([img], [cat], True)[0][0]
            dts = _sorted_topk(ev.dt_dataset.get_instances([img], [cat], True)[0][0], p.maxDets[-1])
            ignore = np.array([int(g.get("iscrowd", 0)) for g in gts])
            gtind = np.argsort(ignore, kind="mergesort")
            ious = np.asarray(ious)[:, gtind]
            gts = [gts[i] for i in gtind]
            ignore = ignore[gtind]
            taken = np.zeros(len(gts), dtype=bool)
            for di, d in enumerate(dts):
                best, m = thr, -1
                for gi in range(len(gts)):
                    if taken[gi] and not ignore[gi]:
                        continue
                    if m > -1 and ignore[m] == 0 and ignore[gi] == 1:
                        break
                    if ious[di, gi] < best:
                        continue
                    best, m = ious[di, gi], gi
                if m > -1:
                    taken[m] = True
                    out[int(d["id"])] = int(gts[m]["id"])
    return out


def _fill_operating_inputs(result: EngineResult, prep: PreparedEval, matches: dict[int, int]) -> None:
    """Evaluated detections (top 100 per image and category by score), without those matched to crowd GT."""
    dets = prep.dets
    if not dets:
        result.op_scores = np.zeros(0)
        result.op_cat_index = np.zeros(0, dtype=np.int64)
        result.op_is_tp = np.zeros(0, dtype=bool)
        return
    n = len(dets)
    img, cat, score = prep.det_columns
    ids = np.arange(1, n + 1)
    # rank within (image, category) by descending score, ties in input order (COCOeval's stable sort)
    order = np.lexsort((ids, -score, cat, img))
    grp = np.concatenate([[True], (img[order][1:] != img[order][:-1]) | (cat[order][1:] != cat[order][:-1])])
    starts = np.flatnonzero(grp)
    rank = np.arange(n) - np.repeat(starts, np.diff(np.append(starts, n)))
    evaluated = np.zeros(n, dtype=bool)
    evaluated[order[rank < 100]] = True
    matched_gt = np.zeros(n, dtype=np.int64)
    if matches:
        d_ids = np.fromiter(matches.keys(), dtype=np.int64, count=len(matches))
        g_ids = np.fromiter(matches.values(), dtype=np.int64, count=len(matches))
        matched_gt[d_ids - 1] = g_ids
    crowd = np.zeros(n, dtype=bool)
    if prep.crowd_ann_ids:
        crowd = np.isin(matched_gt, np.fromiter(prep.crowd_ann_ids, dtype=np.int64))
    keep = evaluated & ~crowd
    cat_index = np.searchsorted(np.asarray(prep.cat_ids), cat)
    result.op_scores = score[keep]
    result.op_cat_index = cat_index[keep]
    result.op_is_tp = (matched_gt > 0)[keep]


def _run_pycocotools(prep: PreparedEval, matching: str, anchor: str,
                     area_ranges: Mapping[str, tuple[float, float]] | None, want_op: bool) -> EngineResult:
    from pycocotools.coco import COCO

    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = prep.gt
        gt.createIndex()
        dt = COCO()
        dt.dataset = {"images": prep.gt["images"], "categories": prep.gt["categories"], "annotations": prep.dets}
        dt.createIndex()
        cls = _pycoco_eval_class(matching, anchor)
        ev = cls(gt, dt, "bbox")
        ev.params.imgIds = [im["id"] for im in prep.gt["images"]]
        ev.params.catIds = list(prep.cat_ids)
        if area_ranges is not None:
            ev.params.areaRng = [list(v) for v in area_ranges.values()]
            ev.params.areaRngLbl = list(area_ranges)
        ev.evaluate()
        ev.accumulate()
        if area_ranges is None:
            ev.summarize()
            stats = list(map(float, ev.stats))
        else:
            stats = [-1.0] * 12  # pycocotools' summarize() only knows small/medium/large
    result = EngineResult(stats, np.asarray(ev.eval["precision"]), np.asarray(ev.params.iouThrs),
                          list(ev.params.areaRngLbl))
    if want_op:
        all_rng = list(ev.params.areaRng[0])
        scores, cats, tps = [], [], []
        cat_pos = {c: k for k, c in enumerate(prep.cat_ids)}
        for e in ev.evalImgs:
            if e is None or list(e["aRng"]) != all_rng:
                continue
            ignore = np.asarray(e["dtIgnore"][0], dtype=bool) if len(e["dtIds"]) else np.zeros(0, dtype=bool)
            match = np.asarray(e["dtMatches"][0]) if len(e["dtIds"]) else np.zeros(0)
            sc = np.asarray(e["dtScores"], dtype=np.float64)
            scores.append(sc[~ignore])
            tps.append((match > 0)[~ignore])
            cats.append(np.full(int((~ignore).sum()), cat_pos[e["category_id"]], dtype=np.int64))
        result.op_scores = np.concatenate(scores) if scores else np.zeros(0)
        result.op_cat_index = np.concatenate(cats) if cats else np.zeros(0, dtype=np.int64)
        result.op_is_tp = np.concatenate(tps) if tps else np.zeros(0, dtype=bool)
    return result


# ----------------------------------------------------------------------------------------------- summaries
def _nullable(x: float) -> float | None:
    """COCO writes -1 for "no GT to score against"; the harness writes null."""
    return None if x is None or x < 0 or not math.isfinite(x) else float(x)


def summarize_precision(precision: np.ndarray, iou_thrs: np.ndarray, iou: float | None = None, area: int = 0,
                        cat: int | None = None) -> float | None:
    """Mean of the interpolated precision over recall points (and IoU thresholds when ``iou`` is None), skipping -1.

    ``precision`` is COCOeval's ``[T, R, K, A, M]`` array; the last maxDets column (100) is used, as for AP.
    """
    p = precision[..., -1]
    if iou is not None:
        t = np.flatnonzero(np.isclose(iou_thrs, iou))
        if len(t) == 0:
            return None
        p = p[t]
    p = p[:, :, :, area] if cat is None else p[:, :, cat, area]
    valid = p[p > -1]
    return float(valid.mean()) if valid.size else None


def _per_category(res: EngineResult, prep: PreparedEval) -> dict[int, tuple[float | None, float | None]]:
    out = {}
    for k, cid in enumerate(prep.cat_ids):
        out[cid] = (summarize_precision(res.precision, res.iou_thrs, 0.5, 0, k),
                    summarize_precision(res.precision, res.iou_thrs, None, 0, k))
    return out


def _safit_block(prep: PreparedEval, engine: str, anchor: str) -> tuple[dict[str, Any], dict[int, tuple]]:
    res = run_engine(prep, engine, "safit", anchor, area_ranges=TINY_AREA_RANGES, operating_point=False)
    labels = list(res.area_labels)

    def ap(iou: float | None = None, area: str = "all") -> float | None:
        return summarize_precision(res.precision, res.iou_thrs, iou, labels.index(area))

    block = {
        "mAP50": ap(0.5), "mAP50_95": ap(), "AP75": ap(0.75),
        "AP_et": ap(area="extremely_tiny"), "AP_t": ap(area="tiny"), "AP_s": ap(area="small"),
        "AP_m": ap(area="medium"), "AP_l": ap(area="large"),
        "anchor": anchor, "C": SAFIT_C,
        "area_ranges": {k: [float(a), float(b)] for k, (a, b) in TINY_AREA_RANGES.items()},
    }
    return block, _per_category(res, prep)


def evaluate(gt: Mapping[str, Any], detections: Sequence[Mapping[str, Any]], engine: str = "faster-coco-eval",
             matching: str = "iou", *, safit_anchor: str = "center", strict: bool = False) -> dict[str, Any]:
    """Score COCO results against COCO ground truth; returns ``{"support", "metrics", "per_category"}``.

    ``detections``: dicts with ``image_id``, ``category_id`` (= label + 1), ``bbox`` ``[x, y, w, h]`` in the GT's
    pixel frame and ``score``. ``matching="safit"`` adds a ``metrics["safit"]`` block and per-category
    ``SAFit_AP50``/``SAFit_AP50_95`` beside the standard IoU numbers (see ``harness.evaluation.safit``).
    ``strict=True`` turns dropped detections (unknown image or category) into an error.
    """
    if engine not in ENGINES:
        raise EvaluationError(f"unknown evaluation engine {engine!r}; use one of {', '.join(ENGINES)} (config eval.engine)")
    if matching not in MATCHINGS:
        raise EvaluationError(f"unknown matching {matching!r}; use one of {', '.join(MATCHINGS)} (config eval.matching)")
    if safit_anchor not in ANCHORS:
        raise EvaluationError(f"unknown SAFit NWD anchor {safit_anchor!r}; use one of {', '.join(ANCHORS)}")
    with _gc_paused():  # millions of short-lived dicts: generational GC passes would cost a third of the time
        prep = prepare(gt, detections, strict=strict)
        res = run_engine(prep, engine, "iou")
    n_gt = np.array([prep.n_gt[c] for c in prep.cat_ids], dtype=np.int64)
    op = max_f1_operating_point(res.op_scores, res.op_cat_index, res.op_is_tp, n_gt)
    stats = [_nullable(s) for s in res.stats]
    per_cat_ap = _per_category(res, prep)
    if not any(n_gt):
        log.warning("the ground truth has no (non-crowd) instances: AP, precision and recall are undefined")

    metrics: dict[str, Any] = {
        "mAP50": stats[1],
        "mAP50_95": stats[0],
        "precision": op.precision if n_gt.any() else None,
        "recall": op.recall if n_gt.any() else None,
        "f1": op.f1 if n_gt.any() else None,
        "conf_threshold": op.conf_threshold,
        "operating_point": OPERATING_POINT,
        "coco_stats": stats,
        "coco_stat_names": list(COCO_STAT_NAMES),
        "engine": engine,
        "matching": matching,
        "detections": len(prep.dets),
        "dropped_detections": dict(prep.dropped),
    }
    if prep.notes:
        metrics["notes"] = list(prep.notes)
    per_category: dict[str, dict[str, Any]] = {}
    for k, cid in enumerate(prep.cat_ids):
        name = prep.cat_names[cid]
        ap50, ap = per_cat_ap[cid]
        pr = op.per_category.get(k)
        per_category[name] = {"AP50": ap50, "AP50_95": ap, "instances": prep.n_gt[cid],
                              "precision": pr[0] if pr else None, "recall": pr[1] if pr else None}
    if matching == "safit":
        with _gc_paused():
            block, safit_cat = _safit_block(prep, engine, safit_anchor)
        metrics["safit"] = block
        for cid in prep.cat_ids:
            per_category[prep.cat_names[cid]]["SAFit_AP50"], per_category[prep.cat_names[cid]]["SAFit_AP50_95"] = safit_cat[cid]

    support: dict[str, Any] = {
        "images": len(prep.image_keys),
        "instances": int(sum(prep.n_gt.values())),
        "image_ids_sha1": _ids_sha1(prep.image_keys),
        "categories": {prep.cat_names[c]: prep.n_gt[c] for c in prep.cat_ids},
    }
    if prep.n_crowd:
        support["crowd"] = prep.n_crowd
    return {"support": support, "metrics": metrics, "per_category": per_category}


def evaluate_with_config(gt: Mapping[str, Any], detections: Sequence[Mapping[str, Any]],
                         cfg: Mapping[str, Any]) -> dict[str, Any]:
    """``evaluate`` with engine, matching and SAFit anchor read from a resolved config's ``eval`` section."""
    ev = cfg.get("eval", cfg)
    return evaluate(gt, detections, engine=ev.get("engine", "faster-coco-eval"), matching=ev.get("matching", "iou"),
                    safit_anchor=ev.get("safit_anchor", "center"), strict=bool(ev.get("strict", False)))
