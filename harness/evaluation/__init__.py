"""Evaluation: COCO AP for every detector and dataset, fold aggregation, the sample-matched guard, SAFit.

Public API (``docs/evaluation.md`` has the definitions)::

    evaluate(gt, detections, engine="faster-coco-eval", matching="iou") -> {"support", "metrics", "per_category"}
    aggregate_folds(list_of_metrics) -> per-fold values, mean and sample SD
    check_sample_matched(results, allow=False, hint=None) -> None | label   (raises SampleMismatchError)

A run's detections reach ``evaluate`` as COCO results written by ``harness.engine.predict`` (the detector's
eval-mode outputs, letterbox undone); predictions made elsewhere come through ``harness score``.
"""

from harness.evaluation.coco import (
    COCO_STAT_NAMES,
    ENGINES,
    MATCHINGS,
    EvaluationError,
    evaluate,
    evaluate_with_config,
)
from harness.evaluation.folds import aggregate_folds, mean_sd
from harness.evaluation.guard import SampleMismatchError, check_sample_matched
from harness.evaluation.operating_point import OPERATING_POINT, max_f1_operating_point
from harness.evaluation.safit import iou_xywh, nwd_xywh, safit_weight, safit_xywh

__all__ = [
    "COCO_STAT_NAMES",
    "ENGINES",
    "MATCHINGS",
    "OPERATING_POINT",
    "EvaluationError",
    "SampleMismatchError",
    "aggregate_folds",
    "check_sample_matched",
    "evaluate",
    "evaluate_with_config",
    "iou_xywh",
    "max_f1_operating_point",
    "mean_sd",
    "nwd_xywh",
    "safit_weight",
    "safit_xywh",
]
