"""Error analysis of one run, computed once at evaluation and stored beside its metrics (``analysis.json``).

``analyse(gt, detections)`` reads the same inputs as ``evaluate`` and uses the evaluator's own preparation and
matching (``harness.evaluation.inputs.prepare``, ``harness.evaluation.pairs``: COCO's greedy matching at IoU 0.50,
area "all", at most 100 detections per image and category, a detection matched to a crowd GT ignored). On that
matching it builds:

* ``tide``: TIDE's six error types (Bolya et al., ECCV 2020) and the mAP50 gained by fixing each one alone;
* ``confusion``: a confusion matrix with a background row and column at IoU 0.50 and the operating point;
* ``pr``: per-category precision-recall curves at IoU 0.50 (COCO's 101 recall points, precision and score);
* ``sizes``: AP50 and AP50:95 per object-size bin (COCO's small/medium/large; SAFit's bins for tiny objects);
* ``images`` and ``gt_found``: per held-out image TP/FP/FN at the operating point, and which GT were found;
* ``worst``: per category the worst misses and the most confident false positives (ids, boxes, scores).

Definitions (``docs/evaluation.md`` section 5 gives them in full):

**TIDE errors.** Every false positive (an evaluated, non-ignored detection the matching left unmatched) gets one
type, tested in this order against the non-crowd GT of its image (``IoU_fg = 0.5``, ``IoU_bg = 0.1``):
``localisation`` if its best IoU with a GT of its own category is in ``[IoU_bg, IoU_fg]``; ``classification`` if
its best IoU with a GT of another category is ``>= IoU_fg``; ``duplicate`` if its best IoU with an already matched
GT of its category is ``>= IoU_fg``; ``background`` if its best IoU with any GT is ``<= IoU_bg`` (or the image has
no GT); ``both`` otherwise. A GT left unmatched is ``missed`` unless a classification or localisation error points
at it. Fixing: a classification (localisation) error whose GT is unmatched becomes a true positive of the GT's
category when it is the highest-scoring of the classification and localisation errors on that GT, and is removed
otherwise; duplicate, background and both errors are removed; a missed GT is removed from the GT count. ``dAP50``
of a type = ``max(mAP50 with that type fixed - mAP50, 0)``, each type fixed alone. The two "special" errors are
TIDE's too: ``false_positives`` (every true positive scored above every false positive) and ``false_negatives``
(the GT count reduced to the true positives). These are the definitions of the ``tidecv`` package, on the
evaluator's matching; one difference: a category with detections but no GT is left out of the mean, as COCO does
(``tidecv`` counts it as AP 0).

**AP** is COCO's: detections of a category sorted by descending score (ties in image order, then rank),
``precision = TP / (TP + FP + eps)`` made non-increasing from the right, read at the 101 recall points
``0, 0.01, ..., 1`` (the first detection whose recall reaches the point), averaged. The baseline ``tide.mAP50``
equals ``metrics.mAP50``.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Mapping, Sequence

import numpy as np

from harness.evaluation.engines import _gc_paused, check_options, run_engine
from harness.evaluation.inputs import PreparedEval, prepare
from harness.evaluation.operating_point import OPERATING_POINT, max_f1_operating_point
from harness.evaluation.pairs import pair_layout
from harness.evaluation.safit import TINY_AREA_RANGES, iou_elementwise

log = logging.getLogger(__name__)

ANALYSIS_SCHEMA = 1
#: What a report shows for a run stored before the analysis existed.
NO_ANALYSIS = "no error analysis stored; rerun with --force"
IOU_FG = 0.5
IOU_BG = 0.1
MAX_DETS = 100
#: TIDE's fix order (``tidecv.TIDE._error_types``): the order of the ``dAP50`` keys.
ERROR_TYPES = ("classification", "localisation", "both", "duplicate", "background", "missed")
SPECIAL_TYPES = ("false_positives", "false_negatives")
#: Display names of the error types (TIDE's abbreviations) and of the two bounds, in the order above.
ERROR_LABELS = dict(
    zip(ERROR_TYPES + SPECIAL_TYPES, ("Cls", "Loc", "Both", "Dupe", "Bkg", "Miss", "FP", "FN"), strict=True)
)
#: COCO's 101 recall points, exactly as ``COCOeval.Params`` builds them.
RECALL_POINTS = np.linspace(0.0, 1.00, int(np.round((1.00 - 0.0) / 0.01)) + 1, endpoint=True)
COCO_AREA_RANGES: dict[str, tuple[float, float]] = {
    "small": (0.0, 32.0**2),
    "medium": (32.0**2, 96.0**2),
    "large": (96.0**2, 1e5**2),
}
#: SAFit's bins (RGBT-Tiny), without "all"
SAFIT_AREA_RANGES: dict[str, tuple[float, float]] = {k: v for k, v in TINY_AREA_RANGES.items() if k != "all"}
#: a dataset is a tiny-object one (SAFit's bins are added) when more than this share of its GT is COCO-small
TINY_SHARE = 0.5
DIGITS = 6  # stored precision and scores (the JSON stays compact; 1e-6 is far below any reported digit)

_LOC, _CLS, _BOTH, _DUPE, _BKG = 1, 0, 2, 3, 4  # FP error codes, indices into ERROR_TYPES
MISS_REASONS = ("missed", "localisation", "classification", "below_threshold")


# ------------------------------------------------------------------------------------------------ small helpers
def _r(x: float | None, digits: int = DIGITS) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


def _rl(a: np.ndarray, digits: int = DIGITS) -> list[float]:
    return [round(v, digits) for v in np.asarray(a, dtype=np.float64).tolist()]


def _segment_first_max(values: np.ndarray, seg: np.ndarray, n_seg: int) -> tuple[np.ndarray, np.ndarray]:
    """Per segment (entries grouped by ``seg``, ascending, in order within each): the maximum and the position of
    its first occurrence (``numpy.argmax``'s tie rule); segments without entries get 0 and -1."""
    best = np.zeros(n_seg)
    arg = np.full(n_seg, -1, dtype=np.int64)
    if len(values) == 0:
        return best, arg
    order = np.lexsort((np.arange(len(values)), -values, seg))
    first = np.r_[True, seg[order][1:] != seg[order][:-1]]
    pick = order[first]
    best[seg[pick]] = values[pick]
    arg[seg[pick]] = pick
    return best, arg


def _same_image_entries(a_img: np.ndarray, b_img: np.ndarray, b_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (a, b) with the same image: ``(a position, b index)``, grouped by a, b in ``b_idx`` order within."""
    if len(a_img) == 0 or len(b_idx) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(b_img[b_idx], kind="stable")
    b_sorted = b_idx[order]
    keys = b_img[b_sorted]
    start = np.searchsorted(keys, a_img, side="left")
    count = np.searchsorted(keys, a_img, side="right") - start
    rep = np.repeat(np.arange(len(a_img)), count)
    offset = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    return rep, b_sorted[np.repeat(start, count) + offset]


def _pr101(tp: np.ndarray, fp: np.ndarray, scores: np.ndarray, n_gt: int) -> tuple[np.ndarray, np.ndarray, float]:
    """COCO's accumulation of one category (detections already in COCO's order): interpolated precision and the
    score at each of the 101 recall points, and the recall reached (``COCOeval.accumulate``)."""
    n = len(tp)
    q = np.zeros(len(RECALL_POINTS))
    ss = np.zeros(len(RECALL_POINTS))
    if n == 0:
        return q, ss, 0.0
    tp_sum = np.cumsum(tp).astype(float)
    fp_sum = np.cumsum(fp).astype(float)
    rc = tp_sum / n_gt
    pr = tp_sum / (fp_sum + tp_sum + np.spacing(1))
    pr = np.maximum.accumulate(pr[::-1])[::-1]
    inds = np.searchsorted(rc, RECALL_POINTS, side="left")
    ok = inds < n
    q[ok] = pr[inds[ok]]
    ss[ok] = scores[inds[ok]]
    return q, ss, float(rc[-1])


# ------------------------------------------------------------------------------------------------ the matching
class _Matched:
    """The evaluator's matching at IoU 0.50 of one prepared evaluation, as flat arrays."""

    def __init__(self, prep: PreparedEval):
        self.prep = prep
        d_img, d_cat, d_score, d_box = prep.det_columns
        g_img, g_cat, g_box, g_crowd = prep.gt_columns
        self.d_img, self.d_cat, self.d_score, self.d_box = d_img, d_cat, d_score, d_box
        self.g_img, self.g_cat, self.g_box, self.g_crowd = g_img, g_cat, g_box, g_crowd
        self.cat_ids = np.asarray(prep.cat_ids, dtype=np.int64)
        layout = pair_layout(prep, MAX_DETS)
        d_idx, g_idx = layout.greedy_match_indices(layout.values(prep, iou_elementwise), threshold=IOU_FG)
        n, g = prep.n_dets, len(g_img)
        self.evaluated = layout.evaluated
        self.match = np.full(n, -1, dtype=np.int64)  # GT index each detection matched (crowd included)
        self.match[d_idx] = g_idx
        self.ignored = np.zeros(n, dtype=bool)
        hit = self.match >= 0
        self.ignored[hit] = g_crowd[self.match[hit]]
        self.tp = (self.match >= 0) & ~self.ignored
        self.fp = self.evaluated & (self.match < 0)
        self.gt_det = np.full(g, -1, dtype=np.int64)  # detection that matched each non-crowd GT
        real = ~g_crowd[g_idx]
        self.gt_det[g_idx[real]] = d_idx[real]
        # COCO's order within a category: image, then rank in the pair (det_order), then stable by descending score
        self.seq = np.full(n, -1, dtype=np.int64)
        self.seq[layout.det_order] = np.arange(len(layout.det_order))
        self.cat_index = np.searchsorted(self.cat_ids, d_cat)
        self.g_cat_index = np.searchsorted(self.cat_ids, g_cat)
        self.n_gt = np.array([prep.n_gt[int(c)] for c in self.cat_ids], dtype=np.int64)
        self.image_key = dict(zip((im["id"] for im in prep.gt["images"]), prep.image_keys))

    def coco_order(self, sel: np.ndarray, scores: np.ndarray | None = None) -> np.ndarray:
        """``sel`` (detection indices) in COCO's accumulation order."""
        s = self.d_score[sel] if scores is None else scores
        return sel[np.lexsort((self.seq[sel], -s))]


# ------------------------------------------------------------------------------------------------ AP and TIDE
def _map50(
    cat: np.ndarray,
    score: np.ndarray,
    tp: np.ndarray,
    fp: np.ndarray,
    seq: np.ndarray,
    n_gt: np.ndarray,
    cats: np.ndarray,
) -> float | None:
    """mAP50 over the categories ``cats`` (indices) of the data points given (COCO's AP of each, see the module
    docstring); a category whose GT count fell to 0 scores 0 if it still has detections and is left out otherwise
    (TIDE's rule)."""
    grid = []
    for k in cats.tolist():
        sel = np.flatnonzero(cat == k)
        if n_gt[k] <= 0:
            if len(sel):
                grid.append(np.zeros(len(RECALL_POINTS)))
            continue
        order = sel[np.lexsort((seq[sel], -score[sel]))]
        q, _, _ = _pr101(tp[order], fp[order], score[order], int(n_gt[k]))
        grid.append(q)
    if not grid:
        return None
    return float(np.stack(grid, axis=1).mean())  # r-major, as COCO's summarize reads its precision array


def _tide(m: _Matched) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray]:
    """TIDE's error types and dAP50; also each FP's error code, best IoU with any GT, and linked GT (or -1)."""
    fps = np.flatnonzero(m.fp)
    nonc = np.flatnonzero(~m.g_crowd)
    rep, gidx = _same_image_entries(m.d_img[fps], m.g_img, nonc)
    iou = iou_elementwise(m.d_box[fps][rep], m.g_box[gidx]) if len(rep) else np.zeros(0)
    same = m.g_cat[gidx] == m.d_cat[fps][rep]
    used = m.gt_det[gidx] >= 0
    nf = len(fps)
    cls_max, cls_arg = _segment_first_max(np.where(same, iou, 0.0), rep, nf)
    oth_max, oth_arg = _segment_first_max(np.where(~same, iou, 0.0), rep, nf)
    dup_max, _ = _segment_first_max(np.where(same & used, iou, 0.0), rep, nf)
    all_max, _ = _segment_first_max(iou, rep, nf)
    has_gt = np.bincount(rep, minlength=nf) > 0 if nf else np.zeros(0, dtype=bool)

    code = np.full(nf, _BOTH, dtype=np.int64)
    linked = np.full(nf, -1, dtype=np.int64)
    undecided = has_gt.copy()
    code[~has_gt] = _BKG
    rules = (
        (_LOC, (cls_max >= IOU_BG) & (cls_max <= IOU_FG), cls_arg),
        (_CLS, oth_max >= IOU_FG, oth_arg),
        (_DUPE, dup_max >= IOU_FG, None),
        (_BKG, all_max <= IOU_BG, None),
    )
    for c, hit, arg in rules:
        take = undecided & hit
        code[take] = c
        if arg is not None:
            linked[take] = gidx[arg[take]]
        undecided &= ~hit

    # which classification / localisation errors can be fixed: the best-scoring one on each unmatched GT
    fixable = linked >= 0
    fixable[fixable] = m.gt_det[linked[fixable]] < 0
    best = np.zeros(nf, dtype=bool)
    cand = np.flatnonzero(fixable)
    if len(cand):
        # TIDE visits images in GT order and detections by descending score; the first of equal scores wins
        order = cand[np.lexsort((m.seq[fps[cand]], -m.d_score[fps[cand]], m.d_img[fps[cand]], linked[cand]))]
        first = np.r_[True, linked[order][1:] != linked[order][:-1]]
        best[order[first]] = True
    usable = np.zeros(len(m.g_img), dtype=bool)
    usable[linked[fixable]] = True
    missed = ~m.g_crowd & (m.gt_det < 0) & ~usable

    # the data points: every evaluated, non-ignored detection
    pts = np.flatnonzero(m.evaluated & ~m.ignored)
    cat, score, tp = m.cat_index[pts].copy(), m.d_score[pts].copy(), m.tp[pts].copy()
    seq = m.seq[pts]
    fp_pos = np.searchsorted(pts, fps)  # fps is a subset of pts, both ascending
    cats = np.flatnonzero(m.n_gt > 0)
    base = _map50(cat, score, tp, ~tp, seq, m.n_gt, cats)

    def fixed(error: int) -> float | None:
        keep = np.ones(len(pts), dtype=bool)
        c, t = cat.copy(), tp.copy()
        n_gt = m.n_gt.copy()
        if error in (_CLS, _LOC):
            mine = code == error
            win = mine & best
            t[fp_pos[win]] = True
            if error == _CLS:
                c[fp_pos[win]] = m.g_cat_index[linked[win]]
            keep[fp_pos[mine & ~win]] = False
        elif error == len(ERROR_TYPES) - 1:  # missed
            n_gt -= np.bincount(m.g_cat_index[missed], minlength=len(n_gt))
        else:
            keep[fp_pos[code == error]] = False
        return _map50(c[keep], score[keep], t[keep], ~t[keep], seq[keep], n_gt, cats)

    d_ap: dict[str, float | None] = {}
    for k, name in enumerate(ERROR_TYPES):
        v = fixed(k)
        d_ap[name] = None if v is None or base is None else max(v - base, 0.0)
    special: dict[str, float | None] = {}
    if base is not None:
        # every TP scored 1 and every FP 0 (recall unchanged); the GT count reduced to the TPs (precision unchanged)
        # (not clipped at 0, as in tidecv)
        special["false_positives"] = (_map50(cat, tp.astype(float), tp, ~tp, seq, m.n_gt, cats) or 0.0) - base
        tp_per_cat = np.bincount(cat[tp], minlength=len(m.n_gt))
        special["false_negatives"] = (_map50(cat, score, tp, ~tp, seq, tp_per_cat, cats) or 0.0) - base
    else:
        special = {k: None for k in SPECIAL_TYPES}

    counts = {name: int((code == k).sum()) for k, name in enumerate(ERROR_TYPES[:-1])}
    counts["missed"] = int(missed.sum())
    per_cat: dict[str, dict[str, int]] = {}
    for k, cid in enumerate(m.cat_ids.tolist()):
        name = m.prep.cat_names[cid]
        mine = m.cat_index[fps] == k
        row = {t: int(((code == j) & mine).sum()) for j, t in enumerate(ERROR_TYPES[:-1])}
        row["missed"] = int((missed & (m.g_cat_index == k)).sum())
        per_cat[name] = row
    block = {
        "mAP50": base,
        "dAP50": d_ap,
        "special": special,
        "counts": counts,
        "counts_per_category": per_cat,
        "iou_foreground": IOU_FG,
        "iou_background": IOU_BG,
        "false_positives": int(nf),
        "true_positives": int(m.tp.sum()),
        "instances": int(m.n_gt.sum()),
    }
    fp_code = np.full(len(m.d_score), -1, dtype=np.int64)
    fp_code[fps] = code
    fp_iou = np.zeros(len(m.d_score))
    fp_iou[fps] = all_max
    fp_link = np.full(len(m.d_score), -1, dtype=np.int64)
    fp_link[fps] = linked
    return block, fp_code, fp_iou, fp_link


