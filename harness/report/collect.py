"""Reading the results store for reports: finished runs grouped into entries, seeds averaged per fold.

A report reads nothing but the store (``harness/store.py``): ``metrics.json`` of finished runs, ``gt.json`` and
``predictions.json`` for re-scoring, ``_profiles/<detector>.json`` and ``<dataset>/_sensing/<analysis>.json``.

Vocabulary used by every table:

* an **entry** is one (dataset, detector, encoding): the rows of the seed's tables;
* a **fold result** is one held-out fold of an entry with its seeds averaged (each metric the mean over the
  seeds that define it); its support is the support the seeds share (seeds scored on different samples are a
  mismatch, labelled like any other);
* the headline numbers of an entry are ``harness.evaluation.aggregate_folds`` over its fold results: mean and
  sample SD over the held-out folds, a category without ground truth in a fold left out of that category's mean.
"""

from __future__ import annotations

import logging
import math
import re
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from harness.errors import HarnessError, StoreError
from harness.store import Run, Store

log = logging.getLogger(__name__)

#: Headline metrics averaged over seeds within a fold.
SEED_METRICS = ("mAP50", "mAP50_95", "precision", "recall", "f1")
#: Per-category metrics averaged over seeds within a fold.
SEED_CATEGORY_METRICS = ("AP50", "AP50_95")


def natural_key(text: str) -> list[Any]:
    """Sort key that puts ``P2`` before ``P10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", text)]


def _mean(values: Iterable[Any]) -> float | None:
    present = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return statistics.fmean(present) if present else None


@dataclass
class FoldResult:
    """One held-out fold of one entry: its runs (one per seed) and their seed-averaged metrics."""

    fold: str
    runs: list[Run]
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

    def fold_metrics(self) -> list[dict[str, Any]]:
        return [f.metrics for f in self.folds.values()]

    def aggregate(self) -> dict[str, Any]:
        """``aggregate_folds`` over the fold results (mean and sample SD over held-out folds)."""
        from harness.evaluation import aggregate_folds

        return aggregate_folds(self.fold_metrics())

    def temperatures(self) -> dict[str, Any] | None:
        """How far the thermal input of this entry's runs is from DJI's own temperatures: ``None`` for exact ones;
        for runs on approximate temperatures (``metrics.json`` ``temperatures``) the record with the worst bound."""
        found = [m["temperatures"] for m in self.fold_metrics() if isinstance(m.get("temperatures"), dict)]
        return max(found, key=lambda t: float(t.get("bound_c") or 0.0)) if found else None

    def environment(self) -> dict[str, Any]:
        """The environment record of the first run that has one (device, threads, versions)."""
        for f in self.folds.values():
            for r in f.runs:
                env = _read_metrics(r).get("environment")
                if env:
                    return env
        return {}

    def complexity(self) -> dict[str, Any]:
        """Params/GFLOPs measured in this entry's own runs (``metrics.json`` ``complexity``, at 640 px).

        ``{}`` when no run recorded one; ``{"mixed": [labels]}`` when its runs were built with different model
        options (their numbers would not describe one model)."""
        from harness.complexity import numbers, options_label

        found: dict[str, dict[str, Any]] = {}
        for f in self.folds.values():
            for r in f.runs:
                nums = numbers(_read_metrics(r).get("complexity"))
                if nums:
                    found.setdefault(options_label(nums["model_options"]) + f"|{nums['params_m']}", nums)
        if len(found) > 1:
            return {"mixed": sorted({options_label(n["model_options"]) or "defaults" for n in found.values()})}
        return next(iter(found.values()), {})

    def unmeasured_runs(self) -> list[str]:
        """Runs of this entry whose metrics.json holds no complexity record (made before it was measured)."""
        return [str(r.key) for f in self.folds.values() for r in f.runs
                if not (_read_metrics(r).get("complexity") or {}).get("gflops")]

    def train_imgsz(self) -> int | None:
        for f in self.folds.values():
            for r in f.runs:
                size = (_read_metrics(r).get("train") or {}).get("imgsz")
                if size:
                    return int(size)
        return None


_METRICS_CACHE: dict[Path, tuple[float, dict[str, Any]]] = {}


def _read_metrics(run: Run) -> dict[str, Any]:
    """``run.read_metrics()`` cached by modification time (tables read the same file many times)."""
    path = run.metrics_path
    mtime = path.stat().st_mtime if path.exists() else -1.0
    hit = _METRICS_CACHE.get(path)
    if hit and hit[0] == mtime:
        return hit[1]
    data = run.read_metrics()
    _METRICS_CACHE[path] = (mtime, data)
    return data


def average_seeds(dataset: str, fold: str, metrics: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The seed-averaged metrics of one fold, in the shape of metrics.json (support of the first seed)."""
    first = metrics[0]
    if len(metrics) == 1:
        out = dict(first)
        out["run"] = {**(first.get("run") or {}), "dataset": dataset, "fold": fold}
        return out
    head = {k: _mean(m["metrics"].get(k) for m in metrics) for k in SEED_METRICS if any(k in m["metrics"] for m in metrics)}
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
    out = {"run": {"dataset": dataset, "fold": fold, "seeds": [m.get("run", {}).get("seed") for m in metrics]},
           "support": first.get("support") or {}, "metrics": head, "per_category": per_category}
    labels = [lab for m in metrics for lab in m.get("labels") or []]
    if labels:  # a risk accepted when a seed was stored (harness score --allow-implausible, eval.allow_degenerate)
        out["labels"] = list(dict.fromkeys(labels))
    return out


