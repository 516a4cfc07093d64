"""COCOeval's matching at every IoU threshold and area range, and its accumulation, in bulk with numpy.

This is what ``COCOevalEvaluateImages`` and ``COCOevalAccumulate`` (faster-coco-eval's C++, itself a port of
pycocotools' ``evaluateImg`` and ``accumulate``) compute, done for every (image, category) pair at once from the
flat layout of ``harness.evaluation.pairs`` instead of one pair and one detection at a time. The arithmetic is the
library's, operation for operation, so the precision, recall and score arrays are bitwise its own (the tests
compare every computed cell):

* **Matching** (per IoU threshold ``t`` and area range ``a``): a ground truth is ignored in ``a`` when it is crowd
  (the prepared ``ignore`` flag) or its ``area`` lies outside ``a``. Detections of a pair, in score order and cut at
  ``maxDets[-1]``, each take among the ground truths not yet taken (crowd ones can be taken again) with value
  ``>= min(t, 1 - 1e-10)`` the one with the highest value, non-ignored ones first, equal values going to the later
  one in COCO's order (non-ignored first, then ignored, each in annotation order). A detection matched to an
  ignored ground truth is ignored; so is an unmatched one whose own area lies outside ``a``.
* **Accumulation** (per category, area range and maxDets ``m``): the category's detections of rank ``< m`` in
  their pair, images in id order and pairs in score order, sorted by descending score (stable);
  ``recall = TP / G`` and ``precision = TP / (TP + FP)`` after each detection (``G``: non-ignored ground truths of
  the category in ``a``; cells with ``G = 0`` stay -1); precision made non-increasing from the right; sampled at
  each recall threshold ``r`` at the first detection whose recall is ``>= r`` (0 beyond the last one).
  Recall rises only at true positives and precision only peaks there, so only true positives are visited.

Only the cells that ``summarize()`` reads are computed: area "all" at every maxDets, the other ranges at the last
maxDets; the others hold -1, as cells without ground truth do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from harness.evaluation.inputs import PreparedEval
from harness.evaluation.pairs import PairLayout, greedy_rounds
from harness.evaluation.safit import iou_elementwise


@dataclass
class Matches:
    """Every match of every (IoU threshold, area range) combination ``c = t * A + a``."""

    combo: np.ndarray  # [K] combination of each match
    det: np.ndarray  # [K] prepared detection index
    gt: np.ndarray  # [K] index into the prepared GT annotations
    n_thr: int
    n_area: int

    def at(self, t: int, a: int) -> tuple[np.ndarray, np.ndarray]:
        """(detection index, GT index) of the matches at threshold ``t`` and area range ``a``."""
        sel = self.combo == t * self.n_area + a
        return self.det[sel], self.gt[sel]


def gt_ignored(gt_area: np.ndarray, gt_ignore: np.ndarray, area_ranges: Sequence[Sequence[float]]) -> np.ndarray:
    """``[A, G]``: ground truth ``g`` is ignored in area range ``a`` (crowd, or its area outside the range)."""
    lo = np.array([float(r[0]) for r in area_ranges])[:, None]
    hi = np.array([float(r[1]) for r in area_ranges])[:, None]
    return gt_ignore[None, :] | (gt_area[None, :] < lo) | (gt_area[None, :] > hi)


def iou_values(layout: PairLayout, prep: PreparedEval) -> np.ndarray:
    """``layout.values(prep, iou_elementwise)``, bitwise, computed only where the boxes overlap horizontally: the
    others have no intersection, hence IoU 0 (as ``iou_elementwise`` gives them), and they are most entries."""
    boxes = prep.det_columns[3]
    if len(layout.det) == 0:
        return np.zeros(0)
    d_x, d_x2 = boxes[:, 0], boxes[:, 0] + boxes[:, 2]
    g_x, g_x2 = layout.gt_box[:, 0], layout.gt_box[:, 0] + layout.gt_box[:, 2]
    det, gt = layout.det, layout.gt
    iw = np.minimum(d_x2[det], g_x2[gt]) - np.maximum(d_x[det], g_x[gt])  # as iou_elementwise computes it
    overlap = np.flatnonzero(iw > 0)
    values = np.zeros(len(det))
    d, g = det[overlap], gt[overlap]
    values[overlap] = iou_elementwise(boxes[d], layout.gt_box[g], layout.gt_crowd[g])
    return values


def match_all(
    layout: PairLayout, values: np.ndarray, iou_thrs: Sequence[float] | np.ndarray, ignored: np.ndarray
) -> Matches:
    """COCO's greedy matching at every IoU threshold and area range (``ignored`` from ``gt_ignored``).

    Only entries with a value at or above the lowest threshold can match. Each such entry is expanded to the
    (threshold, area range) combinations it qualifies for; then one pass per detection rank settles every
    combination and pair at once, in the order COCO prefers (the last entry of each group after sorting by
    non-ignored, value, GT position: ``harness.evaluation.pairs.greedy_rounds``, the loop both paths share)."""
    n_thr, n_area = len(iou_thrs), ignored.shape[0]
    none = np.zeros(0, dtype=np.int64)
    thr = np.minimum(np.asarray(iou_thrs, dtype=np.float64), 1 - 1e-10)
    if not np.all(np.diff(thr) >= 0):
        raise ValueError("IoU thresholds must be ascending")
    passes = np.searchsorted(thr, values, side="right")  # thresholds each entry reaches
    ent = np.flatnonzero(passes > 0)
    if len(ent) == 0:
        return Matches(none, none, none, n_thr, n_area)
    ent = ent[np.argsort(layout.row[ent], kind="stable")]  # by detection rank
    reps = passes[ent] * n_area
    e = np.repeat(ent, reps)
    k = np.arange(len(e)) - np.repeat(np.cumsum(reps) - reps, reps)
    combo = k  # t * n_area + a, t < passes: the first passes * n_area combinations
    g = layout.gt[e]
    nonign = ~ignored[combo % n_area, g]
    crowd = layout.gt_crowd[g]
    pair = layout.pair[e].astype(np.int64)
    group = combo.astype(np.int64) * len(layout.keys) + pair
    taken_key = combo.astype(np.int64) * len(layout.gt_crowd) + g
    chosen = greedy_rounds(
        layout.row[e], group, nonign, crowd, taken_key, n_thr * n_area * len(layout.gt_crowd), layout.col[e], values[e]
    )
    return Matches(combo[chosen].astype(np.int64), layout.det[e[chosen]], g[chosen], n_thr, n_area)


def accumulate(
    prep: PreparedEval, layout: PairLayout, matches: Matches, ignored: np.ndarray, params: Any
) -> dict[str, Any]:
    """``COCOeval.eval`` (``precision``, ``recall``, ``scores``, ``counts``, ``params``) of the summarized cells."""
    rec_thrs = np.asarray(params.recThrs, dtype=np.float64)
    max_dets = [int(m) for m in params.maxDets]
    area_ranges = [(float(r[0]), float(r[1])) for r in params.areaRng]
    cat_ids = np.asarray(params.catIds, dtype=np.int64)
    n_thr, n_rec, n_cat = len(params.iouThrs), len(rec_thrs), len(cat_ids)
    n_area, n_max = len(area_ranges), len(max_dets)
    counts = [n_thr, n_rec, n_cat, n_area, n_max]
    precision = np.full(counts, -1.0)
    scores = np.full(counts, -1.0)
    recall = np.full([n_thr, n_cat, n_area, n_max], -1.0)
    if n_area == 1 or n_max == 1 or params.areaRngLbl[0] != "all":
        cells = [(a, m) for a in range(n_area) for m in range(n_max)]
    else:
        cells = [(0, m) for m in range(n_max)] + [(a, n_max - 1) for a in range(1, n_area)]

    # the evaluated detections, at their position in layout.det_order (pairs ascending, score order within a pair)
    order = layout.det_order
    n_pos = len(order)
    _, d_cat, d_score, d_box = prep.det_columns
    score = d_score[order]
    area = d_box[order, 2] * d_box[order, 3]  # the results' area (w * h), as the library's datasets hold it
    rank = np.arange(n_pos) - np.repeat(layout.det_start, layout.det_count)
    cat = np.searchsorted(cat_ids, d_cat[order])
    # per category, the positions by descending score, ties in position order (images ascending, then rank)
    by_score = np.argsort(-score, kind="stable")
    by_cat = by_score[np.argsort(cat[by_score], kind="stable")]
    cat_start = np.searchsorted(cat[by_cat], np.arange(n_cat + 1))
    index_in_cat = np.empty(n_pos, dtype=np.int64)
    index_in_cat[by_cat] = np.arange(n_pos) - cat_start[cat[by_cat]]

    # matches grouped by (area range, category), then threshold, then place in the category's sequence
    pos_of_det = np.empty(prep.n_dets, dtype=np.int64)
    pos_of_det[order] = np.arange(n_pos)
    m_pos = pos_of_det[matches.det]
    m_thr, m_area = matches.combo // matches.n_area, matches.combo % matches.n_area
    group = m_area * n_cat + cat[m_pos]
    o = np.argsort((group * n_thr + m_thr) * max(n_pos, 1) + index_in_cat[m_pos])  # unique keys
    m_pos, m_thr, group, m_ign = m_pos[o], m_thr[o], group[o], ignored[m_area[o], matches.gt[o]]
    group_start = np.searchsorted(group, np.arange(n_area * n_cat + 1))
    gt_cat = np.searchsorted(cat_ids, prep.gt_columns[1])

    for a in sorted({a for a, _ in cells}):
        lo, hi = area_ranges[a]
        outside = ((area < lo) | (area > hi)) if lo > 0 or hi < np.inf else None
        if outside is not None and not outside.any():
            outside = None
        n_valid_gt = np.bincount(gt_cat[~ignored[a]], minlength=n_cat)
        for k in range(n_cat):
            if n_valid_gt[k] == 0:
                continue
            seq_all = by_cat[cat_start[k] : cat_start[k + 1]]
            g = slice(group_start[a * n_cat + k], group_start[a * n_cat + k + 1])
            for m in (m for a2, m in cells if a2 == a):
                keep = rank[seq_all] < max_dets[m]
                live = rank[m_pos[g]] < max_dets[m]
                if keep.all():
                    seq, place = seq_all, index_in_cat[m_pos[g]][live]
                else:
                    seq, place = seq_all[keep], (np.cumsum(keep) - 1)[index_in_cat[m_pos[g]][live]]
                inside = None if outside is None else ~outside[seq]
                cell = _cell(
                    seq, score, inside, place, m_thr[g][live], m_ign[g][live], int(n_valid_gt[k]), n_thr, rec_thrs
                )
                precision[:, :, k, a, m], scores[:, :, k, a, m], recall[:, k, a, m] = cell
    return {"params": params, "counts": counts, "precision": precision, "recall": recall, "scores": scores}


def _cell(
    seq: np.ndarray,
    score: np.ndarray,
    inside: np.ndarray | None,
    place: np.ndarray,
    thr: np.ndarray,
    ignored: np.ndarray,
    n_gt: int,
    n_thr: int,
    rec_thrs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One (category, area range, maxDets) cell: precision and scores ``[T, R]`` and recall ``[T]``.

    ``seq``: the cell's detections in ranking order; ``inside``: whether each lies inside the area range (``None``:
    all do); ``place``, ``thr``, ``ignored``: the cell's matches (place in ``seq``, threshold index, matched to an
    ignored GT), sorted by threshold, then place."""
    n = len(seq)
    prec = np.zeros((n_thr, len(rec_thrs)))
    scr = np.zeros((n_thr, len(rec_thrs)))
    rc_out = np.zeros(n_thr)
    if n == 0:
        return prec, scr, rc_out
    # detections up to each place that an unmatched detection would leave valid (inside the area range)
    inside_cum = np.arange(1, n + 1) if inside is None else np.cumsum(inside)
    m_inside = np.ones(len(place), dtype=bool) if inside is None else inside[place]
    starts = np.searchsorted(thr, np.arange(n_thr + 1))
    first, later = rec_thrs <= 0, rec_thrs > 0
    scr[:, first] = score[seq[0]]  # the first detection: the best precision overall, the top score
    for t in range(n_thr):
        sl = slice(starts[t], starts[t + 1])
        tp = ~ignored[sl]
        c_tp = np.cumsum(tp)
        rc_out[t] = (c_tp[-1] if len(c_tp) else 0) / n_gt
        at = np.flatnonzero(tp)
        if len(at) == 0:
            continue
        tp_n = c_tp[at]
        # valid (non-ignored) detections up to a true positive: the unmatched ones inside the range, plus the
        # true positives; matched ones are either true positives or ignored
        valid = inside_cum[place[sl][at]] - np.cumsum(m_inside[sl])[at] + tp_n
        env = np.maximum.accumulate((tp_n / valid)[::-1])[::-1]
        j = np.searchsorted(tp_n / n_gt, rec_thrs[later], side="left")
        ok = j < len(at)
        j = np.minimum(j, len(at) - 1)
        prec[t, first] = env[0]
        prec[t, later] = np.where(ok, env[j], 0.0)
        scr[t, later] = np.where(ok, score[seq[place[sl][at][j]]], 0.0)
    return prec, scr, rc_out