# ------------------------------------------------------------------------------------------------ PR curves
def _pr_curves(m: _Matched) -> dict[str, Any]:
    cats: dict[str, Any] = {}
    for k, cid in enumerate(m.cat_ids.tolist()):
        name = m.prep.cat_names[cid]
        n_gt = int(m.n_gt[k])
        sel = np.flatnonzero(m.evaluated & (m.cat_index == k))
        if n_gt == 0:
            cats[name] = {
                "instances": 0,
                "detections": int(len(sel)),
                "AP50": None,
                "precision": None,
                "scores": None,
                "max_recall": None,
            }
            continue
        order = m.coco_order(sel)
        q, ss, rmax = _pr101(m.tp[order], m.fp[order], m.d_score[order], n_gt)
        cats[name] = {
            "instances": n_gt,
            "detections": int(len(sel)),
            "AP50": float(q.mean()),
            "precision": _rl(q),
            "scores": _rl(ss),
            "max_recall": _r(rmax),
        }
    return {
        "iou": IOU_FG,
        "recall": _rl(RECALL_POINTS, 2),
        "categories": cats,
        "definition": "COCO's interpolated precision and the score of the detection that reaches each recall "
        "point (0 beyond the last recall reached); area all, maxDets 100",
    }


# ------------------------------------------------------------------------------------------------ operating point
def _kept(m: _Matched, threshold: float | None) -> np.ndarray:
    """Detections that count at the operating point: evaluated, not ignored, score >= threshold (all when None)."""
    base = m.evaluated & ~m.ignored
    return base if threshold is None else base & (m.d_score >= threshold)


