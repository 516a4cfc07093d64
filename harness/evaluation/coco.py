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

import logging
import math
from typing import Any, Mapping, Sequence

import numpy as np

from harness.evaluation.engines import ENGINES, MATCHINGS, EngineResult, _gc_paused, check_options, run_engine
from harness.evaluation.inputs import EvaluationError, PreparedEval, _ids_sha1, prepare
from harness.evaluation.operating_point import OPERATING_POINT, max_f1_operating_point
from harness.evaluation.safit import SAFIT_C, TINY_AREA_RANGES

log = logging.getLogger(__name__)

#: The 12 numbers of ``COCOeval.summarize()`` for boxes, in order.
COCO_STAT_NAMES = ("AP", "AP50", "AP75", "APs", "APm", "APl", "AR1", "AR10", "AR100", "ARs", "ARm", "ARl")

__all__ = [
    "COCO_STAT_NAMES",
    "ENGINES",
    "MATCHINGS",
    "EvaluationError",
    "evaluate",
    "evaluate_with_config",
    "summarize_precision",
]


# ----------------------------------------------------------------------------------------------- summaries
def _nullable(x: float) -> float | None:
    """COCO writes -1 for "no GT to score against"; the harness writes null."""
    return None if x is None or x < 0 or not math.isfinite(x) else float(x)


def summarize_precision(
    precision: np.ndarray, iou_thrs: np.ndarray, iou: float | None = None, area: int = 0, cat: int | None = None
) -> float | None:
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
        out[cid] = (
            summarize_precision(res.precision, res.iou_thrs, 0.5, 0, k),
            summarize_precision(res.precision, res.iou_thrs, None, 0, k),
        )
    return out


def _safit_block(prep: PreparedEval, engine: str, anchor: str) -> tuple[dict[str, Any], dict[int, tuple]]:
    res = run_engine(prep, engine, "safit", anchor, area_ranges=TINY_AREA_RANGES, operating_point=False)
    labels = list(res.area_labels)

    def ap(iou: float | None = None, area: str = "all") -> float | None:
        return summarize_precision(res.precision, res.iou_thrs, iou, labels.index(area))

    block = {
        "mAP50": ap(0.5),
        "mAP50_95": ap(),
        "AP75": ap(0.75),
        "AP_et": ap(area="extremely_tiny"),
        "AP_t": ap(area="tiny"),
        "AP_s": ap(area="small"),
        "AP_m": ap(area="medium"),
        "AP_l": ap(area="large"),
        "anchor": anchor,
        "C": SAFIT_C,
        "area_ranges": {k: [float(a), float(b)] for k, (a, b) in TINY_AREA_RANGES.items()},
    }
    return block, _per_category(res, prep)


def evaluate(
    gt: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    engine: str = "faster-coco-eval",
    matching: str = "iou",
    *,
    safit_anchor: str = "center",
    strict: bool = False,
) -> dict[str, Any]:
    """Score COCO results against COCO ground truth; returns ``{"support", "metrics", "per_category"}``.

    ``detections``: dicts with ``image_id``, ``category_id`` (= label + 1), ``bbox`` ``[x, y, w, h]`` in the GT's
    pixel frame and ``score``. ``matching="safit"`` adds a ``metrics["safit"]`` block and per-category
    ``SAFit_AP50``/``SAFit_AP50_95`` beside the standard IoU numbers (see ``harness.evaluation.safit``).
    ``strict=True`` turns dropped detections (unknown image or category) into an error.
    """
    check_options(engine, matching, safit_anchor)  # before the inputs are prepared: a typo fails at once
    # Millions of short-lived dicts: with the cyclic GC running, its passes over them cost a third of the time.
    # It stays paused until the private copies are released, so that no collection has to scan them.
    with _gc_paused():
        prep = prepare(gt, detections, strict=strict)
        result = _score(prep, engine, matching, safit_anchor)
        del prep
    return result


def _score(prep: PreparedEval, engine: str, matching: str, safit_anchor: str) -> dict[str, Any]:
    res = run_engine(prep, engine, "iou")
    n_gt = np.array([prep.n_gt[c] for c in prep.cat_ids], dtype=np.int64)
    assert res.op_scores is not None and res.op_cat_index is not None and res.op_is_tp is not None  # "iou" fills them
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
        "detections": prep.n_dets,
        "dropped_detections": dict(prep.dropped),
    }
    if prep.notes:
        metrics["notes"] = list(prep.notes)
    per_category: dict[str, dict[str, Any]] = {}
    for k, cid in enumerate(prep.cat_ids):
        name = prep.cat_names[cid]
        ap50, ap = per_cat_ap[cid]
        pr = op.per_category.get(k)
        per_category[name] = {
            "AP50": ap50,
            "AP50_95": ap,
            "instances": prep.n_gt[cid],
            "precision": pr[0] if pr else None,
            "recall": pr[1] if pr else None,
        }
    if matching == "safit":
        block, safit_cat = _safit_block(prep, engine, safit_anchor)
        metrics["safit"] = block
        for cid in prep.cat_ids:
            per_category[prep.cat_names[cid]]["SAFit_AP50"], per_category[prep.cat_names[cid]]["SAFit_AP50_95"] = (
                safit_cat[cid]
            )

    support: dict[str, Any] = {
        "images": len(prep.image_keys),
        "instances": int(sum(prep.n_gt.values())),
        "image_ids_sha1": _ids_sha1(prep.image_keys),
        "categories": {prep.cat_names[c]: prep.n_gt[c] for c in prep.cat_ids},
    }
    if prep.n_crowd:
        support["crowd"] = prep.n_crowd
    return {"support": support, "metrics": metrics, "per_category": per_category}


def evaluate_with_config(
    gt: Mapping[str, Any], detections: Sequence[Mapping[str, Any]], cfg: Mapping[str, Any]
) -> dict[str, Any]:
    """``evaluate`` with engine, matching and SAFit anchor read from a resolved config's ``eval`` section."""
    ev = cfg.get("eval", cfg)
    return evaluate(
        gt,
        detections,
        engine=ev.get("engine", "faster-coco-eval"),
        matching=ev.get("matching", "iou"),
        safit_anchor=ev.get("safit_anchor", "center"),
        strict=bool(ev.get("strict", False)),
    )
