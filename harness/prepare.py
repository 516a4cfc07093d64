"""The prepared-sample cache: run a dataset's sensing pipeline once, keep the aligned samples, hand out folds.

``prepare(dataset, cfg)`` opens the dataset plugin with the ``dataset`` config section (``root`` and the
plugin's own options) and the ``sensing`` section, and looks for a finished preparation under::

    <cache>/<dataset>/<key>/        <cache> = cache_root argument, else $HARNESS_CACHE, else ./cache
        manifest.json  samples.json  rgb.u8  ir8.u8  thermal.f32  boxes.f32  labels.i64   (harness.prepared)
        coco/all.json  coco/<fold>-train.json  coco/<fold>-val.json                        (thermal frame)

``key = sha1(source fingerprint, sensing config, PREPARE_VERSION)[:16]``: the fingerprint changes with the input
files (names, sizes, modification times, annotation and registration contents) and the dataset's options, so a
changed input or a changed sensing setting prepares again and never reuses stale samples. The samples are
written through ``PreparedWriter`` (a temporary folder renamed into place), so an interrupted preparation leaves
nothing behind; a damaged cache folder is prepared again. Every run, detector and encoding reads the same
prepared arrays: comparisons are sample-matched by construction.

A pair the dataset cannot use is a counted skip (``PrepareReport``), not an error; the counts, reasons and
notes are stored in ``manifest.json`` under ``report`` and printed by ``harness prepare``.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import logging
import os
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from harness.api import DatasetSpec, Fold, PrepareReport
from harness.errors import ConfigError, DataError, SampleError
from harness.io import atomic_write_json
from harness.prepared import PreparedDataset, PreparedWriter

log = logging.getLogger(__name__)

#: Bumped whenever preparation changes what it writes for the same inputs (part of every cache key).
PREPARE_VERSION = 1
ENV_CACHE = "HARNESS_CACHE"
#: How many skipped files are listed by name in the prepared manifest (all are counted).
MAX_LISTED_SKIPS = 2000


def cache_root(root: str | Path | None = None) -> Path:
    """Where prepared datasets live: ``root``, else ``$HARNESS_CACHE``, else ``./cache``."""
    if root is not None:
        return Path(root)
    return Path(os.environ.get(ENV_CACHE) or "cache")


#: ``sensing`` sub-sections that only steer analyses of prepared data, not preparation (left out of the key).
ANALYSIS_ONLY_SENSING = ("displacement",)


def preparation_sensing(sensing: Mapping[str, Any] | None) -> dict[str, Any]:
    """The part of the ``sensing`` section that can change prepared samples."""
    return {k: v for k, v in dict(sensing or {}).items() if k not in ANALYSIS_ONLY_SENSING}


def cache_key(fingerprint: str, sensing: Mapping[str, Any] | None, dataset: str) -> str:
    """``sha1({dataset, fingerprint, sensing, PREPARE_VERSION})`` as 16 hex digits (analysis-only sensing keys,
    such as the displacement study's shifts, are left out)."""
    payload = json.dumps({"dataset": dataset, "fingerprint": fingerprint, "sensing": preparation_sensing(sensing),
                          "version": PREPARE_VERSION}, sort_keys=True, default=str)
    return hashlib.sha1(payload.encode()).hexdigest()[:16]


def _spec(dataset: str | DatasetSpec) -> DatasetSpec:
    if isinstance(dataset, DatasetSpec):
        return dataset
    from harness.plugins import get_host

    return get_host().dataset(dataset)


def open_source(dataset: str | DatasetSpec, cfg: Mapping[str, Any]) -> tuple[DatasetSpec, Any]:
    """Open ``dataset`` with the ``dataset`` config section (``root`` + options) and, when the plugin's ``open``
    takes it, the ``sensing`` section. An option ``open`` does not accept is a ``ConfigError`` naming it."""
    spec = _spec(dataset)
    options = dict(cfg.get("dataset") or {})
    root = options.pop("root", None)
    params = inspect.signature(spec.open).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    if "sensing" in params or takes_any:
        options.setdefault("sensing", dict(cfg.get("sensing") or {}))
    unknown = [k for k in options if k not in params and not takes_any]
    if unknown:
        known = [p for p in params if p not in ("root", "self") and params[p].kind is not inspect.Parameter.VAR_KEYWORD]
        raise ConfigError(f"dataset {spec.name!r} does not take option(s) {', '.join(map(repr, unknown))} "
                          f"(dataset.<option>); it takes: root, {', '.join(known) or 'nothing else'}")
    source = spec.open(root, **options)
    return spec, source


def prepare(dataset: str | DatasetSpec, cfg: Mapping[str, Any], cache_root: str | Path | None = None,
            force: bool = False, progress: bool = True) -> PreparedDataset:
    """Prepared, memory-mapped samples of ``dataset`` under the current config (prepared now if not cached).

    The returned ``PreparedDataset`` has two extra attributes: ``from_cache`` (bool) and ``key``.
    """
    spec, source = open_source(dataset, cfg)
    sensing = preparation_sensing(cfg.get("sensing"))
    fingerprint = source.fingerprint()
    key = cache_key(fingerprint, sensing, spec.name)
    folder = _cache_root(cache_root) / spec.name / key
    if not force and (folder / "manifest.json").exists():
        try:
            ds = PreparedDataset(folder)
            _check_arrays(ds)
        except DataError as exc:
            log.warning("prepared data in %s is damaged (%s); preparing again", folder, exc)
        else:
            _ensure_coco(ds, resolve_folds(spec, ds, cfg))
            log.info("using prepared %s from %s", spec.name, folder)
            ds.from_cache, ds.key = True, key  # type: ignore[attr-defined]
            return ds
    ds = _build(spec, source, folder, key, fingerprint, sensing, progress)
    _ensure_coco(ds, resolve_folds(spec, ds, cfg))
    ds.from_cache, ds.key = False, key  # type: ignore[attr-defined]
    return ds


def _cache_root(root: str | Path | None) -> Path:
    return cache_root(root)


def _check_arrays(ds: PreparedDataset) -> None:
    """The arrays hold exactly what ``samples.json`` describes (a truncated copy is caught here)."""
    px = sum(r["height"] * r["width"] for r in ds.records)
    nb = sum(r["n"] for r in ds.records)
    sizes = {"rgb.u8": px * 3, "ir8.u8": px, "boxes.f32": nb * 16, "labels.i64": nb * 8}
    if ds.radiometric:
        sizes["thermal.f32"] = px * 4
    for name, size in sizes.items():
        got = (ds.folder / name).stat().st_size
        if got != size:
            raise DataError(f"{ds.folder / name}: {got} bytes, expected {size}")


def _build(spec: DatasetSpec, source: Any, folder: Path, key: str, fingerprint: str, sensing: dict[str, Any],
           progress: bool) -> PreparedDataset:
    report = PrepareReport()
    folds = [asdict(f) for f in source.folds()]
    extra = {"key": key, "prepare_version": PREPARE_VERSION, "groups": list(source.groups()), "folds": folds,
             "sensing": sensing}
    total = len(source) if hasattr(source, "__len__") else None
    t0 = time.perf_counter()
    # the source's categories win: a dataset whose categories come from its files (coco-rgbt) registers none
    categories = tuple(getattr(source, "categories", None) or spec.categories)
    if not categories:
        raise DataError(f"dataset {spec.name!r}: no categories (neither the opened source nor the spec names any)")
    writer = PreparedWriter(folder, spec.name, categories, fingerprint=fingerprint, extra=extra)
    try:
        with _Bar(progress, total, f"preparing {spec.name}") as bar:
            for sample in source.samples(report):
                try:
                    writer.add(sample)
                except SampleError as exc:
                    report.skip(sample.meta.get("file_name", sample.image_id) if isinstance(sample.meta, dict)
                                else sample.image_id, f"invalid sample: {exc}")
                bar.advance()
        if not writer.records:
            summary = report.summary()
            raise DataError(f"dataset {spec.name!r}: no usable image pairs ({summary['skipped']} skipped: "
                            f"{_reasons_text(summary['skip_reasons'])}); nothing was cached")
        if hasattr(source, "write_artifacts"):
            source.write_artifacts(writer.tmp)
        summary = report.summary()
        summary["skipped_files"] = [list(s) for s in report.skipped[:MAX_LISTED_SKIPS]]
        summary["seconds"] = round(time.perf_counter() - t0, 3)
        writer.close(summary)
    except BaseException:
        writer.abort()
        raise
    log.info("prepared %d samples of %s in %s (%.1f s)", len(writer.records), spec.name, folder, summary["seconds"])
    return PreparedDataset(folder)


def _reasons_text(reasons: Mapping[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])) or "none"


