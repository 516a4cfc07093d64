"""The report's tables: each built from the results store as tidy records plus a wide, printable layout.

Every table is a ``Table``: typed cells in rows (``Stat`` for mean ± sample SD), the tidy long-format records
behind them (one per number: dataset, detector, encoding, fold, category, metric, value, SD, n, unit, and the
support it was measured on), notes that make the numbers unambiguous, and a loud ``warning`` when its rows were not
scored on the same samples. Renderers: aligned text (``to_text``), Markdown, wide CSV; ``html.py`` renders HTML.

Tables (builders below, all reading only the store through ``reader.StoreView``):

* ``project_table``: the seed's project-grouped table: per held-out fold mAP50 and mAP50:95, their mean ± sample
  SD over folds, Params (M) and GFLOPs measured on the model each run trained;
* ``budget_table``: per detector and encoding, the training budget: epochs run, the selection protocol, how many
  runs reached the plateau and the slope of their last scored epochs (``held_out_note`` names the entries whose
  weights were chosen on the held-out fold);
* ``category_table``: per category, instances and AP50 / AP50:95 as means over the folds that contain it;
* ``ablation_tables``: one per detector run with several encodings on common folds: P, R, mAP50, mAP50:95 and
  AP50 of the seed's two thermal-only defects (delamination, water seepage);
* ``registration_table`` and ``displacement_table``: the sensor-level analyses of ``harness sensing``;
* ``cross_dataset_table``: the cross-dataset comparison of ``harness.report.compare``;
* ``paired_table``: paired comparisons (per-fold differences, bootstrap CIs, a verdict only with three or more
  training seeds per fold) from ``stats.py``;
* the error-analysis tables (error types, AP per size bin) are built in ``evidence.py``.

AP, precision and recall are fractions in the store and in CSV files, and percentages (one decimal) in text,
Markdown and HTML.

Kept in one module: every table of the report is built here in one style (``Table``, tidy records, notes, the
sample-matching warning), and the builders share those helpers.
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

from harness.report.cells import Interval, Stat, format_value
from harness.report.reader import (
    MARKS,
    Entry,
    ResultLabel,
    StoreView,
    find_category,
    label_notes,
    marks,
    natural_key,
    run_plateau,
    run_selection,
)
from harness.textable import text_table

#: The seed's thermal-only defect categories shown in the encoding-ablation table.
ABLATION_CATEGORIES = ("delamination", "water seepage")

#: Columns of the tidy long-format records (``tidy.csv``).
RECORD_FIELDS = (
    "table",
    "dataset",
    "detector",
    "encoding",
    "fold",
    "category",
    "metric",
    "value",
    "sd",
    "n",
    "unit",
    "images",
    "instances",
    "seeds",
    "sample_matched",
)


@dataclass(frozen=True)
class Column:
    """``kind``: text | int | pct (fraction shown in %) | pp (difference of fractions in percentage points) |
    float (``digits`` decimals) | sig (3 significant digits). ``best``: "max" or "min" to mark the best value of the
    column (bold in Markdown and HTML)."""

    key: str
    label: str
    kind: str = "text"
    digits: int = 1
    best: str | None = None
    #: columns sharing a group get one spanning header in HTML, each showing its ``short`` label under it
    group: str | None = None
    short: str | None = None

    @property
    def align(self) -> str:
        return "l" if self.kind == "text" else "r"


@dataclass
class Table:
    name: str
    title: str
    columns: list[Column]
    rows: list[dict[str, Any]] = field(default_factory=list)
    records: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: the loud label: set when the rows were not scored on the same samples
    warning: str | None = None
    warning_details: list[str] = field(default_factory=list)

    # ---------------------------------------------------------------------------------------------- cells
    def cell(self, row: Mapping[str, Any], col: Column) -> str:
        text = format_value(row.get(col.key), col.kind, col.digits)
        mark = (row.get("_marks") or {}).get(col.key)  # the labels of the results behind this number
        if mark and col.kind not in ("text", "int") and text not in ("", "-"):
            text += f" {mark}"
        return text

    def best_rows(self, col: Column) -> set[int]:
        """Indices of the rows holding the best value of ``col`` (ties all count; none when every row is equal;
        summary rows never)."""
        if not col.best:
            return set()
        out: set[int] = set()
        for block in dict.fromkeys(r.get("_block") for r in self.rows):  # each block's best apart (``split_blocks``)
            vals = [
                (i, _number(r.get(col.key)))
                for i, r in enumerate(self.rows)
                if not r.get("_summary") and r.get("_block") == block
            ]
            vals = [(i, v) for i, v in vals if v is not None]
            if len(vals) < 2:
                continue
            lo, hi = min(v for _, v in vals), max(v for _, v in vals)
            if math.isclose(lo, hi, rel_tol=1e-12, abs_tol=1e-12):
                continue  # all equal: nothing stands out
            target = hi if col.best == "max" else lo
            out |= {i for i, v in vals if math.isclose(v, target, rel_tol=1e-12, abs_tol=1e-12)}
        return out

    def split_blocks(self, is_reference: Callable[[Mapping[str, Any]], bool], own: str, references: str) -> None:
        """Put the rows ``is_reference`` picks after the others, each group a labelled block (``own``,
        ``references``) with its own best values; summary rows stay last. Nothing changes unless both are there."""
        body = [r for r in self.rows if not r.get("_summary")]
        refs = [r for r in body if is_reference(r)]
        if not refs or len(refs) == len(body):
            return
        mine = [r for r in body if not is_reference(r)]
        for r in mine:
            r["_block"] = own
        for r in refs:
            r["_block"] = references
        self.rows = mine + refs + [r for r in self.rows if r.get("_summary")]

    def block_starts(self) -> dict[int, str]:
        """Row index -> the label of the block that begins there."""
        out, current = {}, None
        for i, r in enumerate(self.rows):
            b = r.get("_block")
            if b and b != current:
                out[i] = b
            current = b
        return out

    # ---------------------------------------------------------------------------------------------- renderers
    def to_text(self) -> str:
        header = [c.label for c in self.columns]
        starts = self.block_starts()
        body = []
        for i, r in enumerate(self.rows):
            if i in starts:
                body.append([f"-- {starts[i]}"] + [""] * (len(self.columns) - 1))
            body.append([self.cell(r, c) for c in self.columns])
        out = [self.title, "=" * len(self.title)]
        if self.warning:
            out += [f"!!! {self.warning.upper()} !!!", *[f"!!!   {d}" for d in self.warning_details]]
        out.append(text_table(header, body, "".join(c.align for c in self.columns)))
        out += [f"  {n}" for n in self.notes]
        return "\n".join(out)

    def to_markdown(self) -> str:
        out = [f"### {self.title}", ""]
        if self.warning:
            out += [f"> **⚠ {self.warning.upper()}**", *[f"> - {_md_escape(d)}" for d in self.warning_details], ""]
        best = {c.key: self.best_rows(c) for c in self.columns}
        out.append("| " + " | ".join(_md_escape(c.label) for c in self.columns) + " |")
        out.append("|" + "|".join(":---" if c.align == "l" else "---:" for c in self.columns) + "|")
        starts = self.block_starts()
        for i, r in enumerate(self.rows):
            if i in starts:
                out.append(f"| *{_md_escape(starts[i])}* |" + " |" * (len(self.columns) - 1))
            cells = []
            for c in self.columns:
                text = _md_escape(self.cell(r, c))
                if i in best[c.key] and text not in ("", "-"):
                    text = f"**{text}**"
                elif r.get("_summary") and c is self.columns[0]:
                    text = f"*{text}*"
                cells.append(text)
            out.append("| " + " | ".join(cells) + " |")
        if self.notes:
            out.append("")
            out += [f"- {_md_escape(n)}" for n in self.notes]
        return "\n".join(out)

    def to_csv(self) -> str:
        """Wide CSV with raw numbers (fractions, not %): a ``Stat`` column becomes ``<label>`` and ``<label> sd``."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        header: list[str] = []
        for c in self.columns:
            header.append(c.label)
            if any(isinstance(r.get(c.key), Stat) for r in self.rows):
                header.append(f"{c.label} sd")
            if any(isinstance(r.get(c.key), Interval) for r in self.rows):
                header += [f"{c.label} low", f"{c.label} high"]
        w.writerow(header)
        for r in self.rows:
            line: list[Any] = []
            for c in self.columns:
                v = r.get(c.key)
                has_stat = any(isinstance(x.get(c.key), Stat) for x in self.rows)
                has_int = any(isinstance(x.get(c.key), Interval) for x in self.rows)
                if isinstance(v, Stat):
                    line += [_raw(v.mean), _raw(v.sd)]
                elif isinstance(v, Interval):
                    line += [_raw(v.value), _raw(v.low), _raw(v.high)]
                else:
                    line.append(_raw(v))
                    if has_stat:
                        line.append("")
                    if has_int:
                        line += ["", ""]
            w.writerow(line)
        return buf.getvalue()


