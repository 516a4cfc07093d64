"""Why one detector beats another: the stored error analyses of a dataset's detectors, side by side.

Every finished run stores its error analysis (``analysis.json``, ``harness.evaluation.analysis``; read through the
one reader as ``StoredRun.analysis``). Per dataset, for the entries of the project-grouped table, the report shows:

* **Error types** (``tide_table`` and a bar chart): TIDE's mAP50 gained by fixing each error type alone
  (classification, localisation, both, duplicate, background, missed) and the two bounds (all false positives, all
  false negatives), as mean ± sample SD over the held-out folds of each fold's seed mean;
* **Confusion matrices** (one per entry): rows the predicted category then background, columns the ground-truth
  category then background, at IoU 0.50 and each run's operating point, summed over the folds (each fold's matrix
  the mean over its seeds);
* **Precision-recall curves** at IoU 0.50, one panel per category with every entry on it: each fold's 101-point
  interpolated precision (mean over seeds), averaged over the folds that contain the category. The mean of the curve
  is then the mean of the folds' AP50, the per-category table's number;
* **AP per object size** (``size_ap_tables``): AP50 and AP50:95 per COCO size bin (and SAFit's bins for tiny-object
  datasets), mean ± SD over the folds, with the instances of each bin.

A run without an analysis is left out of these numbers and named; an entry without any says, in place of its
numbers, ``no error analysis stored; rerun with --force`` (``NO_ANALYSIS``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from harness.evaluation import mean_sd
from harness.evaluation.analysis import ERROR_LABELS, ERROR_TYPES, NO_ANALYSIS, SPECIAL_TYPES
from harness.report.reader import Entry, StoredRun, label_notes
from harness.report.tables import Column, Stat, Table, _marks, _merge_warning, _slug, match_check, record, stat_record

log = logging.getLogger(__name__)

SIZE_SCHEMES = {"coco": "COCO", "safit": "SAFit"}


@dataclass
class Evidence:
    """One entry's stored analyses: per fold, those of its seeds (seed order); the runs without one and why."""

    entry: Entry
    name: str
    folds: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    runs: dict[str, list[StoredRun]] = field(default_factory=dict)
    missing: list[tuple[str, str]] = field(default_factory=list)  # (FOLD/seedN, why)

    @property
    def empty(self) -> bool:
        return not any(self.folds.values())

    def fold_values(self, get: Callable[[dict[str, Any]], Any]) -> list[float | None]:
        """Per fold (with an analysis), the mean over its seeds of ``get(analysis)`` (None where no seed has one)."""
        out = []
        for analyses in self.folds.values():
            vals = [v for v in (get(a) for a in analyses) if v is not None]
            out.append(mean_sd(vals)["mean"] if vals else None)
        return out

    def stat(self, get: Callable[[dict[str, Any]], Any]) -> Stat:
        """Mean ± sample SD over folds of the seed means of ``get(analysis)``; folds without a value left out."""
        return Stat.from_mean_sd(mean_sd(self.fold_values(get)))

    def record_fields(self, dataset: str) -> dict[str, Any]:
        """The fields of a tidy record (``tables.record``) naming this entry's runs."""
        e = self.entry
        return {"dataset": dataset, "detector": e.detector, "encoding": e.encoding, "seeds": e.seeds}

    def seeds_short(self, get: Callable[[dict[str, Any]], Any]) -> list[str]:
        """The folds where ``get(analysis)`` has a value in fewer seeds than have an analysis: ``"P1 (2 of 3)"``."""
        out = []
        for fold, analyses in self.folds.items():
            k = sum(get(a) is not None for a in analyses)
            if 0 < k < len(analyses):
                out.append(f"{fold} ({k} of {len(analyses)})")
        return out


def _labels(table: Table, evidence: Sequence[Evidence], keys: Sequence[str]) -> None:
    """The labels of each entry's runs (approximate temperatures, accepted risks) as marks beside its numbers and
    notes first among the table's, and a loud warning when the entries' runs were scored on different samples."""
    for row, ev in zip((r for r in table.rows if not r.get("_summary")), evidence):
        marks = _marks(keys, ev.entry.labels)
        if marks:
            row["_marks"] = marks
    table.notes[:0] = label_notes([ev.entry.notes_item(ev.name) for ev in evidence])
    runs = {
        f"{ev.name} {fold}/seed{r.key.seed}": r.metrics for ev in evidence for fold, rs in ev.runs.items() for r in rs
    }
    _merge_warning(table, *match_check(runs))


