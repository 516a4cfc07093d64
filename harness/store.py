"""The results store: one folder per run, every file written atomically, readable by reports alone.

Layout under the store root (``--store``, default ``results/<profile>``)::

    <dataset>/<detector>/<encoding>/<fold>/seed<seed>/
        config.yaml          the fully resolved configuration of the run; ``meta`` holds its identity: the
                             prepared data (``prepared_key``, ``prepared_fingerprint``, ``prepared_samples``) and
                             ``detector_code``, a digest of the detector plugin's code (its modules and the built-in
                             ones it imports; ``harness.cache.key.detector_code``), with ``detector_code_files``
                             ({file: digest}) naming what changed; runs stored before it existed have none
        status.json          {"state": "running" | "finished" | "failed", "config_hash", "started", "updated", ...}
        metrics.json         evaluation of the held-out fold (schema below)
        predictions.json     COCO-format detections on the held-out images (category ids as in the GT), at the
                             full precision they were scored at
        gt.json              the COCO ground truth the predictions were scored against (for re-scoring, bootstrap)
        analysis.json        error analysis of the held-out predictions (``ANALYSIS_SCHEMA`` below), computed once
                             when the run is scored; absent for runs stored before it existed
        log.jsonl            one JSON object per epoch
        checkpoints/         last.pt (resume) and best.pt (by fitness); a run finished under `harness run
                             --keep-weights final` keeps only the one that predicted the held-out fold
        screening_route.json the held-out fold scored under the registration route a new flight gets, written by
                             `harness score-route` (``harness.screen.route``); absent until then
    <dataset>/_sensing/<analysis>.json      sensing-level analyses (registration error, displacement study)
    <dataset>/_dataset.json                  {"dataset", "thermal", "sensing_stage"}: written with the runs, so that
                                             a report knows the dataset without its plugin
    _profiles/<detector>.json                `harness profile`: parameters, FLOPs, latency of a detector (reports
                                             read the complexity each run recorded, not these files)

``metrics.json`` (``METRICS_SCHEMA``)::

    {
      "schema": 1,
      "run":     {"dataset", "detector", "encoding", "fold", "seed"},
      "support": {"images": int, "instances": int, "image_ids_sha1": str, "categories": {name: instances}},
      "metrics": {"mAP50": float, "mAP50_95": float, "precision": float, "recall": float,
                  "conf_threshold": float, "coco_stats": [12 floats], "engine": str},
      "per_category": {name: {"AP50": float | null, "AP50_95": float | null, "instances": int}},
      "model":   {"params": int, ...},               # optional
      "complexity": {"model_options", "params", "params_fused", "bn_folded", "unused_params",
                     "gflops": {"<imgsz>": {"paper", "exact"}, "640": {...}}, ...},   # harness.complexity
      "train":   {"epochs": int, "best_epoch": int, "time_s": float, ...,   # optional
                  "plateau": {"slope_per_epoch", "epochs", "reached", "metric"}},   # harness.engine.trainer
      "selection": {"protocol": "last" | "validation" | "held-out", "weights", "best_epoch", "epochs_run",
                    "validation_groups", ...},      # how the weights that predicted the held-out fold were chosen
      "environment": {...},                          # optional: versions, device, threads, packages, torch_build,
                                                     # kernels, cpu (harness.provenance)
      "degenerate_detections": {"returned", "non_finite", "inverted", "zero_size", "outside_image", "examples"},
                                                     # trained runs: boxes the detector returned, those dropped
      "external": {...},                             # runs of `harness score`: identity and matching counts
      "labels": [str, ...],                          # optional: a risk accepted when the result was stored
      "input_risks": [str, ...],                     # trained runs: dataset input risks accepted (inputs.accept)
      "samples": {"encoding", "train", "held_out", "aligned", "prepared"},  # trained runs: content digests of the
                                                     # samples trained on and
                                                     # scored (PreparedDataset.content_digest); reference results
                                                     # are matched on them (harness.references)
      "temperatures": {"label", "samples", "bound_c", "approximations"}   # optional: approximate temperatures
    }

The last three are read as one concept, a result's labels (``harness.report.reader.ResultLabel``), shown beside
the numbers they concern in every table.

Numbers are fractions in 0..1. A category with no ground truth in the fold has ``AP50 = null``; fold aggregation
skips it rather than counting it as zero.

``analysis.json`` (``ANALYSIS_SCHEMA``; ``harness.evaluation.analysis``, definitions in docs/evaluation.md 4c),
compact JSON; IoU 0.50, COCO's matching, the operating point of ``metrics.conf_threshold``::

    {
      "schema": 1,
      "run": {"dataset", "detector", "encoding", "fold", "seed"},
      "conf_threshold": float | null, "operating_point": str, "categories": [name, ...],
      "tide": {"mAP50": float | null,                          # = metrics.mAP50
               "dAP50": {"classification", "localisation", "both", "duplicate", "background", "missed": float},
               "special": {"false_positives", "false_negatives": float},
               "counts": {type: int}, "counts_per_category": {name: {type: int}},
               "iou_foreground": 0.5, "iou_background": 0.1, "false_positives", "true_positives", "instances": int},
      "confusion": {"rows": "predicted", "columns": "ground truth", "labels": [name, ..., "background"],
                    "matrix": [[int]], "iou": 0.5, "conf_threshold": float | null},
      "pr": {"iou": 0.5, "recall": [101 floats], "definition": str,
             "categories": {name: {"instances", "detections": int, "AP50": float | null, "max_recall": float | null,
                                   "precision": [101 floats] | null, "scores": [101 floats] | null}}},
      "sizes": {"matching": "iou", "area": str,
                "coco": {"ranges": {bin: [lo, hi]}, "AP50": {bin: float | null}, "AP50_95": {...},
                         "instances": {bin: int}, "per_category": {name: {"AP50", "AP50_95", "instances"}}},
                "safit": {...}},                             # tiny-object datasets only
      "images": {"image_id": [...], "gt": [int], "tp": [int], "fp": [int], "fn": [int]},   # gt.json image order
      "gt_found": [1 | 0 | -1, ...],                         # gt.json annotation order: found, missed, crowd
      "worst": {name: {"misses": [{"image_id", "annotation_id", "bbox", "area", "reason", "best_iou", "score"}],
                       "false_positives": [{"image_id", "bbox", "score", "error", "iou", "kept", "gt_category",
                                            "annotation_id"}]}}
    }

or ``{"schema": 1, "run": {...}, "error": str}`` when the analysis failed (the run itself is stored). Runs stored
before the analysis existed have no ``analysis.json``: ``Run.read_analysis()`` returns None.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import socket
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

from harness.errors import HarnessError, StoreError
from harness.io import atomic_write_json, atomic_write_text, read_json

log = logging.getLogger(__name__)

METRICS_SCHEMA = 1
ANALYSIS_SCHEMA = 1  # harness.evaluation.analysis.ANALYSIS_SCHEMA
STATES = ("running", "finished", "failed")


@dataclass(frozen=True, order=True)
class RunKey:
    """What identifies a run: the five levels of the store's folder layout."""

    dataset: str
    detector: str
    encoding: str
    fold: str
    seed: int = 0

    def parts(self) -> tuple[str, str, str, str, str]:
        return (self.dataset, detector_folder(self.detector), self.encoding, _safe(self.fold), f"seed{self.seed}")

    def __str__(self) -> str:
        return f"{self.dataset}/{self.detector}/{self.encoding}/{self.fold}/seed{self.seed}"


