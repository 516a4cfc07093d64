"""The one reader of the results store: finished runs grouped into entries, seeds averaged per fold, their labels.

``harness report``, ``harness compare``, ``harness compare-detectors`` and the tables ``harness run`` and
``harness ablate`` print read the store through this module alone (``harness/store.py`` writes it): the
``metrics.json`` of finished runs, their error analysis (``analysis.json``: ``StoredRun.analysis``), the annotation
source in their ``config.yaml``, and the stored sensing analyses (``<dataset>/_sensing/<analysis>.json``). Re-scoring
and the galleries read ``gt.json`` and ``predictions.json`` of the runs found here (``StoredRun.ground_truth``,
``StoredRun.predictions``).

Vocabulary used by every table:

* a **stored run** (``StoredRun``) is one finished (dataset, detector, encoding, fold, seed) with its
  ``metrics.json``, its labels and its error analysis;
* an **entry** (``Entry``) is one (dataset, detector, encoding): the rows of the seed's tables;
* a **fold result** (``FoldResult``) is one held-out fold of an entry with its seeds averaged (each metric the mean
  over the seeds that define it); its support is the support the seeds share (seeds scored on different samples
  are a mismatch, labelled like any other);
* the headline numbers of an entry are ``harness.evaluation.aggregate_folds`` over its fold results: mean and
  sample SD over the held-out folds, a category without ground truth in a fold left out of that category's mean;
* a **label** (``ResultLabel``) says that a stored number rests on something the reader must know: approximate
  temperatures (``~``), or a risk accepted when the run was stored (``†``: degenerate boxes or implausible
  predictions, ``metrics.json`` ``labels``; a dataset input risk, ``input_risks``). Every table shows the marks
  beside the numbers they concern and one footnote per label (``label_notes``).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from harness.errors import HarnessError, StoreError
from harness.store import Run, Store

log = logging.getLogger(__name__)

#: The name reference results' entries get beside a store's own (``ref:ours``; ``harness.references``).
REFERENCE_PREFIX = "ref:"
#: Headline metrics averaged over seeds within a fold.
SEED_METRICS = ("mAP50", "mAP50_95", "precision", "recall", "f1")
#: Per-category metrics averaged over seeds within a fold.
SEED_CATEGORY_METRICS = ("AP50", "AP50_95")

#: Short names of annotation sources, as the seed's tables write them.
SOURCE_LABELS = {
    "thermal": "T",
    "t": "T",
    "ir": "T",
    "01": "T",
    "visible": "RGB",
    "rgb": "RGB",
    "vis": "RGB",
    "00": "RGB",
}
NO_SOURCE = "-"


def natural_key(text: str) -> list[Any]:
    """Sort key that puts ``P2`` before ``P10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", text)]


def normalise_category(name: Any) -> str:
    """A category name as compared: case, spaces, ``_`` and ``-`` ignored (``Water-Seepage`` = ``water seepage``)."""
    return re.sub(r"[\s_\-]+", " ", str(name)).strip().lower()


def find_category(wanted: str, categories: Iterable[str]) -> str | None:
    """The name in ``categories`` that ``wanted`` means (``normalise_category``), or None."""
    return next((c for c in categories if normalise_category(c) == normalise_category(wanted)), None)


def _mean(values: Iterable[Any]) -> float | None:
    from harness.evaluation import mean_sd

    return mean_sd(list(values))["mean"]