def _confusion(m: _Matched, kept: np.ndarray, found: np.ndarray) -> tuple[dict[str, Any], np.ndarray]:
    """Rows: predicted category, then background; columns: GT category, then background. Matched detections
    (the evaluator's matching) go on the diagonal; then each remaining detection, by descending score, takes the
    remaining GT of its image with the highest IoU >= 0.5 (another category: a confusion); what is left is a false
    positive on background (last column) or a missed GT (last row)."""
    k = len(m.cat_ids)
    mat = np.zeros((k + 1, k + 1), dtype=np.int64)
    diag = kept & m.tp
    np.add.at(mat, (m.cat_index[diag], m.cat_index[diag]), 1)
    left_d = np.flatnonzero(kept & ~m.tp)
    left_g = np.flatnonzero(~m.g_crowd & ~found)
    rep, gidx = _same_image_entries(m.d_img[left_d], m.g_img, left_g)
    confused_gt = np.zeros(len(m.g_img), dtype=bool)
    confused_det = np.zeros(len(left_d), dtype=bool)
    if len(rep):
        iou = iou_elementwise(m.d_box[left_d][rep], m.g_box[gidx])
        cand = np.flatnonzero(iou >= IOU_FG)
        if len(cand):
            # detections by descending score (canonical order on ties), then the highest IoU, first GT on ties
            d = left_d[rep[cand]]
            cand = cand[np.lexsort((gidx[cand], -iou[cand], d, -m.d_score[d]))]
            for e in cand.tolist():
                a, g = int(rep[e]), int(gidx[e])
                if confused_det[a] or confused_gt[g]:
                    continue
                confused_det[a] = True
                confused_gt[g] = True
                mat[m.cat_index[left_d[a]], m.g_cat_index[g]] += 1
    bg_d = left_d[~confused_det]
    np.add.at(mat, (m.cat_index[bg_d], np.full(len(bg_d), k)), 1)
    bg_g = left_g[~confused_gt[left_g]]
    np.add.at(mat, (np.full(len(bg_g), k), m.g_cat_index[bg_g]), 1)
    labels = [m.prep.cat_names[c] for c in m.cat_ids.tolist()] + ["background"]
    return {
        "rows": "predicted",
        "columns": "ground truth",
        "labels": labels,
        "matrix": mat.tolist(),
        "iou": IOU_FG,
    }, confused_gt


