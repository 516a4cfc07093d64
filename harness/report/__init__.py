"""Reports from the results store: the seed's tables, accuracy-versus-GFLOPs plots, paired statistics, HTML.

Public API (``docs/reports.md`` has the definitions)::

    build_report(store, datasets=None, out=None, formats=("md", "csv", "html"), resamples=200, seed=0) -> Report
    compare_detectors(store, dataset, "A[/ENC]", "B[/ENC]", resamples=1000, seed=0) -> PairedComparison
    StoreView(store).entries(dataset) -> [Entry]     finished runs as (detector, encoding) rows, seeds averaged,
                                                     each with its labels (``Entry.labels``, ``ResultLabel``)
    pareto_front(costs, values) -> indices
    resample_coco(gt, image_ids, detections) -> (gt, detections)   duplicates kept under new unique ids

Reports read only the store, through its one reader (``harness.report.reader``, shared with ``harness compare`` and
the tables ``harness run`` prints): ``metrics.json``, ``analysis.json``, ``predictions.json`` and ``gt.json`` of
finished runs, and ``<dataset>/_sensing/<analysis>.json``; the galleries draw their pixels from the prepared cache
the runs name (``harness.report.gallery``).
"""

from harness.report.build import FORMATS, Report, Section, build_report
from harness.report.cells import Interval, Stat
from harness.report.plots import pareto_front
from harness.report.reader import Entry, FoldResult, ResultLabel, StoredRun, StoreView
from harness.report.stats import (
    BootstrapResult,
    BootstrapScorer,
    PairedComparison,
    compare_detectors,
    paired_comparison,
    resample_coco,
)
from harness.report.tables import Column, Table

__all__ = [
    "FORMATS",
    "BootstrapResult",
    "BootstrapScorer",
    "Column",
    "Entry",
    "FoldResult",
    "Interval",
    "PairedComparison",
    "Report",
    "ResultLabel",
    "Section",
    "Stat",
    "StoredRun",
    "StoreView",
    "Table",
    "build_report",
    "compare_detectors",
    "paired_comparison",
    "pareto_front",
    "resample_coco",
]
