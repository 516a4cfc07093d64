"""The two COCO engines behind ``evaluate``: faster-coco-eval (C++) and pycocotools (the reference).

Both get the same prepared inputs (``harness.evaluation.inputs``) and return the same ``EngineResult``: the 12
stats, COCOeval's precision array, and, for the operating point, the evaluated detections at IoU 0.50 with their
TP flags. ``matching="safit"`` swaps the IoU matrix for SAFit's (``harness.evaluation.safit``) in either engine.
"""

from __future__ import annotations

import contextlib
import copy
import gc
import io
import logging
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from harness.evaluation.inputs import EvaluationError, PreparedEval
from harness.evaluation.safit import ANCHORS, SAFIT_C, safit_xywh

log = logging.getLogger(__name__)

ENGINES = ("faster-coco-eval", "pycocotools")
MATCHINGS = ("iou", "safit")


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
