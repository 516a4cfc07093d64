"""Preparing a dataset: run its sensing pipeline once, keep the aligned samples in the cache, check them.

``prepare(dataset, cfg)`` opens the dataset plugin with the ``dataset`` config section (``root`` and the
plugin's own options) and the ``sensing`` section, and looks for a finished preparation under::

    <cache>/<dataset>/<key>/        (harness.cache.key: where, and the key)
        manifest.json  samples.json  rgb.pack  ir8.pack  thermal.pack  boxes.f32  labels.i64   (harness.cache.writer)
        coco/all.json  coco/<fold>-train.json  coco/<fold>-val.json          (harness.cache.folds, thermal frame)

What the plugin returns is checked where it enters (``harness.contracts``: the opened source, its groups, folds and
fingerprint, every sample). The samples are written through ``PreparedWriter`` (a temporary folder renamed into
place), so an interrupted preparation leaves nothing behind; a damaged cache folder is prepared again. Every run,
detector and encoding reads the same prepared arrays: comparisons are sample-matched by construction.

A pair the dataset cannot use is a counted skip (``PrepareReport``), not an error; the counts, reasons and
notes are stored in ``manifest.json`` under ``report`` and printed by ``harness prepare``. Every prepared (or
reused) dataset then passes the plausibility guard (``harness.input_guard``: a fold without labels, mostly
unlabelled images, dropped annotations stop unless ``inputs.accept`` names them). An exception a dataset plugin's
code raises is a ``PluginError`` naming the plugin; two samples with one ``image_id`` are a ``DataError``; nothing is
cached in either case.
"""

from __future__ import annotations

import inspect
import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterable, Mapping

from harness import contracts
from harness.api import DatasetSpec, PrepareReport
from harness.cache.admin import folder_bytes, mark_used
from harness.cache.folds import ensure_coco, resolve_folds
from harness.cache.forms import DEFAULT_FORM, FORMS
from harness.cache.key import PREPARE_VERSION, cache_form, cache_key, cache_root, form_folder, preparation_sensing
from harness.cache.reader import PreparedDataset
from harness.cache.writer import PreparedWriter
from harness.errors import ConfigError, DataError, SampleError
from harness.progress import bar as progress_bar

log = logging.getLogger(__name__)

#: How many skipped files are listed by name in the prepared manifest (all are counted).
MAX_LISTED_SKIPS = 2000


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
        raise ConfigError(
            f"dataset {spec.name!r} does not take option(s) {', '.join(map(repr, unknown))} "
            f"(dataset.<option>); it takes: root, {', '.join(known) or 'nothing else'}"
        )
    label = plugin_label(spec)
    source = contracts.plugin_call(label, "open()", spec.open, root, **options)
    return spec, contracts.check_source(source, label)


def prepare(
    dataset: str | DatasetSpec,
    cfg: Mapping[str, Any],
    cache_root: str | Path | None = None,
    force: bool = False,
    progress: bool = True,
    form: str | None = None,
) -> PreparedDataset:
    """Prepared samples of ``dataset`` under the current config (prepared now if not cached), in cache ``form``
    (``compact`` or ``raw``, default ``$HARNESS_CACHE_FORM`` or ``compact``): every form loads identical samples.

    The returned ``PreparedDataset`` has two extra attributes: ``from_cache`` (bool) and ``key``.
    """
    form = cache_form(form)
    spec, source = open_source(dataset, cfg)
    sensing = preparation_sensing(cfg.get("sensing"))
    label = plugin_label(spec)
    fingerprint = contracts.check_fingerprint(contracts.plugin_call(label, "fingerprint()", source.fingerprint), label)
    key = cache_key(fingerprint, sensing, spec.name)
    folder = form_folder(_cache_root(cache_root), spec.name, key, form)
    ds: PreparedDataset | None = None
    if not force and (folder / "manifest.json").exists():
        try:
            ds = PreparedDataset(folder)
            ds.check_sizes()
        except DataError as exc:
            ds = None
            log.warning("prepared data in %s is damaged (%s); preparing again", folder, exc)
        else:
            if ds.form != form:  # written before cache forms existed: the raw layout in the default folder
                log.info("prepared data in %s is in the %s form; preparing the %s form", folder, ds.form, form)
        if ds is not None and ds.form == form:
            mark_used(folder)
            log.info("using prepared %s from %s", spec.name, folder)
            note_other_versions(ds)
            return _checked(spec, ds, cfg, key, from_cache=True)
    earlier = earlier_identity(_cache_root(cache_root), spec.name, key)
    ds = _build(spec, source, folder, key, fingerprint, sensing, progress, form, earlier)
    mark_used(folder)
    return _checked(spec, ds, cfg, key, from_cache=False)


