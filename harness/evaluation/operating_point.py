"""Precision and recall at one stated operating point: the confidence that maximises mean F1 over categories.

COCO AP has no single precision or recall. The harness reports them at this operating point:

* matching is COCO's at IoU 0.50, area range "all", at most 100 detections per image and category (the same
  greedy matching that AP uses); a detection matched to a crowd GT is ignored (neither TP nor FP);
* for a confidence threshold ``t``, category ``k`` keeps its evaluated detections with ``score >= t``:
  ``P_k(t) = TP / kept`` (0 when it keeps none), ``R_k(t) = TP / GT_k`` (non-crowd GT), ``F1_k = 2PR / (P + R)``;
* ``t*`` maximises ``mean_k F1_k(t)`` over categories with GT in the evaluated set (categories without GT are
  left out, as in AP); candidates are the detections' own scores, so the maximum is exact (no grid, no
  smoothing); among equal maxima the lowest threshold (the most inclusive) wins;
* reported: ``conf_threshold = t*``, ``precision = mean_k P_k(t*)``, ``recall = mean_k R_k(t*)`` and ``f1``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: How ``metrics.precision`` / ``metrics.recall`` are defined, written next to them in every metrics.json.
OPERATING_POINT = ("confidence maximising mean F1 over categories with GT; COCO matching at IoU 0.50, "
                   "area all, maxDets 100")


@dataclass
class OperatingPoint:
    conf_threshold: float | None
    precision: float
    recall: float
    f1: float
    #: per category index (only categories with GT): (precision, recall)
    per_category: dict[int, tuple[float, float]] = field(default_factory=dict)


def _pr_curves(scores: np.ndarray, is_tp: np.ndarray, n_gt: int, thresholds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall of one category at each threshold (detections with score >= threshold)."""
    order = np.argsort(-scores, kind="mergesort")
    s = scores[order]
    cum_tp = np.concatenate([[0], np.cumsum(is_tp[order], dtype=np.int64)])
    kept = np.searchsorted(-s, -thresholds, side="right")  # how many scores are >= each threshold
    tp = cum_tp[kept]
    precision = np.where(kept > 0, tp / np.maximum(kept, 1), 0.0)
    recall = tp / n_gt
    return precision, recall


def _f1(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(p + r > 0, 2 * p * r / (p + r), 0.0)


def max_f1_operating_point(scores: np.ndarray, labels: np.ndarray, is_tp: np.ndarray, n_gt: np.ndarray) -> OperatingPoint:
    """The operating point defined in this module's docstring.

    ``scores``, ``labels`` (category index 0..K-1) and ``is_tp`` describe the evaluated, non-ignored detections;
    ``n_gt[k]`` is the number of non-crowd GT of category ``k``.
    """
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    is_tp = np.asarray(is_tp, dtype=bool)
    n_gt = np.asarray(n_gt, dtype=np.int64)
    cats = np.flatnonzero(n_gt > 0)
    if len(cats) == 0:
        return OperatingPoint(None, 0.0, 0.0, 0.0, {})
    keep = np.isin(labels, cats)
    scores, labels, is_tp = scores[keep], labels[keep], is_tp[keep]
    if len(scores) == 0:
        return OperatingPoint(None, 0.0, 0.0, 0.0, {int(k): (0.0, 0.0) for k in cats})
    thresholds = np.unique(scores)  # ascending: argmax picks the lowest threshold among ties
    f1_sum = np.zeros(len(thresholds))
    by_cat = {int(k): labels == k for k in cats}
    for k in cats:
        m = by_cat[int(k)]
        p, r = _pr_curves(scores[m], is_tp[m], int(n_gt[k]), thresholds)
        f1_sum += _f1(p, r)
    best = int(np.argmax(f1_sum))
    t = thresholds[best : best + 1]
    per_cat: dict[int, tuple[float, float]] = {}
    for k in cats:
        m = by_cat[int(k)]
        p, r = _pr_curves(scores[m], is_tp[m], int(n_gt[k]), t)
        per_cat[int(k)] = (float(p[0]), float(r[0]))
    ps = np.array([v[0] for v in per_cat.values()])
    rs = np.array([v[1] for v in per_cat.values()])
    return OperatingPoint(float(t[0]), float(ps.mean()), float(rs.mean()), float(_f1(ps, rs).mean()), per_cat)
