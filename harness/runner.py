"""The main job: prepare -> folds -> (train -> predict -> evaluate -> store) for every fold and seed.

``run(RunRequest(detector=..., dataset=...))`` resolves the detector, dataset and encoding through the plugin
host, resolves the configuration (``harness.config.load_config``: default < protocol < detector defaults < profile
< files < ``--set``), prepares the dataset once (``harness.cache.prepare``: every detector and encoding reads the
same cached, aligned samples), resolves the folds, and then for each fold and seed:

* a run that already **finished** with the same configuration hash is skipped (its stored metrics are reused);
  one that finished with a different configuration is refused before anything is trained, unless ``force``. The
  hash holds the detector plugin's code (``meta.detector_code``: an edited helper module is another configuration);
  a run that differs only in the prepared data's cache key and recorded the samples prepared now (by content) is
  the same run;
* a run that was **interrupted** resumes from its last checkpoint (``checkpoints/last.pt``);
* otherwise the detector is built (seeded), optionally initialised from ``init``, trained, and the selected weights
  predict the held-out images once, which ``harness.evaluation.evaluate`` scores.

Which weights predict the held-out fold is ``protocol.selection`` (``SELECTIONS``), recorded in each run's
``config.yaml`` and ``metrics.json`` (``selection``):

* ``validation``: the fold's training groups are divided (``harness.cache.folds.validation_split``: the smallest
  training group held back whole, or ``protocol.validation_groups``); the model trains on the others, its EMA weights
  are scored on the validation group each epoch, the best by fitness is kept and early stopping watches it. The
  held-out images are predicted once, at the end;
* ``last``: trained on every training group for ``protocol.epochs``; the last epoch's EMA weights, no per-epoch
  scoring and no early stopping;
* ``held-out``: the seed's protocol: scored on the held-out fold each epoch, the best epoch on it kept (so the
  reported number was chosen on the data it reports).

``eval.log_held_out: true`` (``validation``/``last``) also scores the held-out fold each epoch into ``log.jsonl``
(``observed``) to measure what selecting on it would have gained; it never selects anything.

Everything lands in the results store (``harness.store``): ``config.yaml``, ``status.json``, ``log.jsonl``,
``checkpoints/``, ``predictions.json``, ``gt.json`` and ``metrics.json`` (support, metrics, per-category AP, model
parameters, training summary and environment). ``ablate`` runs one fold over several encodings for the seed's
encoding-ablation table.

Under ``torchrun`` every process runs this same job (``harness.distributed``): rank 0 prepares the dataset first and
is the only one that writes the store; training and prediction are shared by all processes.

Kept in one module: the request, the plan, the run identity that decides skip/resume/refuse and the per-run job are
one lifecycle, read in order from ``RunRequest`` to ``run_one``.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import logging
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping, Sequence, TypedDict, Unpack

from harness import tracking
from harness.errors import ConfigError, HarnessError, StoreError
from harness.io import atomic_write_json, file_digest, read_json
from harness.progress import OverallProgress
from harness.report.reader import StoredRun, read_run
from harness.store import KEEP_WEIGHTS, Run, RunBusyError, RunKey, Store, config_hash, image_ids_hash

if TYPE_CHECKING:
    import torch

    from harness.api import DatasetSpec, DetectorSpec, EncodingSpec, Fold
    from harness.cache import PreparedDataset
    from harness.plugins import PluginHost

log = logging.getLogger(__name__)

#: Keys that change how fast a run goes but not what it computes; left out of the configuration hash.
HASH_EXCLUDE = {
    ("train", "workers"),
    ("eval", "batch"),
    ("train", "threads"),
    ("train", "cache_mb"),
    ("eval", "allow_degenerate"),
}  # speed only, or whether a run is stored (labelled), not its numbers
#: Keys that only say where something lies: the data is identified by the prepared data's fingerprint
#: (``meta.prepared_fingerprint``) and cache key (``meta.prepared_key``, which also hashes the dataset plugin's code,
#: the sensing settings and the preparation version) and an initial checkpoint by its content (``meta.init_sha1``).
LOCATION_KEYS = {("dataset", "root"), ("train", "init")}
#: Keys that decide whether a run may use its samples, not what it computes (the plausibility guard's ``inputs``
#: section and the accepted findings it labels the run with): left out of the identity.
GUARD_KEYS = {("meta", "input_risks")}
#: ``protocol.selection``: what chooses the weights that predict the held-out fold (see the module docstring).
SELECTIONS = ("validation", "last", "held-out")


def selection_of(cfg: Mapping[str, Any]) -> str:
    """The config's ``protocol.selection`` (``held-out`` when unset, as runs stored before it existed were made)."""
    sel = str((cfg.get("protocol") or {}).get("selection") or "held-out")
    if sel not in SELECTIONS:
        raise ConfigError(f"protocol.selection: {sel!r} is not one of {', '.join(SELECTIONS)}")
    return sel


#: The digest of which sample each image id held when a run was planned (``harness.cache`` ``sample_identity``): not
#: part of the identity (runs stored before it existed stay "finished"), but a finished run that recorded another
#: one than the prepared data has now was scored on other pictures under the same cache key, and is a conflict.
SAMPLES_KEY = ("meta", "prepared_samples")
#: The digest of the detector plugin's code (``harness.cache.key.detector_code``): part of the identity, so an edited
#: detector (a helper module it imports included) never reuses a finished run; compared only when the stored run
#: recorded one (runs stored before it existed, the shipped references among them, keep their state). Beside it,
#: ``meta.detector_code_files`` (each file's digest, left out of the identity) names the files that changed.
CODE_KEY, CODE_FILES_KEY = ("meta", "detector_code"), ("meta", "detector_code_files")
#: Where the prepared data lies under which key: a finished run that differs only in these and recorded the same
#: samples (by content, ``PreparedDataset.content_digest``) as the prepared data holds now is the same run.
CACHE_KEYS = (("meta", "prepared_key"), ("meta", "prepared_fingerprint"))


