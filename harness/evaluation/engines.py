"""The two COCO engines behind ``evaluate``: faster-coco-eval (C++) and pycocotools (the reference).

Both get the same prepared inputs (``harness.evaluation.inputs``) and return the same ``EngineResult``: the 12
stats, COCOeval's precision array, and, for the operating point, the evaluated detections at IoU 0.50 with their
TP flags. ``matching="safit"`` swaps the IoU matrix for SAFit's (``harness.evaluation.safit``) in either engine.

With faster-coco-eval, the work the library does one (image, category) pair at a time is done in bulk with numpy
for every pair at once: the IoU matrices (``harness.evaluation.pairs``, bitwise the library's own), and its matching
at every IoU threshold and area range and its accumulation (``harness.evaluation.bulk``, the same arithmetic as its
C++ ``COCOevalEvaluateImages`` and ``COCOevalAccumulate``; the tests compare every computed cell). The library's
parameters and ``summarize()`` give the statistics; its own, slower path runs wherever the bulk one does not apply.
The operating point reads the bulk matching at IoU 0.50, area "all". pycocotools is run exactly as published.
"""

from __future__ import annotations

import contextlib
import copy
import gc
import io
import logging
from dataclasses import dataclass
from functools import partial
from typing import Any, Mapping

import numpy as np

from harness.evaluation.bulk import Matches, accumulate, gt_ignored, iou_values, match_all
from harness.evaluation.inputs import EvaluationError, PreparedEval
from harness.evaluation.pairs import PairLayout, pair_layout
from harness.evaluation.safit import ANCHORS, SAFIT_C, iou_elementwise, safit_elementwise, safit_xywh

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


def _coco_objects(prep: PreparedEval) -> tuple[Any, Any]:
    """faster-coco-eval ``COCO`` objects of the prepared GT and detections (only its own preparation needs them)."""
    from faster_coco_eval.core.coco import COCO

    gt = COCO(prep.gt, print_function=_silent)
    dt = COCO(print_function=_silent)
    dt.dataset = {"images": prep.gt["images"], "categories": prep.gt["categories"], "annotations": prep.dets}
    dt.createIndex()
    return gt, dt


def _faster_eval_class(matching: str, anchor: str) -> type:
    from faster_coco_eval.core.faster_eval_api import COCOeval_faster

    class HarnessEvalFaster(COCOeval_faster):  # type: ignore[misc, valid-type]
        """faster-coco-eval with the per-pair work done in bulk: the IoU (or SAFit) matrices of every pair in one
        vectorised pass, then COCO's matching at every IoU threshold and area range and the accumulation of the
        cells ``summarize()`` reads (``harness.evaluation.bulk``), bitwise what the library's C++ computes. Without
        ``harness_inputs``, for other evaluation modes, or if the library's parameters moved, it behaves as the
        stock class, with SAFit computed pair by pair."""

        harness_inputs: PreparedEval | None = None
        _harness_layout: PairLayout | None = None
        _harness_values: np.ndarray | None = None
        _harness_matches: Matches | None = None

        def evaluate(self) -> None:
            prep = self.harness_inputs
            try:
                p = self.params
                if (
                    prep is None
                    or p.iouType != "bbox"
                    or self.lvis_style
                    or not p.useCats
                    or self.separate_eval
                    or self.extra_calc
                ):
                    return self._stock_evaluate()
                self._bulk_evaluate(prep)
            except AttributeError as exc:  # the library's parameters changed: do it its own way
                log.warning(
                    "faster-coco-eval bulk evaluation unavailable (%s); using the library's own, slower evaluation", exc
                )
                self._harness_layout = self._harness_values = self._harness_matches = None
                return self._stock_evaluate()

        def _bulk_evaluate(self, prep: PreparedEval) -> None:
            p = self.params
            img_ids = [int(i) for i in np.unique(np.asarray(p.imgIds, dtype=np.int64))]
            cat_ids = [int(c) for c in np.unique(np.asarray(p.catIds, dtype=np.int64))]
            max_dets = sorted(p.maxDets)
            area_rng, iou_thrs = [list(r) for r in p.areaRng], np.asarray(p.iouThrs, dtype=np.float64)
            _ = p.recThrs, p.areaRngLbl  # read by the accumulation: fail here, before anything is changed
            layout = pair_layout(prep, max_dets[-1])
            if layout.img_ids.tolist() != img_ids or layout.cat_ids.tolist() != cat_ids:
                raise EvaluationError("internal: the evaluated image and category ids differ from the prepared ones")
            if matching == "iou":
                values = iou_values(layout, prep)
            else:
                values = layout.values(prep, partial(safit_elementwise, c=SAFIT_C, anchor=anchor))  # type: ignore[arg-type]
            anns = prep.gt["annotations"]
            # the fields the library's C++ reads: "area", and "ignore" (prepare sets it to "iscrowd")
            gt_area = np.fromiter((a["area"] for a in anns), dtype=np.float64, count=len(anns))
            gt_ignore = np.fromiter((bool(a.get("ignore", 0)) for a in anns), dtype=bool, count=len(anns))
            ignored = gt_ignored(gt_area, gt_ignore, area_rng)
            matches = match_all(layout, values, iou_thrs, ignored)
            p.imgIds, p.catIds, p.maxDets = img_ids, cat_ids, max_dets
            self._harness_layout, self._harness_values, self._harness_matches = layout, values, matches
            self._paramsEval = copy.deepcopy(p)
            self.eval = accumulate(prep, layout, matches, ignored, self._paramsEval)

        def _stock_evaluate(self) -> None:
            if self.cocoGt is None and self.harness_inputs is not None:  # type: ignore[has-type]
                self.cocoGt, self.cocoDt = _coco_objects(self.harness_inputs)
            self.harness_inputs = None
            if not self.cocoDt.anns and self.cocoDt.dataset.get("annotations"):
                self.cocoDt.createIndex()
            return super().evaluate()

        def computeIoU(self, imgId: int, catId: int) -> Any:  # noqa: N802 (COCOeval's name)
            if matching == "iou":
                return super().computeIoU(imgId, catId)
            p = self.params
            cat = [catId] if p.useCats else p.catIds
            gt = self.gt_dataset.get_instances([imgId], cat, bool(p.useCats))[0][0]
            dt = self.dt_dataset.get_instances([imgId], cat, bool(p.useCats))[0][0]
            return _safit_matrix(gt, dt, p.maxDets[-1], anchor)

    return HarnessEvalFaster


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