def collect(rows: Sequence[Entry], names: dict[str, str]) -> list[Evidence]:
    """The evidence of each entry (``names``: the row names of the tables)."""
    out = []
    for e in rows:
        ev = Evidence(e, names.get(e.label, e.label))
        for fold, fr in e.folds.items():
            for run in fr.runs:
                if run.analysis is None:
                    ev.missing.append((run.name, run.analysis_missing or NO_ANALYSIS))
                    continue
                ev.folds.setdefault(fold, []).append(run.analysis)
                ev.runs.setdefault(fold, []).append(run)
        out.append(ev)
    return out


def missing_notes(evidence: Sequence[Evidence]) -> list[str]:
    """One note per entry whose runs lack an analysis: which runs, and why (the stored reason, said once)."""
    notes = []
    for ev in evidence:
        if not ev.missing:
            continue
        reasons: dict[str, list[str]] = {}
        for run, why in ev.missing:
            reasons.setdefault(why, []).append(run)
        for why, runs in reasons.items():
            where = "every run" if ev.empty else f"run{'s' if len(runs) > 1 else ''} {', '.join(runs)}"
            notes.append(f"{ev.name}: {why} ({where}; left out here)")
    return notes


def _get(*path: str) -> Callable[[dict[str, Any]], Any]:
    def get(a: dict[str, Any]) -> Any:
        cur: Any = a
        for p in path:
            if not isinstance(cur, dict):
                return None
            cur = cur.get(p)
        return cur

    return get


# ------------------------------------------------------------------------------------------------ error types
def tide_table(dataset: str, evidence: Sequence[Evidence]) -> Table:
    """Rows: entries; columns: mAP50 and the dAP50 of each TIDE error type and bound, mean ± SD over folds."""
    name = f"{_slug(dataset)}-errors"
    cols = [Column("detector", "Detector"), Column("folds", "Folds", "int"), Column("mAP50", "mAP50", "pct")]
    cols += [
        Column(t, ERROR_LABELS[t], "pct", group="mAP50 gained by fixing each error type alone", short=ERROR_LABELS[t])
        for t in ERROR_TYPES
    ]
    cols += [Column(t, ERROR_LABELS[t], "pct", group="bounds", short=ERROR_LABELS[t]) for t in SPECIAL_TYPES]
    table = Table(name, f"{dataset}: error types (TIDE, mAP50 gained in points, IoU 0.50)", cols)
    uneven: list[str] = []
    for ev in evidence:
        row: dict[str, Any] = {"detector": ev.name, "folds": len(ev.folds)}
        if ev.empty:
            row["mAP50"] = NO_ANALYSIS
            table.rows.append(row)
            continue
        row["mAP50"] = ev.stat(_get("tide", "mAP50"))
        for t in ERROR_TYPES:
            row[t] = ev.stat(_get("tide", "dAP50", t))
        for t in SPECIAL_TYPES:
            row[t] = ev.stat(_get("tide", "special", t))
        for key in ("mAP50", *ERROR_TYPES, *SPECIAL_TYPES):
            get = (
                _get("tide", "mAP50")
                if key == "mAP50"
                else _get("tide", "dAP50" if key in ERROR_TYPES else "special", key)
            )
            short = ev.seeds_short(get)
            if short:
                uneven.append(
                    f"{ev.name}: {ERROR_LABELS.get(key, key)} averages fewer seeds than the runs have "
                    f"analyses in {', '.join(short)} (a seed without the value is left out)"
                )
            s = row[key]
            table.records.append(
                stat_record(
                    name,
                    f"dAP50_{key}" if key != "mAP50" else "mAP50",
                    s,
                    **ev.record_fields(dataset),
                    fold="mean",
                    images=ev.entry.images,
                    instances=ev.entry.instances,
                )
            )
        table.rows.append(row)
    table.notes.append(
        "TIDE (Bolya et al., ECCV 2020) on the evaluator's own matching (docs/evaluation.md 4c): each "
        "false positive gets one type (Cls: right box, wrong category; Loc: right category, IoU "
        "0.1-0.5; Both; Dupe: a duplicate of a found object; Bkg: IoU <= 0.1 with every object), an "
        "object never detected is Miss. Each column is the mAP50 the detector would gain if that "
        "error type alone were fixed; FP and FN bound what removing every false positive or finding "
        "every object would give. Mean ± sample SD over the held-out folds (each fold the mean over its "
        "seeds), in points."
    )
    table.notes += uneven
    _labels(table, evidence, ("mAP50", *ERROR_TYPES, *SPECIAL_TYPES))
    return table