class _Bar:
    """A rich progress bar (or nothing when disabled)."""

    def __init__(self, enabled: bool, total: int | None, description: str):
        self.enabled, self.total, self.description = enabled, total, description
        self.bar: Any = None

    def __enter__(self) -> "_Bar":
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                TimeRemainingColumn())
            self.task = self.bar.add_task(self.description, total=self.total)
            self.bar.start()
        return self

    def advance(self) -> None:
        if self.bar is not None:
            self.bar.advance(self.task)

    def __exit__(self, *exc: Any) -> None:
        if self.bar is not None:
            self.bar.stop()


# ------------------------------------------------------------------------------------------------ folds
def resolve_folds(dataset_spec: DatasetSpec | str, prepared: PreparedDataset, cfg: Mapping[str, Any],
                  selection: str | Sequence[str] | None = "all") -> list[Fold]:
    """The evaluation folds: ``cfg["protocol"]["folds"]`` (``{fold name: [held-out groups]}``, training on every
    other group present) when set, else the dataset's own folds recorded at preparation. ``selection``: ``"all"``,
    a fold name, a comma-separated list of names, or a list of names."""
    name = dataset_spec.name if isinstance(dataset_spec, DatasetSpec) else str(dataset_spec)
    present = sorted(set(prepared.groups))
    spec_folds = (cfg.get("protocol") or {}).get("folds")
    folds: list[Fold] = []
    if spec_folds:
        if not isinstance(spec_folds, Mapping):
            raise ConfigError(f"protocol.folds must map fold names to lists of held-out groups, got {spec_folds!r}")
        for fold_name, held in spec_folds.items():
            held_t = (held,) if isinstance(held, str) else tuple(held or ())
            missing = [g for g in held_t if g not in present]
            if missing:
                raise ConfigError(f"protocol.folds: fold {fold_name!r} holds out {', '.join(map(repr, missing))}, "
                                  f"which dataset {name!r} does not have; its groups are {', '.join(present)}")
            if not held_t:
                raise ConfigError(f"protocol.folds: fold {fold_name!r} holds out no group")
            folds.append(Fold(str(fold_name), tuple(g for g in present if g not in held_t), held_t))
    else:
        recorded = prepared.manifest.get("folds") or []
        for f in recorded:
            val = tuple(g for g in f["val_groups"] if g in present)
            if val:
                folds.append(Fold(f["name"], tuple(g for g in f["train_groups"] if g in present), val))
        if not folds:  # nothing recorded: leave one group out
            folds = [Fold(g, tuple(x for x in present if x != g), (g,)) for g in present]
    return select_folds(folds, selection)


