"""Every (image, category) pair of detections and ground truth, laid out flat so that COCO's per-pair work runs
in bulk with numpy: grouping detections and GT by pair, the matching matrices (IoU or SAFit) and COCO's greedy
matching at one threshold.

Within a pair, detections are ordered by descending score (ties in input order) and cut at ``max_det``; GT keep
their annotation order. These are the orders ``COCOeval.computeIoU`` and ``COCOeval.evaluateImg`` use, so the
matrices are exactly the ones COCOeval builds one pair at a time, and ``greedy_match`` reproduces its matching.

A pair is keyed by ``image_index * K + category_index`` (indices into the sorted image and category ids).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from harness.evaluation.inputs import PreparedEval


@dataclass
class PairLayout:
    img_ids: np.ndarray  # [I] sorted image ids
    cat_ids: np.ndarray  # [K] sorted category ids
    #: evaluated detections (index into the prepared detections), grouped by pair key, score-descending within a pair
    det_order: np.ndarray
    det_keys: np.ndarray  # [Pd] pair keys that have detections, ascending
    det_start: np.ndarray  # [Pd] first position in det_order
    det_count: np.ndarray  # [Pd] evaluated detections in the pair (at most max_det)
    #: GT annotations (index into prep.gt["annotations"]) grouped by pair key, annotation order within a pair
    gt_order: np.ndarray
    gt_keys: np.ndarray  # [Pg] pair keys that have GT, ascending
    gt_start: np.ndarray
    gt_count: np.ndarray
    keys: np.ndarray  # [P] pair keys with both detections and GT, ascending
    rows: np.ndarray  # [P] detections in the pair (after the max_det cut)
    cols: np.ndarray  # [P] GT in the pair
    det: np.ndarray  # [E] index into the prepared detections of each matrix entry (pair-major, row, column)
    gt: np.ndarray  # [E] index into prep.gt["annotations"]
    pair: np.ndarray  # [E]
    row: np.ndarray  # [E] detection rank in its pair
    col: np.ndarray  # [E] GT position in its pair
    gt_box: np.ndarray  # [G, 4] all GT boxes
    gt_crowd: np.ndarray  # [G]
    gt_id: np.ndarray  # [G] annotation ids
    #: [N] per prepared detection: within the first ``max_det`` of its (image, category) by score, i.e. evaluated
    evaluated: np.ndarray

    @property
    def keys_img(self) -> np.ndarray:
        """[P] image id of each pair with both detections and GT."""
        return self.img_ids[self.keys // len(self.cat_ids)]

    @property
    def keys_cat(self) -> np.ndarray:
        """[P] category id of each pair with both detections and GT."""
        return self.cat_ids[self.keys % len(self.cat_ids)]

    def values(self, prep: PreparedEval, measure: Callable[..., np.ndarray]) -> np.ndarray:
        """``measure(d, g, crowd)`` of every entry (element-wise on [E, 4] boxes)."""
        if len(self.det) == 0:
            return np.zeros(0)
        return measure(prep.det_columns[3][self.det], self.gt_box[self.gt], self.gt_crowd[self.gt])

    def blocks(self, values: np.ndarray) -> list[np.ndarray]:
        """The ``[D, G]`` matrix of every pair with both detections and GT, in ``keys`` order (views of ``values``)."""
        ends = np.cumsum(self.rows * self.cols).tolist()
        return [values[e - r * c : e].reshape(r, c) for e, r, c in zip(ends, self.rows.tolist(), self.cols.tolist())]

    def matrices(self, values: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        """``{(image_id, category_id): [D, G] matrix}`` for the pairs with both detections and GT."""
        return dict(zip(zip(self.keys_img.tolist(), self.keys_cat.tolist()), self.blocks(values)))

    def greedy_match_indices(self, values: np.ndarray, threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
        """COCO's greedy matching at one threshold, area "all": (detection index, GT index) of every match.

        ``COCOeval.evaluateImg``: detections in score order each take, among GT not yet taken (crowd GT can be taken
        again), the one with the highest value >= threshold, preferring non-crowd GT; equal values go to the later
        GT in COCO's order (non-crowd GT first, then crowd, each in annotation order).
        """
        none = np.zeros(0, dtype=np.int64)
        thr = min(threshold, 1 - 1e-10)
        cand = np.flatnonzero(values >= thr)  # only these entries can ever match
        if len(cand) == 0:
            return none, none
        cand = cand[np.argsort(self.row[cand], kind="stable")]
        cand_gt = self.gt[cand]
        cand_crowd = self.gt_crowd[cand_gt]
        chosen = greedy_rounds(
            self.row[cand],
            self.pair[cand],
            ~cand_crowd,
            cand_crowd,
            cand_gt,
            len(self.gt_box),
            self.col[cand],
            values[cand],
        )
        if len(chosen) == 0:
            return none, none
        return self.det[cand[chosen]], cand_gt[chosen]

    def greedy_match(self, prep: PreparedEval, values: np.ndarray, threshold: float = 0.5) -> dict[int, int]:
        """``greedy_match_indices`` as ``{detection id: matched GT annotation id}`` (detection ids are 1..N)."""
        dets, gts = self.greedy_match_indices(values, threshold)
        return dict(zip((dets + 1).tolist(), self.gt_id[gts].tolist()))


def greedy_rounds(
    row: np.ndarray,
    group: np.ndarray,
    preferred: np.ndarray,
    crowd: np.ndarray,
    taken_key: np.ndarray,
    n_keys: int,
    col: np.ndarray,
    value: np.ndarray,
) -> np.ndarray:
    """COCO's greedy matching loop (``COCOeval.evaluateImg``), one pass per detection rank for every group at once:
    the positions of the chosen entries, rank by rank.

    The arrays describe candidate entries (a detection and a GT that may match), ordered by ``row`` (the detection's
    rank in its pair). At each rank, within each ``group`` (a pair, or a pair under one threshold and area range),
    the detection takes among the entries whose GT is not yet taken (``crowd`` GT can be taken again; ``taken_key``
    in ``0..n_keys-1`` names a GT within its group's matching) the last after sorting by (``preferred``, ``value``,
    ``col``): preferred GT first, then the highest value, equal values going to the later GT. The one matching loop
    of both evaluation paths: ``PairLayout.greedy_match_indices`` and ``harness.evaluation.bulk.match_all``.
    """
    if len(row) == 0:
        return np.zeros(0, dtype=np.int64)
    taken = np.zeros(n_keys, dtype=bool)
    bounds = np.flatnonzero(np.r_[True, row[1:] != row[:-1], True])
    out: list[np.ndarray] = []
    for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist()):  # one detection rank at a time
        s = np.arange(lo, hi)
        s = s[crowd[s] | ~taken[taken_key[s]]]
        if len(s) == 0:
            continue
        # the last entry per group after sorting by (group, preferred, value, col) is the one COCO picks
        s = s[np.lexsort((col[s], value[s], preferred[s], group[s]))]
        chosen = s[np.r_[group[s][1:] != group[s][:-1], True]]
        taken[taken_key[chosen[~crowd[chosen]]]] = True
        out.append(chosen)
    return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)


def pair_layout(prep: PreparedEval, max_det: int = 100) -> PairLayout:
    """The flat layout of every (image, category) pair of the prepared detections and GT."""
    d_img, d_cat, d_score, _ = prep.det_columns
    g_img, g_cat, g_box, g_crowd = prep.gt_columns
    g_id = np.arange(1, len(g_img) + 1, dtype=np.int64)  # prepare numbers GT annotations 1..N in order
    img_ids = np.unique(
        np.fromiter((im["id"] for im in prep.gt["images"]), dtype=np.int64, count=len(prep.gt["images"]))
    )
    cat_ids = np.asarray(prep.cat_ids, dtype=np.int64)
    n_cat = len(cat_ids)

    def pair_key(img: np.ndarray, cat: np.ndarray) -> np.ndarray:
        # every detection is on an image and of a category of the GT (prepare dropped the others)
        return np.searchsorted(img_ids, img) * n_cat + np.searchsorted(cat_ids, cat)

    # detections: by pair, then descending score, ties in input order; keep the first max_det of each pair
    d_key = pair_key(d_img, d_cat)
    order = np.lexsort((-d_score, d_key))  # lexsort is stable: ties keep input order
    dk, d_start, d_count = _runs(d_key[order])
    n_det = len(order)
    evaluated = np.ones(n_det, dtype=bool)
    if n_det and d_count.max() > max_det:
        rank = np.arange(n_det) - np.repeat(d_start, d_count)
        keep = rank < max_det
        evaluated[order[~keep]] = False
        order = order[keep]
        d_count = np.minimum(d_count, max_det)
        d_start = np.cumsum(d_count) - d_count
    det_order = order

    # GT: by pair, annotation order within a pair
    g_key = pair_key(g_img, g_cat)
    gt_order = np.argsort(g_key, kind="stable")
    gk, g_start, g_count = _runs(g_key[gt_order])

    # matrix entries of the pairs with both
    keys, di, gi = np.intersect1d(dk, gk, assume_unique=True, return_indices=True)
    rows, cols = d_count[di], g_count[gi]
    sizes = rows * cols
    pair = np.repeat(np.arange(len(keys)), sizes)
    offset = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    row = offset // cols[pair]
    col = offset % cols[pair]
    det = det_order[d_start[di][pair] + row]
    gt = gt_order[g_start[gi][pair] + col]
    return PairLayout(
        img_ids,
        cat_ids,
        det_order,
        dk,
        d_start,
        d_count,
        gt_order,
        gk,
        g_start,
        g_count,
        keys,
        rows,
        cols,
        det,
        gt,
        pair,
        row,
        col,
        g_box,
        g_crowd,
        g_id,
        evaluated,
    )


def _runs(sorted_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct values of a sorted array with the start and length of each run (``np.unique`` without a sort)."""
    n = len(sorted_keys)
    if n == 0:
        return sorted_keys, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    start = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    return sorted_keys[start], start, np.diff(np.r_[start, n])