class StoreView:
    """Read-only, report-oriented view of a results store."""

    def __init__(self, store: Store | str | Path):
        self.store = store if isinstance(store, Store) else Store(store)
        if not self.store.root.is_dir():
            raise StoreError(f"{self.store.root}: no results store here; pass --store (the folder `harness run` wrote "
                             f"into)")
        self._entries: dict[str, list[Entry]] = {}
        self._profiles: dict[str, dict[str, Any]] | None = None
        #: files that could not be read (named, with the reason); the report lists them instead of failing
        self.problems: list[str] = []

    @property
    def root(self) -> Path:
        return self.store.root

    def _problem(self, text: str) -> None:
        if text not in self.problems:
            log.warning("%s", text)
            self.problems.append(text)

    def finished_runs(self, dataset: str) -> list[Run]:
        """Finished runs of ``dataset``; a run whose status or metrics cannot be read is skipped and recorded."""
        out = []
        for run in self.store.runs(dataset=dataset, finished_only=False):
            try:
                if not run.is_finished():
                    continue
                m = _read_metrics(run)
            except HarnessError as exc:
                self._problem(f"{run.key}: skipped, {exc}")
                continue
            missing = [k for k in ("support", "metrics", "per_category") if not isinstance(m.get(k), dict)]
            if missing:
                self._problem(f"{run.key}: skipped, {run.metrics_path} has no {', '.join(missing)} section")
                continue
            out.append(run)
        return out

    # ------------------------------------------------------------------------------------------ what is there
    def datasets(self) -> list[str]:
        """Datasets with finished runs or sensing analyses, sorted."""
        names = {r.key.dataset for r in self.store.runs(finished_only=False)}
        for p in self.root.glob("*/_sensing/*.json"):
            names.add(p.parent.parent.name)
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
        if dataset in self._entries:
            return self._entries[dataset]
        from harness.evaluation import check_sample_matched

        grouped: dict[tuple[str, str], dict[str, list[Run]]] = {}
        for run in self.finished_runs(dataset):
            grouped.setdefault((run.key.detector, run.key.encoding), {}).setdefault(run.key.fold, []).append(run)
        entries = []
        for (det, enc), folds in sorted(grouped.items(), key=lambda kv: (natural_key(kv[0][0]), natural_key(kv[0][1]))):
            entry = Entry(dataset, det, enc)
            for fold in sorted(folds, key=natural_key):
                runs = sorted(folds[fold], key=lambda r: r.key.seed)
                metrics = [_read_metrics(r) for r in runs]
                label = None
                if len(metrics) > 1:
                    label = check_sample_matched({f"seed{r.key.seed}": m for r, m in zip(runs, metrics)}, allow=True)
                entry.folds[fold] = FoldResult(fold, runs, average_seeds(dataset, fold, metrics), label)
            entries.append(entry)
        self._entries[dataset] = entries
        return entries

    def entry(self, dataset: str, spec: str) -> Entry:
        """The entry named ``DETECTOR`` or ``DETECTOR/ENCODING``; ambiguity and unknown names are clear errors.

        A detector name may itself hold a ``/`` (``external/NAME``, scored with ``harness score``): the whole name
        is tried as a detector first, then the part after the last ``/`` as the encoding."""
        entries = self.entries(dataset)
        found = [e for e in entries if e.detector == spec] or [e for e in entries if e.label == spec]
        available = ", ".join(e.label for e in entries) or "none"
        if not found:
            det = spec if spec.startswith("external/") else spec.partition("/")[0]
            how = (f"harness score --dataset {dataset} --name {det.partition('/')[2]} ..."
                   if det.startswith("external/") else f"harness run --detector {det} --dataset {dataset}")
            raise StoreError(f"{self.root}: no finished runs of {spec!r} on dataset {dataset!r} (available: "
                             f"{available}); run `{how}` into this store")
        if len(found) > 1:
            raise HarnessError(f"{spec!r} has runs with several encodings on {dataset!r} "
                               f"({', '.join(e.label for e in found)}); name one as DETECTOR/ENCODING")
        return found[0]

    # ------------------------------------------------------------------------------------------ other files
    def profiles(self) -> dict[str, dict[str, Any]]:
        """``_profiles/<detector>.json`` by detector; an unreadable file is skipped and recorded."""
        if self._profiles is None:
            from harness.io import read_json

            self._profiles = {}
            for path in sorted((self.root / "_profiles").glob("*.json")):
                try:
                    data = read_json(path)
                except HarnessError as exc:
                    self._problem(f"profile skipped: {exc}")
                    continue
                if isinstance(data, dict):
                    self._profiles[path.stem] = data
                else:
                    self._problem(f"profile skipped: {path} does not hold a JSON object")
        return self._profiles

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


def profile_numbers(profile: Mapping[str, Any] | None) -> dict[str, Any]:
    """Params (M), GFLOPs (paper convention) and the profiling conditions of a ``_profiles/<detector>.json``."""
    if not profile:
        return {}
    params = profile.get("params") or {}
    flops = profile.get("flops") or {}
    count = params.get("fused", params.get("total"))
    paper = flops.get("paper") or {}
    exact = flops.get("exact") or {}
    return {
        "params_m": None if count is None else float(count) / 1e6,
        "gflops": paper.get("gflops"),
        "gflops_exact": exact.get("gflops"),
        "convention": paper.get("convention"),
        "imgsz": profile.get("imgsz"),
        "input_kind": profile.get("input_kind"),
        "num_classes": profile.get("num_classes"),
        "machine": (profile.get("environment") or {}).get("machine"),
        "torch": (profile.get("environment") or {}).get("torch"),
    }
