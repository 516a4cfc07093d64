"""Cross-dataset comparison: the seed's table of images, instances, mAP50 and mAP50:95 per dataset, annotation
source and detector, built from the results store alone.

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
from typing import Any, Iterable, Sequence

from harness.errors import HarnessError, StoreError
from harness.io import read_json
from harness.store import Run, Store


#: Short names of annotation sources, as the seed's tables write them.
SOURCE_LABELS = {"thermal": "T", "t": "T", "ir": "T", "01": "T", "visible": "RGB", "rgb": "RGB", "vis": "RGB", "00": "RGB"}
NO_SOURCE = "-"


class SupportMismatch(HarnessError):
    """Detectors of one dataset and annotation source were scored on different samples."""


@dataclass
class FoldResult:
    """One held-out fold of one (detector, encoding): support and metrics, averaged over its seeds."""

    fold: str
    seeds: list[int]
    images: int
    instances: int
    image_ids_sha1: str
    map50: float | None
    map50_95: float | None
    safit50: float | None = None
    safit50_95: float | None = None


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
    per_fold: list[FoldResult] = field(default_factory=list)
    #: the model options the runs were built with (``scale=n``; "mixed: ..." when they differ between folds)
    options: str = ""
    #: set when the runs' thermal input rests on approximate temperatures (``metrics.json`` ``temperatures``)
    temperatures: dict[str, Any] | None = None


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
        approx = " ~" if r.temperatures else ""  # beside every number that rests on approximate temperatures
        cells = [r.dataset, r.source, name, r.encoding, str(len(r.folds)), str(r.images), str(r.instances),
                 _pct(r.map50, r.map50_sd) + approx, _pct(r.map50_95, r.map50_95_sd) + approx]
        if self.safit:
            cells += [_pct(r.safit50, r.safit50_sd) + approx, _pct(r.safit50_95, r.safit50_95_sd) + approx]
        return cells

    def approximate_note(self) -> str | None:
        """What ``~`` means, when a row rests on approximate temperatures."""
        found = [r for r in self.rows if r.temperatures]
        if not found:
            return None
        worst = max(float(r.temperatures.get("bound_c") or 0.0) for r in found)  # type: ignore[union-attr]
        return (f"~ measured on approximate temperatures ({', '.join(f'{r.detector}/{r.encoding}' for r in found)}: "
                f"within {worst:g} C of DJI's SDK at worst; docs/sensing.md)")

    def to_text(self) -> str:
        cols = self.columns()
        body = [self._cells(r) for r in self.rows]
        widths = [max(len(c), *(len(b[i]) for b in body)) if body else len(c) for i, c in enumerate(cols)]
        right = {"folds", "images", "instances", "mAP50", "mAP50:95", "SAFit-AP50", "SAFit-AP50:95"}

        from harness.textable import column_panels, fit_text

        out: list[str] = []
        for panel in column_panels(widths, keep=4):  # wider than the terminal: panels that repeat the row names
            def line(cells: Sequence[str], idx: Sequence[int] = panel) -> str:
                return "  ".join(cells[i].rjust(widths[i]) if cols[i] in right else cells[i].ljust(widths[i])
                                 for i in idx).rstrip()

            out += [line(cols), line(["-" * w for w in widths])]
            prev = None
            for r, cells in zip(self.rows, body):
                if prev is not None and (r.dataset, r.source) != prev:
                    out.append("")
                prev = (r.dataset, r.source)
                out.append(line(cells))
            out.append("")
        out.append("AP in %, mean ± sample SD over held-out folds; images and instances summed over held-out folds.")
        if self.approximate_note():
            out.append(self.approximate_note())  # type: ignore[arg-type]
        if self.mismatches:
            out.append("! NOT SAMPLE-MATCHED: these rows were scored on different supports and must not be compared:")
            out.extend(f"  - {m}" for m in self.mismatches)
        return fit_text("\n".join(out))

    def to_markdown(self) -> str:
        cols = self.columns()
        out = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
        out += ["| " + " | ".join(self._cells(r)) + " |" for r in self.rows]
        if self.approximate_note():
            out += ["", str(self.approximate_note())]
        if self.mismatches:
            out.append("")
            out += [f"**Not sample-matched:** {m}" for m in self.mismatches]
        return "\n".join(out)

    def to_csv(self) -> str:
        buf = io.StringIO()
        fields = ["dataset", "source", "detector", "encoding", "folds", "seeds", "images", "instances", "map50",
                  "map50_sd", "map50_95", "map50_95_sd", "safit50", "safit50_95", "matched"]
        w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        for r in self.rows:
            d = {k: v for k, v in asdict(r).items() if k in fields}
            d["folds"], d["seeds"] = " ".join(r.folds), " ".join(map(str, r.seeds))
            w.writerow(d)
        return buf.getvalue()

    def to_json(self) -> str:
        return json.dumps({"store": self.store, "safit": self.safit, "mismatches": self.mismatches,
                           "rows": [asdict(r) for r in self.rows]}, indent=2)

    def render(self, fmt: str) -> str:
        return {"text": self.to_text, "markdown": self.to_markdown, "csv": self.to_csv, "json": self.to_json}[fmt]()


def _pct(value: float | None, sd: float | None = None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{100 * value:.1f}" + (f" ± {100 * sd:.1f}" if sd is not None else "")


# ---------------------------------------------------------------------------------------------- reading the store
def annotation_source(run: Run) -> str:
    """The annotation source of a run: ``dataset.gt`` of its resolved config, else the ``-T``/``-RGB`` suffix a
    dataset gives its fold names (RGBT-Tiny), else ``-`` (the dataset has a single annotation set)."""
    gt = None
    if run.config_path.exists():
        from harness.config import read_yaml

        cfg = read_yaml(run.config_path)
        ds = cfg.get("dataset") if isinstance(cfg, dict) else None
        gt = ds.get("gt") if isinstance(ds, dict) else None
    if gt is not None:
        return SOURCE_LABELS.get(str(gt).strip().lower(), str(gt))
    fold = run.key.fold
    for suffix in ("T", "RGB"):
        if fold.endswith(f"-{suffix}"):
            return suffix
    return NO_SOURCE


def _safit_rescored(run: Run) -> dict[str, Any]:
    """The SAFit block of a run, re-scored by the one evaluator from its stored predictions and ground truth."""
    from harness.evaluation import evaluate

    for path in (run.gt_path, run.predictions_path):
        if not path.exists():
            raise StoreError(f"{path}: missing; SAFit-AP is re-scored from a run's gt.json and predictions.json")
    result = evaluate(read_json(run.gt_path), read_json(run.predictions_path), matching="safit")
    return result["metrics"]["safit"]


def _options(metrics: Any) -> str:
    """The model options recorded in the runs' complexity (``scale=n``), or ``mixed: a; b`` when they differ."""
    from harness.complexity import options_label

    found = {options_label((m.get("complexity") or {}).get("model_options") or {}) for m in metrics}
    if len(found) > 1:
        return "mixed: " + "; ".join(sorted(o or "defaults" for o in found))
    return next(iter(found), "")