def check_options(engine: str, matching: str, anchor: str) -> None:
    """Refuse an unknown engine, matching or SAFit anchor, naming the config key that sets it."""
    if engine not in ENGINES:
        raise EvaluationError(
            f"unknown evaluation engine {engine!r}; use one of {', '.join(ENGINES)} (config eval.engine)"
        )
    if matching not in MATCHINGS:
        raise EvaluationError(
            f"unknown matching {matching!r}; use one of {', '.join(MATCHINGS)} (config eval.matching)"
        )
    if anchor not in ANCHORS:
        raise EvaluationError(
            f"unknown SAFit NWD anchor {anchor!r}; use one of {', '.join(ANCHORS)} (config eval.safit_anchor)"
        )


def run_engine(
    prep: PreparedEval,
    engine: str = "faster-coco-eval",
    matching: str = "iou",
    anchor: str = "center",
    area_ranges: Mapping[str, tuple[float, float]] | None = None,
    operating_point: bool = True,
) -> EngineResult:
    """Run one engine on prepared inputs. ``area_ranges`` replaces COCO's small/medium/large (first must be 'all')."""
    check_options(engine, matching, anchor)
    if engine == "faster-coco-eval":
        return _run_faster(prep, matching, anchor, area_ranges, operating_point)
    return _run_pycocotools(prep, matching, anchor, area_ranges, operating_point)


def _run_faster(
    prep: PreparedEval, matching: str, anchor: str, area_ranges: Mapping[str, tuple[float, float]] | None, want_op: bool
) -> EngineResult:
    ranges = None
    if area_ranges is not None:
        ranges = {k: list(v) for k, v in area_ranges.items() if k != "all"}
    cls = _faster_eval_class(matching, anchor)
    # no COCO index objects: the bulk path reads the prepared inputs (the stock fallback builds them)
    ev = cls(None, None, iouType="bbox", print_function=_silent, ranges=ranges)
    ev.harness_inputs = prep
    ev.params.imgIds = [im["id"] for im in prep.gt["images"]]
    ev.params.catIds = list(prep.cat_ids)
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    result = EngineResult(
        list(map(float, ev.stats[:12])),
        np.asarray(ev.eval["precision"]),
        np.asarray(ev.params.iouThrs),
        list(ev.params.areaRngLbl),
    )
    if want_op:
        _fill_operating_inputs(
            result,
            prep,
            *_matches_at_50(ev, prep),
            getattr(ev, "_harness_layout", None) or pair_layout(prep, ev.params.maxDets[-1]),
        )
    return result


def _matches_at_50(ev: Any, prep: PreparedEval) -> tuple[np.ndarray, np.ndarray]:
    """(detection index, GT index) of COCO's matches at threshold 0.50, area "all": from the bulk matching where it
    ran (with the run's measure), else matched afresh on IoU."""
    matches: Matches | None = getattr(ev, "_harness_matches", None)
    layout = getattr(ev, "_harness_layout", None)
    thrs = np.asarray(ev.params.iouThrs, dtype=np.float64)
    if matches is not None and ev.params.areaRngLbl[0] == "all" and np.any(thrs == 0.5):
        return matches.at(int(np.flatnonzero(thrs == 0.5)[0]), 0)
    layout = layout or pair_layout(prep, ev.params.maxDets[-1])
    return layout.greedy_match_indices(layout.values(prep, iou_elementwise), threshold=0.5)


def _fill_operating_inputs(
    result: EngineResult, prep: PreparedEval, det_idx: np.ndarray, gt_idx: np.ndarray, layout: PairLayout
) -> None:
    """Evaluated detections (top 100 per image and category), without those matched to crowd GT."""
    n = prep.n_dets
    _, cat, score, _ = prep.det_columns
    matched = np.zeros(n, dtype=bool)
    matched[det_idx] = True
    crowd = np.zeros(n, dtype=bool)
    crowd[det_idx] = layout.gt_crowd[gt_idx]
    keep = layout.evaluated & ~crowd
    cat_index = np.searchsorted(np.asarray(prep.cat_ids, dtype=np.int64), cat)
    result.op_scores = score[keep]
    result.op_cat_index = cat_index[keep]
    result.op_is_tp = matched[keep]


def _run_pycocotools(
    prep: PreparedEval, matching: str, anchor: str, area_ranges: Mapping[str, tuple[float, float]] | None, want_op: bool
) -> EngineResult:
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
    result = EngineResult(
        stats, np.asarray(ev.eval["precision"]), np.asarray(ev.params.iouThrs), list(ev.params.areaRngLbl)
    )
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
