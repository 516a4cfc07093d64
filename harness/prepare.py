"""The prepared-sample cache: run a dataset's sensing pipeline once, keep the aligned samples, hand out folds.

``prepare(dataset, cfg)`` opens the dataset plugin with the ``dataset`` config section (``root`` and the
plugin's own options) and the ``sensing`` section, and looks for a finished preparation under::

    <cache>/<dataset>/<key>/        <cache> = cache_root argument, else $HARNESS_CACHE, else ./cache
        manifest.json  samples.json  rgb.u8  ir8.u8  thermal.f32  boxes.f32  labels.i64   (harness.prepared)
        coco/all.json  coco/<fold>-train.json  coco/<fold>-val.json                        (thermal frame)

``key = sha1(source fingerprint, sensing config, PREPARE_VERSION, plugin code)[:16]``: the fingerprint changes with
the input files (names, sizes, modification times, annotation and registration contents) and the dataset's options,
so a changed input, a changed sensing setting or an edited plugin prepares again and never reuses stale samples.
The samples are written through ``PreparedWriter`` (a temporary folder renamed into place), so an interrupted
preparation leaves nothing behind; a damaged cache folder is prepared again. Every run, detector and encoding reads the same
prepared arrays: comparisons are sample-matched by construction.

A pair the dataset cannot use is a counted skip (``PrepareReport``), not an error; the counts, reasons and
notes are stored in ``manifest.json`` under ``report`` and printed by ``harness prepare``. Every prepared (or
reused) dataset then passes the plausibility guard (``harness.input_guard``: a fold without labels, mostly
unlabelled images, dropped annotations stop unless ``inputs.accept`` names them). An exception a dataset plugin's
code raises is a ``PluginError`` naming the plugin; two samples with one ``image_id`` are a ``DataError``; nothing is
cached in either case.
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
from harness.cache_forms import DEFAULT_FORM, ENV_FORM, check_form
from harness.errors import ConfigError, DataError, SampleError
from harness.io import atomic_write_json
from harness.prepared import PreparedDataset, PreparedWriter
from harness.progress import bar as progress_bar

log = logging.getLogger(__name__)

#: Bumped whenever preparation changes what it writes for the same inputs (part of every cache key).
PREPARE_VERSION = 2
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
                          "version": PREPARE_VERSION, "code": plugin_code_fingerprint(dataset)},
                         sort_keys=True, default=str)
    return hashlib.sha1(payload.encode()).hexdigest()[:16]


def plugin_code_fingerprint(dataset: str) -> str:
    """sha1 of the source of the registered dataset plugin: the module defining its ``open`` and the modules of
    the same package it imports names from, so an edited plugin prepares again ("" for an unregistered name)."""
    import sys

    try:
        from harness.plugins import get_host

        opener = get_host().dataset(dataset).open
    except Exception:  # noqa: BLE001 - a name no plugin registers (tests, analyses of a cache) has no code to key
        return ""
    home = inspect.getmodule(opener)
    if home is None:
        return ""
    top = home.__name__.split(".")[0]
    names = {home.__name__} | {getattr(v, "__module__", None) or getattr(v, "__name__", "")
                               for v in vars(home).values() if inspect.ismodule(v) or inspect.isclass(v)
                               or inspect.isfunction(v)}
    h = hashlib.sha1()
    for name in sorted(n for n in names if n and n.split(".")[0] == top and top != "harness"):
        path = getattr(sys.modules.get(name), "__file__", None)
        if path and Path(path).is_file():
            h.update(name.encode() + b"\0" + Path(path).read_bytes())
    return h.hexdigest()


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
    source = plugin_call(spec, "open()", spec.open, root, **options)
    return spec, source


def cache_form(form: str | None = None) -> str:
    """The cache form: ``form``, else ``$HARNESS_CACHE_FORM``, else ``compact`` (see ``harness.cache_forms``)."""
    return check_form(form or os.environ.get(ENV_FORM) or DEFAULT_FORM)


def form_folder(root: Path, dataset: str, key: str, form: str) -> Path:
    """``<root>/<dataset>/<key>`` (compact) or ``<root>/<dataset>/<key>-raw``: both forms can sit side by side."""
    return root / dataset / (key if form == DEFAULT_FORM else f"{key}-{form}")


def prepare(dataset: str | DatasetSpec, cfg: Mapping[str, Any], cache_root: str | Path | None = None,
            force: bool = False, progress: bool = True, form: str | None = None) -> PreparedDataset:
    """Prepared samples of ``dataset`` under the current config (prepared now if not cached), in cache ``form``
    (``compact`` or ``raw``, default ``$HARNESS_CACHE_FORM`` or ``compact``): every form loads identical samples.

    The returned ``PreparedDataset`` has two extra attributes: ``from_cache`` (bool) and ``key``.
    """
    form = cache_form(form)
    spec, source = open_source(dataset, cfg)
    sensing = preparation_sensing(cfg.get("sensing"))
    fingerprint = plugin_call(spec, "fingerprint()", source.fingerprint)
    key = cache_key(fingerprint, sensing, spec.name)
    folder = form_folder(_cache_root(cache_root), spec.name, key, form)
    ds: PreparedDataset | None = None
    if not force and (folder / "manifest.json").exists():
        try:
            ds = PreparedDataset(folder)
            _check_arrays(ds)
        except DataError as exc:
            ds = None
            log.warning("prepared data in %s is damaged (%s); preparing again", folder, exc)
        else:
            if ds.form != form:  # written before cache forms existed: the raw layout in the default folder
                log.info("prepared data in %s is in the %s form; preparing the %s form", folder, ds.form, form)
        if ds is not None and ds.form == form:
            mark_used(folder)
            log.info("using prepared %s from %s", spec.name, folder)
            return _checked(spec, ds, cfg, key, from_cache=True)
    ds = _build(spec, source, folder, key, fingerprint, sensing, progress, form)
    mark_used(folder)
    return _checked(spec, ds, cfg, key, from_cache=False)


def _checked(spec: DatasetSpec, ds: PreparedDataset, cfg: Mapping[str, Any], key: str,
             from_cache: bool) -> PreparedDataset:
    """The COCO files of the folds written, the plausibility guard passed (``harness.input_guard``: an unaccepted
    finding is a ``DataError``), and the extra attributes set: ``from_cache``, ``key`` and ``input_risks`` (the
    accepted findings, as dicts, that label every result on these samples)."""
    from harness import input_guard

    folds = resolve_folds(spec, ds, cfg)
    _ensure_coco(ds, folds)
    risks = input_guard.check(ds, folds, cfg)
    for line in input_guard.describe(risks):
        log.warning("%s: %s", spec.name, line)
    ds.from_cache, ds.key = from_cache, key  # type: ignore[attr-defined]
    ds.input_risks = [f.as_dict() for f in risks]  # type: ignore[attr-defined]
    return ds


def _cache_root(root: str | Path | None) -> Path:
    return cache_root(root)


USED_MARK = ".last-used"


def mark_used(folder: Path) -> None:
    """Touch ``<folder>/.last-used`` (what ``harness cache rm --unused`` goes by); a read-only cache is fine."""
    try:
        (folder / USED_MARK).touch()
    except OSError:
        pass


def _check_arrays(ds: PreparedDataset) -> None:
    """The arrays hold exactly what ``samples.json`` describes (a truncated copy is caught here)."""
    px = sum(r["height"] * r["width"] for r in ds.records)
    nb = sum(r["n"] for r in ds.records)
    sizes = {"rgb.u8": px * 3, "ir8.u8": px, "boxes.f32": nb * 16, "labels.i64": nb * 8}
    if ds.radiometric:
        sizes["thermal.f32"] = px * 4
    if ds.form != "raw":
        ends = {name: max([sum(r[ch]) for r in ds.records if ch in r], default=0)
                for name, ch in (("rgb.pack", "rgb"), ("ir8.pack", "ir8"), ("thermal.pack", "thermal"))}
        sizes = {"boxes.f32": nb * 16, "labels.i64": nb * 8, "rgb.pack": ends["rgb.pack"], "ir8.pack": ends["ir8.pack"]}
        if ds.radiometric:
            sizes["thermal.pack"] = ends["thermal.pack"]
        if ds.codec == "zstd":
            from harness.cache_forms import _zstd

            _zstd(str(ds.folder))  # written where zstandard was installed: prepared again (png) when it is not here
        missing = [str(p) for p in ds.sources if not p.is_dir()]
        if missing:
            raise DataError(f"the source folder(s) its samples refer to are gone: {', '.join(missing)}")
    for name, size in sizes.items():
        got = (ds.folder / name).stat().st_size
        if got != size:
            raise DataError(f"{ds.folder / name}: {got} bytes, expected {size}")


def _reference_bases(source: Any) -> list[Path]:
    """Folders an 8-bit sample's ``meta`` file names may be relative to (the dataset's image and root folders)."""
    out: list[Path] = []
    for attr in ("images_dir", "root", "base"):
        value = getattr(source, attr, None)
        if isinstance(value, (str, Path)) and Path(value).is_dir() and Path(value) not in out:
            out.append(Path(value))
    return out


def _build(spec: DatasetSpec, source: Any, folder: Path, key: str, fingerprint: str, sensing: dict[str, Any],
           progress: bool, form: str = DEFAULT_FORM) -> PreparedDataset:
    report = PrepareReport()
    folds = [asdict(f) for f in plugin_call(spec, "folds()", source.folds)]
    groups = list(plugin_call(spec, "groups()", source.groups))
    extra = {"key": key, "prepare_version": PREPARE_VERSION, "groups": groups, "folds": folds,
             "sensing": sensing}
    total = len(source) if hasattr(source, "__len__") else None
    missing: dict[str, int] = {}
    routes: dict[str, Any] = {}
    t0 = time.perf_counter()
    # the source's categories win: a dataset whose categories come from its files (coco-rgbt) registers none
    categories = tuple(getattr(source, "categories", None) or spec.categories)
    if not categories:
        raise DataError(f"dataset {spec.name!r}: no categories (neither the opened source nor the spec names any)")
    bases = _reference_bases(source)
    if bases:
        from harness.cache_admin import folder_bytes

        extra["source_bytes"] = folder_bytes(bases[-1] if getattr(source, "root", None) is None else Path(source.root))
    writer = PreparedWriter(folder, spec.name, categories, fingerprint=fingerprint, extra=extra, form=form,
                            sources=bases if form == "compact" else (),
                            pixel_files=getattr(source, "pixel_files", None))
    seen: dict[Any, str] = {}
    try:
        with progress_bar(f"preparing {spec.name}", total, enabled=progress, eta=True, transient=False) as bar:
            for sample in _plugin_samples(spec, source, report):
                where = sample.meta.get("file_name", sample.image_id) if isinstance(sample.meta, dict) \
                    else sample.image_id
                _check_unique(spec, seen, sample, str(where))
                try:
                    writer.add(sample)
                except SampleError as exc:
                    report.skip(where, f"invalid sample: {exc}")
                else:
                    _count_missing(missing, sample)
                    _count_route(routes, sample)
                bar.advance()
        if not writer.records:
            summary = report.summary()
            raise DataError(f"dataset {spec.name!r}: no usable image pairs ({summary['skipped']} skipped: "
                            f"{_reasons_text(summary['skip_reasons'])}); nothing was cached")
        if hasattr(source, "write_artifacts"):
            source.write_artifacts(writer.tmp)
        summary = report.summary()
        summary["skipped_files"] = [list(s) for s in report.skipped[:MAX_LISTED_SKIPS]]
        summary["missing_temperatures"] = {"samples": len(missing), "pixels": sum(missing.values()),
                                           "per_sample": dict(list(missing.items())[:MAX_LISTED_SKIPS])}
        if routes:
            summary.update(routes)
            if "approximate_temperatures" in routes:
                a = routes["approximate_temperatures"]
                report.note(f"{a['samples']} sample(s) hold approximate temperatures (within {a['bound_c']:g} C of "
                            f"DJI's SDK at worst: {', '.join(a['approximations'])}); results on them say so")
                summary["notes"] = list(report.notes)
        summary["seconds"] = round(time.perf_counter() - t0, 3)
        writer.close(summary)
    except BaseException:
        writer.abort()
        raise
    log.info("prepared %d samples of %s in %s (%.1f s)", len(writer.records), spec.name, folder, summary["seconds"])
    return PreparedDataset(folder)


def plugin_label(spec: DatasetSpec) -> str:
    """``dataset 'NAME' (plugin P)``: how an error names a dataset and the plugin that registered it."""
    try:
        from harness.plugins import get_host

        owner = get_host().owner("dataset", spec.name)
    except Exception:  # noqa: BLE001 - a spec no plugin registered (tests, the API) has no owner to name
        owner = getattr(spec.open, "__module__", None)
    return f"dataset {spec.name!r}" + (f" (plugin {owner})" if owner else "")


def plugin_call(spec: DatasetSpec, what: str, func: Any, *args: Any, **kwargs: Any) -> Any:
    """``func(*args, **kwargs)`` of a dataset plugin; an exception its code raises becomes a ``PluginError`` naming the
    dataset, its plugin, the call (``what``) and where it was raised. A ``HarnessError`` passes unchanged."""
    from harness.errors import HarnessError, PluginError
    from harness.plugins import where

    try:
        return func(*args, **kwargs)
    except (HarnessError, KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:
        raise PluginError(f"{plugin_label(spec)}: {what} raised {type(exc).__name__}: {exc}{where(exc)}") from exc


def _plugin_samples(spec: DatasetSpec, source: Any, report: PrepareReport) -> Iterable[Any]:
    """``source.samples(report)``, with an exception the plugin's code raises turned into a ``PluginError`` that names
    the dataset, its plugin and where it was raised (a ``HarnessError`` it raises on purpose passes unchanged)."""
    from harness.errors import HarnessError, PluginError
    from harness.plugins import where

    try:
        yield from source.samples(report)
    except (HarnessError, KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:
        raise PluginError(f"{plugin_label(spec)}: samples() raised {type(exc).__name__}: {exc}{where(exc)}; "
                          f"nothing was cached") from exc


def _check_unique(spec: DatasetSpec, seen: dict[Any, str], sample: Any, where: str) -> None:
    """Two samples with one ``image_id`` are a ``DataError`` (not a skip: keeping the first would publish a cache
    without the others and every result on it would be wrong)."""
    import numbers

    iid = getattr(sample, "image_id", None)
    if isinstance(iid, numbers.Integral) and not isinstance(iid, bool):
        iid = int(iid)
        if iid in seen:
            raise DataError(f"{plugin_label(spec)}: image_id {iid!r} is given to two samples ({seen[iid]} and "
                            f"{where}); every sample needs its own image_id. Nothing was cached")
        seen[iid] = where


def _count_missing(missing: dict[str, int], sample: Any) -> None:
    """Record how many of a kept sample's temperatures are missing (NaN or inf), when any."""
    if sample.thermal is not None:
        from harness.sensing.c2 import invalid_count

        n = invalid_count(sample.thermal)
        if n:
            missing[sample.name] = n


def _count_route(routes: dict[str, Any], sample: Any) -> None:
    """Record a kept sample's thermal route when it is not DJI's own correction: ``approximate_temperatures``
    (samples, worst bound, approximations) and ``converted_temperatures`` (samples)."""
    meta = sample.meta if isinstance(sample.meta, dict) else {}
    route = meta.get("thermal_route")
    if route == "approximate":
        a = routes.setdefault("approximate_temperatures", {"label": "approximate temperatures", "samples": 0,
                                                           "bound_c": 0.0, "approximations": []})
        a["samples"] += 1
        a["bound_c"] = max(a["bound_c"], float(meta.get("temperature_bound_c") or 0.0))
        if meta.get("approximation") and meta["approximation"] not in a["approximations"]:
            a["approximations"].append(meta["approximation"])
    elif route:
        c = routes.setdefault(f"{route}_temperatures", {"samples": 0})
        c["samples"] += 1


def _reasons_text(reasons: Mapping[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])) or "none"


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
    if not train and not fold.train_groups:
        raise DataError(f"fold {fold.name!r} holds out every group of the prepared data "
                        f"({', '.join(fold.val_groups)}): nothing is left to train on; give the dataset a second "
                        f"group or set protocol.folds")
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