def _fold_result(fold: str, runs: list[Run], safit: bool) -> tuple[FoldResult, dict[str, Any]]:
    """The fold's seeds averaged, and one representative metrics dict (for the sample-matched guard)."""
    from harness.evaluation import check_sample_matched, mean_sd

    metrics = {str(r.key): r.read_metrics() for r in runs}
    try:
        check_sample_matched(metrics, hint="Re-run the odd seed on the current prepared data (harness run ... --seeds "
                                           "N --force).")
    except HarnessError as exc:
        raise SupportMismatch(f"the seeds of one fold were scored on different samples: {exc}") from None
    first = next(iter(metrics.values()))
    sup = first["support"]
    out = FoldResult(fold, sorted(r.key.seed for r in runs), int(sup["images"]), int(sup["instances"]),
                     str(sup.get("image_ids_sha1", "")),
                     mean_sd([m["metrics"].get("mAP50") for m in metrics.values()])["mean"],
                     mean_sd([m["metrics"].get("mAP50_95") for m in metrics.values()])["mean"])
    blocks = []
    for run, m in zip(runs, metrics.values()):
        block = m["metrics"].get("safit")
        if block is None and safit:
            block = _safit_rescored(run)
        blocks.append(block)
    if all(b is not None for b in blocks):
        out.safit50 = mean_sd([b.get("mAP50") for b in blocks])["mean"]
        out.safit50_95 = mean_sd([b.get("mAP50_95") for b in blocks])["mean"]
    return out, first


def collect(store: Store, datasets: Iterable[str]) -> dict[tuple[str, str], dict[tuple[str, str], dict[str, list[Run]]]]:
    """``{(dataset, source): {(detector, encoding): {fold: [runs]}}}`` over finished runs."""
    out: dict[tuple[str, str], dict[tuple[str, str], dict[str, list[Run]]]] = {}
    for ds in datasets:
        for run in store.runs(dataset=ds):
            key = (ds, annotation_source(run))
            out.setdefault(key, {}).setdefault((run.key.detector, run.key.encoding), {}).setdefault(run.key.fold, []).append(run)
    return out


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


def _support_signature(folds: dict[str, FoldResult]) -> str:
    return json.dumps({f: [r.images, r.instances, r.image_ids_sha1] for f, r in sorted(folds.items())}, sort_keys=True)