@dataclass
class RunRequest:
    """What ``harness run`` asks for (see ``harness run --help``)."""

    detector: str
    dataset: str
    encoding: str | None = None
    folds: str = "all"
    seeds: Sequence[int] | None = None
    profile: str | None = "smoke"
    config_files: Sequence[str | Path] = ()
    overrides: Sequence[str] = ()
    store: str | Path | None = None
    force: bool = False
    init: str | Path | None = None
    progress: bool = True
    #: the checkpoints a finished run keeps: ``all`` or ``final`` (``harness.store.KEEP_WEIGHTS``)
    keep_weights: str = "all"


class RunSettings(TypedDict, total=False):
    """How a request runs, as keyword arguments of ``RunRequest`` (which holds their defaults): what the functions that
    build requests for ``run`` (``ablate``, ``harness.commands.pretrain.pretrain``) pass on unchanged."""

    profile: str | None
    config_files: Sequence[str | Path]
    overrides: Sequence[str]
    store: str | Path | None
    force: bool
    init: str | Path | None
    progress: bool
    keep_weights: str


@dataclass
class RunOutcome:
    """One (fold, seed) run of a request: what the store holds for it (read back through the store's reader) and
    what this request did with it."""

    stored: StoredRun
    state: str  # "trained", "resumed" or "skipped" (finished earlier with the same configuration)
    train_images: int = 0
    val_images: int = 0

    @property
    def key(self) -> RunKey:
        return self.stored.key

    @property
    def path(self) -> Path:
        return self.stored.path

    @property
    def metrics(self) -> dict[str, Any]:
        return self.stored.metrics


@dataclass
class RunSummary:
    detector: str
    dataset: str
    encoding: str
    profile: str | None
    store: Path
    config: dict[str, Any]
    categories: list[str]
    results: list[RunOutcome] = field(default_factory=list)


# ------------------------------------------------------------------------------------------------- resolution
def prepare_dataset(dataset: str, cfg: Mapping[str, Any]) -> PreparedDataset:
    """The dataset's prepared samples (``harness.cache.prepare``: computed once, then read from the cache)."""
    from harness.cache import prepare

    return prepare(dataset, dict(cfg))


def resolve_folds(
    dataset_spec: DatasetSpec, prepared: PreparedDataset, cfg: Mapping[str, Any], selection: str
) -> list[Fold]:
    from harness.cache import resolve_folds as _resolve

    return _resolve(dataset_spec, prepared, dict(cfg), selection)


def fold_indices(prepared: PreparedDataset, fold: Fold) -> tuple[list[int], list[int]]:
    from harness.cache import fold_indices as _indices

    train_idx, val_idx = _indices(prepared, fold)
    return list(train_idx), list(val_idx)


def choose_encoding(
    detector: DetectorSpec, dataset: DatasetSpec, requested: str | None, host: PluginHost
) -> EncodingSpec:
    """The encoding a run uses: the requested one, else the detector's (dual-stream) or the dataset's default."""
    dual = detector.input_kind == "dual"
    name = requested or (detector.default_thermal_encoding if dual else dataset.default_encoding)
    enc = host.encoding(name)
    if dual and enc.channels == 0:
        raise ConfigError(
            f"detector {detector.name!r} is dual-stream and needs a thermal encoding, but {name!r} adds no channel; "
            f"use e.g. --encoding {detector.default_thermal_encoding}"
        )
    if dataset.thermal == "8bit" and enc.needs == "thermal":
        raise ConfigError(
            f"encoding {name!r} needs radiometric thermal, but dataset {dataset.name!r} has only 8-bit thermal; "
            f"use an 8-bit encoding such as 'proxy8' or 'ir8'"
        )
    return enc


def resolve_config(request: RunRequest, detector: DetectorSpec | None, dataset: DatasetSpec) -> dict[str, Any]:
    """The request's configuration (``harness.config.load_config``); without ``detector``, the one before a detector
    is known: its profile, the dataset's protocol, the files and overrides (``pretrain`` reads its folds there)."""
    from harness.config import load_config

    own: dict[str, Any] = (
        {"detector": detector.name, "detector_defaults": detector.defaults} if detector is not None else {}
    )
    return load_config(
        request.profile, protocol=dataset.protocol, files=request.config_files, overrides=request.overrides, **own
    )


#: Training seeds seed numpy's generator, which takes 0 .. 2**32 - 1.
SEED_RANGE = (0, 2**32 - 1)


def parse_seeds(text: str | Sequence[int] | None) -> list[int] | None:
    """``--seeds``: ``None`` when not given (the protocol's seeds); a given value must name at least one seed, each
    once, within ``SEED_RANGE``: a seed given twice would run twice and count twice in the mean and SD."""
    if text is None:
        return None
    if isinstance(text, str):
        try:
            seeds = [int(s) for s in text.split(",") if s.strip()]
        except ValueError:
            raise ConfigError(f"--seeds {text!r}: expected comma-separated integers such as 0,1,2") from None
        if not seeds:
            raise ConfigError(
                f"--seeds {text!r}: names no seed; give e.g. 0,1,2, or leave the option out for the protocol's seeds"
            )
    else:
        seeds = [int(s) for s in text]
    bad = [s for s in seeds if not SEED_RANGE[0] <= s <= SEED_RANGE[1]]
    if bad:
        raise ConfigError(f"--seeds {_shown(text)}: seed {bad[0]} is outside {SEED_RANGE[0]}..{SEED_RANGE[1]}")
    from harness.cache.folds import refuse_repeats

    refuse_repeats(seeds, f"--seeds {_shown(text)}: seed ", "each seed is one run", str)
    return seeds


def _shown(value: str | Sequence[int]) -> str:
    return repr(value) if isinstance(value, str) else repr(",".join(map(str, value)))


def run_config(cfg: Mapping[str, Any], key: RunKey, extra: Mapping[str, Any]) -> dict[str, Any]:
    """The configuration recorded for one run: the resolved config plus the run's identity under ``meta``."""
    out = copy.deepcopy(dict(cfg))
    out["meta"] = {
        **out.get("meta", {}),
        "detector": key.detector,
        "dataset": key.dataset,
        "encoding": key.encoding,
        "fold": key.fold,
        "seed": key.seed,
        **extra,
    }
    return out