# -------------------------------------------------------------------------------------------------- formatting
def _number(v: Any) -> float | None:
    if isinstance(v, Stat):
        v = v.mean
    elif isinstance(v, Interval):
        v = v.value
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(float(v)) else None


def _raw(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    return v


def _md_escape(text: str) -> str:
    return str(text).replace("|", "\\|")


def record(
    table: str,
    metric: str,
    value: Any,
    *,
    dataset: str = "",
    detector: str = "",
    encoding: str = "",
    fold: str = "",
    category: str = "",
    sd: float | None = None,
    n: int | None = None,
    unit: str = "fraction",
    images: int | None = None,
    instances: int | None = None,
    seeds: Iterable[int] = (),
    sample_matched: bool | None = True,
) -> dict[str, Any]:
    """One tidy long-format record (the columns of ``tidy.csv``)."""
    return {
        "table": table,
        "dataset": dataset,
        "detector": detector,
        "encoding": encoding,
        "fold": fold,
        "category": category,
        "metric": metric,
        "value": value,
        "sd": sd,
        "n": n,
        "unit": unit,
        "images": images,
        "instances": instances,
        "seeds": " ".join(str(s) for s in seeds),
        "sample_matched": sample_matched,
    }


def stat_record(table: str, metric: str, s: Stat, **where: Any) -> dict[str, Any]:
    """``record`` of a mean ± sample SD: its mean as the value, with its SD and n."""
    return record(table, metric, s.mean, sd=s.sd, n=s.n, **where)


def records_csv(records: Sequence[Mapping[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(RECORD_FIELDS), lineterminator="\n")
    w.writeheader()
    for r in records:
        w.writerow({k: _raw(r.get(k)) for k in RECORD_FIELDS})
    return buf.getvalue()


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", text).strip("-").lower()


# -------------------------------------------------------------------------------------------------- sample matching
def match_check(metrics_by_label: Mapping[str, Mapping[str, Any]]) -> tuple[str | None, list[str]]:
    """(loud label, detail lines) from ``harness.evaluation.check_sample_matched``; ``(None, [])`` when matched.

    The metrics dicts carry their dataset and fold in ``run``; only results of the same (dataset, fold) are compared.
    """
    from harness.evaluation import SampleMismatchError, check_sample_matched

    try:
        check_sample_matched(dict(metrics_by_label))
    except SampleMismatchError as exc:
        label = check_sample_matched(dict(metrics_by_label), allow=True) or "NOT sample-matched"
        details = [ln.strip() for ln in str(exc).splitlines()[1:] if ln.startswith("  ")]
        return label, details
    return None, []


def _marks(keys: Iterable[str], labels: Sequence[ResultLabel]) -> dict[str, str]:
    """``row["_marks"]``: the marks of ``labels`` beside the numbers of columns ``keys`` (``Table.cell``)."""
    m = marks(labels)
    return {k: m for k in keys} if m else {}


def _label_notes(table: Table, entries: Sequence[Entry]) -> None:
    """One note per label of the entries' results, first among the table's notes (``reader.label_notes``)."""
    table.notes[:0] = label_notes([e.notes_item() for e in entries])


def _merge_warning(table: Table, label: str | None, details: Sequence[str]) -> None:
    if not label:
        return
    table.warning = label if not table.warning else f"{table.warning}; {label.replace('NOT sample-matched: ', '')}"
    table.warning_details.extend(details)


def main_entries(entries: Sequence[Entry]) -> tuple[list[Entry], list[Entry], list[str]]:
    """(rows, left out, folds) of a dataset's project-grouped tables.

    The rows are the entries evaluated on every fold any entry was evaluated on; an entry covering fewer folds (an
    encoding-ablation run on one fold, say) is left out and named in a note. When no entry covers every fold, all
    entries are rows and the table is labelled (its means are over different folds).
    """
    folds: list[str] = []
    for e in entries:
        folds.extend(f for f in e.fold_names if f not in folds)
    folds.sort(key=natural_key)
    full = [e for e in entries if set(e.fold_names) == set(folds)]
    if not full:
        return list(entries), [], folds
    return full, [e for e in entries if e not in full], folds


def _fold_matching(rows: Sequence[Entry], folds: Sequence[str]) -> tuple[str | None, list[str]]:
    """Sample-matched check of the rows' fold results, fold by fold, plus rows that miss folds or mix seeds."""
    label, details = match_check({f"{e.label}@{f}": e.folds[f].metrics for e in rows for f in folds if f in e.folds})
    kinds = [label] if label else []
    missing = [
        f"{e.label}: not evaluated on fold(s) {', '.join(f for f in folds if f not in e.folds)}"
        for e in rows
        if any(f not in e.folds for f in folds)
    ]
    if missing:
        kinds.append("NOT sample-matched: rows cover different folds")
        details = details + missing
    seed_issues = [
        f"{e.label} fold {f}: seeds {fr.seed_mismatch}" for e in rows for f, fr in e.folds.items() if fr.seed_mismatch
    ]
    if seed_issues:
        kinds.append("NOT sample-matched: seeds of a fold differ")
        details = details + seed_issues
    if not kinds:
        return None, []
    merged = "NOT sample-matched: " + "; ".join(k.replace("NOT sample-matched: ", "") for k in kinds)
    return merged, details


def _entry_names(rows: Sequence[Entry]) -> dict[str, str]:
    """Short row names: the detector alone when each detector appears once, else detector/encoding."""
    dets = [e.detector for e in rows]
    return {e.label: (e.detector if dets.count(e.detector) == 1 else e.label) + _options_suffix(e) for e in rows}


def _options_suffix(e: Entry) -> str:
    """`` [scale=n]``: the model options the entry's runs were built with (measured in the runs), if any."""
    from harness.complexity import options_label

    c = e.complexity()
    if c.get("mixed"):
        return f" [mixed: {'; '.join(c['mixed'])}]"
    text = options_label(c.get("model_options") or {})
    return f" [{text}]" if text else ""


def _seeds_note(rows: Sequence[Entry]) -> str:
    seeds = sorted({s for e in rows for s in e.seeds})
    return f"seed(s) {', '.join(map(str, seeds))}" + (
        "; each fold's value is the mean over its seeds" if len(seeds) > 1 else ""
    )


# -------------------------------------------------------------------------------------------------- project table
def project_table(view: StoreView, dataset: str, pareto: set[str] | None = None) -> Table | None:
    """The seed's project-grouped table for ``dataset`` (None when the store has no finished runs of it)."""
    entries = view.entries(dataset)
    if not entries:
        return None
    rows_e, left_out, folds = main_entries(entries)
    name = f"{_slug(dataset)}-folds"
    cols = [Column("detector", "Detector"), Column("encoding", "Encoding")]
    for f in folds:
        cols += [
            Column(f"{f}:mAP50", f"{f} mAP50", "pct", best="max", group=f, short="mAP50"),
            Column(f"{f}:mAP50_95", f"{f} mAP50:95", "pct", best="max", group=f, short="mAP50:95"),
        ]
    cols += [
        Column("mAP50", "mAP50 mean ± SD", "pct", best="max", group="mean ± SD", short="mAP50"),
        Column("mAP50_95", "mAP50:95 mean ± SD", "pct", best="max", group="mean ± SD", short="mAP50:95"),
        Column("params", "Params (M)", "sig", best="min"),
        Column("gflops", "GFLOPs", "sig", best="min"),
        Column("images", "Images", "int"),
        Column("instances", "Inst.", "int"),
    ]
    if pareto is not None:
        cols.append(Column("pareto", "Pareto"))
    table = Table(name, f"{dataset}: project-grouped folds (held-out mAP, %)", cols)
    _merge_warning(table, *_fold_matching(rows_e, folds))
    names = _entry_names(rows_e)
    no_profile = []
    for e in rows_e:
        agg = e.aggregate()["metrics"]
        prof = e.complexity()
        if not prof.get("params_m"):
            no_profile.append(e)
        row: dict[str, Any] = {
            "detector": names[e.label],
            "encoding": e.encoding,
            "mAP50": Stat.from_mean_sd(agg.get("mAP50")),
            "mAP50_95": Stat.from_mean_sd(agg.get("mAP50_95")),
            "params": prof.get("params_m"),
            "gflops": prof.get("gflops"),
            "images": e.images,
            "instances": e.instances,
        }
        if pareto is not None:
            row["pareto"] = "yes" if e.label in pareto else ""
        row["_marks"] = _marks(("mAP50", "mAP50_95"), e.labels)
        matched = table.warning is None
        for f in folds:
            fr = e.folds.get(f)
            if fr is None:
                continue
            row["_marks"].update(_marks((f"{f}:mAP50", f"{f}:mAP50_95"), fr.labels))
            for key in ("mAP50", "mAP50_95"):
                row[f"{f}:{key}"] = fr.metrics["metrics"].get(key)
                table.records.append(
                    record(
                        name,
                        key,
                        row[f"{f}:{key}"],
                        dataset=dataset,
                        detector=e.detector,
                        encoding=e.encoding,
                        fold=f,
                        images=fr.images,
                        instances=fr.instances,
                        seeds=fr.seeds,
                        sample_matched=matched,
                    )
                )
        for key in ("mAP50", "mAP50_95"):
            s = row[key]
            table.records.append(
                stat_record(
                    name,
                    f"{key}_mean",
                    s,
                    dataset=dataset,
                    detector=e.detector,
                    encoding=e.encoding,
                    fold="mean",
                    images=e.images,
                    instances=e.instances,
                    seeds=e.seeds,
                    sample_matched=matched,
                )
            )
        for key, unit in (("params", "M"), ("gflops", "GFLOPs")):
            if row[key] is not None:
                table.records.append(
                    record(
                        name,
                        key,
                        row[key],
                        dataset=dataset,
                        detector=e.detector,
                        encoding=e.encoding,
                        unit=unit,
                        sample_matched=None,
                    )
                )
        table.rows.append(row)
    if table.warning is None and rows_e:
        ref = rows_e[0]
        sup: dict[str, Any] = {
            "detector": "support",
            "encoding": "img / inst",
            "_summary": True,
            "images": ref.images,
            "instances": ref.instances,
            "pareto": "",
        }
        for f in folds:
            fr = ref.folds[f]
            sup[f"{f}:mAP50"] = f"{fr.images} img"
            sup[f"{f}:mAP50_95"] = f"{fr.instances} inst"
        table.rows.append(sup)
    n_folds = len(folds)
    table.notes.append(
        f"Held-out folds {', '.join(folds)}; mean ± sample SD (n - 1) over the {n_folds} fold(s); "
        f"{_seeds_note(rows_e)}. AP is COCO box AP (mAP50: IoU 0.50; mAP50:95: IoU 0.50:0.05:0.95; "
        f"101 recall points, maxDets 100), in %."
    )
    table.notes.append(
        "Images and Inst.: held-out images and instances summed over the folds (each image is held out "
        "once); the support row gives them per fold."
    )
    _profile_notes(table, rows_e, no_profile, view)
    if left_out:
        table.notes.append(
            "Not in this table (evaluated on fewer folds; see the encoding ablation): "
            + ", ".join(f"{e.label} [{', '.join(e.fold_names)}]" for e in left_out)
        )
    if pareto is not None:
        table.notes.append(
            "Pareto: on the accuracy (mAP50:95) vs GFLOPs front: no other row has fewer or equal "
            "GFLOPs and a higher mean mAP50:95."
        )
    _label_notes(table, rows_e)
    return table


def _profile_notes(table: Table, rows: Sequence[Entry], missing: Sequence[Entry], view: StoreView) -> None:
    profs = [c for c in (e.complexity() for e in rows) if c.get("params_m")]
    if profs:
        ncls = sorted({p.get("num_classes") for p in profs if p.get("num_classes")})
        folded = {p.get("bn_folded") for p in profs}
        params = (
            "after BatchNorm folding"
            if folded == {True}
            else "as built (no BatchNorm fold declared)"
            if folded == {False}
            else "after BatchNorm folding where the detector declares one"
        )
        table.notes.append(
            f"Params (M): parameter count {params}; GFLOPs: 'paper' convention (BN folded, 1 multiply-add = 2 FLOPs, "
            f"forward_raw without decoding/NMS) at 640x640, batch 1, both inputs for dual-stream detectors, "
            f"{'/'.join(map(str, ncls))} class(es); measured on the model each run trained (metrics.json complexity)."
        )
    for e in rows:
        if e.complexity().get("source") == "given":
            table.notes.append(
                f"{e.label}: Params and GFLOPs as given with `harness score`, not measured by the "
                "harness (its predictions came from outside)."
            )
    for e in missing:
        mixed = e.complexity().get("mixed")
        if e.detector.startswith("external/") and not mixed:
            table.notes.append(
                f"{e.label}: Params and GFLOPs not given; re-score with `harness score ... --params M "
                "--gflops G --force` to show them."
            )
        elif mixed:
            table.notes.append(
                f"{e.label}: Params and GFLOPs absent, its runs were built with different model "
                f"options ({'; '.join(mixed)}); re-run them with one setting."
            )
        else:
            table.notes.append(
                f"{e.label}: Params and GFLOPs absent, run(s) without a complexity record "
                f"({', '.join(e.unmeasured_runs()[:3])}); re-run with --force to measure them."
            )


# -------------------------------------------------------------------------------------------------- training budget
#: What the seed's protocol (weights chosen on the held-out fold) added to the number it reports, measured on the
#: benchmark's learning-curve runs: docs/learning-curves/README.md, table "Which weights" (largest "inflation of the
#: seed's protocol", ours/c2 over 60 epochs: +5.09 points of held-out mAP50:95, best held-out epoch over the last).
HELD_OUT_INFLATION_POINTS = 5.09

#: The plateau record's metric when a run stored none, by selection protocol (as ``harness.runner`` names them).
_PLATEAU_METRIC = {
    "validation": "validation fitness",
    "held-out": "held-out fitness",
    "last": "held-out fitness, logged only",
}


def _epochs_run(metrics: Mapping[str, Any]) -> int | None:
    sel = run_selection(metrics)
    n = sel.get("epochs_run")
    if n is None:
        n = (metrics.get("train") or {}).get("epochs_run")
    return int(n) if isinstance(n, (int, float)) and not isinstance(n, bool) else None


def _range(values: Sequence[int]) -> str:
    if not values:
        return "-"
    lo, hi = min(values), max(values)
    return str(lo) if lo == hi else f"{lo}-{hi}"


#: A run whose slope is under the plateau threshold still rises when the slope is at least this share of its
#: held-out fitness (0.1 mAP50 + 0.9 mAP50:95) per epoch: a curve that low has barely started (a CMA-Det after 12
#: epochs on tiny targets: fitness 1.9 points, slope 0.15). No m3t-synth reference run is affected (the lowest, 4.4
#: points, falls).
RELATIVE_RISE = 0.05


def _rising_for_its_level(metrics: Mapping[str, Any], slope: Any) -> bool:
    """Whether ``slope`` (points per epoch) is at least ``RELATIVE_RISE`` of the run's held-out fitness in points."""
    m = metrics.get("metrics") if isinstance(metrics, Mapping) else None
    if slope is None or not isinstance(m, Mapping) or m.get("mAP50_95") is None:
        return False
    level = 100.0 * (0.1 * float(m.get("mAP50") or 0.0) + 0.9 * float(m["mAP50_95"]))
    return float(slope) > 0 and float(slope) >= RELATIVE_RISE * level


def run_still_rising(metrics: Mapping[str, Any]) -> bool | None:
    """Whether a run was still improving when it stopped (its plateau record over the threshold, or under it but
    rising by ``RELATIVE_RISE`` of its level); None for a run without a plateau record."""
    from harness.report.reader import run_plateau

    rec = run_plateau(metrics)
    if rec is None:
        return None
    return not rec.get("reached") or _rising_for_its_level(metrics, rec.get("slope_per_epoch"))


def _low_text(low: int) -> str:
    return (
        f"; {low} of them under the slope threshold, but rising by {RELATIVE_RISE * 100:g} % of their level or more "
        "per epoch"
        if low
        else ""
    )


def budget_table(entries: Sequence[Entry], dataset: str) -> tuple[Table | None, list[str]]:
    """The training budget of each (detector, encoding) of ``dataset``: epochs run (min-max over its runs), the
    selection protocol(s) (``reader.run_selection``), how many runs reached the plateau (``reader.run_plateau``), the
    mean and largest slope of the plateau records (points per epoch over the last epochs) and the metric it was
    measured on. A run under the slope threshold that still rises by ``RELATIVE_RISE`` of its level counts as rising.
    Returns (table, sentences): one sentence per entry with runs still rising or low, one naming the entries
    with runs that recorded no plateau. None when there are no entries."""
    if not entries:
        return None, []
    name = f"{_slug(dataset)}-budget"
    cols = [
        Column("detector", "Detector"),
        Column("encoding", "Encoding"),
        Column("runs", "Runs", "int"),
        Column("epochs", "Epochs run"),
        Column("selection", "Selection"),
        Column("reached", "Plateau reached"),
        Column("slope_mean", "Slope mean", "float", digits=2),
        Column("slope_max", "Slope max", "float", digits=2),
        Column("metric", "Slope of"),
    ]
    table = Table(name, f"{dataset}: training budget (plateau slope in points/epoch)", cols)
    names = _entry_names(entries)
    plain = _plain_names(entries)
    rising: list[str] = []
    unrecorded: list[str] = []
    window: set[int] = set()
    threshold: set[float] = set()
    for e in entries:
        runs = e.runs()
        epochs = [n for n in (_epochs_run(r.metrics) for r in runs) if n is not None]
        protocols = list(dict.fromkeys(str(run_selection(r.metrics).get("protocol")) for r in runs))
        recs = [(r, p) for r in runs if (p := run_plateau(r.metrics)) is not None]
        slopes = [float(p["slope_per_epoch"]) for _, p in recs if p.get("slope_per_epoch") is not None]
        low = sum(1 for r, p in recs if p.get("reached") and _rising_for_its_level(r.metrics, p.get("slope_per_epoch")))
        reached = sum(1 for _, p in recs if p.get("reached")) - low
        metrics = list(
            dict.fromkeys(
                str(p.get("metric") or _PLATEAU_METRIC.get(str(run_selection(r.metrics).get("protocol")), "?"))
                for r, p in recs
            )
        )
        window |= {int(p["epochs"]) for _, p in recs if p.get("epochs")}
        threshold |= {float(p["threshold"]) for _, p in recs if p.get("threshold") is not None}
        mean = sum(slopes) / len(slopes) if slopes else None
        top = max(slopes) if slopes else None
        table.rows.append(
            {
                "detector": names[e.label],
                "encoding": e.encoding,
                "runs": len(runs),
                "epochs": _range(epochs),
                "selection": ", ".join(protocols),
                "reached": f"{reached} of {len(recs)}" if recs else "not recorded",
                "slope_mean": mean,
                "slope_max": top,
                "metric": "; ".join(metrics) or "-",
            }
        )
        where = {"dataset": dataset, "detector": e.detector, "encoding": e.encoding, "seeds": e.seeds}
        table.records += [
            record(name, "epochs_run_max", max(epochs) if epochs else None, n=len(epochs), unit="epochs", **where),
            record(name, "plateau_reached_runs", reached if recs else None, n=len(recs), unit="runs", **where),
            record(name, "plateau_slope_mean", mean, n=len(slopes), unit="points/epoch", **where),
            record(name, "plateau_slope_max", top, n=len(slopes), unit="points/epoch", **where),
        ]
        still = len(recs) - reached
        if still:
            over = max(int(p.get("epochs") or 0) for _, p in recs)
            rising.append(
                f"{plain[e.label]}: {still} of {len(recs)} runs still rising (slope up to {top:.2f} point/epoch over "
                f"the last {over} epochs{_low_text(low)}): its numbers may rise with more epochs."
            )
        if len(recs) < len(runs):
            gap = len(runs) - len(recs)
            unrecorded.append(plain[e.label] + (f" ({gap} of {len(runs)} runs)" if recs else ""))
    sentences = list(rising)
    if unrecorded:
        sentences.append(
            f"Plateau not recorded for {', '.join(unrecorded)}: runs made before plateau records, or without "
            "per-epoch scores."
        )
    over = " " + "/".join(str(n) for n in sorted(window)) if window else ""
    below = (
        "; the plateau is reached below " + "/".join(f"{t:g}" for t in sorted(threshold)) + " point/epoch"
        if threshold
        else ""
    )
    table.notes.append(
        f"Slope: least-squares slope of the per-epoch fitness (0.1 mAP50 + 0.9 mAP50:95, points) over the last{over} "
        f"scored epochs of each run (metrics.json train.plateau){below}, and at a slope under "
        f"{RELATIVE_RISE * 100:g} % of the run's held-out fitness per epoch (a curve near zero rising slowly has not "
        "reached one). Epochs run: min-max over the runs; "
        "selection: which weights predicted the held-out fold (protocol.selection)."
    )
    return table, sentences


def _plain_names(entries: Sequence[Entry]) -> dict[str, str]:
    """Entry names for sentences: the detector alone when each detector appears once, else detector/encoding."""
    dets = [e.detector for e in entries]
    return {e.label: e.detector if dets.count(e.detector) == 1 else e.label for e in entries}


def held_out_note(entries: Sequence[Entry]) -> str | None:
    """The note a table carries when some of its entries' weights were chosen on the held-out fold (the seed's
    protocol, ``reader.run_selection``: runs stored before the record existed count as such), else None."""
    names = _plain_names(entries)
    chosen = []
    for e in entries:
        runs = e.runs()
        k = sum(1 for r in runs if run_selection(r.metrics).get("protocol") == "held-out")
        if k:
            chosen.append(names[e.label] + (f" ({k} of {len(runs)} runs)" if k < len(runs) else ""))
    if not chosen:
        return None
    return (
        f"Weights chosen on the held-out fold (the seed's protocol) for: {', '.join(chosen)}; their numbers are "
        "optimistic: on the benchmark's learning-curve runs choosing the best held-out epoch added up to "
        f"{HELD_OUT_INFLATION_POINTS:.1f} points of mAP50:95 over the last epoch (docs/learning-curves/README.md, "
        'table "Which weights").'
    )


# -------------------------------------------------------------------------------------------------- per category
def category_table(view: StoreView, dataset: str) -> Table | None:
    """Per category: instances (summed over held-out folds) and AP50 / AP50:95, mean ± SD over the folds whose
    held-out images contain the category (a fold without it is left out, not counted as zero)."""
    entries = view.entries(dataset)
    if not entries:
        return None
    rows_e, _, folds = main_entries(entries)
    names = _entry_names(rows_e)
    aggs = {e.label: e.aggregate() for e in rows_e}
    cats: list[str] = []
    for e in rows_e:
        for m in e.fold_metrics():
            cats.extend(c for c in m.get("per_category", {}) if c not in cats)
    name = f"{_slug(dataset)}-categories"
    cols = [Column("category", "Category"), Column("instances", "Instances", "int"), Column("folds", "Folds")]
    multi = len(rows_e) > 1
    for e in rows_e:
        prefix = f"{names[e.label]} " if multi else ""
        group = names[e.label] if multi else None
        cols += [
            Column(
                f"{e.label}:AP50", f"{prefix}AP50", "pct", best="max" if not multi else None, group=group, short="AP50"
            ),
            Column(
                f"{e.label}:AP50_95",
                f"{prefix}AP50:95",
                "pct",
                best="max" if not multi else None,
                group=group,
                short="AP50:95",
            ),
        ]
    table = Table(name, f"{dataset}: per category (AP over the folds that contain the category, %)", cols)
    _merge_warning(table, *_fold_matching(rows_e, folds))
    ref = aggs[rows_e[0].label]["per_category"]
    for c in cats:
        ref_c = ref.get(c) or {}
        row: dict[str, Any] = {
            "category": c,
            "instances": ref_c.get("instances", 0),
            "folds": f"{ref_c.get('folds_present', 0)}/{len(folds)}",
            "_marks": {},
        }
        for e in rows_e:
            row["_marks"].update(_marks((f"{e.label}:AP50", f"{e.label}:AP50_95"), e.labels))
            pc = aggs[e.label]["per_category"].get(c) or {}
            for key in ("AP50", "AP50_95"):
                s = Stat.from_mean_sd(pc.get(key))
                row[f"{e.label}:{key}"] = s
                table.records.append(
                    stat_record(
                        name,
                        key,
                        s,
                        dataset=dataset,
                        detector=e.detector,
                        encoding=e.encoding,
                        fold="mean",
                        category=c,
                        instances=int(pc.get("instances") or 0),
                        seeds=e.seeds,
                        sample_matched=table.warning is None,
                    )
                )
        table.rows.append(row)
    table.notes.append(
        "Instances: ground-truth instances summed over the held-out folds; Folds: held-out folds "
        "containing the category / all folds. A category absent from a fold has no AP there and is "
        "excluded from its mean (not counted as zero); SD is the sample SD over those folds."
    )
    if multi:
        table.notes.append("Columns per detector: " + ", ".join(f"{names[e.label]} = {e.label}" for e in rows_e))
    _label_notes(table, rows_e)
    return table


# -------------------------------------------------------------------------------------------------- ablation
def ablation_tables(
    view: StoreView, dataset: str, categories: Sequence[str] = ABLATION_CATEGORIES
) -> tuple[list[Table], list[str]]:
    """One encoding-ablation table per detector run with two or more encodings on common folds.

    Returns (tables, notes): notes say why a detector's encodings could not be tabulated (no common fold).
    """
    by_det: dict[str, list[Entry]] = {}
    for e in view.entries(dataset):
        by_det.setdefault(e.detector, []).append(e)
    tables: list[Table] = []
    notes: list[str] = []
    for det, entries in by_det.items():
        if len(entries) < 2:
            continue
        common = sorted(set.intersection(*(set(e.fold_names) for e in entries)), key=natural_key)
        if not common:
            notes.append(
                f"{det}: encodings {', '.join(e.encoding for e in entries)} share no held-out fold; "
                f"run them on the same fold (`harness ablate --detector {det} --dataset {dataset} "
                f"--encodings ... --folds F`)."
            )
            continue
        tables.append(_ablation_table(dataset, det, entries, common, categories))
    return tables, notes


def _ablation_table(
    dataset: str, det: str, entries: Sequence[Entry], folds: Sequence[str], categories: Sequence[str]
) -> Table:
    from harness.evaluation import aggregate_folds

    present: list[str] = []
    for e in entries:
        for f in folds:
            present.extend(c for c in e.folds[f].metrics.get("per_category", {}) if c not in present)
    chosen, missing = [], []
    for want in categories:
        hit = find_category(want, present)
        (chosen if hit else missing).append(hit or want)
    name = f"{_slug(dataset)}-ablation-{_slug(det)}"
    cols = [
        Column("encoding", "Encoding"),
        Column("images", "Images", "int"),
        Column("instances", "Inst.", "int"),
        Column("precision", "P", "pct", best="max"),
        Column("recall", "R", "pct", best="max"),
        Column("mAP50", "mAP50", "pct", best="max"),
        Column("mAP50_95", "mAP50:95", "pct", best="max"),
    ]
    cols += [Column(f"cat:{c}", f"AP50 {c}", "pct", best="max") for c in chosen]
    fold_text = ", ".join(folds)
    table = Table(
        name,
        f"{dataset}: encoding ablation of {det} (held-out fold{'s' if len(folds) > 1 else ''} {fold_text}, %)",
        cols,
    )
    _merge_warning(table, *_fold_matching(entries, folds))
    shown = [e.restricted(folds) for e in entries]  # the labels of the folds in this table
    for e, s_e in zip(entries, shown):
        metrics = [e.folds[f].metrics for f in folds]
        agg = aggregate_folds(metrics)
        images = sum(e.folds[f].images for f in folds)
        instances = sum(e.folds[f].instances for f in folds)
        seeds = sorted({s for f in folds for s in e.folds[f].seeds})
        row: dict[str, Any] = {
            "encoding": e.encoding,
            "images": images,
            "instances": instances,
            "_marks": _marks(("precision", "recall", "mAP50", "mAP50_95", *(f"cat:{c}" for c in chosen)), s_e.labels),
        }
        for key in ("precision", "recall", "mAP50", "mAP50_95"):
            s = Stat.from_mean_sd(agg["metrics"].get(key))
            row[key] = s if len(folds) > 1 else s.mean
            table.records.append(
                stat_record(
                    name,
                    key,
                    s,
                    dataset=dataset,
                    detector=det,
                    encoding=e.encoding,
                    fold=fold_text,
                    images=images,
                    instances=instances,
                    seeds=seeds,
                    sample_matched=table.warning is None,
                )
            )
        for c in chosen:
            pc = agg["per_category"].get(c) or {}
            s = Stat.from_mean_sd(pc.get("AP50"))
            row[f"cat:{c}"] = s if len(folds) > 1 else s.mean
            table.records.append(
                stat_record(
                    name,
                    "AP50",
                    s,
                    dataset=dataset,
                    detector=det,
                    encoding=e.encoding,
                    fold=fold_text,
                    category=c,
                    instances=int(pc.get("instances") or 0),
                    seeds=seeds,
                    sample_matched=table.warning is None,
                )
            )
        table.rows.append(row)
    first = aggregate_folds([entries[0].folds[f].metrics for f in folds])["per_category"]
    cat_support = ", ".join(f"{c} {int((first.get(c) or {}).get('instances') or 0)}" for c in chosen)
    table.notes.append(
        f"Same detector, same held-out images, one row per encoding of the fourth channel; "
        f"{_seeds_note(entries)}. P and R at the confidence that maximises the mean F1 over categories "
        f"(IoU 0.50); AP in %." + (" Values are means over the folds." if len(folds) > 1 else "")
    )
    if chosen:
        table.notes.append(f"Instances of the AP50 columns: {cat_support}.")
    if missing:
        table.notes.append(f"Categories not in this dataset (no column): {', '.join(missing)}.")
    _label_notes(table, shown)
    return table


# -------------------------------------------------------------------------------------------------- sensing
def registration_table(result: Mapping[str, Any], dataset: str) -> Table:
    """``harness sensing registration-error``: mean, median, P95 and max error (thermal px), overall and per scene."""
    name = f"{_slug(dataset)}-registration-error"
    cols = [
        Column("scene", "Scene"),
        Column("n", "Landmarks", "int"),
        Column("mean", "Mean (px)", "float", 2),
        Column("median", "Median (px)", "float", 2),
        Column("p95", "P95 (px)", "float", 2),
        Column("max", "Max (px)", "float", 2),
    ]
    table = Table(name, f"{dataset}: RGB-to-thermal registration error (thermal pixels)", cols)
    rows = [{"scene": "all", **{k: result.get(k) for k in ("n", "mean", "median", "p95", "max")}, "_summary": True}]
    for scene, v in (result.get("per_scene") or {}).items():
        rows.append({"scene": scene, **{k: v.get(k) for k in ("n", "mean", "median", "p95", "max")}})
    table.rows = rows[1:] + rows[:1] if len(rows) > 1 else rows
    for r in table.rows:
        for k in ("mean", "median", "p95", "max"):
            if r.get(k) is not None:
                table.records.append(
                    record(
                        name,
                        f"registration_error_{k}",
                        r[k],
                        dataset=dataset,
                        category=r["scene"],
                        n=r.get("n"),
                        unit="px",
                        sample_matched=None,
                    )
                )
    mode = result.get("mode", "")
    table.notes.append(
        f"Error = distance between a landmark's thermal position and its RGB position mapped by the "
        f"homography ({mode}); Landmarks = point pairs scored."
    )
    if result.get("outside_support"):
        table.notes.append(f"{result['outside_support']} landmark(s) outside the common support left out.")
    if result.get("groups_skipped"):
        table.notes.append(f"Groups with too few landmarks for leave-one-out: {', '.join(result['groups_skipped'])}.")
    if result.get("landmarks_file"):
        table.notes.append(
            f"Landmarks: {result['landmarks_file']}"
            + (f"; homographies: {result['homographies_file']}" if result.get("homographies_file") else "")
        )
    return table


def screening_route_table(runs: Sequence[Any], dataset: str) -> Table | None:
    """``harness score-route``: each run's held-out mAP with its samples' registration (landmarks), under the route a
    new flight gets (automatic registration pooled per inspection group, the prior where it fails) and with the
    factory prior alone; None when no run of ``dataset`` was scored so."""
    name = f"{_slug(dataset)}-screening-route"
    cols = [
        Column("run", "Run"),
        Column("landmarks", "mAP50-95 landmarks %", "pct"),
        Column("automatic", "mAP50-95 automatic %", "pct"),
        Column("prior", "mAP50-95 prior %", "pct"),
        Column("registered", "Registered automatically"),
        Column("route", "Samples registered by"),
    ]
    table = Table(name, f"{dataset}: accuracy under the screening route (held-out fold, mAP50-95, %)", cols)
    for run in runs:
        result = run.screening_route()
        if not result:
            continue
        routes = result.get("routes") or {}
        auto = routes.get("automatic") or {}
        row = {
            "run": f"{run.key.detector}/{run.key.encoding}/{run.name}",
            **{r: (routes.get(r) or {}).get("mAP50_95") for r in ("landmarks", "automatic", "prior")},
            "registered": f"{auto.get('registered_automatically', 0)} of {auto.get('screened', 0)} frames"
            if auto
            else "-",
            "route": str((result.get("recorded_route") or {}).get("route", "not recorded")),
        }
        table.rows.append(row)
        for r in ("landmarks", "automatic", "prior"):
            if row[r] is not None:
                table.records.append(
                    record(
                        name,
                        f"mAP50_95_{r}",
                        row[r],
                        dataset=dataset,
                        detector=run.key.detector,
                        encoding=run.key.encoding,
                        fold=run.key.fold,
                        seeds=[run.key.seed],
                        images=(routes.get(r) or {}).get("images"),
                    )
                )
    if not table.rows:
        return None
    table.notes.append(
        "landmarks: the run's own score (its samples' registration); automatic: the held-out raw "
        "captures through `harness screen` with its default options (each inspection group registered "
        "automatically, pooled over its captures, the factory prior where that is rejected); prior: "
        "every group by the factory prior. Boxes are scored against the run's ground truth."
    )
    return table


def displacement_table(result: Mapping[str, Any], dataset: str) -> Table:
    """``harness sensing displacement``: relative in-box C2 amplitude R_c(d) per class and displacement."""
    name = f"{_slug(dataset)}-c2-displacement"
    shifts = list(result.get("shifts") or [])[1:]
    cols = [Column("class", "Class"), Column("boxes", "Boxes", "int"), Column("A0", "A(0)", "float", 4)]
    cols += [Column(f"R{d}", f"R({d} px) %", "float", 1) for d in shifts]
    table = Table(name, f"{dataset}: C2 amplitude kept under thermal displacement (R_c(d), %)", cols)
    for cls, v in (result.get("classes") or {}).items():
        row: dict[str, Any] = {"class": cls, "boxes": v.get("boxes", 0)}
        A, R = v.get("A"), v.get("R")
        if A:
            row["A0"] = A[0]
            for d, r in zip(shifts, (R or [])[1:]):
                row[f"R{d}"] = r
                table.records.append(
                    record(
                        name,
                        "R",
                        r,
                        dataset=dataset,
                        category=cls,
                        fold=f"{d}px",
                        n=v.get("boxes"),
                        unit="%",
                        sample_matched=None,
                    )
                )
            table.records.append(
                record(
                    name,
                    "A0",
                    A[0],
                    dataset=dataset,
                    category=cls,
                    n=v.get("boxes"),
                    unit="|C2-0.5|",
                    sample_matched=None,
                )
            )
        table.rows.append(row)
    mean = result.get("mean_over_classes")
    if mean:
        row = {"class": "mean (classes)", "boxes": result.get("boxes"), "A0": mean["A"][0], "_summary": True}
        for d, r in zip(shifts, mean["R"][1:]):
            row[f"R{d}"] = r
        table.rows.append(row)
    params = result.get("params") or {}
    table.notes.append(
        f"R_c(d) = 100 A_c(d) / A_c(0); A_c(d) = mean over class-c boxes of the mean |C2 - 0.5| in "
        f"the box after shifting the thermal map d px ({params.get('directions', 'four directions')}, "
        f"C2 recomputed; sigma {params.get('sigma')}, percentile {params.get('percentile')}, floor "
        f"{params.get('floor')} C)."
    )
    table.notes.append(f"Support: {result.get('images', '-')} images, {result.get('boxes', '-')} boxes.")
    return table


# -------------------------------------------------------------------------------------------------- cross-dataset
def cross_dataset_table(view: StoreView, datasets: Sequence[str]) -> Table:
    """The cross-dataset table of ``harness.report.compare.build_table``, restricted to the project tables' rows.

    The builder aggregates every (dataset, annotation source, detector, encoding) of the store; entries evaluated on
    fewer folds (encoding ablations) are left out here, as in the project-grouped tables, and named in a note. Rows
    of a dataset whose entries were not scored on the same samples are marked ``!`` and the table is labelled.
    """
    from harness.report.compare import build_table

    with_runs = [d for d in datasets if view.entries(d)]
    if not with_runs:
        return Table("cross-dataset", "Cross-dataset comparison", [])
    ct = build_table(view, with_runs, allow_mismatched=True)
    keep: set[tuple[str, str, str]] = set()
    bad: set[str] = set()
    table = Table("cross-dataset", "Cross-dataset comparison (held-out mAP, %)", [])
    for ds in with_runs:
        rows_e, _, folds = main_entries(view.entries(ds))
        keep.update((ds, e.detector, e.encoding) for e in rows_e)
        label, details = _fold_matching(rows_e, folds)
        if label:
            bad.add(ds)
            _merge_warning(table, label, [f"{ds}: {d}" for d in details])
    cols = [
        Column("dataset", "Dataset"),
        Column("source", "GT"),
        Column("detector", "Detector"),
        Column("encoding", "Encoding"),
        Column("folds", "Folds", "int"),
        Column("images", "Images", "int"),
        Column("instances", "Instances", "int"),
        Column("mAP50", "mAP50", "pct"),
        Column("mAP50_95", "mAP50:95", "pct"),
    ]
    if ct.safit:
        cols += [Column("safit50", "SAFit-AP50", "pct"), Column("safit50_95", "SAFit-AP50:95", "pct")]
    table.columns = cols
    left_out = []
    shown = []
    for r in ct.rows:
        if (r.dataset, r.detector, r.encoding) not in keep:
            left_out.append(f"{r.dataset}/{r.detector}/{r.encoding} [{', '.join(r.folds)}]")
            continue
        shown.append(r)
        matched = r.dataset not in bad
        row: dict[str, Any] = {
            "dataset": r.dataset,
            "source": r.source,
            "detector": r.detector + ("" if matched else " !"),
            "encoding": r.encoding,
            "folds": len(r.folds),
            "images": r.images,
            "instances": r.instances,
            "mAP50": Stat(r.map50, r.map50_sd, len(r.folds)),
            "mAP50_95": Stat(r.map50_95, r.map50_95_sd, len(r.folds)),
            "_marks": _marks(("mAP50", "mAP50_95", "safit50", "safit50_95"), r.labels),
        }
        if ct.safit:
            row["safit50"] = Stat(r.safit50, r.safit50_sd, len(r.folds))
            row["safit50_95"] = Stat(r.safit50_95, r.safit50_95_sd, len(r.folds))
        table.rows.append(row)
        for key, s in (("mAP50", row["mAP50"]), ("mAP50_95", row["mAP50_95"])):
            table.records.append(
                stat_record(
                    "cross-dataset",
                    f"{key}_mean",
                    s,
                    dataset=r.dataset,
                    detector=r.detector,
                    encoding=r.encoding,
                    fold=" ".join(r.folds),
                    category=f"GT {r.source}",
                    images=r.images,
                    instances=r.instances,
                    seeds=r.seeds,
                    sample_matched=matched,
                )
            )
    table.notes.append(
        "One row per dataset, annotation source (GT: T thermal, RGB visible, - single set), detector "
        "and encoding, aggregated by `harness compare`; AP in %, mean ± sample SD over held-out folds; "
        "images and instances summed over held-out folds."
    )
    if left_out:
        table.notes.append(
            "Not in this table (evaluated on fewer folds; see the encoding ablations): " + ", ".join(left_out)
        )
    table.notes[:0] = label_notes([r.notes_item(len(with_runs) > 1) for r in shown])
    return table


# -------------------------------------------------------------------------------------------------- paired
def paired_table(comparisons: Sequence[Any], name: str, title: str) -> Table:
    """Paired comparisons (``stats.PairedComparison``): per-fold differences and paired bootstrap 95 % CIs; a verdict
    only where both sides were trained with three or more seeds per fold (the two-level bootstrap)."""
    cols = [
        Column("a", "A"),
        Column("b", "B"),
        Column("folds", "Folds", "int"),
        Column("seeds", "Seeds (A/B)"),
        Column("images", "Images", "int"),
        Column("instances", "Inst.", "int"),
        Column("fold_d50", "Δ mAP50 per fold", "pp"),
        Column("boot_d50", "Δ mAP50 [95 % CI]", "pp"),
        Column("fold_d5095", "Δ mAP50:95 per fold", "pp"),
        Column("boot_d5095", "Δ mAP50:95 [95 % CI]", "pp"),
        Column("wins", "A better (folds)"),
        Column("p_beats", "P(A > B), new run (mAP50:95)", "float", 2),
        Column("needed", "Seeds needed (mAP50:95)"),
        Column("verdict", "CI excludes 0"),
    ]
    if not any(c.verdict_allowed for c in comparisons):  # about new training runs: only with three seeds or more
        cols = [c for c in cols if c.key not in ("p_beats", "needed")]
    from harness.report.stats import SEEDS_IMAGES as SEEDS_LEVEL

    table = Table(name, title, cols)
    resamples: dict[str, set[tuple[int, int, int]]] = {}
    for c in comparisons:
        fd = c.fold_differences
        row: dict[str, Any] = {
            "a": c.a,
            "b": c.b,
            "folds": len(c.folds),
            "images": c.images,
            "instances": c.instances,
            "fold_d50": fd["mAP50"].stat,
            "fold_d5095": fd["mAP50_95"].stat,
            "seeds": "/".join(_seed_counts(c.seeds.get(k, [])) for k in ("a", "b")),
            "wins": f"{fd['mAP50_95'].wins}/{len(c.folds)}",
        }
        shown = "".join(c.fold_marks.get("a", []) + c.fold_marks.get("b", []))  # a difference rests on both sides
        m = "".join(ch for ch in dict.fromkeys(MARKS.values()) if ch in shown)
        row["_marks"] = {k: m for k in ("fold_d50", "boot_d50", "fold_d5095", "boot_d5095")} if m else {}
        verdicts = []
        pair: dict[str, Any] = {"dataset": c.dataset, "detector": f"{c.a} - {c.b}", "fold": " ".join(c.folds)}
        for key, col in (("mAP50", "boot_d50"), ("mAP50_95", "boot_d5095")):
            b = (c.bootstrap or {}).get(key)
            if b is not None:
                row[col] = Interval(b.delta, b.ci_low, b.ci_high)
                resamples.setdefault(b.level, set()).add((b.resamples, b.valid, b.seed))
                if c.verdict(key) is not None:
                    verdicts.append(f"{key.replace('_', ':')} {c.verdict(key)}")
                table.records.append(
                    record(
                        name,
                        f"delta_{key}_bootstrap",
                        b.delta,
                        **pair,
                        images=c.images,
                        instances=c.instances,
                        n=b.valid,
                        unit="fraction",
                    )
                )
                for bound, value in (("ci_low", b.ci_low), ("ci_high", b.ci_high)):
                    table.records.append(record(name, f"delta_{key}_{bound}", value, **pair, n=b.valid))
                if b.p_a_beats_b is not None:
                    table.records.append(
                        record(name, f"p_a_beats_b_{key}", b.p_a_beats_b, **pair, n=b.valid, unit="probability")
                    )
                if key == "mAP50_95" and b.level == SEEDS_LEVEL:
                    row["p_beats"] = b.p_a_beats_b
                    row["needed"] = str(b.seeds_needed) if b.seeds_needed is not None else "-"
            table.records.append(
                stat_record(name, f"delta_{key}_per_fold", fd[key].stat, **pair, images=c.images, instances=c.instances)
            )
        if not c.bootstrap:
            row["verdict"] = "no bootstrap"
        elif not c.verdict_allowed:
            row["verdict"] = f"none: {c.training_runs} seed{'s' if c.training_runs != 1 else ''} per fold"
        else:
            row["verdict"] = ", ".join(verdicts)
        table.rows.append(row)
    table.notes.append(
        "Δ = A - B in percentage points. Per fold: mean ± sample SD of the per-fold differences "
        "(each fold's value averaged over its seeds); 'A better': folds where A's mAP50:95 is higher. "
        "Seeds: training seeds per fold (the fewest of any fold)."
    )
    for level, runs in sorted(resamples.items()):
        desc = "; ".join(f"{r} resamples ({v} valid), seed {s}" for r, v, s in sorted(runs))
        if level == SEEDS_LEVEL:
            table.notes.append(
                f"Three or more seeds per fold: two-level bootstrap (training seeds resampled, then "
                f"held-out images, within each fold), statistic = mean over folds; percentile 95 % CI; "
                f"'CI excludes 0' is its verdict. P(A > B), new run: the probability that one new "
                f"training run of A beats one of B (Bouthillier et al., MLSys 2021). Seeds needed: the "
                f"seeds per fold at which the observed spread would resolve the difference "
                f"(docs/reports.md); {desc}."
            )
        else:
            table.notes.append(
                f"Fewer than three seeds per fold: paired bootstrap over images only (same resample "
                f"for A and B, duplicated images given new ids, statistic = mean over folds, percentile "
                f"95 % CI): it holds the trained models fixed, so it compares trained models, not "
                f"detectors, and gives no significance verdict; train with --seeds 0,1,2 for one; "
                f"{desc}."
            )
    if not resamples:
        table.notes.append("No bootstrap (resamples = 0): per-fold differences only.")
    table.notes[:0] = list(dict.fromkeys(n for c in comparisons for n in c.label_notes))
    return table


def _seed_counts(per_fold: Sequence[int]) -> str:
    """Seeds per fold as shown: ``3``, or ``2-3`` when folds differ, ``?`` when unknown."""
    if not per_fold:
        return "?"
    lo, hi = min(per_fold), max(per_fold)
    return str(lo) if lo == hi else f"{lo}-{hi}"