# ------------------------------------------------------------------------------------------------ confusion
def confusion(ev: Evidence) -> tuple[list[str], np.ndarray, int]:
    """(labels, matrix summed over folds of each fold's seed mean, seeds per fold at most) of one entry; labels
    are the union of the folds' (the categories, then ``background``)."""
    labels: list[str] = []
    for analyses in ev.folds.values():
        for a in analyses:
            labels.extend(c for c in (a.get("confusion") or {}).get("labels") or [] if c not in labels)
    if "background" in labels:
        labels.remove("background")
        labels.append("background")
    pos = {c: i for i, c in enumerate(labels)}
    total = np.zeros((len(labels), len(labels)))
    seeds = 0
    for analyses in ev.folds.values():
        mats = []
        for a in analyses:
            conf = a.get("confusion") or {}
            m = np.asarray(conf.get("matrix") or [], dtype=np.float64)
            idx = [pos[c] for c in conf.get("labels") or []]
            if m.shape != (len(idx), len(idx)):
                continue
            full = np.zeros_like(total)
            full[np.ix_(idx, idx)] = m
            mats.append(full)
        if mats:
            total += np.mean(mats, axis=0)
            seeds = max(seeds, len(mats))
    return labels, total, seeds


def confusion_records(dataset: str, ev: Evidence, labels: Sequence[str], matrix: np.ndarray) -> list[dict[str, Any]]:
    """The matrix as tidy records: metric ``confusion:<predicted>`` per ground-truth category."""
    return [
        record(
            f"{_slug(dataset)}-confusion",
            f"confusion:{p}",
            float(matrix[i, j]),
            **ev.record_fields(dataset),
            fold="sum",
            category=g,
            unit="count",
        )
        for i, p in enumerate(labels)
        for j, g in enumerate(labels)
    ]


# ------------------------------------------------------------------------------------------------ PR curves
@dataclass
class Curve:
    """One entry's mean precision-recall curve of one category."""

    name: str
    recall: np.ndarray
    precision: np.ndarray
    folds: int

    @property
    def ap50(self) -> float:
        return float(self.precision.mean())


def pr_curves(evidence: Sequence[Evidence]) -> dict[str, list[Curve]]:
    """category -> the curve of every entry that has one (module docstring: mean over folds of seed means)."""
    cats: list[str] = []
    for ev in evidence:
        for analyses in ev.folds.values():
            for a in analyses:
                cats.extend(c for c in (a.get("pr") or {}).get("categories") or {} if c not in cats)
    out: dict[str, list[Curve]] = {}
    for cat in cats:
        for ev in evidence:
            per_fold, recall = [], None
            for analyses in ev.folds.values():
                curves = []
                for a in analyses:
                    pr = a.get("pr") or {}
                    rec = (pr.get("categories") or {}).get(cat) or {}
                    if rec.get("precision") is not None and rec.get("instances"):
                        curves.append(np.asarray(rec["precision"], dtype=np.float64))
                        recall = np.asarray(pr["recall"], dtype=np.float64)
                if curves:
                    per_fold.append(np.mean(curves, axis=0))
            if per_fold and recall is not None:
                out.setdefault(cat, []).append(Curve(ev.name, recall, np.mean(per_fold, axis=0), len(per_fold)))
    return out