def _image_counts(m: _Matched, kept: np.ndarray, found: np.ndarray) -> dict[str, Any]:
    images = np.array([im["id"] for im in m.prep.gt["images"]], dtype=np.int64)
    by_id = np.argsort(images, kind="stable")
    n = len(images)

    def count(ids: np.ndarray) -> list[int]:
        pos = by_id[np.searchsorted(images[by_id], ids)]
        return np.bincount(pos, minlength=n).tolist()

    real = ~m.g_crowd
    return {
        "image_id": [m.image_key[i] for i in images.tolist()],
        "gt": count(m.g_img[real]),
        "tp": count(m.g_img[real & found]),
        "fp": count(m.d_img[kept & ~m.tp]),
        "fn": count(m.g_img[real & ~found]),
    }


def _worst(
    m: _Matched,
    kept: np.ndarray,
    found: np.ndarray,
    confused_gt: np.ndarray,
    fp_code: np.ndarray,
    fp_iou: np.ndarray,
    fp_link: np.ndarray,
    gt_ids: list[Any],
    n: int,
) -> dict[str, Any]:
    """Per category: the ``n`` most confident false positives and the ``n`` worst misses at the operating point."""
    # misses: their best IoU with a kept detection of the same category, and why they were missed
    miss = np.flatnonzero(~m.g_crowd & ~found)
    kept_idx = np.flatnonzero(kept)
    rep, didx = _same_image_entries(m.g_img[miss], m.d_img, kept_idx)
    same = m.d_cat[didx] == m.g_cat[miss][rep] if len(rep) else np.zeros(0, dtype=bool)
    iou = iou_elementwise(m.d_box[didx], m.g_box[miss][rep]) if len(rep) else np.zeros(0)
    best_same, _ = _segment_first_max(np.where(same, iou, 0.0), rep, len(miss))
    matched_below = m.gt_det[miss] >= 0
    reason = np.zeros(len(miss), dtype=np.int64)  # missed
    reason[best_same >= IOU_BG] = 1  # localisation
    reason[confused_gt[miss]] = 2  # classification
    reason[matched_below] = 3  # found below the operating point's threshold
    area = m.g_box[miss, 2] * m.g_box[miss, 3]
    out: dict[str, Any] = {}
    for k, cid in enumerate(m.cat_ids.tolist()):
        name = m.prep.cat_names[cid]
        mine = np.flatnonzero(m.g_cat_index[miss] == k)
        mine = mine[np.lexsort((-area[mine], best_same[mine], reason[mine]))][:n]
        misses = [
            {
                "image_id": m.image_key[int(m.g_img[miss[i]])],
                "annotation_id": gt_ids[int(miss[i])],
                "bbox": _rl(m.g_box[miss[i]], 2),
                "area": _r(area[i], 2),
                "reason": MISS_REASONS[reason[i]],
                "best_iou": _r(best_same[i], 4),
                "score": _r(m.d_score[m.gt_det[miss[i]]], 4) if matched_below[i] else None,
            }
            for i in mine.tolist()
        ]
        fps = np.flatnonzero((fp_code >= 0) & (m.cat_index == k))
        fps = fps[np.lexsort((m.seq[fps], -m.d_score[fps]))][:n]
        false_pos = []
        for j in fps.tolist():
            link = int(fp_link[j])
            false_pos.append(
                {
                    "image_id": m.image_key[int(m.d_img[j])],
                    "bbox": _rl(m.d_box[j], 2),
                    "score": _r(m.d_score[j], 4),
                    "error": ERROR_TYPES[fp_code[j]],
                    "iou": _r(fp_iou[j], 4),
                    "kept": bool(kept[j]),
                    "gt_category": m.prep.cat_names[int(m.g_cat[link])] if link >= 0 else None,
                    "annotation_id": gt_ids[link] if link >= 0 else None,
                }
            )
        out[name] = {"misses": misses, "false_positives": false_pos}
    return out