#: The file of a prepared folder that records which sample each image id holds (``sample_identity``).
IDENTITY_FILE = "identity.json"


def sample_identity(sample: Any, where: Any) -> list[Any]:
    """``[image_id, name, digest of the 8-bit thermal pixels]``: what an image id stands for in a preparation."""
    import hashlib

    import numpy as np

    return [int(sample.image_id), str(where), hashlib.sha1(np.ascontiguousarray(sample.ir8).tobytes()).hexdigest()[:16]]


def identity_digest(rows: list[list[Any]]) -> str:
    """One digest of which sample every image id holds (a run records it as ``meta.prepared_samples``)."""
    import hashlib
    import json

    return hashlib.sha1(json.dumps(sorted([r[0], r[2]] for r in rows)).encode()).hexdigest()[:16]


def earlier_identity(root: Path, dataset: str, key: str) -> tuple[Path, dict[int, list[Any]]] | None:
    """(folder, image id -> identity) of an earlier preparation under the same ``key`` (the folder being prepared
    again, or the other cache form's), or None when there is none (or it predates identity records)."""
    import json

    for f in FORMS:
        path = form_folder(root, dataset, key, f) / IDENTITY_FILE
        try:
            rows = json.loads(path.read_text(encoding="utf-8"))
            return path.parent, {int(r[0]): list(r) for r in rows}
        except (OSError, ValueError, TypeError, IndexError, KeyError):
            continue
    return None


def _compare_identity(label: str, earlier: tuple[Path, dict[int, list[Any]]], rows: list[list[Any]]) -> None:
    """A ``DataError`` when an image id of this preparation holds another sample than in the earlier preparation of
    the same key (a plugin whose sample order or ids change between calls)."""
    folder, old = earlier
    new = {int(r[0]): r for r in rows}
    changed = [i for i in sorted(set(old) & set(new)) if old[i][2] != new[i][2]]
    gone, added = sorted(set(old) - set(new)), sorted(set(new) - set(old))
    if not (changed or gone or added):
        return
    examples = [f"image_id {i}: {old[i][1]} before, {new[i][1]} now" for i in changed[:3]]
    examples += [f"image_id {i}: {old[i][1]} before, absent now" for i in gone[: max(0, 3 - len(examples))]]
    examples += [f"image_id {i}: new, {new[i][1]}" for i in added[: max(0, 3 - len(examples))]]
    raise DataError(
        f"{label}: samples() gave other samples under the same image ids than the earlier preparation with the "
        f"same cache key ({folder}): {len(changed)} of {len(new)} id(s) hold another picture, {len(gone)} gone, "
        f"{len(added)} new; e.g. " + "; ".join(examples) + ". The plugin's sample order or image ids change between "
        "calls (a folder listing or a set iterated without sorting?): give every file the same image_id each time. "
        "Runs and reports on the earlier samples would draw and score other pictures; nothing was cached. To "
        f"replace the earlier samples anyway, remove {folder} (harness cache) and prepare again"
    )


