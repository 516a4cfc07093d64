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
OPERATING_POINT = (
    "confidence maximising mean F1 over categories with GT; COCO matching at IoU 0.50, area all, maxDets 100"
)


@dataclass
class OperatingPoint:
    conf_threshold: float | None
    precision: float
    recall: float
    f1: float
    #: per category index (only categories with GT): (precision, recall)
    per_category: dict[int, tuple[float, float]] = field(default_factory=dict)


def _f1(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(p + r > 0, 2 * p * r / (p + r), 0.0)


def _precision_recall(kept: np.ndarray, tp: np.ndarray, n_gt: int) -> tuple[np.ndarray, np.ndarray]:
    """``P = TP / kept`` (0 when nothing is kept) and ``R = TP / GT`` from counts."""
    precision = np.where(kept > 0, tp / np.maximum(kept, 1), 0.0)
    return precision, tp / n_gt


def max_f1_operating_point(
    scores: np.ndarray, labels: np.ndarray, is_tp: np.ndarray, n_gt: np.ndarray
) -> OperatingPoint:
    """The operating point defined in this module's docstring.

    ``scores``, ``labels`` (category index 0..K-1) and ``is_tp`` describe the evaluated, non-ignored detections;
    ``n_gt[k]`` is the number of non-crowd GT of category ``k``.

    One sort of all detections by descending score gives every candidate threshold at once: the end of each group
    of equal scores is the last detection kept at that threshold, and per-category running counts of kept and
    true-positive detections there give ``P_k`` and ``R_k`` at every threshold.
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
    order = np.argsort(-scores, kind="stable")
    s, lab, tp = scores[order], labels[order], is_tp[order]
    ends = np.r_[np.flatnonzero(s[1:] != s[:-1]), len(s) - 1]  # thresholds s[ends], descending
    f1_sum = np.zeros(len(ends))
    counts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for k in cats:
        m = lab == k
        counts[int(k)] = (np.cumsum(m)[ends], np.cumsum(tp & m)[ends])  # kept, TP at each threshold
        f1_sum += _f1(*_precision_recall(*counts[int(k)], int(n_gt[k])))
    # the maximum at the lowest threshold among equal maxima (thresholds are descending here)
    best = len(ends) - 1 - int(np.argmax(f1_sum[::-1]))
    per_cat: dict[int, tuple[float, float]] = {}
    for k in cats:
        kept, tp_k = counts[int(k)]
        p, r = _precision_recall(kept[best : best + 1], tp_k[best : best + 1], int(n_gt[k]))
        per_cat[int(k)] = (float(p[0]), float(r[0]))
    ps = np.array([v[0] for v in per_cat.values()])
    rs = np.array([v[1] for v in per_cat.values()])
    return OperatingPoint(float(s[ends[best]]), float(ps.mean()), float(rs.mean()), float(_f1(ps, rs).mean()), per_cat)