# ---------------------------------------------------------------------------------------------------- selection
def run_selection(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """How one run's held-out weights were chosen (``metrics.json`` ``selection``, written by ``harness.runner``):
    ``protocol`` (``validation``, ``last`` or ``held-out``), ``validation_groups``, ``best_epoch``, ``epochs_run``.
    A run stored before the field existed selected its best epoch on the held-out fold: ``held-out``, with the
    best epoch of its training summary."""
    sel = metrics.get("selection")
    if isinstance(sel, Mapping):
        return dict(sel)
    train = metrics.get("train") or {}
    weights = str((metrics.get("model") or {}).get("weights") or "best")
    return {
        "protocol": "held-out",
        "weights": weights,
        "best_epoch": train.get("best_epoch") if weights == "best" else None,
        "epochs_run": train.get("epochs_run"),
        "validation_groups": [],
    }


def run_plateau(metrics: Mapping[str, Any]) -> dict[str, Any] | None:
    """Whether one run had stopped improving (``metrics.json`` ``train.plateau``, ``harness.engine.trainer.plateau``):
    ``slope_per_epoch`` (least-squares slope of the selecting fitness over the last ``epochs`` scored epochs, points
    per epoch), ``reached`` (under ``threshold``) and ``metric`` (``validation fitness``, or ``held-out fitness``
    under the seed's protocol); None for a run without per-epoch scores (``protocol.selection=last``) or stored
    before the record existed."""
    rec = (metrics.get("train") or {}).get("plateau")
    return dict(rec) if isinstance(rec, Mapping) else None


# ---------------------------------------------------------------------------------------------------- labels
APPROXIMATE = "approximate-temperatures"
ACCEPTED = "accepted-risk"
INPUT_RISK = "input-risk"
#: The mark beside a number that rests on a result with a label of that kind, in the order marks are written.
MARKS = {APPROXIMATE: "~", ACCEPTED: "†", INPUT_RISK: "†"}
_PHRASES = {ACCEPTED: "accepted risk", INPUT_RISK: "accepted input risk"}


@dataclass(frozen=True)
class ResultLabel:
    """What a stored number rests on that a reader must know (see the module docstring).

    ``kind``: ``APPROXIMATE``, ``ACCEPTED`` or ``INPUT_RISK``; ``text``: the stored sentence (for approximate
    temperatures the record's label); ``runs``: the runs it comes from, as ``FOLD/seedN``; ``record``: the
    ``temperatures`` record of approximate temperatures (the worst bound when merged)."""

    kind: str
    text: str
    runs: tuple[str, ...] = ()
    record: Mapping[str, Any] | None = field(default=None, compare=False)

    @property
    def mark(self) -> str:
        return MARKS[self.kind]

    @property
    def bound_c(self) -> float:
        return float((self.record or {}).get("bound_c") or 0.0)


def run_labels(metrics: Mapping[str, Any], run: str = "") -> list[ResultLabel]:
    """The labels of one run's ``metrics.json``, read from the three fields runs have written them to."""
    where = (run,) if run else ()
    out = [ResultLabel(ACCEPTED, str(t), where) for t in metrics.get("labels") or []]
    out += [ResultLabel(INPUT_RISK, str(t), where) for t in metrics.get("input_risks") or []]
    temps = metrics.get("temperatures")
    if isinstance(temps, Mapping):
        out.append(ResultLabel(APPROXIMATE, str(temps.get("label") or "approximate temperatures"), where, temps))
    return out


def merge_labels(labels: Iterable[ResultLabel]) -> list[ResultLabel]:
    """One label per (kind, text), with the runs of all; approximate temperatures keep the record with the worst
    bound, listing every approximation met."""
    merged: dict[tuple[str, str], ResultLabel] = {}
    for lab in labels:
        key = (lab.kind, "" if lab.kind == APPROXIMATE else lab.text)
        old = merged.get(key)
        if old is None:
            merged[key] = lab
            continue
        runs = old.runs + tuple(r for r in lab.runs if r not in old.runs)
        record = old.record
        if lab.kind == APPROXIMATE:
            worst = lab.record if lab.bound_c > old.bound_c else old.record
            kinds = [a for r in (old.record, lab.record) for a in (r or {}).get("approximations") or []]
            record = {**(worst or {}), "approximations": list(dict.fromkeys(kinds))}
        merged[key] = replace(old, runs=runs, record=record)
    return list(merged.values())


def marks(labels: Iterable[ResultLabel]) -> str:
    """The marks of ``labels`` (``~``, ``†``, ``~†``), each once, or ``""``."""
    found = {lab.mark for lab in labels}
    return "".join(m for m in dict.fromkeys(MARKS.values()) if m in found)


def label_notes(items: Sequence[tuple[str | None, Sequence[ResultLabel], Sequence[str]]]) -> list[str]:
    """The footnotes of the labels of a table's rows, one per label (approximate temperatures: one for all rows).

    ``items``: (row name or None, its labels, every run of the row as ``FOLD/seedN``); a label of only some of a
    row's runs names them."""
    approx = [(name, lab) for name, labels, _ in items for lab in labels if lab.kind == APPROXIMATE]
    out = []
    if approx:
        names = ", ".join(dict.fromkeys(name for name, _ in approx if name))
        worst = max(lab.bound_c for _, lab in approx)
        kinds = sorted({a for _, lab in approx for a in (lab.record or {}).get("approximations") or []})
        out.append(
            f"{MARKS[APPROXIMATE]} measured on approximate temperatures ({names + ': ' if names else ''}"
            f"within {worst:g} C of DJI's SDK at worst; {', '.join(kinds) or 'approximate route'}; "
            f"docs/sensing.md)"
        )
    for name, labels, runs in items:
        for lab in labels:
            if lab.kind == APPROXIMATE:
                continue
            where = [name] if name else []
            if set(lab.runs) != set(runs):
                where.append(("run " if len(lab.runs) == 1 else "runs ") + ", ".join(lab.runs))
            scope = f" ({', '.join(where)})" if where else ""
            out.append(f"{lab.mark} {_PHRASES[lab.kind]}{scope}: {lab.text}")
    return out


# ---------------------------------------------------------------------------------------------------- runs
class StoredRun(Run):
    """One finished run as stored: its folder (a ``Run``), its ``metrics.json``, the labels it carries and its error
    analysis."""

    def __init__(self, run: Run, metrics: dict[str, Any]):
        self.key, self.path = run.key, run.path
        self.metrics = metrics

    @property
    def name(self) -> str:
        """``FOLD/seedN``: how labels and notes name the run within its entry."""
        return f"{self.key.fold}/seed{self.key.seed}"

    @cached_property
    def labels(self) -> list[ResultLabel]:
        return run_labels(self.metrics, self.name)

    @cached_property
    def config(self) -> dict[str, Any]:
        """The run's resolved configuration (``config.yaml``), ``{}`` when the run has none."""
        if not self.config_path.exists():
            return {}
        from harness.config import read_yaml

        cfg = read_yaml(self.config_path)
        return cfg if isinstance(cfg, dict) else {}

    @cached_property
    def _analysis(self) -> tuple[dict[str, Any] | None, str | None]:
        from harness.evaluation.analysis import analysis_of

        return analysis_of(self)

    @property
    def analysis(self) -> dict[str, Any] | None:
        """The run's stored error analysis (``analysis.json``, schema in ``harness/store.py``), read once; None when
        there is none (``analysis_missing`` says why: what a report shows in its place)."""
        return self._analysis[0]

    @property
    def analysis_missing(self) -> str | None:
        """Why the run has no error analysis (``no error analysis stored; rerun with --force``, unreadable, failed),
        or None."""
        return self._analysis[1]

    def screening_route(self) -> dict[str, Any] | None:
        """The run's held-out fold scored under the screening route (``screening_route.json``, written by
        ``harness score-route``; ``harness.screen.route``), or None when it was not scored so."""
        path = self.path / "screening_route.json"
        if not path.is_file():
            return None
        from harness.io import read_json

        result = read_json(path)
        return result if isinstance(result, dict) else None

    def ground_truth(self) -> dict[str, Any]:
        """The COCO ground truth the run was scored against (``gt.json``); a missing file is a ``StoreError``."""
        return self._json(self.gt_path, "ground truth")

    def predictions(self) -> list[dict[str, Any]]:
        """The run's COCO detections on its held-out images (``predictions.json``)."""
        return self._json(self.predictions_path, "predictions")

    def _json(self, path: Path, what: str) -> Any:
        from harness.io import read_json

        if not path.is_file():
            raise StoreError(
                f"{path}: missing; the run's {what} are needed here. Re-run the fold with `harness run "
                f"... --force` to write them"
            )
        return read_json(path)

    @cached_property
    def source(self) -> str:
        """The annotation source: ``dataset.gt`` of the run's config, else the ``-T``/``-RGB`` suffix a dataset
        gives its fold names (RGBT-Tiny), else ``-`` (the dataset has a single annotation set)."""
        ds = self.config.get("dataset")
        gt = ds.get("gt") if isinstance(ds, dict) else None
        if gt is not None:
            return SOURCE_LABELS.get(str(gt).strip().lower(), str(gt))
        for suffix in ("T", "RGB"):
            if self.key.fold.endswith(f"-{suffix}"):
                return suffix
        return NO_SOURCE


_METRICS_CACHE: dict[Path, tuple[tuple[int, int], dict[str, Any]]] = {}


def read_run(run: Run) -> StoredRun:
    """The stored run of ``run`` (``metrics.json`` cached by modification time and size: tables read the same file
    often)."""
    path = run.metrics_path
    try:
        st = path.stat()
        stamp = (st.st_mtime_ns, st.st_size)
    except OSError:
        stamp = (-1, -1)
    hit = _METRICS_CACHE.get(path)
    if not hit or hit[0] != stamp:
        hit = (stamp, run.read_metrics())
        _METRICS_CACHE[path] = hit
    return StoredRun(run, hit[1])


def average_seeds(dataset: str, fold: str, metrics: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The seed-averaged metrics of one fold, in the shape of metrics.json (support of the first seed)."""
    first = metrics[0]
    if len(metrics) == 1:
        out = dict(first)
        out["run"] = {**(first.get("run") or {}), "dataset": dataset, "fold": fold}
        return out
    head: dict[str, Any] = {
        k: _mean(m["metrics"].get(k) for m in metrics) for k in SEED_METRICS if any(k in m["metrics"] for m in metrics)
    }
    head["seeds"] = len(metrics)
    names: list[str] = []
    for m in metrics:
        names.extend(n for n in m.get("per_category", {}) if n not in names)
    per_category: dict[str, Any] = {}
    for name in names:
        entries = [m["per_category"].get(name) or {} for m in metrics]
        rec: dict[str, Any] = {k: _mean(e.get(k) for e in entries) for k in SEED_CATEGORY_METRICS}
        rec["instances"] = int(entries[0].get("instances") or 0)
        per_category[name] = rec
    return {
        "run": {"dataset": dataset, "fold": fold, "seeds": [m.get("run", {}).get("seed") for m in metrics]},
        "support": first.get("support") or {},
        "metrics": head,
        "per_category": per_category,
    }


@dataclass
class FoldResult:
    """One held-out fold of one entry: its runs (one per seed) and their seed-averaged metrics."""

    fold: str
    runs: list[StoredRun]
    metrics: dict[str, Any]  # the shape of metrics.json: run, support, metrics, per_category
    #: label from ``check_sample_matched`` when the seeds of this fold were scored on different samples
    seed_mismatch: str | None = None

    @property
    def seeds(self) -> list[int]:
        return sorted(r.key.seed for r in self.runs)

    @property
    def support(self) -> dict[str, Any]:
        return self.metrics.get("support") or {}

    @property
    def images(self) -> int:
        return int(self.support.get("images") or 0)

    @property
    def instances(self) -> int:
        return int(self.support.get("instances") or 0)

    @property
    def labels(self) -> list[ResultLabel]:
        return merge_labels(lab for r in self.runs for lab in r.labels)

    @property
    def source(self) -> str:
        return self.runs[0].source


def fold_result(dataset: str, fold: str, runs: Sequence[StoredRun]) -> FoldResult:
    """The runs of one fold (one per seed) as a fold result: seeds averaged, a seed mismatch labelled."""
    from harness.evaluation import check_sample_matched

    runs = sorted(runs, key=lambda r: r.key.seed)
    label = None
    if len(runs) > 1:
        label = check_sample_matched({f"seed{r.key.seed}": r.metrics for r in runs}, allow=True)
    return FoldResult(fold, runs, average_seeds(dataset, fold, [r.metrics for r in runs]), label)


@dataclass
class Entry:
    """One (dataset, detector, encoding) with its fold results, in fold order."""

    dataset: str
    detector: str
    encoding: str
    folds: dict[str, FoldResult] = field(default_factory=dict)

    @property
    def label(self) -> str:
        return f"{self.detector}/{self.encoding}"

    @property
    def fold_names(self) -> list[str]:
        return list(self.folds)

    @property
    def seeds(self) -> list[int]:
        return sorted({s for f in self.folds.values() for s in f.seeds})

    @property
    def images(self) -> int:
        return sum(f.images for f in self.folds.values())

    @property
    def instances(self) -> int:
        return sum(f.instances for f in self.folds.values())

    def runs(self) -> list[StoredRun]:
        return [r for f in self.folds.values() for r in f.runs]

    def fold_metrics(self) -> list[dict[str, Any]]:
        return [f.metrics for f in self.folds.values()]

    def aggregate(self) -> dict[str, Any]:
        """``aggregate_folds`` over the fold results (mean and sample SD over held-out folds)."""
        from harness.evaluation import aggregate_folds

        return aggregate_folds(self.fold_metrics())

    def restricted(self, folds: Iterable[str]) -> Entry:
        """The same entry with only ``folds`` (in this entry's order)."""
        keep = set(folds)
        return Entry(self.dataset, self.detector, self.encoding, {f: r for f, r in self.folds.items() if f in keep})

    def by_source(self) -> dict[str, Entry]:
        """The entry split by annotation source (``StoredRun.source``), sources sorted."""
        sources = sorted({fr.source for fr in self.folds.values()})
        return {s: self.restricted(f for f, fr in self.folds.items() if fr.source == s) for s in sources}

    @property
    def labels(self) -> list[ResultLabel]:
        """The labels of every run of the entry, merged (``merge_labels``)."""
        return merge_labels(lab for f in self.folds.values() for lab in f.labels)

    def notes_item(self, name: str | None = "") -> tuple[str | None, list[ResultLabel], list[str]]:
        """This entry's part of ``label_notes``: (name, labels, runs); ``name`` defaults to ``label``."""
        return (self.label if name == "" else name), self.labels, [r.name for r in self.runs()]

    def environment(self) -> dict[str, Any]:
        """The environment record of the first run that has one (device, threads, versions)."""
        return next((r.metrics["environment"] for r in self.runs() if r.metrics.get("environment")), {})

    def complexity(self) -> dict[str, Any]:
        """Params/GFLOPs measured in this entry's own runs (``metrics.json`` ``complexity``, at 640 px).

        ``{}`` when no run recorded one; ``{"mixed": [labels]}`` when its runs were built with different model
        options (their numbers would not describe one model)."""
        from harness.complexity import numbers, options_label

        found: dict[str, dict[str, Any]] = {}
        for r in self.runs():
            nums = numbers(r.metrics.get("complexity"))
            if nums:
                found.setdefault(options_label(nums["model_options"]) + f"|{nums['params_m']}", nums)
        if len(found) > 1:
            return {"mixed": sorted({options_label(n["model_options"]) or "defaults" for n in found.values()})}
        return next(iter(found.values()), {})

    def options_label(self) -> str:
        """The model options the runs were built with (``scale=n``), ``mixed: a; b`` when they differ, or ``""``."""
        from harness.complexity import options_label

        c = self.complexity()
        if c.get("mixed"):
            return "mixed: " + "; ".join(c["mixed"])
        return options_label(c.get("model_options") or {})

    def unmeasured_runs(self) -> list[str]:
        """Runs of this entry whose metrics.json holds no complexity record (made before it was measured)."""
        return [str(r.key) for r in self.runs() if not (r.metrics.get("complexity") or {}).get("gflops")]

    def train_imgsz(self) -> int | None:
        return next((int(s) for r in self.runs() if (s := (r.metrics.get("train") or {}).get("imgsz"))), None)


def group_entries(dataset: str, runs: Iterable[StoredRun]) -> list[Entry]:
    """Runs of ``dataset`` as entries: (detector, encoding) in natural order, folds in natural order, seeds averaged."""
    grouped: dict[tuple[str, str], dict[str, list[StoredRun]]] = {}
    for run in runs:
        grouped.setdefault((run.key.detector, run.key.encoding), {}).setdefault(run.key.fold, []).append(run)
    entries = []
    for (det, enc), folds in sorted(grouped.items(), key=lambda kv: (natural_key(kv[0][0]), natural_key(kv[0][1]))):
        entry = Entry(dataset, det, enc)
        for fold in sorted(folds, key=natural_key):
            entry.folds[fold] = fold_result(dataset, fold, folds[fold])
        entries.append(entry)
    return entries


class StoreView:
    """Read-only, report-oriented view of a results store."""

    def __init__(self, store: Store | str | Path, references: Any = None):
        self.store = store if isinstance(store, Store) else Store(store)
        if not self.store.root.is_dir():
            raise StoreError(
                f"{self.store.root}: no results store here; pass --store (the folder `harness run` wrote into)"
            )
        self._entries: dict[str, list[Entry]] = {}
        #: files that could not be read (named, with the reason); the report lists them instead of failing
        self.problems: list[str] = []
        #: reference results read beside the store (``harness.references.ReferenceSet``, with its ``siblings`` of
        #: other datasets): their runs join the store's as ``ref:<detector>`` entries once the store's runs of that
        #: dataset are checked to use the same samples
        self.references = references
        self._reference_runs: dict[str, list[StoredRun]] = {}
        #: per dataset: notes on the reference results (what they are, which folds they lack)
        self.reference_notes: dict[str, list[str]] = {}
        self._references_paired = False

    @property
    def root(self) -> Path:
        return self.store.root

    def reference_sets(self) -> list[Any]:
        """Every reference store read beside the store (one per dataset), or none."""
        refs = self.references
        if refs is None:
            return []
        return list(refs.all()) if hasattr(refs, "all") else [refs]

    def references_for(self, dataset: str) -> Any:
        """The reference store of ``dataset`` read beside the store, or None."""
        return next((r for r in self.reference_sets() if r.dataset == dataset), None)

    def drop_references(self, dataset: str) -> None:
        """Read no reference results of ``dataset`` (those of other datasets stay)."""
        kept = [r for r in self.reference_sets() if r.dataset != dataset]
        if not kept:
            self.references = None
            return
        first = kept[0]
        if hasattr(first, "siblings"):
            import dataclasses

            first = dataclasses.replace(first, siblings=kept[1:])
        self.references = first

    def problem(self, text: str) -> None:
        """Record (and log) a file that could not be read; each is recorded once."""
        if text not in self.problems:
            log.warning("%s", text)
            self.problems.append(text)

    def finished_runs(self, dataset: str) -> list[StoredRun]:
        """Finished runs of ``dataset``; a run whose status or metrics cannot be read is skipped and recorded."""
        out = []
        for run in self.store.runs(dataset=dataset, finished_only=False):
            try:
                if not run.is_finished():
                    continue
                stored = read_run(run)
            except HarnessError as exc:
                self.problem(f"{run.key}: skipped, {exc}")
                continue
            missing = [k for k in ("support", "metrics", "per_category") if not isinstance(stored.metrics.get(k), dict)]
            if missing:
                self.problem(f"{run.key}: skipped, {run.metrics_path} has no {', '.join(missing)} section")
                continue
            out.append(stored)
        if self.references_for(dataset) is not None:
            out += self.reference_runs(dataset, out)
        return out

    def reference_runs(self, dataset: str, own: Sequence[StoredRun]) -> list[StoredRun]:
        """The reference results' runs of ``dataset``, after checking that ``own`` (the store's runs) used the same
        samples (``harness.references.check_matched``: a mismatch is an error naming what differs)."""
        if dataset not in self._reference_runs:
            refs = self.references_for(dataset)  # a harness.references.ReferenceSet: it checks the store's runs
            notes = refs.check_matched(own)
            runs = refs.runs()
            for text in refs.problems:
                self.problem(f"reference results: {text}")
            self._reference_runs[dataset] = runs
            trained = [r for r in own if not r.metrics.get("external")]
            same = refs.same_training(trained) if trained else True
            self.reference_notes[dataset] = (
                [
                    f"Reference results ({len(runs)} runs, entries named ref:DETECTOR): {refs.describe()}; read from "
                    f"{refs.root}. "
                    + (
                        "The store's runs were checked against the references' samples: identical content digests "
                        "except where a note below measures a difference within a library release's tolerance."
                        if any(n.startswith("Compared within the tolerance") for n in notes)
                        else "The store's runs were checked to use the same samples (content digests)."
                    )
                ]
                + (
                    [
                        "The store's runs were trained at another image size or number of epochs than the reference "
                        "results: they are shown side by side, not paired (a comparison of two training budgets, "
                        "not of detectors)."
                    ]
                    if not same
                    else []
                )
                + notes
            )
            self._references_paired = same
        return list(self._reference_runs[dataset])

    def pairs_with_references(self, dataset: str) -> bool:
        """Whether paired comparisons may pair the store's entries with the reference entries of ``dataset``."""
        if self.references_for(dataset) is None:
            return False
        if dataset not in self._reference_runs:
            self.finished_runs(dataset)
        return self._references_paired

    # ------------------------------------------------------------------------------------------ what is there
    def datasets(self) -> list[str]:
        """Datasets with finished runs or sensing analyses, sorted."""
        names = {r.key.dataset for r in self.store.runs(finished_only=False)}
        for p in self.root.glob("*/_sensing/*.json"):
            names.add(p.parent.parent.name)
        names.update(r.dataset for r in self.reference_sets())
        return sorted((n for n in names if not n.startswith("_")), key=natural_key)

    def unfinished(self, dataset: str) -> list[tuple[str, str]]:
        """(run key, state) of runs in the store that are not finished (running, failed, or without metrics)."""
        out = []
        for r in self.store.runs(dataset=dataset, finished_only=False):
            try:
                if not r.is_finished():
                    state = (r.status() or {}).get("state", "unknown")
                    if state == "running" and not r.is_held():  # its process is gone (killed, crashed)
                        state = "interrupted"
                    out.append((str(r.key), state))
            except HarnessError:
                out.append((str(r.key), "unreadable status"))
        return out

    def entries(self, dataset: str) -> list[Entry]:
        """Every (detector, encoding) of ``dataset`` with its folds (natural order) and seeds averaged per fold."""
        if dataset not in self._entries:
            self._entries[dataset] = group_entries(dataset, self.finished_runs(dataset))
        return self._entries[dataset]

    def entry(self, dataset: str, spec: str) -> Entry:
        """The entry named ``DETECTOR`` or ``DETECTOR/ENCODING``; ambiguity and unknown names are clear errors.

        A detector name may itself hold a ``/`` (``external/NAME``, scored with ``harness score``): the whole name
        is tried as a detector first, then the part after the last ``/`` as the encoding."""
        entries = self.entries(dataset)
        found = [e for e in entries if e.detector == spec] or [e for e in entries if e.label == spec]
        available = ", ".join(e.label for e in entries) or "none"
        if not found:
            det = spec if spec.startswith("external/") else spec.partition("/")[0]
            if det.startswith(REFERENCE_PREFIX):  # a reference result: read with the references, never run here
                raise StoreError(
                    f"{self.root}: {spec!r} is a reference result, not a run of this store (available: "
                    f"{available}); give the reference results with --reference-results shipped (or their folder)"
                )
            how = (
                f"harness score --dataset {dataset} --name {det.partition('/')[2]} ..."
                if det.startswith("external/")
                else f"harness run --detector {det} --dataset {dataset}"
            )
            raise StoreError(
                f"{self.root}: no finished runs of {spec!r} on dataset {dataset!r} (available: "
                f"{available}); run `{how}` into this store"
            )
        if len(found) > 1:
            raise HarnessError(
                f"{spec!r} has runs with several encodings on {dataset!r} "
                f"({', '.join(e.label for e in found)}); name one as DETECTOR/ENCODING"
            )
        return found[0]

    # ------------------------------------------------------------------------------------------ other files
    def sensing_stage(self, dataset: str) -> bool:
        """Whether ``dataset`` has a sensing stage (registration, warp), as its runs recorded it
        (``<dataset>/_dataset.json``). A store written before runs recorded it: the installed plugin's
        ``DatasetSpec.sensing_stage``; True when neither knows (the report then keeps the sensing sections)."""
        from harness.io import read_json

        path = self.store.dataset_path(dataset)
        try:
            info = read_json(path) if path.exists() else None
        except HarnessError as exc:
            self.problem(f"{path}: unreadable ({exc})")
            info = None
        if isinstance(info, dict) and isinstance(info.get("sensing_stage"), bool):
            return info["sensing_stage"]
        from harness.plugins import get_host

        try:
            return bool(get_host().dataset(dataset).sensing_stage)
        except HarnessError:
            return True

    def sensing(self, dataset: str, analysis: str) -> dict[str, Any] | None:
        """``<dataset>/_sensing/<analysis>.json`` or None; an unreadable file raises a ``DataError`` naming it."""
        from harness.errors import DataError
        from harness.io import read_json

        path = self.store.sensing_path(dataset, analysis)
        if not path.exists():
            return None
        data = read_json(path)
        if not isinstance(data, dict):
            raise DataError(f"{path}: expected a JSON object")
        return data