def cached(dataset: str, key: str, cache_root: str | Path | None = None) -> PreparedDataset | None:
    """The prepared ``dataset`` stored under ``key`` (a run records it as ``meta.prepared_key``) in either form, or
    None when the cache holds no such folder. Nothing is prepared and no plugin is needed: the report draws held-out
    samples from it."""
    root = _cache_root(cache_root)
    for form in dict.fromkeys((cache_form(), *FORMS)):
        folder = form_folder(root, dataset, key, form)
        if (folder / "manifest.json").is_file():
            ds = PreparedDataset(folder)
            ds.check_sizes()
            return ds
    return None


def note_other_versions(ds: PreparedDataset) -> list[str]:
    """Warn when the prepared samples were made with other releases of the packages that shape samples than this
    environment has (``harness.provenance``): they are used as they are, so every run on them stays on one set of
    samples, and ``--force`` prepares them again here. Returns the differences."""
    from harness import provenance

    then = ds.manifest.get("environment")
    if not isinstance(then, dict):
        log.info("prepared data in %s does not record the package versions that made it", ds.folder)
        return []
    diffs = provenance.differences(provenance.sample_environment(), then, provenance.SAMPLE_PACKAGES, "prepared with")
    if diffs:
        log.warning(
            "prepared data in %s was made with other package versions than this environment has (%s); its samples "
            "are used as they are (`harness prepare --force` prepares them again with these versions)",
            ds.folder,
            "; ".join(diffs),
        )
    return diffs


def _checked(
    spec: DatasetSpec, ds: PreparedDataset, cfg: Mapping[str, Any], key: str, from_cache: bool
) -> PreparedDataset:
    """The COCO files of the folds written, the plausibility guard passed (``harness.input_guard``: an unaccepted
    finding is a ``DataError``), and the extra attributes set: ``from_cache``, ``key`` and ``input_risks`` (the
    accepted findings, as dicts, that label every result on these samples)."""
    from harness import input_guard

    try:
        folds = resolve_folds(spec, ds, cfg)
        ensure_coco(ds, folds)
    except DataError:
        input_guard.check(ds, [], cfg)  # samples left out on the way (invalid, dropped boxes) explain an empty fold
        raise
    risks = input_guard.check(ds, folds, cfg)
    for line in input_guard.describe(risks):
        log.warning("%s: %s", spec.name, line)
    ds.from_cache, ds.key = from_cache, key  # type: ignore[attr-defined]
    ds.input_risks = [f.as_dict() for f in risks]  # type: ignore[attr-defined]
    return ds


def _cache_root(root: str | Path | None) -> Path:
    return cache_root(root)


def _reference_bases(source: Any) -> list[Path]:
    """Folders an 8-bit sample's ``meta`` file names may be relative to (the dataset's image and root folders)."""
    out: list[Path] = []
    for attr in ("images_dir", "root", "base"):
        value = getattr(source, attr, None)
        if isinstance(value, (str, Path)) and Path(value).is_dir() and Path(value) not in out:
            out.append(Path(value))
    return out


