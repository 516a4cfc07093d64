"""Cross-dataset comparison: the seed's table of images, instances, mAP50 and mAP50:95 per dataset, annotation
source and detector, read from the results store through its one reader (``harness.report.reader``).

One row per (dataset, annotation source, detector, encoding). A row aggregates the finished runs of that
combination: the support is summed over its held-out folds (each fold's images and instances, once per fold), and
the metrics are the mean (and sample SD when there is more than one fold) of the per-fold values, each fold
first averaged over its seeds.

Rows are only comparable when every detector was scored on the same samples. Within one (dataset, annotation
source) the folds and, per fold, the support (image ids, instances) must be identical for every detector; a table
with differing supports is refused (``SupportMismatch``), or, when asked, printed with the differing rows marked
``!`` and the differences listed under it.

SAFit-AP (RGBT-Tiny's scale-adaptive matching) is shown beside standard mAP when the runs were evaluated with
``eval.matching: safit`` (the RGBT-Tiny protocol does so; their metrics carry a ``safit`` block), and on request
for other runs, re-scored from each run's stored ``predictions.json`` against its ``gt.json`` by the one evaluator.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from harness.errors import HarnessError, StoreError
from harness.io import read_json
from harness.report.cells import Stat, format_value
from harness.report.reader import (
    APPROXIMATE,
    Entry,
    FoldResult,
    ResultLabel,
    StoredRun,
    StoreView,
    label_notes,
    marks,
)


class SupportMismatch(HarnessError):
    """Detectors of one dataset and annotation source were scored on different samples."""


@dataclass
class CompareRow:
    dataset: str
    source: str
    detector: str
    encoding: str
    folds: list[str]
    seeds: list[int]
    images: int
    instances: int
    map50: float | None
    map50_sd: float | None
    map50_95: float | None
    map50_95_sd: float | None
    safit50: float | None = None
    safit50_95: float | None = None
    safit50_sd: float | None = None
    safit50_95_sd: float | None = None
    #: False when the support differs from the other detectors of the same dataset and source
    matched: bool = True
    #: per held-out fold: fold, seeds, images, instances, image_ids_sha1 and the seed-averaged numbers
    per_fold: list[dict[str, Any]] = field(default_factory=list)
    #: the model options the runs were built with (``scale=n``; "mixed: ..." when they differ between folds)
    options: str = ""
    #: set when the runs' thermal input rests on approximate temperatures (``metrics.json`` ``temperatures``)
    temperatures: dict[str, Any] | None = None
    #: what the numbers rest on (``harness.report.reader.ResultLabel``), and the runs behind the row
    labels: list[ResultLabel] = field(default_factory=list)
    runs: list[str] = field(default_factory=list)

    def notes_item(self, with_dataset: bool = False) -> tuple[str, list[ResultLabel], list[str]]:
        """This row's part of ``label_notes`` (named with its dataset in a table of several)."""
        return f"{self.dataset + ' ' if with_dataset else ''}{self.detector}/{self.encoding}", self.labels, self.runs