#: Predictions scored from another codebase are stored as detector ``external/NAME``, in the folder ``external.NAME``.
EXTERNAL = "external/"
_EXTERNAL_FOLDER = "external."


def detector_folder(detector: str) -> str:
    """The store folder of a detector name (``external/NAME`` -> ``external.NAME``; others unchanged)."""
    if detector.startswith(EXTERNAL):
        return _EXTERNAL_FOLDER + _safe(detector[len(EXTERNAL) :])
    return detector


def detector_name(folder: str) -> str:
    """Inverse of ``detector_folder``."""
    return EXTERNAL + folder[len(_EXTERNAL_FOLDER) :] if folder.startswith(_EXTERNAL_FOLDER) else folder


def _safe(part: str) -> str:
    """Fold names such as 'P4+P5' are fine as folder names; path separators and '..' are not."""
    if not part or "/" in part or "\\" in part or part in (".", "..") or part.startswith("_"):
        raise StoreError(f"{part!r} cannot be used as a folder name in the results store")
    return part


def config_hash(config: dict[str, Any]) -> str:
    """Stable hash of a resolved config (key order does not matter)."""
    return hashlib.sha1(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


def image_ids_hash(image_ids: list[int]) -> str:
    return hashlib.sha1(",".join(str(int(i)) for i in sorted(image_ids)).encode()).hexdigest()


def slim_final_checkpoint(path: Path) -> bool:
    """Rewrite a finished run's ``last.pt`` as the weights that predicted its held-out fold alone (the EMA weights, as
    ``best.pt`` holds them), without the optimiser, random and schedule state that only a resume needs: a quarter of
    the size. ``harness screen --run`` and ``state_dict_of`` read it as before. Returns whether it was rewritten."""
    from harness.engine import checkpoint as ckpt

    try:
        obj = ckpt.load(path)
    except HarnessError as exc:  # not a checkpoint this harness wrote: left as it is
        log.warning("%s: kept as it is (%s)", path, exc)
        return False
    if obj.get("format") != ckpt.FORMAT or "optimizer" not in obj:
        return False  # already slim, or not a harness training checkpoint
    ckpt.save(
        path,
        {
            "format": ckpt.FORMAT,
            "version": obj.get("version", ckpt.VERSION),
            "epoch": obj.get("epoch"),
            "done": bool(obj.get("done", True)),
            "model": ckpt.state_dict_of(obj),
        },
    )
    return True


class RunBusyError(StoreError):
    """Another process holds the run's lock (it is training that run now)."""


class _RunFile:
    """A file (or folder) of a run's folder, as a read-only attribute: ``run.metrics_path``.

    ``packed``: the file may be stored gzip-compressed as ``<name>.gz`` (the shipped reference results keep their
    ground truth, predictions and training log so); the path is then that of the ``.gz`` file when only it exists, and
    ``harness.io.read_json`` reads either."""

    def __init__(self, name: str, packed: bool = False):
        self.name, self.packed = name, packed

    def __get__(self, run: Run, owner: type | None = None) -> Path:
        path = run.path / self.name
        return packed_or_plain(path) if self.packed else path


def packed_or_plain(path: Path) -> Path:
    """``path``, or, when only that exists, its gzip-compressed ``<name>.gz`` or (detections) its packed columns
    ``<stem>.npz`` (``harness.io.pack_detections``); ``read_json`` reads each."""
    if not path.exists():
        for other in (path.with_name(path.name + ".gz"), path.with_suffix(".npz")):
            if other.exists():
                return other
    return path


class Run:
    """The folder of one run and typed access to its files."""

    def __init__(self, root: Path, key: RunKey):
        self.key = key
        self.path = Path(root).joinpath(*key.parts())

    # paths
    config_path = _RunFile("config.yaml")
    status_path = _RunFile("status.json")
    metrics_path = _RunFile("metrics.json")
    predictions_path = _RunFile("predictions.json", packed=True)
    gt_path = _RunFile("gt.json", packed=True)
    log_path = _RunFile("log.jsonl", packed=True)
    checkpoint_dir = _RunFile("checkpoints")
    lock_path = _RunFile(".lock")

    @contextlib.contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold the run's lock (an advisory ``flock`` on ``.lock``) while the block runs.

        Two processes given the same run (two sweeps, or a sweep and a ``harness run`` on one store) cannot train it
        at once: the second gets a ``RunBusyError`` naming the holder. The operating system drops the lock when its
        holder exits, even after ``kill -9``, so a crashed run never leaves a stale lock behind.
        """
        import fcntl

        self.recover()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            lock = open(self.lock_path, "a+", encoding="utf-8")
        except OSError as exc:
            raise StoreError(
                f"cannot write run {self.key} into the results store: {exc.strerror or exc} "
                f"({exc.filename or self.path}); make the store writable or choose another --store"
            ) from None
        with lock as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                f.seek(0)
                holder = f.read().strip() or "unknown process"
                raise RunBusyError(
                    f"run {self.key} ({self.path}) is being trained by another process ({holder}); "
                    f"wait for it to finish, or use another --store"
                ) from None
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()} on {socket.gethostname()} since {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
            f.flush()
            try:
                yield
            finally:
                f.seek(0)
                f.truncate()
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)

    def is_held(self) -> bool:
        """Whether a live process holds the run's lock (a ``running`` status without one is a dead run)."""
        import fcntl

        if not self.lock_path.exists():
            return False
        with open(self.lock_path, "r", encoding="utf-8") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
            return False

    # replacement: a new attempt is built beside the run and swapped in only once it has finished
    @property
    def staging_path(self) -> Path:
        """Where a replacement of this run is built (``.seed<k>.new``: not a run folder for ``Store.runs``)."""
        return self.path.parent / f".{self.path.name}.new"

    @property
    def retired_path(self) -> Path:
        return self.path.parent / f".{self.path.name}.old"

    def staging(self) -> "Run":
        """The run that replaces this one: same key, built in ``staging_path`` (emptied first)."""
        staged = Run.__new__(Run)
        staged.key, staged.path = self.key, self.staging_path
        return staged

    def replace_with(self, staged: "Run") -> None:
        """Swap the finished ``staged`` run in place of this one, then delete the old folder.

        The old folder is renamed aside and the new one renamed into place; a crash between the two renames
        leaves the old run beside the empty slot, and ``recover`` (called by ``exclusive``) puts it back.
        """
        import shutil

        if not staged.is_finished():
            raise StoreError(f"{staged.path}: the replacement of run {self.key} has not finished; the old run is kept")
        shutil.rmtree(self.retired_path, ignore_errors=True)
        if self.path.exists():
            os.rename(self.path, self.retired_path)
        try:
            os.rename(staged.path, self.path)
        except OSError:
            self.recover()
            raise
        shutil.rmtree(self.retired_path, ignore_errors=True)

    def recover(self) -> None:
        """Undo a replacement interrupted between its two renames: the old run goes back into its slot."""
        old = self.retired_path
        if old.is_dir() and not (self.path / "status.json").exists():
            if self.path.exists():
                import shutil

                shutil.rmtree(self.path)
            os.rename(old, self.path)

    # status
    def status(self) -> dict[str, Any] | None:
        if not self.status_path.exists():
            return None
        return read_json(self.status_path)

    def is_finished(self) -> bool:
        st = self.status()
        return bool(st and st.get("state") == "finished" and self.metrics_path.exists())

    def set_status(self, state: str, **extra: Any) -> None:
        if state not in STATES:
            raise ValueError(f"unknown run state {state!r}")
        previous = self.status() or {}
        now = time.strftime("%Y-%m-%dT%H:%M:%S")
        record = {**previous, **extra, "state": state, "updated": now}
        record.setdefault("started", now)
        atomic_write_json(self.status_path, record)

    # content
    def write_config(self, config: dict[str, Any]) -> str:
        from harness.config import dump_yaml

        digest = config_hash(config)
        atomic_write_text(self.config_path, f"# resolved configuration; config_hash {digest}\n" + dump_yaml(config))
        return digest

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        metrics = {"schema": METRICS_SCHEMA, "run": asdict(self.key), **metrics}
        atomic_write_json(self.metrics_path, metrics)

    @property
    def analysis_path(self) -> Path:
        return self.path / "analysis.json"

    def write_analysis(self, analysis: dict[str, Any]) -> None:
        """Write ``analysis.json`` (compact JSON: it holds per-image and per-GT arrays)."""
        atomic_write_json(self.analysis_path, {"run": asdict(self.key), **analysis}, indent=None)

    def read_analysis(self) -> dict[str, Any] | None:
        """The stored error analysis (``analysis.json``, or ``analysis.json.gz`` in the shipped reference results),
        or None for a run stored before the analysis existed."""
        path = packed_or_plain(self.analysis_path)
        if not path.exists():
            return None
        data = read_json(path)
        if not isinstance(data, dict) or data.get("schema") != ANALYSIS_SCHEMA:
            found = data.get("schema") if isinstance(data, dict) else None
            raise StoreError(f"{path}: analysis schema {found!r}, expected {ANALYSIS_SCHEMA}")
        return data

    def read_metrics(self) -> dict[str, Any]:
        if not self.metrics_path.exists():
            raise StoreError(f"{self.metrics_path}: no metrics for run {self.key} (not finished?)")
        data = read_json(self.metrics_path)
        if data.get("schema") != METRICS_SCHEMA:
            raise StoreError(f"{self.metrics_path}: metrics schema {data.get('schema')!r}, expected {METRICS_SCHEMA}")
        return data

    def append_log(self, record: dict[str, Any]) -> None:
        """Append one JSON line; a partial last line from a crash is ignored by ``read_log``."""
        self.path.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "a", encoding="utf-8") as f:
            f.write(json.dumps(record, default=str) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def read_log(self) -> list[dict[str, Any]]:
        if not self.log_path.exists():
            return []
        out = []
        from harness.io import read_packed_text

        for line in read_packed_text(self.log_path).splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out

    # weights
    def final_checkpoint(self) -> Path | None:
        """The checkpoint whose weights predicted the held-out fold, as ``train.final`` in ``config.yaml`` says:
        ``best.pt``, or ``last.pt`` under ``final: last`` or when no ``best.pt`` was written (what ``harness screen
        --run`` loads); None when neither exists."""
        from harness.config import read_yaml

        final = "best"
        if self.config_path.is_file():
            final = str((read_yaml(self.config_path).get("train") or {}).get("final", "best"))
        best, last = self.checkpoint_dir / "best.pt", self.checkpoint_dir / "last.pt"
        chosen = best if final == "best" and best.exists() else last
        return chosen if chosen.exists() else None

    def keep_final_checkpoint(self) -> list[Path]:
        """Delete the checkpoints of a finished run other than ``final_checkpoint`` (``last.pt`` with its optimiser
        state, kept to resume an interrupted run, which a finished one never is); returns what was deleted. A run
        that has not finished keeps everything."""
        if not self.is_finished() or not self.checkpoint_dir.is_dir():
            return []
        keep = self.final_checkpoint()
        dropped = [p for p in sorted(self.checkpoint_dir.iterdir()) if p.is_file() and p != keep]
        for p in dropped:
            p.unlink()
        if keep is not None and keep.name == "last.pt":
            slim_final_checkpoint(keep)
        if dropped:
            self._forget_checkpoints(dropped)
        return dropped

    def _forget_checkpoints(self, dropped: Sequence[Path]) -> None:
        """``metrics.json``'s ``train.best_path`` / ``train.last_path`` that name a deleted checkpoint become null, so
        that no recorded path leads to a missing file."""
        from harness.io import atomic_write_json, read_json

        metrics = read_json(self.metrics_path)
        train = metrics.get("train") if isinstance(metrics, dict) else None
        if not isinstance(train, dict):
            return
        gone = {p.name for p in dropped}
        changed = False
        for k in ("best_path", "last_path"):
            if isinstance(train.get(k), str) and Path(train[k]).name in gone:
                train[k] = None
                changed = True
        if changed:
            atomic_write_json(self.metrics_path, metrics)


#: What ``harness run --keep-weights`` keeps of a finished run's checkpoints: ``all`` (``last.pt`` and ``best.pt``),
#: ``final`` (only the weights that predicted the held-out fold, ``Run.keep_final_checkpoint``).
KEEP_WEIGHTS = ("all", "final")


class Store:
    """A results store rooted at ``root``."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def run(self, key: RunKey) -> Run:
        return Run(self.root, key)

    def runs(
        self, dataset: str | None = None, detector: str | None = None, finished_only: bool = True
    ) -> Iterator[Run]:
        """Every run in the store (sorted), optionally filtered; only finished ones unless asked."""
        if not self.root.exists():
            return
        for status in sorted(self.root.glob("*/*/*/*/seed*/status.json")):
            ds, det, enc, fold, seed = status.parent.relative_to(self.root).parts
            det = detector_name(det)
            if ds.startswith("_") or (dataset and ds != dataset) or (detector and det != detector):
                continue
            try:
                key = RunKey(ds, det, enc, fold, int(seed[4:]))
            except ValueError:
                continue
            run = Run(self.root, key)
            if finished_only and not run.is_finished():
                continue
            yield run

    def sensing_path(self, dataset: str, analysis: str) -> Path:
        return self.root / dataset / "_sensing" / f"{analysis}.json"

    def dataset_path(self, dataset: str) -> Path:
        return self.root / _safe(dataset) / "_dataset.json"

    def write_dataset(self, spec: Any) -> Path:
        """``<dataset>/_dataset.json``: what a report needs to know about a dataset (written with its runs)."""
        return atomic_write_json(
            self.dataset_path(spec.name),
            {"dataset": spec.name, "thermal": spec.thermal, "sensing_stage": bool(spec.sensing_stage)},
        )

    def profile_path(self, detector: str) -> Path:
        return self.root / "_profiles" / f"{detector}.json"

    def write_sensing(self, dataset: str, analysis: str, result: dict[str, Any]) -> Path:
        return atomic_write_json(self.sensing_path(dataset, analysis), result)

    def write_profile(self, detector: str, result: dict[str, Any]) -> Path:
        return atomic_write_json(self.profile_path(detector), result)
