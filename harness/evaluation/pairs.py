"""Every (image, category) pair of detections and ground truth, laid out flat so that COCO's per-pair work runs
in bulk with numpy: the matching matrices (IoU or SAFit) and COCO's greedy matching at one threshold.

Within a pair, detections are ordered by descending score (ties in input order) and cut at ``max_det``; GT keep
their annotation order. These are the orders ``COCOeval.computeIoU`` and ``COCOeval.evaluateImg`` use, so the
matrices are exactly the ones COCOeval builds one pair at a time, and ``greedy_match`` reproduces its matching.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from harness.evaluation.inputs import PreparedEval


@dataclass
class PairLayout:
    keys_img: np.ndarray  # [P] image id of each pair with both detections and GT
    keys_cat: np.ndarray  # [P] category id
    rows: np.ndarray  # [P] detections in the pair (after the max_det cut)
    cols: np.ndarray  # [P] GT in the pair
    det: np.ndarray  # [E] index into prep.dets of each matrix entry (pair-major, then row, then column)
    gt: np.ndarray  # [E] index into prep.gt["annotations"]
    pair: np.ndarray  # [E]
    row: np.ndarray  # [E] detection rank in its pair
    col: np.ndarray  # [E] GT position in its pair
    gt_box: np.ndarray  # [G, 4] all GT boxes
    gt_crowd: np.ndarray  # [G]
    gt_id: np.ndarray  # [G] annotation ids
    #: [N] per detection of prep.dets: within the first ``max_det`` of its (image, category) by score, i.e. evaluated
    evaluated: np.ndarray

    def values(self, prep: PreparedEval, measure: Callable[..., np.ndarray]) -> np.ndarray:
        """``measure(d, g, crowd)`` of every entry (element-wise on [E, 4] boxes)."""
        if len(self.det) == 0:
            return np.zeros(0)
        return measure(prep.det_columns[3][self.det], self.gt_box[self.gt], self.gt_crowd[self.gt])

    def matrices(self, values: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        """``{(image_id, category_id): [D, G] matrix}`` for the pairs with both detections and GT."""
        sizes = self.rows * self.cols
        blocks = np.split(values, np.cumsum(sizes)[:-1]) if len(sizes) else []
        return {(i, c): b.reshape(r, k) for i, c, b, r, k in
                zip(self.keys_img.tolist(), self.keys_cat.tolist(), blocks, self.rows.tolist(), self.cols.tolist())}

    def greedy_match(self, prep: PreparedEval, values: np.ndarray, threshold: float = 0.5) -> dict[int, int]:
        """COCO's greedy matching at one threshold, area "all": detection id -> matched GT annotation id.

        ``COCOeval.evaluateImg``: detections in score order each take, among GT not yet taken (crowd GT can be taken
        again), the one with the highest value >= threshold, preferring non-crowd GT; equal values go to the later
        GT in COCO's order (non-crowd GT first, then crowd, each in annotation order).
        """
        if len(values) == 0:
            return {}
        thr = min(threshold, 1 - 1e-10)
        crowd = self.gt_crowd[self.gt]
        taken = np.zeros(len(self.gt_box), dtype=bool)
        by_row = np.argsort(self.row, kind="stable")
        bounds = np.searchsorted(self.row[by_row], np.arange(int(self.row.max()) + 2))
        out_det: list[np.ndarray] = []
        out_gt: list[np.ndarray] = []
        for r in range(len(bounds) - 1):
            e = by_row[bounds[r]:bounds[r + 1]]
            e = e[(values[e] >= thr) & (crowd[e] | ~taken[self.gt[e]])]
            if len(e) == 0:
                continue
            # the last entry per pair after sorting by (pair, non-crowd, value, col) is the one COCO picks
            o = np.lexsort((self.col[e], values[e], ~crowd[e], self.pair[e]))
            e = e[o]
            last = np.r_[self.pair[e][1:] != self.pair[e][:-1], True]
            chosen = e[last]
            g = self.gt[chosen]
            taken[g[~self.gt_crowd[g]]] = True
            out_det.append(self.det[chosen])
            out_gt.append(g)
        if not out_det:
            return {}
        dets = np.concatenate(out_det)
        gts = np.concatenate(out_gt)
        det_ids = np.fromiter((prep.dets[i]["id"] for i in dets.tolist()), dtype=np.int64, count=len(dets))
        return dict(zip(det_ids.tolist(), self.gt_id[gts].tolist()))


def pair_layout(prep: PreparedEval, max_det: int = 100) -> PairLayout:
    """The flat layout of every (image, category) pair that has both detections and GT."""
    d_img, d_cat, d_score, _ = prep.det_columns
    anns = prep.gt["annotations"]
    n_ann = len(anns)
    g_img = np.fromiter((a["image_id"] for a in anns), dtype=np.int64, count=n_ann)
    g_cat = np.fromiter((a["category_id"] for a in anns), dtype=np.int64, count=n_ann)
    g_box = np.asarray([a["bbox"] for a in anns], dtype=np.float64).reshape(-1, 4)
    g_crowd = np.fromiter((a["iscrowd"] for a in anns), dtype=bool, count=n_ann)
    g_id = np.fromiter((a["id"] for a in anns), dtype=np.int64, count=n_ann)
    empty = np.zeros(0, dtype=np.int64)
    if len(d_img) == 0:
        return PairLayout(empty, empty, empty, empty, empty, empty, empty, empty, empty, g_box, g_crowd, g_id,
                          np.zeros(0, dtype=bool))
    # every detection is on an image of the GT (prepare dropped the others), so every one has a pair key
    img_ids = np.unique(np.fromiter((im["id"] for im in prep.gt["images"]), dtype=np.int64))
    cat_ids = np.asarray(prep.cat_ids, dtype=np.int64)
    n_cat = len(cat_ids)

    def pair_key(img: np.ndarray, cat: np.ndarray) -> np.ndarray:
        return np.searchsorted(img_ids, img) * n_cat + np.searchsorted(cat_ids, cat)

    d_key = pair_key(d_img, d_cat)
    order = np.lexsort((np.arange(len(d_key)), -d_score, d_key))
    d_key_sorted = d_key[order]
    starts = np.flatnonzero(np.r_[True, d_key_sorted[1:] != d_key_sorted[:-1]])
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    keep = rank < max_det
    evaluated = np.zeros(len(d_key), dtype=bool)
    evaluated[order[keep]] = True
    if n_ann == 0:
        return PairLayout(empty, empty, empty, empty, empty, empty, empty, empty, empty, g_box, g_crowd, g_id, evaluated)
    d_sorted, d_key_sorted = order[keep], d_key_sorted[keep]
    dk, d_start, d_count = np.unique(d_key_sorted, return_index=True, return_counts=True)

    g_key = pair_key(g_img, g_cat)
    g_sorted = np.argsort(g_key, kind="stable")
    gk, g_start, g_count = np.unique(g_key[g_sorted], return_index=True, return_counts=True)

    keys, di, gi = np.intersect1d(dk, gk, assume_unique=True, return_indices=True)
    rows, cols = d_count[di], g_count[gi]
    sizes = rows * cols
    pair = np.repeat(np.arange(len(keys)), sizes)
    offset = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    row = offset // cols[pair]
    col = offset % cols[pair]
    det = d_sorted[d_start[di][pair] + row]
    gt = g_sorted[g_start[gi][pair] + col]
    return PairLayout(img_ids[keys // n_cat], cat_ids[keys % n_cat], rows, cols, det, gt, pair, row, col,
                      g_box, g_crowd, g_id, evaluated)