@dataclass
class CompareTable:
    rows: list[CompareRow]
    #: human-readable differences in support, one per (dataset, source) that is not sample-matched
    mismatches: list[str]
    safit: bool = False
    store: str = ""

    # ------------------------------------------------------------------ formats
    def columns(self) -> list[str]:
        cols = ["dataset", "GT", "detector", "encoding", "folds", "images", "instances", "mAP50", "mAP50:95"]
        return cols + (["SAFit-AP50", "SAFit-AP50:95"] if self.safit else [])

    def _cells(self, r: CompareRow) -> list[str]:
        mark = "" if r.matched else " !"
        name = r.detector + (f" [{r.options}]" if r.options else "") + mark
        labelled = f" {m}" if (m := marks(r.labels)) else ""  # beside every number the labels concern
        values = [(r.map50, r.map50_sd), (r.map50_95, r.map50_95_sd)]
        if self.safit:
            values += [(r.safit50, r.safit50_sd), (r.safit50_95, r.safit50_95_sd)]
        return [
            r.dataset,
            r.source,
            name,
            r.encoding,
            str(len(r.folds)),
            str(r.images),
            str(r.instances),
            *(format_value(Stat(v, sd), "pct") + labelled for v, sd in values),
        ]

    def label_notes(self) -> list[str]:
        """What the marks beside the numbers mean (``harness.report.reader.label_notes``)."""
        several = len({r.dataset for r in self.rows}) > 1
        return label_notes([r.notes_item(several) for r in self.rows])

    def to_text(self) -> str:
        cols = self.columns()
        body = [self._cells(r) for r in self.rows]
        widths = [max(len(c), *(len(b[i]) for b in body)) if body else len(c) for i, c in enumerate(cols)]
        right = {"folds", "images", "instances", "mAP50", "mAP50:95", "SAFit-AP50", "SAFit-AP50:95"}

        from harness.textable import column_panels, fit_text

        out: list[str] = []
        for panel in column_panels(widths, keep=4):  # wider than the terminal: panels that repeat the row names

            def line(cells: Sequence[str], idx: Sequence[int] = panel) -> str:
                return "  ".join(
                    cells[i].rjust(widths[i]) if cols[i] in right else cells[i].ljust(widths[i]) for i in idx
                ).rstrip()

            out += [line(cols), line(["-" * w for w in widths])]
            prev = None
            for r, cells in zip(self.rows, body):
                if prev is not None and (r.dataset, r.source) != prev:
                    out.append("")
                prev = (r.dataset, r.source)
                out.append(line(cells))
            out.append("")
        out.append("AP in %, mean ± sample SD over held-out folds; images and instances summed over held-out folds.")
        out += self.label_notes()
        if self.mismatches:
            out.append("! NOT SAMPLE-MATCHED: these rows were scored on different supports and must not be compared:")
            out.extend(f"  - {m}" for m in self.mismatches)
        return fit_text("\n".join(out))

    def to_markdown(self) -> str:
        cols = self.columns()
        out = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
        out += ["| " + " | ".join(self._cells(r)) + " |" for r in self.rows]
        if self.label_notes():
            out += ["", *self.label_notes()]
        if self.mismatches:
            out.append("")
            out += [f"**Not sample-matched:** {m}" for m in self.mismatches]
        return "\n".join(out)

    def to_csv(self) -> str:
        buf = io.StringIO()
        fields = [
            "dataset",
            "source",
            "detector",
            "encoding",
            "folds",
            "seeds",
            "images",
            "instances",
            "map50",
            "map50_sd",
            "map50_95",
            "map50_95_sd",
            "safit50",
            "safit50_95",
            "matched",
        ]
        w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        for r in self.rows:
            d = {k: v for k, v in asdict(r).items() if k in fields}
            d["folds"], d["seeds"] = " ".join(r.folds), " ".join(map(str, r.seeds))
            w.writerow(d)
        return buf.getvalue()

    def to_json(self) -> str:
        return json.dumps(
            {
                "store": self.store,
                "safit": self.safit,
                "mismatches": self.mismatches,
                "rows": [_json_row(r) for r in self.rows],
            },
            indent=2,
        )

    def render(self, fmt: str) -> str:
        return {"text": self.to_text, "markdown": self.to_markdown, "csv": self.to_csv, "json": self.to_json}[fmt]()


def _json_row(r: CompareRow) -> dict[str, Any]:
    """A row as JSON: its labels (kind, text, runs) only when it has any."""
    d = asdict(r)
    d.pop("runs")
    labels = d.pop("labels")
    if labels:
        d["labels"] = [{k: lab[k] for k in ("kind", "text", "runs")} for lab in labels]
    return d