def select_folds(folds: list[Fold], selection: str | Sequence[str] | None) -> list[Fold]:
    if selection is None or selection == "all" or selection == ["all"]:
        return folds
    names = [s.strip() for s in selection.split(",")] if isinstance(selection, str) else [str(s) for s in selection]
    by_name = {f.name: f for f in folds}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ConfigError(f"unknown fold(s) {', '.join(map(repr, unknown))}; available: "
                          f"{', '.join(by_name)} (or 'all')")
    return [by_name[n] for n in names]


def fold_indices(prepared: PreparedDataset, fold: Fold) -> tuple[list[int], list[int]]:
    """Sample indices (into ``prepared``) of the fold's training and held-out groups."""
    train, val = prepared.indices(fold.train_groups), prepared.indices(fold.val_groups)
    if not val:
        raise DataError(f"fold {fold.name!r}: no prepared images in the held-out group(s) "
                        f"{', '.join(fold.val_groups)}")
    if not train:
        raise DataError(f"fold {fold.name!r}: no prepared images to train on (groups {', '.join(fold.train_groups)})")
    return train, val


@dataclass
class FoldSupport:
    fold: str
    train_groups: tuple[str, ...]
    val_groups: tuple[str, ...]
    train_images: int
    train_instances: int
    val_images: int
    val_instances: int
    val_categories: dict[str, int]


def fold_support(prepared: PreparedDataset, folds: Iterable[Fold]) -> list[FoldSupport]:
    """Images and instances of each fold's training and held-out parts (what ``harness folds`` prints)."""
    out = []
    for f in folds:
        tr, va = fold_indices(prepared, f)
        st, sv = prepared.support(tr), prepared.support(va)
        out.append(FoldSupport(f.name, f.train_groups, f.val_groups, st["images"], st["instances"], sv["images"],
                               sv["instances"], sv["categories"]))
    return out


# ------------------------------------------------------------------------------------------------ COCO
_SAFE = re.compile(r"[^A-Za-z0-9_.+-]")


def coco_path(prepared: PreparedDataset, fold: Fold | None = None, split: str = "val") -> Path:
    """The COCO ground-truth file (thermal frame) of a fold's split, written when missing; ``fold=None``: all."""
    if fold is None:
        path = prepared.folder / "coco" / "all.json"
        idx = None
    else:
        if split not in ("train", "val"):
            raise ValueError(f"split must be 'train' or 'val', got {split!r}")
        path = prepared.folder / "coco" / f"{_SAFE.sub('_', fold.name)}-{split}.json"
        tr, va = fold_indices(prepared, fold)
        idx = tr if split == "train" else va
    if not path.exists():
        coco = prepared.coco(idx)
        coco["info"].update({"fold": None if fold is None else fold.name, "split": split if fold else "all",
                             "key": prepared.manifest.get("key")})
        atomic_write_json(path, coco, indent=None)
    return path


def _ensure_coco(prepared: PreparedDataset, folds: Iterable[Fold]) -> None:
    coco_path(prepared)
    for f in folds:
        for split in ("train", "val"):
            coco_path(prepared, f, split)