# ------------------------------------------------------------------------------------------------ size bins
def size_ap_tables(dataset: str, evidence: Sequence[Evidence]) -> list[Table]:
    """AP50 and AP50:95 per size bin (COCO's; SAFit's too where stored), mean ± SD over folds, and the instances of
    each bin summed over the folds (a support row)."""
    tables = []
    have = [ev for ev in evidence if not ev.empty]
    for scheme, title in SIZE_SCHEMES.items():
        bins: list[str] = []
        for ev in have:
            for analyses in ev.folds.values():
                for a in analyses:
                    block = (a.get("sizes") or {}).get(scheme) or {}
                    bins.extend(b for b in block.get("ranges") or {} if b not in bins)
        if not bins:
            continue
        name = f"{_slug(dataset)}-size-ap-{scheme}"
        cols = [Column("detector", "Detector"), Column("folds", "Folds", "int")]
        for metric in ("AP50", "AP50_95"):
            cols += [
                Column(
                    f"{metric}:{b}",
                    f"{metric.replace('_', ':')} {b}",
                    "pct",
                    best="max",
                    group=metric.replace("_", ":"),
                    short=b,
                )
                for b in bins
            ]
        table = Table(name, f"{dataset}: AP per object size, {title} bins (%)", cols)
        for ev in evidence:
            row: dict[str, Any] = {"detector": ev.name, "folds": len(ev.folds)}
            if ev.empty:
                row[f"AP50:{bins[0]}"] = NO_ANALYSIS
                table.rows.append(row)
                continue
            for metric in ("AP50", "AP50_95"):
                for b in bins:
                    s = ev.stat(_get("sizes", scheme, metric, b))
                    row[f"{metric}:{b}"] = s
                    table.records.append(
                        stat_record(
                            name,
                            f"{metric}_{scheme}_{b}",
                            s,
                            **ev.record_fields(dataset),
                            fold="mean",
                            images=ev.entry.images,
                        )
                    )
            table.rows.append(row)

        # the objects per bin: one row when the entries' runs saw the same objects in every fold they share (a fold
        # without an analysis says nothing), else one row per entry
        def objects(analysis: dict[str, Any]) -> dict[str, int]:
            return {b: int(_get("sizes", scheme, "instances", b)(analysis) or 0) for b in bins}

        per_fold: dict[str, list[dict[str, int]]] = {}
        for ev in have:
            for fold, analyses in ev.folds.items():
                per_fold.setdefault(fold, []).append(objects(analyses[0]))
        same = all(all(c == counts[0] for c in counts) for counts in per_fold.values())
        shown = (
            [("instances", [c[0] for c in per_fold.values()])]
            if same
            else [(f"instances ({ev.name})", [objects(a[0]) for a in ev.folds.values()]) for ev in have]
        )
        for label, folds in shown:
            total = {b: sum(c[b] for c in folds) for b in bins}
            table.rows.append(
                {
                    "detector": label,
                    "_summary": True,
                    **{f"{m}:{b}": f"{total[b]:,}" for m in ("AP50", "AP50_95") for b in bins},
                }
            )
        _labels(table, evidence, [f"{m}:{b}" for m in ("AP50", "AP50_95") for b in bins])
        if not same:
            table.notes.append(
                "The entries' runs saw different objects per bin (one instances row each): their "
                "numbers are not sample-matched."
            )
        ranges = next(
            ((a.get("sizes") or {}).get(scheme) or {}).get("ranges")
            for ev in have
            for analyses in ev.folds.values()
            for a in analyses
            if (a.get("sizes") or {}).get(scheme)
        )
        edges = ", ".join(f"{b} {_range_text(lo, hi)}" for b, (lo, hi) in (ranges or {}).items())
        table.notes.append(
            f"Bins on the ground-truth box area in px² of the prepared frame ({edges}); the evaluator's "
            f"IoU matching per bin, as COCO's APs/APm/APl. Mean ± sample SD over held-out folds (each "
            f"fold the mean over its seeds); a bin without objects in a fold is left out of its mean. "
            f"Last row{'' if same else 's'}: objects per bin over all folds."
        )
        tables.append(table)
    return tables