def run_identity(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """What determines a run's result: the config without speed-only keys and without locations (the data is
    identified by its prepared fingerprint, an initial checkpoint by its sha1)."""
    trimmed = copy.deepcopy(dict(cfg))
    for section, key in HASH_EXCLUDE | LOCATION_KEYS:
        if isinstance(trimmed.get(section), dict):
            trimmed[section].pop(key, None)
    # the registration route is a record of how the prepared samples (identified by their fingerprint) were made
    trimmed["meta"] = {
        k: v
        for k, v in trimmed.get("meta", {}).items()
        if k not in ("sources", "registration")
        and ("meta", k) not in GUARD_KEYS
        and ("meta", k) not in (SAMPLES_KEY, CODE_FILES_KEY)
    }
    proto, ev = trimmed.get("protocol"), trimmed.get("eval")
    if isinstance(proto, dict) and proto.get("selection", "held-out") == "held-out":
        # the seed's protocol, which runs stored before the key existed used: their identity is unchanged
        proto.pop("selection", None)
        proto.pop("validation_groups", None)
    if isinstance(proto, dict) and not proto.get("validation_groups"):
        proto.pop("validation_groups", None)
    if isinstance(ev, dict):
        ev.pop("log_held_out", None)  # per-epoch held-out scores in the log only: never used, never change a number
    trimmed.pop("tracking", None)  # where copies of the run are logged, not what it computes
    trimmed.pop("inputs", None)  # the plausibility guard's settings: whether the samples may be used
    return trimmed


def run_hash(cfg: Mapping[str, Any]) -> str:
    """Hash of ``run_identity(cfg)``."""
    return config_hash(run_identity(cfg))


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, Mapping) or not d:
        return {prefix: d} if prefix else {}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def without_meta(cfg: Mapping[str, Any], keys: Sequence[tuple[str, str]]) -> Mapping[str, Any]:
    """``cfg`` without the ``meta`` entries ``keys`` (a shallow copy; ``cfg`` itself when it holds none of them)."""
    meta = cfg.get("meta")
    if not isinstance(meta, Mapping) or not any(k in meta for _, k in keys):
        return cfg
    return {**cfg, "meta": {k: v for k, v in meta.items() if ("meta", k) not in keys}}


def comparable(stored: Mapping[str, Any] | None, now: Mapping[str, Any]) -> Mapping[str, Any]:
    """``now`` as it compares with ``stored``: without ``meta.detector_code`` when ``stored`` recorded none (a run
    stored before the key existed keeps its state; the code it ran is unknown, not different)."""
    if stored is not None and (stored.get("meta") or {}).get(CODE_KEY[1]):
        return now
    return without_meta(now, [CODE_KEY])


def identity_diff(old: Mapping[str, Any], new: Mapping[str, Any], limit: int = 8) -> list[str]:
    """``key: old -> new`` for every setting of the run identity that differs (at most ``limit``, then a count);
    ``meta.detector_code`` only when both recorded one, with the files that changed."""
    old, new = comparable(new, old), comparable(old, new)
    a, b = _flat(run_identity(old)), _flat(run_identity(new))
    keys = sorted(k for k in a.keys() | b.keys() if a.get(k, "<unset>") != b.get(k, "<unset>"))
    out = [f"{k}: {a.get(k, '<unset>')} -> {b.get(k, '<unset>')}" for k in keys[:limit]]
    code = ".".join(CODE_KEY)
    if code in keys[:limit]:
        from harness.cache.key import changed_code_files

        files = changed_code_files(*((c.get("meta") or {}).get(CODE_FILES_KEY[1]) for c in (old, new)))
        shown = ", ".join(files[:4]) + (f" (+{len(files) - 4} more)" if len(files) > 4 else "")
        out[keys.index(code)] += f" (the detector plugin's code changed{': ' + shown if shown else ''})"
    if len(keys) > limit:
        out.append(f"(+{len(keys) - limit} more)")
    return out


class SamplesCheck:
    """Whether a finished run that differs only in where its prepared data lies (``CACHE_KEYS``) trained on and scored
    the samples the prepared data holds now: the content digests it recorded (``metrics.json`` ``samples.train`` and
    ``samples.held_out``, with its encoding) against those of the prepared data, computed once per fold and encoding
    for the whole plan (every seed shares them). A run whose ``meta.prepared_samples`` differs from the prepared
    data's is refused without reading a sample."""

    def __init__(self, prepared: Any, encoding: Any) -> None:
        self.prepared, self.encoding = prepared, encoding
        self._digests: dict[tuple[str, str], dict[str, str]] = {}
        self.noted = False

    def now(self, fold: Fold, params: Mapping[str, Any]) -> dict[str, str]:
        memo = (fold.name, json.dumps(dict(params), sort_keys=True, default=str))
        if memo not in self._digests:
            train_idx, val_idx = fold_indices(self.prepared, fold)
            digest = self.prepared.content_digest
            self._digests[memo] = {
                "train": digest(train_idx, self.encoding, dict(params)),
                "held_out": digest(val_idx, self.encoding, dict(params)),
            }
        return self._digests[memo]