def _build(
    spec: DatasetSpec,
    source: Any,
    folder: Path,
    key: str,
    fingerprint: str,
    sensing: dict[str, Any],
    progress: bool,
    form: str = DEFAULT_FORM,
    earlier: tuple[Path, dict[int, list[Any]]] | None = None,
) -> PreparedDataset:
    report = PrepareReport()
    label = plugin_label(spec)
    folds = [asdict(f) for f in contracts.check_folds(contracts.plugin_call(label, "folds()", source.folds), label)]
    groups = contracts.check_groups(contracts.plugin_call(label, "groups()", source.groups), label)
    extra = {"key": key, "prepare_version": PREPARE_VERSION, "groups": groups, "folds": folds, "sensing": sensing}
    total = len(source) if hasattr(source, "__len__") else None
    missing: dict[str, int] = {}
    routes: dict[str, Any] = {}
    t0 = time.perf_counter()
    # the source's categories win: a dataset whose categories come from its files (coco-rgbt) registers none
    categories = tuple(getattr(source, "categories", None) or spec.categories)
    if not categories:
        raise DataError(f"dataset {spec.name!r}: no categories (neither the opened source nor the spec names any)")
    order = category_order(tuple(spec.categories or ()), categories)
    bases = _reference_bases(source)
    if bases:
        extra["source_bytes"] = folder_bytes(bases[-1] if getattr(source, "root", None) is None else Path(source.root))
    writer = PreparedWriter(
        folder,
        spec.name,
        categories,
        fingerprint=fingerprint,
        extra=extra,
        form=form,
        sources=bases if form == "compact" else (),
        pixel_files=getattr(source, "pixel_files", None),
    )
    seen: dict[int, str] = {}
    implausible: dict[str, Any] = {"samples": 0, "examples": [], "pixels": 0}
    identity: list[list[Any]] = []
    try:
        with progress_bar(f"preparing {spec.name}", total, enabled=progress, eta=True, transient=False) as bar:
            for sample in _plugin_samples(label, source, report):
                where = _sample_where(sample)
                contracts.check_unique_id(seen, sample, str(where), label)
                try:
                    sample = _plausible_temperatures(sample, where, implausible)
                    writer.add(sample)
                except SampleError as exc:
                    report.skip(where, f"invalid sample: {exc}")
                else:
                    _count_missing(missing, sample)
                    _count_route(routes, sample)
                    identity.append(sample_identity(sample, where))
                bar.advance()
        if not writer.records:
            summary = report.summary()
            raise DataError(
                f"dataset {spec.name!r}: no usable image pairs ({summary['skipped']} skipped: "
                f"{_reasons_text(summary['skip_reasons'])}); nothing was cached"
            )
        if earlier is not None:
            _compare_identity(label, earlier, identity)
        from harness.io import atomic_write_json

        atomic_write_json(writer.tmp / IDENTITY_FILE, identity, indent=None)
        if hasattr(source, "write_artifacts"):
            contracts.plugin_call(label, "write_artifacts()", source.write_artifacts, writer.tmp)
        summary = report.summary()
        summary["skipped_files"] = [list(s) for s in report.skipped[:MAX_LISTED_SKIPS]]
        summary["samples_identity"] = identity_digest(identity)
        summary["missing_temperatures"] = {
            "samples": len(missing),
            "pixels": sum(missing.values()),
            "per_sample": dict(list(missing.items())[:MAX_LISTED_SKIPS]),
        }
        if order:
            summary["category_order"] = order
        from harness.sensing.radiometry import KELVIN, PLAUSIBLE_C

        kelvin_like = implausible.get("coolest", -KELVIN) >= PLAUSIBLE_C[0] + KELVIN
        if implausible["samples"] or implausible["pixels"] or kelvin_like:
            summary["implausible_temperatures"] = {
                **implausible,
                "range_c": list(PLAUSIBLE_C),
                **({"kelvin_like": True} if kelvin_like else {}),
            }
        if routes:
            summary.update(routes)
            if "approximate_temperatures" in routes:
                a = routes["approximate_temperatures"]
                report.note(
                    f"{a['samples']} sample(s) hold approximate temperatures (within {a['bound_c']:g} C of "
                    f"DJI's SDK at worst: {', '.join(a['approximations'])}); results on them say so"
                )
                summary["notes"] = list(report.notes)
        summary["seconds"] = round(time.perf_counter() - t0, 3)
        writer.close(summary)
    except BaseException:
        writer.abort()
        raise
    log.info("prepared %d samples of %s in %s (%.1f s)", len(writer.records), spec.name, folder, summary["seconds"])
    return PreparedDataset(folder)


def category_order(spec_categories: tuple[str, ...], categories: tuple[str, ...]) -> dict[str, Any] | None:
    """When the spec and the opened source name the same categories in another order (so label ``k`` names another
    category than the spec says): ``{"spec": [...], "source": [...], "moved": ["label 0: 'b' (the spec's 1)", ...]}``,
    else None. A source naming other categories than the spec (from its files or an option) is not this."""
    if not spec_categories or spec_categories == categories or sorted(spec_categories) != sorted(categories):
        return None
    moved = [
        f"label {k}: {name!r} (the spec's label {spec_categories.index(name)}, {spec_categories[k]!r})"
        for k, name in enumerate(categories)
        if spec_categories[k] != name
    ]
    return {"spec": list(spec_categories), "source": list(categories), "moved": moved}