# ---------------------------------------------------------------------------------------------- reading the store
def _safit_rescored(run: StoredRun) -> dict[str, Any]:
    """The SAFit block of a run, re-scored by the one evaluator from its stored predictions and ground truth, with
    the run's own evaluation settings (``eval`` of its config: engine, SAFit anchor)."""
    from harness.evaluation import evaluate_with_config

    for path in (run.gt_path, run.predictions_path):
        if not path.exists():
            raise StoreError(f"{path}: missing; SAFit-AP is re-scored from a run's gt.json and predictions.json")
    settings = {**(run.config.get("eval") or {}), "matching": "safit"}
    result = evaluate_with_config(read_json(run.gt_path), read_json(run.predictions_path), {"eval": settings})
    return result["metrics"]["safit"]


def _finite(value: Any) -> float | None:
    return None if value is None or not math.isfinite(float(value)) else float(value)


def _fold_record(fr: FoldResult, safit: bool) -> dict[str, Any]:
    """One fold of a row as ``per_fold`` shows it: support and its seed-averaged numbers (SAFit when every seed has
    a SAFit block, or re-scored ones with ``safit``). Seeds scored on different samples are refused."""
    from harness.evaluation import check_sample_matched, mean_sd

    if fr.seed_mismatch:
        try:
            check_sample_matched(
                {str(r.key): r.metrics for r in fr.runs},
                hint="Re-run the odd seed on the current prepared data (harness run ... --seeds N --force).",
            )
        except HarnessError as exc:
            raise SupportMismatch(f"the seeds of one fold were scored on different samples: {exc}") from None
    head = fr.metrics["metrics"]
    out: dict[str, Any] = {
        "fold": fr.fold,
        "seeds": fr.seeds,
        "images": fr.images,
        "instances": fr.instances,
        "image_ids_sha1": str(fr.support.get("image_ids_sha1", "")),
        "map50": _finite(head.get("mAP50")),
        "map50_95": _finite(head.get("mAP50_95")),
        "safit50": None,
        "safit50_95": None,
    }
    blocks = []
    for run in fr.runs:
        block = run.metrics["metrics"].get("safit")
        blocks.append(_safit_rescored(run) if block is None and safit else block)
    if all(b is not None for b in blocks):
        out["safit50"] = mean_sd([b.get("mAP50") for b in blocks])["mean"]
        out["safit50_95"] = mean_sd([b.get("mAP50_95") for b in blocks])["mean"]
    return out


def _row(source: str, entry: Entry, safit: bool, matched: bool) -> CompareRow:
    """The row of one entry (its folds of one annotation source): support summed, mean ± sample SD over folds."""
    from harness.evaluation import mean_sd

    per_fold = [_fold_record(fr, safit) for fr in entry.folds.values()]

    def over_folds(key: str) -> dict[str, Any]:
        return mean_sd([f[key] for f in per_fold])

    m50, m95 = over_folds("map50"), over_folds("map50_95")
    approx = next((lab for lab in entry.labels if lab.kind == APPROXIMATE), None)
    row = CompareRow(
        entry.dataset,
        source,
        entry.detector,
        entry.encoding,
        entry.fold_names,
        entry.seeds,
        sum(f["images"] for f in per_fold),
        sum(f["instances"] for f in per_fold),
        m50["mean"],
        m50["sd"],
        m95["mean"],
        m95["sd"],
        matched=matched,
        per_fold=per_fold,
        options=entry.options_label(),
        temperatures=dict(approx.record or {}) if approx else None,
        labels=entry.labels,
        runs=[r.name for r in entry.runs()],
    )
    s50, s95 = over_folds("safit50"), over_folds("safit50_95")
    if s50["n"] == len(per_fold):
        row.safit50, row.safit50_95, row.safit50_sd, row.safit50_95_sd = s50["mean"], s95["mean"], s50["sd"], s95["sd"]
    return row