def _range_text(lo: float, hi: float) -> str:
    side = lambda a: f"{a**0.5:g}²"  # noqa: E731
    if hi >= 1e9:
        return f">= {side(lo)}"
    if lo <= 0:
        return f"< {side(hi)}"
    return f"{side(lo)}-{side(hi)}"


# ------------------------------------------------------------------------------------------------ sections
def evidence_sections(
    dataset: str, rows: Sequence[Entry], names: dict[str, str], out: Path | None, store_root: Path
) -> tuple[list[Any], list[Table], list[Evidence]]:
    """The sections "Error types", "Confusion matrices" and "Precision-recall curves" of ``dataset``, the tables of
    AP per object size (for the object-size section) and the evidence they were built from."""
    from harness.report.document import FigureOut, Section
    from harness.report.evidence_plots import confusion_figure, pr_figure, tide_figure

    evidence = collect(rows, names)
    notes = missing_notes(evidence)
    have = [ev for ev in evidence if not ev.empty]
    fill = (
        f"{NO_ANALYSIS} (`harness run --detector D --dataset {dataset} --folds all --force --store {store_root}`)"
        if rows
        else f"no finished runs of {dataset}; fill with `harness run --detector D --dataset {dataset} "
        f"--folds all --store {store_root}`."
    )
    figures = out / "figures" if out is not None else None
    slug = _slug(dataset)
    order = [ev.name for ev in evidence]

    errors = Section("errors", "Error types (TIDE)", dataset)
    confusions = Section("confusion", "Confusion matrices", dataset)
    curves = Section("pr", "Precision-recall curves", dataset)
    if not have:
        for sec in (errors, confusions, curves):
            sec.absent = fill
        return [errors, confusions, curves], [], evidence

    table = tide_table(dataset, evidence)
    table.notes += notes
    errors.tables.append(table)
    caption = (
        f"{dataset}: mAP50 (points) each detector would gain by fixing one error type alone, mean over the "
        f"held-out folds; error bars ± 1 sample SD over folds."
    )
    svg, files = tide_figure(
        [
            (ev.name, {t: table.rows[i][t] for t in (*ERROR_TYPES, *SPECIAL_TYPES)})
            for i, ev in enumerate(evidence)
            if not ev.empty
        ],
        order,
        figures / f"errors_{slug}" if figures else None,
        f"Error types, {dataset}",
    )
    errors.figures.append(FigureOut(f"errors_{slug}", "Error types", svg, caption, files))

    mats = []
    for ev in have:
        labels, matrix, seeds = confusion(ev)
        mats.append((ev.name, labels, matrix, seeds))
        table.records += confusion_records(dataset, ev, labels, matrix)
    threshold = "each run's operating point (metrics.conf_threshold: the confidence maximising mean F1)"
    caption = (
        f"{dataset}: rows the predicted category, columns the ground truth, plus background (a false "
        f"positive on background is in the last column, a missed object in the last row); IoU 0.50 and "
        f"{threshold}; counts summed over the held-out folds (each fold the mean over its seeds); colour: "
        f"share of each ground-truth column."
    )
    svg, files = confusion_figure(
        mats, figures / f"confusion_{slug}" if figures else None, f"Confusion matrices, {dataset}"
    )
    confusions.figures.append(FigureOut(f"confusion_{slug}", "Confusion matrices", svg, caption, files))
    confusions.notes += notes

    pr = pr_curves(have)
    if pr:
        caption = (
            f"{dataset}: per category, COCO's interpolated precision at 101 recall points, IoU 0.50, area all, "
            f"100 detections per image; each fold the mean over its seeds, then the mean over the folds that "
            f"contain the category (the curve's mean is the per-category table's AP50, shown in the legend)."
        )
        svg, files = pr_figure(
            pr, order, figures / f"pr_{slug}" if figures else None, f"Precision-recall at IoU 0.50, {dataset}"
        )
        curves.figures.append(FigureOut(f"pr_{slug}", "Precision-recall curves", svg, caption, files))
        curves.notes += notes
    else:
        curves.absent = f"no stored analysis of {dataset} has a category with ground truth."
    return [errors, confusions, curves], size_ap_tables(dataset, evidence), evidence