def _plausible_temperatures(sample: Any, where: Any, implausible: dict[str, Any]) -> Any:
    """``sample`` with its temperatures held to ``radiometry.PLAUSIBLE_C`` (``harness.sensing.plausible``): a few
    pixels outside become missing (NaN, counted on the console), a map more than 5 % outside (a wrong unit: 8-bit
    counts read as centi-Kelvin give -273 C) is kept as it is and counted as an implausible sample, which the input
    guard refuses unless ``inputs.accept`` names ``temperature-range``; so is a dataset whose coolest pixel is above
    -100 C + 273.15 (temperatures in Kelvin)."""
    import dataclasses

    import numpy as np

    from harness.sensing import plausible

    t = getattr(sample, "thermal", None)
    if not isinstance(t, np.ndarray) or t.dtype.kind != "f" or t.ndim != 2:
        return sample  # the contract check names what is wrong
    seen = plausible.classify(t, units=False)  # the one check every thermal input passes
    if seen.finite:  # the coolest pixel of all samples: above -100 C + 273.15 everywhere reads as Kelvin
        implausible["coolest"] = min(implausible.get("coolest", seen.lo), seen.lo)
    if not seen.outside:
        return sample
    if seen.refused:  # more than plausible.GARBAGE_FRACTION outside (or byte-swapped): counted, kept for the guard
        implausible["samples"] += 1
        if len(implausible["examples"]) < MAX_LISTED_SKIPS:
            implausible["examples"].append(
                f"{where}: {seen.outside} of {seen.finite} values outside, {seen.lo:.6g}..{seen.hi:.6g} C"
            )
        return sample
    kept = t.copy()
    implausible["pixels"] += plausible.check(kept, str(where), "the dataset plugin", units=False)
    return dataclasses.replace(sample, thermal=kept)


def plugin_label(spec: DatasetSpec) -> str:
    """``dataset 'NAME' (plugin P)``: how an error names a dataset and the plugin that registered it."""
    return contracts.plugin_label("dataset", spec.name, spec.open)


def _plugin_samples(label: str, source: Any, report: PrepareReport) -> Iterable[Any]:
    """``source.samples(report)``, with an exception the plugin's code raises turned into a ``PluginError`` that names
    the dataset, its plugin and where it was raised (a ``HarnessError`` it raises on purpose passes unchanged)."""
    from harness.contracts import where
    from harness.errors import HarnessError, PluginError

    try:
        yield from source.samples(report)
    except (HarnessError, KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:
        raise PluginError(
            f"{label}: samples() raised {type(exc).__name__}: {exc}{where(exc)}; nothing was cached"
        ) from exc


def _sample_where(sample: Any) -> Any:
    """How a skip names a sample: its file name, else its image id (whatever the plugin yielded)."""
    meta = getattr(sample, "meta", None)
    iid = getattr(sample, "image_id", None)
    if isinstance(meta, dict):
        return meta.get("file_name", iid)
    return iid if iid is not None else type(sample).__name__


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
        a = routes.setdefault(
            "approximate_temperatures",
            {"label": "approximate temperatures", "samples": 0, "bound_c": 0.0, "approximations": []},
        )
        a["samples"] += 1
        a["bound_c"] = max(a["bound_c"], float(meta.get("temperature_bound_c") or 0.0))
        if meta.get("approximation") and meta["approximation"] not in a["approximations"]:
            a["approximations"].append(meta["approximation"])
    elif route:
        c = routes.setdefault(f"{route}_temperatures", {"samples": 0})
        c["samples"] += 1


def _reasons_text(reasons: Mapping[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])) or "none"
