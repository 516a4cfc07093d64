"""Fold aggregation: per-fold values, their mean and sample standard deviation.

The seed's rule: a category with no ground truth in a held-out fold has no AP in that fold (``null``); it is
excluded from that category's mean, not counted as zero. The headline numbers (mAP50, mAP50:95, precision, recall)
are averaged over the folds that define them, each fold's value being COCO's mean over its own categories with GT.
The standard deviation is the sample one (``n - 1`` in the denominator), ``null`` with fewer than two values.
"""

from __future__ import annotations

import math
import statistics
from typing import Any, Mapping, Sequence

from harness.evaluation.inputs import EvaluationError

#: Headline metrics aggregated over folds (SAFit ones are added as ``safit_<name>`` when present).
FOLD_METRICS = ("mAP50", "mAP50_95", "precision", "recall", "f1")
SAFIT_METRICS = ("mAP50", "mAP50_95", "AP75", "AP_et", "AP_t", "AP_s", "AP_m", "AP_l")
CATEGORY_METRICS = ("AP50", "AP50_95", "SAFit_AP50", "SAFit_AP50_95")


def mean_sd(values: Sequence[float | None]) -> dict[str, Any]:
    """``{"values", "mean", "sd", "n"}``; ``None`` values (undefined in that fold) are left out of mean and SD."""
    present = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    n = len(present)
    return {
        "values": list(values),
        "mean": statistics.fmean(present) if n else None,
        "sd": statistics.stdev(present) if n >= 2 else None,
        "n": n,
    }


def _fold_name(m: Mapping[str, Any], i: int) -> str:
    run = m.get("run") or {}
    return str(run.get("fold", i))


def aggregate_folds(list_of_metrics: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Aggregate the ``evaluate`` results (or metrics.json contents) of several folds.

    Returns ``{"folds", "support", "metrics": {name: mean_sd}, "per_category": {name: {"AP50": mean_sd,
    "AP50_95": mean_sd, "instances": total, "folds_present": k}}}``.
    """
    items = list(list_of_metrics)
    if not items:
        raise EvaluationError("aggregate_folds: no fold results given")
    for i, m in enumerate(items):
        if not isinstance(m, Mapping) or "metrics" not in m or "per_category" not in m:
            raise EvaluationError(
                f"aggregate_folds: item {i} is not an evaluation result (needs 'metrics' and 'per_category')"
            )

    metrics: dict[str, Any] = {}
    for key in FOLD_METRICS:
        if any(key in m["metrics"] for m in items):
            metrics[key] = mean_sd([m["metrics"].get(key) for m in items])
    if any("safit" in m["metrics"] for m in items):
        for key in SAFIT_METRICS:
            metrics[f"safit_{key}"] = mean_sd([(m["metrics"].get("safit") or {}).get(key) for m in items])

    names: list[str] = []
    for m in items:
        names.extend(n for n in m["per_category"] if n not in names)
    per_category: dict[str, Any] = {}
    for name in names:
        entries = [m["per_category"].get(name) or {} for m in items]
        rec: dict[str, Any] = {}
        for key in CATEGORY_METRICS:
            if any(key in e for e in entries):
                rec[key] = mean_sd([e.get(key) for e in entries])
        rec["instances"] = int(sum(int(e.get("instances") or 0) for e in entries))
        rec["folds_present"] = sum(1 for e in entries if int(e.get("instances") or 0) > 0)
        per_category[name] = rec

    supports = [m.get("support") or {} for m in items]
    cats: dict[str, int] = {}
    for s in supports:
        for name, count in (s.get("categories") or {}).items():
            cats[name] = cats.get(name, 0) + int(count)
    support = {
        "images": int(sum(int(s.get("images") or 0) for s in supports)),
        "instances": int(sum(int(s.get("instances") or 0) for s in supports)),
        "categories": cats,
    }
    return {
        "folds": [_fold_name(m, i) for i, m in enumerate(items)],
        "support": support,
        "metrics": metrics,
        "per_category": per_category,
    }
