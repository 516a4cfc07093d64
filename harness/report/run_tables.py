"""The tables ``harness run`` and ``harness ablate`` print when they finish, from the runs as stored.

Each row is one (fold, seed) run as the store holds it (``harness.report.reader.StoredRun``, read back after the run
was written, or found finished): its metrics, and the labels its results carry, shown as marks beside the numbers
they concern with one footnote per label, as in every table of the store's reader. The ``mean ± SD`` rows are the
mean and sample SD over the rows (``harness.evaluation.aggregate_folds``: every run a row, seeds not averaged
first).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

from harness.evaluation import aggregate_folds, mean_sd
from harness.report.cells import Stat, format_value
from harness.report.reader import ResultLabel, StoredRun, label_notes, marks, merge_labels
from harness.textable import fit_text, text_table

if TYPE_CHECKING:
    from harness.runner import AblationSummary, RunSummary


def _num(v: Any) -> str:
    return format_value(v, "float", 3)


def _pm(stats: dict[str, Any]) -> str:
    """``0.512 ± 0.034`` (or ``0.512`` from one value, ``-`` from none)."""
    return _num(Stat(stats.get("mean"), stats.get("sd")))


def _marked(row: list[str], col_marks: Sequence[str]) -> list[str]:
    """``row`` with each column's marks beside its numbers (text and empty cells left alone)."""
    return [
        f"{c} {m}" if m and c not in ("", "-") and c[:1].isdigit() else c
        for c, m in zip(row, [*col_marks, *[""] * (len(row) - len(col_marks))])
    ]


def _runs(summary: RunSummary) -> list[StoredRun]:
    return [r.stored for r in summary.results]


def _labels(runs: Sequence[StoredRun]) -> list[ResultLabel]:
    return merge_labels(lab for r in runs for lab in r.labels)


def _notes(items: Sequence[tuple[str | None, Sequence[StoredRun]]]) -> str:
    """The footnotes of the labels of ``items`` (name, runs), one line each, fitted to the terminal."""
    notes = label_notes([(name, _labels(runs), [r.name for r in runs]) for name, runs in items])
    return "".join("\n" + fit_text(n) for n in notes)


def fold_table(summary: RunSummary) -> str:
    """Per fold (and seed): support, P, R, mAP50, mAP50:95, epochs; then mean ± sample SD over the rows."""
    headers = ["fold", "seed", "train", "val", "inst", "P", "R", "mAP50", "mAP50:95", "epochs", "state"]
    keys = ("precision", "recall", "mAP50", "mAP50_95")
    runs = _runs(summary)
    rows = []
    for r in summary.results:
        m, tr = r.metrics["metrics"], r.metrics.get("train") or {}
        epochs = f"{tr.get('best_epoch') or '-'}/{tr.get('epochs_run', '-')}"
        row = [
            r.key.fold,
            str(r.key.seed),
            str(r.train_images),
            str(r.val_images),
            str(r.metrics["support"].get("instances", "-")),
            *(_num(m.get(k)) for k in keys),
            epochs,
            r.state,
        ]
        rows.append(_marked(row, [""] * 5 + [marks(r.stored.labels)] * 4))
    if len(runs) > 1:
        agg = aggregate_folds([r.metrics for r in runs])["metrics"]
        row = ["mean ± SD", "", "", "", "", *(_pm(agg.get(k, {})) for k in keys), "", ""]
        rows.append(_marked(row, [""] * 5 + [marks(_labels(runs))] * 4))
    title = (
        f"{summary.detector} on {summary.dataset}, encoding {summary.encoding}, profile {summary.profile} "
        f"(best epoch / epochs run)"
    )
    return fit_text(title) + "\n" + text_table(headers, rows) + _notes([(None, runs)])


def category_table(summary: RunSummary) -> str:
    """Per category: AP50 in each fold, then AP50 and AP50:95 as mean ± sample SD over the folds with instances."""
    runs = _runs(summary)
    seeds = len({r.key.seed for r in runs}) > 1
    labels = [r.key.fold + (f"/s{r.key.seed}" if seeds else "") for r in runs]
    agg = aggregate_folds([r.metrics for r in runs])["per_category"] if runs else {}
    headers = ["category", "inst", *[f"AP50 {lab}" for lab in labels], "AP50", "AP50:95"]
    col_marks = ["", "", *(marks(r.labels) for r in runs), *[marks(_labels(runs))] * 2]
    rows = []
    for cat in summary.categories:
        per = [r.metrics["per_category"].get(cat) or {} for r in runs]
        inst = sum(int(p.get("instances") or 0) for p in per)
        a = agg.get(cat, {})
        row = [cat, str(inst), *(_num(p.get("AP50")) for p in per), _pm(a.get("AP50", {})), _pm(a.get("AP50_95", {}))]
        rows.append(_marked(row, col_marks))
    return (
        "per category (AP50 mean ± SD over the folds where the category has instances)\n"
        + text_table(headers, rows)
        + _notes([(None, runs)])
    )


def ablation_table(ab: AblationSummary) -> str:
    """The seed's encoding-ablation table: P, R, mAP50, mAP50:95 and AP50 of the chosen categories."""
    headers = ["encoding", "P", "R", "mAP50", "mAP50:95", *[f"AP50 {c}" for c in ab.categories]]
    rows = []
    for enc, summary in ab.runs.items():
        ms = [r.metrics for r in _runs(summary)]

        def col(get: Any) -> str:
            return _pm(mean_sd([get(m) for m in ms])) if len(ms) > 1 else _num(get(ms[0]))

        row = [
            enc,
            *(col(lambda m, k=k: m["metrics"].get(k)) for k in ("precision", "recall", "mAP50", "mAP50_95")),
            *(col(lambda m, c=c: (m["per_category"].get(c) or {}).get("AP50")) for c in ab.categories),
        ]
        rows.append(_marked(row, ["", *[marks(_labels(_runs(summary)))] * (len(row) - 1)]))
    seeds = sorted({r.key.seed for s in ab.runs.values() for r in s.results})
    title = f"encoding ablation: {ab.detector} on {ab.dataset}, fold {ab.fold}, seed(s) {','.join(map(str, seeds))}"
    return (
        fit_text(title)
        + "\n"
        + text_table(headers, rows)
        + _notes([(enc, _runs(summary)) for enc, summary in ab.runs.items()])
    )