def build_table(store_root: str | Path, datasets: Sequence[str], allow_mismatched: bool = False,
                safit: bool = False) -> CompareTable:
    """The cross-dataset table for ``datasets`` from the store at ``store_root`` (see the module docstring).

    SAFit columns appear when the runs were evaluated with ``eval.matching=safit`` (their metrics carry a SAFit
    block) or when ``safit=True`` (runs without the block are re-scored from their stored predictions).
    """
    from harness.evaluation import aggregate_folds

    store = Store(store_root)
    if not store.root.is_dir():
        raise StoreError(f"{store.root}: no results store here; pass --store (the folder `harness run` wrote into)")
    found = collect(store, datasets)
    missing = [d for d in datasets if not any(k[0] == d for k in found)]
    if missing:
        present = sorted({r.key.dataset for r in store.runs()})
        raise StoreError(
            f"{store.root}: no finished runs for dataset(s) {', '.join(missing)}; run `harness run --dataset NAME ...` "
            f"into this store first (finished runs found for: {', '.join(present) or 'none'})"
        )
    rows: list[CompareRow] = []
    mismatches: list[str] = []
    order = {d: i for i, d in enumerate(datasets)}
    for (ds, source), entries in sorted(found.items(), key=lambda kv: (order[kv[0][0]], kv[0][1])):
        results: dict[tuple[str, str], dict[str, FoldResult]] = {}
        representative: dict[tuple[str, str], dict[str, dict[str, Any]]] = {}
        for k, folds in entries.items():
            for fold, runs in folds.items():
                fr, metrics = _fold_result(fold, runs, safit)
                results.setdefault(k, {})[fold] = fr
                representative.setdefault(k, {})[fold] = metrics
        problems = check_matched(ds, source, representative)
        mismatches.extend(problems)
        bad = _mismatched_entries(results) if problems else set()
        for (det, enc), folds in sorted(results.items()):
            fr = [folds[f] for f in sorted(folds)]
            agg = aggregate_folds([_fold_metrics(ds, f) for f in fr])
            m = agg["metrics"]
            row = CompareRow(ds, source, det, enc, [f.fold for f in fr], sorted({s for f in fr for s in f.seeds}),
                             agg["support"]["images"], agg["support"]["instances"],
                             m["mAP50"]["mean"], m["mAP50"]["sd"], m["mAP50_95"]["mean"], m["mAP50_95"]["sd"],
                             matched=(det, enc) not in bad, per_fold=fr,
                             options=_options(representative[(det, enc)].values()),
                             temperatures=next((m["temperatures"] for m in representative[(det, enc)].values()
                                                if isinstance(m.get("temperatures"), dict)), None))
            if "safit_mAP50" in m and m["safit_mAP50"]["n"] == len(fr):
                row.safit50, row.safit50_95 = m["safit_mAP50"]["mean"], m["safit_mAP50_95"]["mean"]
                row.safit50_sd, row.safit50_95_sd = m["safit_mAP50"]["sd"], m["safit_mAP50_95"]["sd"]
            rows.append(row)
    table = CompareTable(rows, mismatches, safit=safit or any(r.safit50 is not None for r in rows), store=str(store.root))
    if mismatches and not allow_mismatched:
        raise SupportMismatch(
            "refusing to compare detectors scored on different samples:\n  - " + "\n  - ".join(mismatches)
            + "\nre-run them on the same prepared data, or pass --allow-mismatched to print the table with those rows marked '!'"
        )
    return table


def _fold_metrics(dataset: str, f: FoldResult) -> dict[str, Any]:
    """A fold's seed-averaged numbers in the shape ``aggregate_folds`` reads."""
    metrics: dict[str, Any] = {"mAP50": f.map50, "mAP50_95": f.map50_95}
    if f.safit50 is not None:
        metrics["safit"] = {"mAP50": f.safit50, "mAP50_95": f.safit50_95}
    return {"run": {"dataset": dataset, "fold": f.fold}, "metrics": metrics, "per_category": {},
            "support": {"images": f.images, "instances": f.instances, "image_ids_sha1": f.image_ids_sha1}}


def _mismatched_entries(results: dict[tuple[str, str], dict[str, FoldResult]]) -> set[tuple[str, str]]:
    """Entries whose support differs from the most common support of their dataset and source."""
    sigs = {k: _support_signature(v) for k, v in results.items()}
    counts: dict[str, int] = {}
    for s in sigs.values():
        counts[s] = counts.get(s, 0) + 1
    best = max(counts.values())
    majority = [s for s, c in counts.items() if c == best]
    if len(majority) > 1:  # no majority: every entry is suspect
        return set(results)
    return {k for k, s in sigs.items() if s != majority[0]}