# ------------------------------------------------------------------------------------------------- the job
@dataclass
class PlannedRun:
    """One (fold, seed) of a request, before anything is trained: its store folder, configuration and hash."""

    fold: Fold
    seed: int
    run: Run
    config: dict[str, Any]
    digest: str
    samples: SamplesCheck | None = None

    @property
    def state(self) -> str:
        """``finished`` (same configuration: skipped), ``conflict`` (finished with another one), or ``todo``."""
        if not self.run.is_finished():
            return "todo"
        if self._other_samples():
            return "conflict"
        stored = self.stored_config()
        now = comparable(stored, self.config)
        hashes = {self.digest if now is self.config else run_hash(now)}
        if stored is None:  # nothing to tell whether it recorded the code: either hash it may have been stored with
            hashes.add(self.digest)
        if (self.run.status() or {}).get("config_hash") in hashes:
            return "finished"
        if stored is None:
            return "conflict"
        then = comparable(now, stored)  # the code compared only when both recorded it
        if run_hash(then) in hashes:  # a run stored before the identity left out locations: compare settings
            return "finished"
        return "finished" if self._same_samples(then, now)[0] else "conflict"

    def _same_samples(self, stored: Mapping[str, Any], now: Mapping[str, Any]) -> tuple[bool, str]:
        """(True when ``stored`` differs from ``now`` only in ``CACHE_KEYS`` and recorded the samples the prepared data
        holds now, why not otherwise: "" when it differs in more, or cannot tell)."""
        moved_only = run_hash(without_meta(stored, CACHE_KEYS)) == run_hash(without_meta(now, CACHE_KEYS))
        if self.samples is None or not moved_only:
            return False, ""
        then_meta, now_meta = stored.get("meta") or {}, now.get("meta") or {}
        then_ids, now_ids = then_meta.get(SAMPLES_KEY[1]), now_meta.get(SAMPLES_KEY[1])
        if then_ids and now_ids and then_ids != now_ids:
            return False, f"meta.prepared_samples: {then_ids} -> {now_ids} (other samples under its image ids)"
        try:
            recorded = read_json(self.run.metrics_path).get("samples") or {}
        except (OSError, ValueError, AttributeError):
            recorded = {}
        then = {k: str(recorded.get(k) or "") for k in ("train", "held_out")}
        if not all(then.values()) or recorded.get("encoding") != self.run.key.encoding:
            return False, ""  # stored before runs recorded their samples: nothing to compare
        params = ((now.get("encoding") or {}).get(self.run.key.encoding)) or {}
        here = self.samples.now(self.fold, params if isinstance(params, Mapping) else {})
        if here != then:
            return False, (
                f"samples: train {then['train'][:12]}.. held-out {then['held_out'][:12]}.. -> train "
                f"{here['train'][:12]}.. held-out {here['held_out'][:12]}.. (the samples it trained on and scored "
                "differ from those prepared now)"
            )
        if not self.samples.noted:
            self.samples.noted = True
            log.info(
                "%s: the prepared data's cache key changed (meta.prepared_key %s -> %s) but the samples are identical "
                "to those the finished run trained on and scored: it stays finished",
                self.run.key,
                then_meta.get("prepared_key"),
                now_meta.get("prepared_key"),
            )
        return True, ""

    def stored_config(self) -> dict[str, Any] | None:
        from harness.config import read_yaml

        try:
            data = read_yaml(self.run.config_path)
        except Exception:  # noqa: BLE001 - a missing or unreadable config.yaml: nothing to compare
            return None
        return data if isinstance(data, dict) else None

    def _other_samples(self) -> str | None:
        """``meta.prepared_samples: OLD -> NEW ...`` when the finished run recorded which samples its image ids held
        and the prepared data under the same key now holds others; else None."""
        meta_now, meta_then = self.config.get("meta") or {}, (self.stored_config() or {}).get("meta") or {}
        now, then = meta_now.get(SAMPLES_KEY[1]), meta_then.get(SAMPLES_KEY[1])
        if now and then and now != then and meta_now.get("prepared_key") == meta_then.get("prepared_key"):
            return (
                f"meta.prepared_samples: {then} -> {now} (the same cache key now holds other samples under "
                "its image ids: the dataset plugin's sample order changed)"
            )
        return None

    def differences(self) -> list[str]:
        other = self._other_samples()
        if other:
            return [other]
        stored = self.stored_config()
        if stored is None:
            return [
                f"stored configuration hash {(self.run.status() or {}).get('config_hash')}, "
                f"now {self.digest} (no readable {self.run.config_path})"
            ]
        now = comparable(stored, self.config)
        why = self._same_samples(comparable(now, stored), now)[1]
        return identity_diff(stored, self.config) + ([why] if why else [])


@dataclass
class RunPlan:
    """What ``run`` would do for a request: the resolved plugins, configuration, prepared data and runs."""

    detector: DetectorSpec
    dataset: DatasetSpec
    encoding: EncodingSpec
    config: dict[str, Any]
    init: str | None
    store: Store
    prepared: PreparedDataset
    runs: list[PlannedRun]

    def conflicts(self) -> list[str]:
        return [f"{p.run.key} ({'; '.join(p.differences())})" for p in self.runs if p.state == "conflict"]


def conflict_error(conflicts: Sequence[str], store: Store) -> StoreError:
    return StoreError(
        "these runs already finished with a different configuration: "
        + "; ".join(conflicts)
        + f". Re-run with --force to replace them, or choose another --store (now {store.root})"
    )


def plan(request: RunRequest) -> RunPlan:
    """Resolve the request (plugins, configuration, prepared dataset, folds, seeds) into its runs."""
    from harness import distributed as hd
    from harness.plugins import get_host

    host = get_host()
    det = host.detector(request.detector)
    ds = host.dataset(request.dataset)
    enc = choose_encoding(det, ds, request.encoding, host)
    cfg = resolve_config(request, det, ds)
    if request.init:
        cfg["train"]["init"] = str(request.init)
    init = cfg["train"].get("init")
    seeds = parse_seeds(request.seeds) or [int(s) for s in cfg["protocol"].get("seeds") or [0]]
    store = Store(request.store or Path("results") / (request.profile or "default"))
    init_info = _init_info(init)
    check_settings(det, ds, enc, cfg)  # bad options fail here, before any store folder is touched
    selection = selection_of(cfg)
    tracking.resolve((cfg.get("tracking") or {}).get("loggers") or [])  # unknown or uninstalled: stop before work

    with hd.main_first():  # under torchrun rank 0 fills the cache, then the others read it
        prepared = prepare_dataset(ds.name, cfg)
    folds = resolve_folds(ds, prepared, cfg, "all" if request.folds is None else request.folds)
    if not folds:
        raise ConfigError(f"--folds {request.folds!r} selects no fold of dataset {ds.name!r}")
    fingerprint = str(prepared.manifest.get("fingerprint", ""))
    # the cache key hashes what produced the samples: fingerprint, sensing settings, preparation version and the
    # dataset plugin's code, so a finished run on other samples is never reused as "same configuration"
    prepared_key = str(getattr(prepared, "key", None) or prepared.manifest.get("key", ""))
    registration = _registration_routes(prepared)
    from harness.cache.key import detector_code

    code, code_files = detector_code(det.name)
    code_meta = {CODE_KEY[1]: code, CODE_FILES_KEY[1]: code_files} if code else {}
    samples = SamplesCheck(prepared, enc)
    risks = [f"{r['kind']}: {r['message']}" for r in getattr(prepared, "input_risks", None) or []]
    if risks:
        cfg["meta"] = {**cfg.get("meta", {}), "input_risks": risks}

    runs = []
    for fold in folds:
        carved: dict[str, Any] = {}
        if selection == "validation":  # a fold that cannot be divided fails here, before anything trains
            from harness.cache.folds import validation_split

            carved = {"validation_groups": list(validation_split(prepared, fold, cfg).groups)}
        for seed in seeds:
            key = RunKey(ds.name, det.name, enc.name, fold.name, seed)
            samples_digest = (prepared.manifest.get("report") or {}).get("samples_identity")
            rcfg = run_config(
                cfg,
                key,
                {
                    "prepared_fingerprint": fingerprint,
                    "prepared_key": prepared_key,
                    **({SAMPLES_KEY[1]: samples_digest} if samples_digest else {}),
                    **code_meta,
                    "val_groups": list(fold.val_groups),
                    "train_groups": list(fold.train_groups),
                    **carved,
                    **init_info,
                    **({"registration": registration} if registration else {}),
                },
            )
            runs.append(PlannedRun(fold, seed, store.run(key), rcfg, run_hash(rcfg), samples))
    return RunPlan(det, ds, enc, cfg, init, store, prepared, runs)