# ------------------------------------------------------------------------------------------------ size bins
def _is_tiny(prep: PreparedEval) -> bool:
    areas = np.array([a["area"] for a in prep.gt["annotations"] if not a["iscrowd"]], dtype=np.float64)
    return bool(len(areas)) and float((areas <= COCO_AREA_RANGES["small"][1]).mean()) > TINY_SHARE


def _sizes(prep: PreparedEval, engine: str, tiny: bool) -> dict[str, Any]:
    from harness.evaluation.coco import summarize_precision

    ranges: dict[str, tuple[float, float]] = {"all": (0.0, 1e5**2)}
    ranges.update({f"coco.{k}": v for k, v in COCO_AREA_RANGES.items()})
    if tiny:
        ranges.update({f"safit.{k}": v for k, v in SAFIT_AREA_RANGES.items()})
    res = run_engine(prep, engine, "iou", area_ranges=ranges, operating_point=False)
    labels = list(res.area_labels)
    areas = np.array([a["area"] for a in prep.gt["annotations"]], dtype=np.float64)
    crowd = np.array([bool(a["iscrowd"]) for a in prep.gt["annotations"]], dtype=bool)
    cats = np.array([a["category_id"] for a in prep.gt["annotations"]], dtype=np.int64)

    def block(scheme: str, bins: Mapping[str, tuple[float, float]]) -> dict[str, Any]:
        out: dict[str, Any] = {
            "ranges": {b: [float(lo), float(hi)] for b, (lo, hi) in bins.items()},
            "AP50": {},
            "AP50_95": {},
            "instances": {},
            "per_category": {},
        }
        for b, (lo, hi) in bins.items():
            a = labels.index(f"{scheme}.{b}")
            inside = ~crowd & (areas >= lo) & (areas <= hi)  # COCO's area ranges include both edges
            out["AP50"][b] = summarize_precision(res.precision, res.iou_thrs, 0.5, a)
            out["AP50_95"][b] = summarize_precision(res.precision, res.iou_thrs, None, a)
            out["instances"][b] = int(inside.sum())
            for k, cid in enumerate(prep.cat_ids):
                pc = out["per_category"].setdefault(prep.cat_names[cid], {"AP50": {}, "AP50_95": {}, "instances": {}})
                pc["AP50"][b] = summarize_precision(res.precision, res.iou_thrs, 0.5, a, k)
                pc["AP50_95"][b] = summarize_precision(res.precision, res.iou_thrs, None, a, k)
                pc["instances"][b] = int((inside & (cats == cid)).sum())
        return out

    sizes: dict[str, Any] = {
        "matching": "iou",
        "area": "GT area field, px^2 of the prepared frame",
        "coco": block("coco", COCO_AREA_RANGES),
    }
    if tiny:
        sizes["safit"] = block("safit", SAFIT_AREA_RANGES)
    return sizes