def check_matched(dataset: str, source: str, entries: dict[tuple[str, str], dict[str, dict[str, Any]]]) -> list[str]:
    """What differs between the supports of the (detector, encoding) entries of one dataset and source.

    ``entries``: ``{(detector, encoding): {fold: metrics}}``. Every entry must cover the same folds, and per fold the
    evaluator's guard (``harness.evaluation.check_sample_matched``: image-id hash, images, instances, instances per
    category) must pass. Returns ``[]`` when the entries are sample-matched.
    """
    from harness.evaluation import check_sample_matched

    if len(entries) < 2:
        return []
    problems: list[str] = []
    names = {k: f"{k[0]}/{k[1]}" for k in entries}
    fold_sets = {k: tuple(sorted(v)) for k, v in entries.items()}
    if len(set(fold_sets.values())) > 1:
        listing = "; ".join(f"{names[k]}: {', '.join(f) or 'none'}" for k, f in fold_sets.items())
        problems.append(f"[GT {source}] dataset {dataset!r}: detectors were evaluated on different folds ({listing})")
    common = set.intersection(*(set(f) for f in fold_sets.values()))
    for fold in sorted(common):
        try:
            check_sample_matched({names[k]: v[fold] for k, v in entries.items()})
        except HarnessError as exc:
            detail = str(exc).split("\n")[1].strip() if "\n" in str(exc) else str(exc)
            problems.append(f"[GT {source}] {detail}")
    return problems


def _support_signature(folds: Sequence[Mapping[str, Any]]) -> str:
    return json.dumps({f["fold"]: [f["images"], f["instances"], f["image_ids_sha1"]] for f in folds}, sort_keys=True)


def build_table(
    store: StoreView | str | Path, datasets: Sequence[str], allow_mismatched: bool = False, safit: bool = False
) -> CompareTable:
    """The cross-dataset table for ``datasets`` from the store at ``store`` (see the module docstring).

    SAFit columns appear when the runs were evaluated with ``eval.matching=safit`` (their metrics carry a SAFit
    block) or when ``safit=True`` (runs without the block are re-scored from their stored predictions).
    """
    view = store if isinstance(store, StoreView) else StoreView(store)
    missing = [d for d in datasets if not view.entries(d)]
    if missing:
        present = [d for d in view.datasets() if view.entries(d)]
        raise StoreError(
            f"{view.root}: no finished runs for dataset(s) {', '.join(missing)}; run `harness run --dataset NAME ...` "
            f"into this store first (finished runs found for: {', '.join(present) or 'none'})"
        )
    rows: list[CompareRow] = []
    mismatches: list[str] = []
    for ds in dict.fromkeys(datasets):
        by_source: dict[str, list[Entry]] = {}
        for entry in view.entries(ds):
            for source, part in entry.by_source().items():
                by_source.setdefault(source, []).append(part)
        for source, entries in sorted(by_source.items()):
            problems = check_matched(
                ds, source, {(e.detector, e.encoding): {f: fr.metrics for f, fr in e.folds.items()} for e in entries}
            )
            mismatches.extend(problems)
            found = [_row(source, e, safit, True) for e in entries]
            bad = _mismatched_rows(found) if problems else set()
            for i, row in enumerate(found):
                row.matched = i not in bad
            rows.extend(found)
    table = CompareTable(
        rows, mismatches, safit=safit or any(r.safit50 is not None for r in rows), store=str(view.root)
    )
    if mismatches and not allow_mismatched:
        raise SupportMismatch(
            "refusing to compare detectors scored on different samples:\n  - "
            + "\n  - ".join(mismatches)
            + "\nre-run them on the same prepared data, or pass --allow-mismatched to print the table with those rows "
            "marked '!'"
        )
    return table


def _mismatched_rows(rows: Sequence[CompareRow]) -> set[int]:
    """Rows whose support differs from the most common support of their dataset and source."""
    sigs = [_support_signature(r.per_fold) for r in rows]
    counts: dict[str, int] = {}
    for s in sigs:
        counts[s] = counts.get(s, 0) + 1
    best = max(counts.values())
    majority = [s for s, c in counts.items() if c == best]
    if len(majority) > 1:  # no majority: every row is suspect
        return set(range(len(rows)))
    return {i for i, s in enumerate(sigs) if s != majority[0]}