def _registration_routes(prepared: Any) -> dict[str, Any] | None:
    """The registration route the prepared samples were registered by, per inspection group (``meta.registration``
    of every run on them; ``harness.sensing.registration.dataset.recorded_routes``); None for a prepared dataset
    without a folder (a stand-in)."""
    from harness.sensing.registration.dataset import recorded_routes

    folder = getattr(prepared, "folder", None)
    return recorded_routes(Path(folder)) if folder is not None else None


def run(request: RunRequest) -> RunSummary:
    """Train and evaluate every selected fold and seed; see the module docstring."""
    from harness import distributed as hd

    if request.keep_weights not in KEEP_WEIGHTS:
        raise ConfigError(f"--keep-weights {request.keep_weights!r}: use one of {', '.join(KEEP_WEIGHTS)}")
    hd.init_from_env()
    p = plan(request)
    det, ds, enc, prepared, init = p.detector, p.dataset, p.encoding, p.prepared, p.init
    conflicts = p.conflicts()
    if conflicts and not request.force:
        raise conflict_error(conflicts, p.store)
    if hd.is_main():
        p.store.write_dataset(ds)

    summary = RunSummary(
        det.name, ds.name, enc.name, request.profile, p.store.root, p.config, list(prepared.categories)
    )
    todo = [x for x in p.runs if x.state != "finished" or request.force]
    overall = OverallProgress(len(todo), int(p.config["protocol"]["epochs"]), enabled=hd.is_main() and request.progress)
    measured: dict[Any, Any] = {}  # complexity records of the architectures built so far (this process)
    for planned in p.runs:
        fold, r, digest = planned.fold, planned.run, planned.digest
        train_idx, val_idx = fold_indices(prepared, fold)
        if planned.state == "finished" and not request.force:
            log.info("%s: finished earlier with the same configuration, skipped (use --force to redo)", r.key)
            summary.results.append(RunOutcome(read_run(r), "skipped", len(train_idx), len(val_idx)))
            _keep_weights(r, request.keep_weights)
            continue
        with _run_lock(r):
            st = r.status() or {}
            if (
                not request.force and r.is_finished() and st.get("config_hash") == digest and not hd.info().active
            ):  # finished by another process while this one waited its turn
                log.info("%s: finished by another process meanwhile, skipped", r.key)
                summary.results.append(RunOutcome(read_run(r), "skipped", len(train_idx), len(val_idx)))
                _keep_weights(r, request.keep_weights)
                continue
            overall.start_run(str(r.key))
            result = run_one(
                det,
                enc,
                prepared,
                planned,
                train_idx,
                val_idx,
                request,
                init,
                overall=overall,
                complexity_memo=measured,
            )
            overall.finish_run()
            _keep_weights(r, request.keep_weights)
        summary.results.append(result)
    return summary


def _keep_weights(r: Run, keep: str) -> None:
    """``keep="final"``: the finished run ``r`` keeps only the checkpoint that predicted its held-out fold, the one
    ``harness screen --run`` loads (a report reads no checkpoint); ``last.pt`` serves only to resume an interrupted
    run, which a finished one never is. The process that writes the store (rank 0) deletes."""
    from harness import distributed as hd

    if keep == "all" or not hd.is_main():
        return
    dropped = r.keep_final_checkpoint()
    if dropped:
        log.info("%s: kept only the final weights; deleted checkpoints/%s", r.key, ", ".join(p.name for p in dropped))


@contextlib.contextmanager
def _run_lock(r: Run) -> Iterator[None]:
    """The run's store lock, held by the process that writes the store (rank 0 under torchrun); every rank learns
    whether it was free, so all of them stop together when another process is training that run."""
    from harness import distributed as hd

    with contextlib.ExitStack() as stack:
        busy: str | None = None
        if hd.is_main():
            try:
                stack.enter_context(r.exclusive())
            except RunBusyError as exc:
                busy = str(exc)
        busy = hd.broadcast_object(busy)
        if busy is not None:
            raise RunBusyError(busy)
        yield