# ------------------------------------------------------------------------------------------------ entry point
def analyse(
    gt: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    *,
    conf_threshold: float | None = None,
    engine: str = "faster-coco-eval",
    matching: str = "iou",
    examples: int = 10,
    tiny: bool | None = None,
) -> dict[str, Any]:
    """The error analysis of one run (module docstring; schema in ``harness/store.py``).

    ``conf_threshold``: the operating point's confidence (``metrics.conf_threshold``); computed here, by the same
    definition, when not given. ``tiny``: add SAFit's size bins (default: when ``matching == "safit"`` or more than
    half of the GT is COCO-small). ``examples``: worst misses and false positives kept per category.
    """
    check_options(engine, matching, "center")
    with _gc_paused():
        prep = prepare(gt, detections)
        m = _Matched(prep)
        if conf_threshold is None:
            kept0 = m.evaluated & ~m.ignored
            op = max_f1_operating_point(m.d_score[kept0], m.cat_index[kept0], m.tp[kept0], m.n_gt)
            conf_threshold = op.conf_threshold
        kept = _kept(m, conf_threshold)
        found = np.zeros(len(m.g_img), dtype=bool)
        has = m.gt_det >= 0
        found[has] = kept[m.gt_det[has]]
        tide, fp_code, fp_iou, fp_link = _tide(m)
        confusion, confused_gt = _confusion(m, kept, found)
        confusion["conf_threshold"] = conf_threshold
        gt_ids = [a.get("id") for a in gt["annotations"]]
        is_tiny = (matching == "safit" or _is_tiny(prep)) if tiny is None else bool(tiny)
        gt_found = np.where(m.g_crowd, -1, found.astype(np.int64)).tolist()
        result = {
            "schema": ANALYSIS_SCHEMA,
            "conf_threshold": conf_threshold,
            "operating_point": OPERATING_POINT,
            "categories": [prep.cat_names[c] for c in prep.cat_ids],
            "tide": tide,
            "confusion": confusion,
            "pr": _pr_curves(m),
            "sizes": _sizes(prep, engine, is_tiny),
            "images": _image_counts(m, kept, found),
            "gt_found": gt_found,
            "worst": _worst(m, kept, found, confused_gt, fp_code, fp_iou, fp_link, gt_ids, examples),
        }
        del m, prep
    return result