def run_one(
    det: DetectorSpec,
    enc: EncodingSpec,
    prepared: PreparedDataset,
    planned: PlannedRun,
    train_idx: Sequence[int],
    val_idx: Sequence[int],
    request: RunRequest,
    init: str | Path | None = None,
    overall: OverallProgress | None = None,
    complexity_memo: dict[Any, Any] | None = None,
) -> RunOutcome:
    """Train, predict and evaluate one (fold, seed) of ``request`` (``planned``: its store folder, configuration and
    hash; ``init``: the checkpoint the plan resolved) and write its folder in the results store.

    ``complexity_memo`` keeps the complexity record of each architecture already measured (by the detector, its
    model options, classes, input, the names and shapes of its state and the random generator's state), so the
    folds of one ``run`` measure their common model once, with the same results as measuring it each time."""
    import torch

    from harness import distributed as hd
    from harness.cache.folds import validation_split
    from harness.complexity import measure as measure_complexity
    from harness.engine import checkpoint as ckpt
    from harness.engine.data import AugmentSettings, SampleSource, TrainDataset
    from harness.engine.predict import DegenerateBoxes, predict
    from harness.engine.runtime import environment, seed_everything
    from harness.engine.trainer import Trainer, TrainSettings
    from harness.evaluation import evaluate_with_config
    from harness.evaluation.analysis import store_analysis
    from harness.scoring.agreement import check_run

    fold, seed, r, cfg, digest = planned.fold, planned.seed, planned.run, planned.config, planned.digest
    force, progress = request.force, request.progress
    if not train_idx:
        raise ConfigError(f"fold {fold.name!r}: no training images (train groups {list(fold.train_groups)})")
    if not val_idx:
        raise ConfigError(f"fold {fold.name!r}: no held-out images (groups {list(fold.val_groups)})")
    dist = hd.info()
    main = dist.is_main
    st = r.status() or {}
    # under torchrun rank 0 decides (before it writes the status the other processes would otherwise read)
    fresh = hd.broadcast_object(force or st.get("config_hash") != digest)
    # a finished run is never touched by its replacement: the new attempt is built beside it and swapped in at the end
    replacing = hd.broadcast_object(bool(fresh and r.is_finished()))
    target = r
    if replacing:
        r = target.staging()
    if main:
        if replacing:
            shutil.rmtree(r.path, ignore_errors=True)
        elif fresh and r.path.exists():
            for stale in (
                r.checkpoint_dir / "last.pt",
                r.checkpoint_dir / "best.pt",
                r.log_path,
                r.metrics_path,
                r.analysis_path,
            ):
                stale.unlink(missing_ok=True)
        r.path.mkdir(parents=True, exist_ok=True)
        r.write_config(cfg)
        r.set_status(
            "running",
            config_hash=digest,
            fold=fold.name,
            seed=seed,
            error=None,
            **({"world_size": dist.world_size} if dist.active else {}),
        )
    hd.barrier()
    stored = False
    tracker = tracking.for_run(cfg, r.path.parents[len(r.key.parts()) - 1]) if main else tracking.Tracker()
    tracker.start(
        str(r.key),
        tracking.flatten_params(cfg),
        {"detector": det.name, "dataset": r.key.dataset, "encoding": enc.name, "fold": fold.name, "seed": str(seed)},
    )
    try:
        settings = TrainSettings.from_config(cfg, seed)
        eval_cfg = cfg["eval"]
        selection = selection_of(cfg)
        split = validation_split(prepared, fold, cfg) if selection == "validation" else None
        fit_idx = list(split.train) if split is not None else list(train_idx)
        enc_params = dict((cfg.get("encoding") or {}).get(enc.name, {}) or {})
        cache_mb = float(cfg["train"].get("cache_mb") or 0)
        train_src = SampleSource(prepared, fit_idx, enc, enc_params, cache_mb=cache_mb)
        val_src = SampleSource(prepared, val_idx, enc, enc_params, cache_mb=cache_mb)
        sel_src = (
            SampleSource(prepared, list(split.validation), enc, enc_params, cache_mb=cache_mb)
            if split is not None
            else None
        )
        train_src.warm()
        aug = AugmentSettings.from_config(cfg["augment"], train_src.extra)
        gt = prepared.coco(val_idx)
        ncls = len(prepared.categories)
        in_channels = det.model_channels(train_src.channels)

        seed_everything(seed, settings.deterministic)
        model = build_model(det, ncls, in_channels, cfg.get("model") or {})
        init_report = ckpt.init_from(model, init, det.load_official) if init else None
        complexity = None
        if main:
            # measuring folds a copy of the model, and a fold that builds layers draws their initial weights from
            # torch's generator, which training then continues from (dropout): a record is reused only from the
            # same generator state, and the state the measurement left behind is restored with it
            rng = torch.get_rng_state()
            arch = (
                det.name,
                det.input_kind,
                in_channels,
                det.thermal_channels,
                settings.imgsz,
                ncls,
                json.dumps(cfg.get("model") or {}, sort_keys=True, default=str),
                tuple((k, tuple(v.shape), str(v.dtype)) for k, v in model.state_dict().items()),
                hashlib.sha1(rng.numpy().tobytes()).hexdigest(),
            )
            memo = complexity_memo if complexity_memo is not None else {}
            if arch in memo:
                torch.set_rng_state(memo[arch][1])
            else:
                record = measure_complexity(
                    model,
                    det.input_kind,
                    in_channels,
                    det.thermal_channels,
                    settings.imgsz,
                    ncls,
                    cfg.get("model") or {},
                    label=f"detector {det.name!r}",
                )
                memo[arch] = (record, torch.get_rng_state())
            complexity = copy.deepcopy(memo[arch][0])
        name = f"{det.name}/{enc.name}/{fold.name}/seed{seed}"

        def scorer(src: Any, truth: dict[str, Any]) -> Callable[[Any], dict[str, Any] | None]:
            def score(m: Any) -> dict[str, Any] | None:
                return _score(m, src, truth)

            return score

        def _score(m: Any, src: Any, truth: dict[str, Any]) -> dict[str, Any] | None:
            dets = predict(
                m,
                src,
                settings.imgsz,
                int(eval_cfg["batch"]),
                det.input_kind,
                det.thermal_channels,
                next(m.parameters()).device,
                eval_cfg["conf"],
                eval_cfg["iou"],
                eval_cfg["max_det"],
                ncls,
                name=det.name,
                distributed=dist.active,
            )
            if not main:
                return None  # rank 0 scores the gathered predictions; the trainer broadcasts its metrics
            res = evaluate_with_config(truth, dets, cfg)
            out = {k: res["metrics"].get(k) for k in ("precision", "recall", "mAP50", "mAP50_95")}
            out["AP50_per_category"] = {c: v.get("AP50") for c, v in res["per_category"].items()}
            return out

        def on_epoch(record: dict[str, Any]) -> None:
            r.append_log({"fold": fold.name, "seed": seed, **record})
            tracker.log_epoch(int(record["epoch"]), tracking.epoch_metrics(record))
            if overall is not None:
                overall.epoch_done(int(record["epoch"]), int(record["epochs"]))

        # the weights' per-epoch score that selects them: the validation split, the held-out fold (the seed's
        # protocol), or none (the last epoch); the held-out fold scored for the log only under eval.log_held_out
        if sel_src is not None:
            validate = scorer(sel_src, prepared.coco(list(sel_src.indices)))
        elif selection == "held-out":
            validate = scorer(val_src, gt)
        else:
            validate = None
        observe = scorer(val_src, gt) if selection != "held-out" and bool(eval_cfg.get("log_held_out", False)) else None
        trainer = Trainer(
            model,
            TrainDataset(train_src, settings.imgsz, aug, seed),
            settings,
            det.input_kind,
            det.thermal_channels,
            r.checkpoint_dir,
            validate,  # type: ignore[arg-type]
            on_epoch,
            progress,
            digest,
            name,
            observe=observe,  # type: ignore[arg-type]
            select=selection != "last",
        )
        resumed = (r.checkpoint_dir / "last.pt").exists() and not fresh
        result = trainer.fit(resume=not fresh)
        final = trainer.eval_model
        weights = "best" if selection != "last" and cfg["train"].get("final", "best") == "best" else "last"
        if weights == "best" and result.best_path:
            final.load_state_dict(ckpt.load(result.best_path)["model"])
        elif weights == "best":
            weights = "last"
        final.eval()
        t0 = time.perf_counter()
        visited: list[int] = []
        degenerate = DegenerateBoxes()
        dets = predict(
            final,
            val_src,
            settings.imgsz,
            int(eval_cfg["batch"]),
            det.input_kind,
            det.thermal_channels,
            trainer.device,
            eval_cfg["conf"],
            eval_cfg["iou"],
            eval_cfg["max_det"],
            ncls,
            progress=progress,
            name=det.name,
            distributed=dist.active,
            visited=visited,
            degenerate=degenerate,
        )
        predict_s = time.perf_counter() - t0
        if not main:  # rank 0 scores and writes; the others read its metrics once they are stored
            hd.barrier()
            return RunOutcome(read_run(r), "resumed" if resumed else "trained", len(train_idx), len(val_idx))
        # most boxes malformed (e.g. x, y, w, h returned): stop naming the detector, unless accepted (then labelled)
        degenerate_note = degenerate.check(det.name, bool(eval_cfg.get("allow_degenerate", False)))
        # the predictions as a whole against the ground truth: another reading far better stops naming the detector
        misread = check_run(det.name, dets, gt, ncls, bool(eval_cfg.get("allow_degenerate", False)), settings.imgsz)
        for note in misread:
            log.warning("%s", note)
        evaluation = evaluate_with_config(gt, dets, cfg)
        if degenerate_note:
            log.warning("%s", degenerate_note)
        elif degenerate.warning(det.name):  # malformed boxes under the stop rule are said, and labelled when many
            log.warning("%s", degenerate.warning(det.name))
        support = dict(evaluation["support"])
        support.setdefault("image_ids_sha1", image_ids_hash([int(i["id"]) for i in gt["images"]]))
        params = sum(p.numel() for p in model.parameters())
        train_summary = result.summary()
        if train_summary.get("plateau"):  # the slope of the per-epoch score: say which images it was measured on
            train_summary["plateau"]["metric"] = {
                "validation": "validation fitness",
                "held-out": "held-out fitness",
                "last": "held-out fitness, logged only",  # eval.log_held_out: the last epoch's weights regardless
            }[selection]
        if r is not target:  # checkpoint paths as they will be once the replacement is swapped in
            for k in ("best_path", "last_path"):
                if train_summary.get(k):
                    train_summary[k] = str(target.path / Path(train_summary[k]).relative_to(r.path))
        metrics = {
            "support": support,
            "metrics": evaluation["metrics"],
            "per_category": evaluation["per_category"],
            "model": {
                "params": int(params),
                "trainable": int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
                "in_channels": in_channels,
                "input_kind": det.input_kind,
                "weights": weights,
            },
            # what chose the weights that predicted the held-out fold (protocol.selection), and on which images
            "selection": {
                "protocol": selection,
                "weights": weights,
                "best_epoch": result.best_epoch if weights == "best" else None,
                "epochs_run": result.epochs_run,
                **(
                    split.record()
                    if split is not None
                    else {"validation_groups": [], "validation_images": 0, "train_images": len(fit_idx)}
                ),
                **(
                    {"validation_digest": prepared.content_digest(list(split.validation), enc, enc_params)}
                    if split is not None
                    else {}
                ),
            },
            "train": {
                **train_summary,
                "images": len(fit_idx),
                "imgsz": settings.imgsz,
                "batch": settings.batch,
                "init": init_report,
                "predict_s": round(predict_s, 3),
                "predict_images": len(visited),
                "processes": dist.world_size,
                "predict_images_per_s": round(len(val_idx) / predict_s, 2) if predict_s > 0 else None,
            },
            "complexity": complexity,
            "environment": {
                **environment(trainer.device),
                "torch_deterministic": torch.are_deterministic_algorithms_enabled(),
            },
            "degenerate_detections": degenerate.to_dict(),
            # the samples by content (harness.cache.reader.PreparedDataset.content_digest): what reference results
            # are matched on, so a code change that leaves the samples identical keeps a comparison valid
            "samples": {
                "encoding": enc.name,
                "train": prepared.content_digest(train_idx, enc, enc_params),
                "held_out": prepared.content_digest(val_idx, enc, enc_params),
                "aligned": {"train": prepared.content_digest(train_idx), "held_out": prepared.content_digest(val_idx)},
                # where they were read from: a comparison that finds other digests measures by how much they differ
                # (harness.references, harness.cache.fingerprint)
                **({"prepared": str(prepared.folder)} if getattr(prepared, "folder", None) else {}),
            },
            "input_risks": list((cfg.get("meta") or {}).get("input_risks") or []),  # accepted by inputs.accept
        }
        if degenerate_note:
            metrics["labels"] = [degenerate_note]
        elif degenerate.label(det.name):
            metrics["labels"] = [f"{degenerate.label(det.name)} (under the stop rule: more than half)"]
        if misread:
            metrics["labels"] = list(metrics.get("labels") or []) + misread
        approx = (prepared.manifest.get("report") or {}).get("approximate_temperatures")
        if approx:  # the thermal input rests on approximate temperatures: every table built on this run says so
            metrics["temperatures"] = dict(approx)
        atomic_write_json(r.predictions_path, dets, indent=None)
        atomic_write_json(r.gt_path, gt, indent=None)
        # the error analysis (TIDE, confusion, PR, size bins, per-image evidence), stored once beside the metrics
        store_analysis(r, gt, dets, cfg, evaluation["metrics"].get("conf_threshold"))
        r.write_metrics(metrics)
        r.set_status("finished", config_hash=digest, error=None)
        if r is not target:  # the finished replacement takes the old run's place in one swap
            target.replace_with(r)
            r = target
        stored = True
        tracker.log_final(tracking.final_metrics(metrics))
        for artefact in (r.config_path, r.metrics_path, r.log_path):
            if artefact.exists():
                tracker.log_artifact(artefact)
        tracker.finish("FINISHED")
        hd.barrier()
        m = evaluation["metrics"]
        log.info(
            "%s: mAP50 %.3f  mAP50:95 %.3f  (%d held-out images, %d instances)",
            name,
            m.get("mAP50") or 0.0,
            m.get("mAP50_95") or 0.0,
            support.get("images", 0),
            support.get("instances", 0),
        )
        return RunOutcome(read_run(r), "resumed" if resumed else "trained", len(train_idx), len(val_idx))
    except BaseException as exc:
        if main and not stored:
            reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
            r.set_status("failed", config_hash=digest, error=reason)
            tracker.finish("KILLED" if isinstance(exc, KeyboardInterrupt) else "FAILED")
            if r is not target:
                target.set_status("finished", replacement={"state": "failed", "error": reason, "path": str(r.path)})
                log.error(
                    "%s: the replacement run failed (%s); the finished run is kept unchanged, the failed "
                    "attempt is in %s",
                    target.key,
                    reason,
                    r.path,
                )
        raise


#: Detector attributes the host sets from ``eval.*`` before predicting (``harness.engine.predict.configure``).
HOST_SET = ("conf", "iou", "max_det")


def check_settings(det: DetectorSpec, dataset: DatasetSpec, enc: EncodingSpec, cfg: Mapping[str, Any]) -> None:
    """The training settings and the model options of a request, checked by building the model once (discarded):
    ``harness run``, ``sweep`` and ``sweep --dry-run`` refuse a bad ``--set`` before anything is stored."""
    from harness.engine.trainer import TrainSettings

    TrainSettings.from_config(cfg, 0)
    in_channels = det.model_channels(3 + int(enc.channels))
    options = dict(cfg.get("model") or {})
    host_set = [k for k in HOST_SET if k in options]
    if host_set:  # the host sets these attributes from eval.* before every prediction: a model.* value is lost
        raise ConfigError(
            f"--set {', '.join(f'model.{k}' for k in host_set)}: the host sets the detector's "
            f"{', '.join(host_set)} from {', '.join(f'eval.{k}' for k in host_set)} before predicting, so a model "
            f"option of that name would have no effect; use --set {', '.join(f'eval.{k}=...' for k in host_set)}"
        )
    try:
        # a dataset whose categories come from its files (coco-rgbt) registers none: any count checks the options
        model = build_model(det, len(dataset.categories) or 1, in_channels, options)
    except HarnessError as exc:
        if repr(det.name) in str(exc):
            raise
        raise type(exc)(f"detector {det.name!r}: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - a plugin's own exception, named with the options that caused it
        raise ConfigError(
            f"detector {det.name!r} could not be built with model options {options}: {type(exc).__name__}: {exc}"
        ) from exc
    from harness.contracts import plugin_label
    from harness.profiling.model_io import check_input_channels

    check_input_channels(
        model,
        plugin_label("detector", det.name),
        det.input_kind,
        in_channels,
        in_channels,
        int((cfg.get("protocol") or {}).get("imgsz") or 64),
    )


def build_model(det: DetectorSpec, num_classes: int, in_channels: int, model_cfg: Mapping[str, Any]) -> torch.nn.Module:
    """``det.build(num_classes, in_channels=..., **model_cfg)`` with bad options reported as a config error."""
    from harness.contracts import check_built_model, check_class_count

    try:
        model = det.build(num_classes, in_channels=in_channels, **dict(model_cfg))
    except TypeError as exc:
        if "keyword argument" in str(exc):
            raise ConfigError(
                f"detector {det.name!r} does not accept the model options {sorted(model_cfg)}: {exc}"
            ) from None
        raise
    check_built_model(model, det.name)
    check_class_count(model, det.name, num_classes)
    return model


def _init_info(init: str | Path | None) -> dict[str, Any]:
    if not init:
        return {}
    if not Path(init).is_file():
        raise ConfigError(f"train.init / --init {init}: no such checkpoint file")
    return {"init_sha1": file_digest(init)}


# ------------------------------------------------------------------------------------------------- ablation
DEFAULT_ABLATION_CATEGORIES = ("delamination", "water seepage")


@dataclass
class AblationSummary:
    detector: str
    dataset: str
    fold: str
    categories: list[str]
    runs: dict[str, RunSummary]  # encoding -> its run


def ablate(
    detector: str,
    dataset: str,
    encodings: Sequence[str],
    fold: str,
    seeds: Sequence[int] | None = None,
    *,
    categories: Sequence[str] = DEFAULT_ABLATION_CATEGORIES,
    **settings: Unpack[RunSettings],
) -> AblationSummary:
    """The encoding ablation: the same detector, fold and seeds, once per encoding (runs are stored like any other);
    ``settings`` as for ``run``."""
    if not encodings:
        raise ConfigError("--encodings: name at least one encoding, e.g. none,ir8,linear16,c2")
    if "," in fold or fold == "all":
        raise ConfigError(f"--folds {fold!r}: the ablation uses one fold, e.g. P4+P5")
    request = RunRequest(detector, dataset, folds=fold, seeds=seeds, **settings)
    runs = {enc: run(replace(request, encoding=enc)) for enc in encodings}
    first = next(iter(runs.values()))
    return AblationSummary(detector, dataset, fold, [match_category(c, first.categories) for c in categories], runs)


def match_category(wanted: str, categories: Sequence[str]) -> str:
    """``"water seepage"`` finds ``water_seepage`` or ``Water-Seepage``; an unknown name is a clear error."""
    from harness.report.reader import find_category

    found = find_category(wanted, categories)
    if found is None:
        raise ConfigError(f"category {wanted!r} is not in the dataset (categories: {', '.join(categories)})")
    return found