def analyse_with_config(
    gt: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    cfg: Mapping[str, Any],
    conf_threshold: float | None = None,
) -> dict[str, Any]:
    """``analyse`` with the engine and matching of a resolved config's ``eval`` section."""
    ev = cfg.get("eval", cfg)
    return analyse(
        gt,
        detections,
        conf_threshold=conf_threshold,
        engine=ev.get("engine", "faster-coco-eval"),
        matching=ev.get("matching", "iou"),
    )


def store_analysis(
    run: Any,
    gt: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    cfg: Mapping[str, Any],
    conf_threshold: float | None,
) -> bool:
    """Compute and write ``run``'s ``analysis.json``; a failure is logged and recorded in the file (the run's
    metrics and predictions are never lost to it). Returns whether the analysis was stored."""
    try:
        result = analyse_with_config(gt, detections, cfg, conf_threshold)
    except Exception as exc:  # noqa: BLE001 - the analysis is additive: the run itself stands
        log.error(
            "%s: error analysis failed (%s: %s); the run's metrics are stored without it",
            run.key,
            type(exc).__name__,
            exc,
        )
        run.write_analysis({"schema": ANALYSIS_SCHEMA, "error": f"{type(exc).__name__}: {exc}"})
        return False
    run.write_analysis(result)
    return True


def analysis_of(run: Any) -> tuple[dict[str, Any] | None, str | None]:
    """A stored run's analysis, or ``(None, why not)``: what a report shows in its place (``NO_ANALYSIS`` for a run
    stored before the analysis existed)."""
    from harness.errors import HarnessError

    try:
        data = run.read_analysis()
    except HarnessError as exc:
        return None, f"error analysis unreadable ({exc}); rerun with --force"
    if data is None:
        return None, NO_ANALYSIS
    if data.get("error"):
        return None, f"error analysis failed: {data['error']}"
    return data, None
