"""Reference results: the benchmark's results store, exported compact and versioned, shipped with the project.

A plugin author compares a new detector with the four reference detectors without training them again: a report (or
``compare-detectors``) reads the reference store beside the user's store through the same reader, and the reference
entries appear under the names ``ref:<detector>``. A comparison is only made on the same samples: every trained run
records content digests of the samples it trained on and scored (``metrics.json`` ``samples``, from
``PreparedDataset.content_digest``), the reference store records those of its runs, and a user's run whose digest
differs (another generator version, seed or profile of the synthetic set, other sensing options) is refused with
what differs. A code change that leaves the samples identical keeps the references valid.

Layout (``export_references``)::

    <folder>/references.json             manifest (``MANIFEST_SCHEMA`` below)
    <folder>/<dataset>/<detector>/<encoding>/<fold>/seed<seed>/
        config.yaml status.json metrics.json
        gt.json.gz analysis.json.gz                       (gzip, read by ``harness.io.read_json``; no checkpoints)
        predictions.npz                                   (``harness.io.pack_detections``: exact columns; or
                                                           predictions.json.gz where they would not be exact)
        log.jsonl.gz                                      (gzip, read by ``harness.io.read_packed_text``)

``references.json``::

    {"schema": 1, "dataset": str, "profile": str,
     "generator": {"name", "version", "profile", "seed"} | null,     # the synthetic set the samples came from
     "samples": {"<fold>/<encoding>": {"train": digest, "held_out": digest}},
     "aligned": {"<fold>": {"train": digest, "held_out": digest}},   # the same samples before encoding
     "cells": ["<detector>/<encoding>/<fold>/seed<seed>", ...],
     "training": {"imgsz", "epochs", "scale", "threads", "selection",   # the first run's
                  "epochs_by_detector": {"<detector>": epochs}},   # each detector's budget
     "environment": {...},                                           # torch build, CPU, threads of the runs
     "benchmark": {"wall_s", "cpu_s", "lanes", "cpu"} | null,        # how long `harness benchmark run` took
     "samples_environment": {...},   # Python and the sample-shaping packages the samples were reproduced with
     "torch_build": {...}}           # BLAS, LAPACK, oneDNN builds of the runs' torch build

``samples.npz`` beside it is the fingerprint of the samples (``harness.cache.fingerprint``): a user's samples whose
digests differ are measured against it, and compared, labelled, when they differ only as a library release makes
them differ (``check_matched``).
"""

from __future__ import annotations

import gzip
import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence, overload

from harness.errors import StoreError
from harness.io import pack_detections, read_json
from harness.report.reader import REFERENCE_PREFIX

log = logging.getLogger(__name__)

MANIFEST = "references.json"
MANIFEST_SCHEMA = 1
#: The name entries of the reference store get in a report: ``ref:ours``.
PREFIX = REFERENCE_PREFIX
#: The folder of the shipped references under ``references/`` (``harness.shipped_references`` when installed).
SHIPPED = "m3t-synth-benchmark"
#: Every shipped reference folder, one per benchmark suite (``harness.benchmark.SUITES``); ``shipped`` reads each that
#: exists, ``SHIPPED`` first and the others as its ``siblings``.
SHIPPED_FOLDERS = (SHIPPED, "rgbt-tiny-synth-benchmark")
#: The built-in synthetic dataset, whose generator a reference records.
SYNTHETIC = "m3t-synth"
#: Largest reference store the project ships.
MAX_BYTES = 10 * 2**20
#: Largest the shipped reference folders may take together (``SHIPPED_FOLDERS`` side by side: 15 MB).
MAX_TOTAL_BYTES = 15 * 10**6
#: Run files copied as they are, and those gzip-compressed.
COPIED = ("config.yaml", "status.json", "metrics.json")
PACKED = ("gt.json", "predictions.json", "analysis.json")
#: ... of which the detections are kept as packed columns where they give back every value exactly
#: (``harness.io.pack_detections``, ``predictions.npz``), else gzip-compressed too.
DETECTIONS = "predictions.json"
#: Run files gzip-compressed when the run has them (a training log; runs scored from checkpoints have none).
PACKED_IF_ANY = ("log.jsonl",)


class ReferenceMismatchError(StoreError):
    """The user's runs and the reference results were not trained or scored on the same samples."""


def shipped_root() -> Path:
    """The folder holding the shipped reference stores: the installed copy (``harness.shipped_references``), or
    ``references/`` of the checkout the code runs from."""
    from harness.config import data_package_dir

    installed = data_package_dir("harness.shipped_references", f"{SHIPPED}/{MANIFEST}")
    if installed is not None:
        return installed
    return Path(__file__).resolve().parent.parent / "references"


def resolve(spec: str | Path) -> Path:
    """``shipped`` -> the shipped reference store; anything else is a folder."""
    if str(spec) == "shipped":
        return shipped_root() / SHIPPED
    return Path(spec)


def _digests(metrics: Mapping[str, Any]) -> dict[str, Any] | None:
    s = metrics.get("samples")
    return s if isinstance(s, dict) and s.get("held_out") else None


@dataclass
class ReferenceSet:
    """A reference store: its manifest and its runs."""

    root: Path
    manifest: dict[str, Any]
    problems: list[str] = field(default_factory=list)
    #: the other shipped reference stores (of other datasets), read with this one when ``shipped`` was asked for;
    #: a report matches each on its own dataset's samples
    siblings: list["ReferenceSet"] = field(default_factory=list)

    @property
    def dataset(self) -> str:
        return str(self.manifest["dataset"])

    def all(self) -> list["ReferenceSet"]:
        """This reference store and its ``siblings``."""
        return [self, *self.siblings]

    @property
    def profile(self) -> str:
        return str(self.manifest.get("profile") or "?")

    def describe(self) -> str:
        """``m3t-synth (generator v2, small, seed 0), benchmark profile: 192 px, epochs ours 30, eme 80, ...,
        scale n`` (one number of epochs when every detector trained for as many)."""
        g = self.manifest.get("generator") or {}
        t = self.manifest.get("training") or {}
        gen = f" (generator v{g.get('version')}, {g.get('profile')}, seed {g.get('seed')})" if g else ""
        own = t.get("epochs_by_detector") or {}
        epochs = (
            "epochs " + ", ".join(f"{d} {n}" for d, n in own.items())
            if len(set(own.values())) > 1
            else (f"{t['epochs']} epochs" if t.get("epochs") is not None else None)
        )
        px = f"{t['imgsz']} px" if t.get("imgsz") is not None else None
        train = ", ".join(x for x in (px, epochs) if x)
        scale = f", scale {t['scale']}" if t.get("scale") else ""
        return f"{self.dataset}{gen}, {self.profile} profile: {train}{scale}"

    def runs(self) -> list[Any]:
        """The finished reference runs, each named ``ref:<detector>`` (its folder unchanged)."""
        from harness.report.reader import StoreView
        from harness.store import RunKey

        view = StoreView(self.root)
        out = []
        for run in view.finished_runs(self.dataset):
            k = run.key
            run.key = RunKey(k.dataset, PREFIX + k.detector, k.encoding, k.fold, k.seed)
            out.append(run)
        self.problems += view.problems
        return out

    def check_matched(self, runs: Iterable[Any]) -> list[str]:
        """``check_matched(self, runs)``: the store's runs against these references (a mismatch is an error)."""
        return check_matched(self, runs)

    def same_training(self, runs: Sequence[Any]) -> bool:
        """``same_training(self, runs)``: whether ``runs`` were trained at these references' budget."""
        return same_training(self, runs)

    def held_out_digest(self, fold: str, encoding: str) -> str | None:
        return ((self.manifest.get("samples") or {}).get(f"{fold}/{encoding}") or {}).get("held_out")

    def aligned_digest(self, fold: str) -> str | None:
        return ((self.manifest.get("aligned") or {}).get(fold) or {}).get("held_out")


@overload
def load_references(spec: str | Path) -> ReferenceSet: ...
@overload
def load_references(spec: None) -> None: ...
def load_references(spec: str | Path | None) -> ReferenceSet | None:
    """The reference store at ``spec`` (``shipped`` or a folder; None: none); a missing or malformed one is a clear
    error. ``shipped``: the m3t-synth references, with every other shipped folder of ``SHIPPED_FOLDERS`` that exists
    as its ``siblings`` (another dataset each)."""
    if spec is None or str(spec) == "":
        return None
    refs = _load_one(spec)
    if str(spec) == "shipped":
        for name in SHIPPED_FOLDERS[1:]:
            if (shipped_root() / name / MANIFEST).is_file():
                sibling = _load_one(shipped_root() / name)
                if sibling.dataset == refs.dataset or any(s.dataset == sibling.dataset for s in refs.siblings):
                    raise StoreError(f"{sibling.root}: a second shipped reference store of dataset {sibling.dataset}")
                refs.siblings.append(sibling)
    return refs


def _load_one(spec: str | Path) -> ReferenceSet:
    from harness.io import read_json

    root = resolve(spec)
    path = root / MANIFEST
    if not path.is_file():
        hint = (
            "the shipped reference results are missing from this installation"
            if str(spec) == "shipped"
            else "pass the folder `harness benchmark export` wrote, or `shipped`"
        )
        raise StoreError(f"{path}: no reference results here ({hint})")
    manifest = read_json(path)
    if not isinstance(manifest, dict) or manifest.get("schema") != MANIFEST_SCHEMA or "dataset" not in manifest:
        raise StoreError(f"{path}: not a reference manifest of schema {MANIFEST_SCHEMA} (with a 'dataset')")
    return ReferenceSet(root, manifest)


# ------------------------------------------------------------------------------------------------- matching
def _generator_of(run: Any) -> dict[str, Any] | None:
    """The synthetic set a run was trained on, as far as its data folder (``synth.json`` beside the images, written
    by the generator) or, failing that, its dataset options (``dataset.profile``, ``dataset.seed``) tell."""
    from harness.io import read_json

    ds = (run.config.get("dataset") or {}) if isinstance(run.config, dict) else {}
    root = ds.get("root")
    if root and (Path(root) / "synth.json").is_file():
        try:
            info = read_json(Path(root) / "synth.json")
        except Exception:
            info = None
        if isinstance(info, dict):
            return {k: info.get(k) for k in ("generator_version", "profile", "seed")} | {"root": str(root)}
    if run.key.dataset != SYNTHETIC:
        return None
    found = _opened_root(run.key.dataset, ds)
    if found is not None and (found / "synth.json").is_file():
        try:
            info = read_json(found / "synth.json")
            return {k: info.get(k) for k in ("generator_version", "profile", "seed")} | {"root": str(found)}
        except Exception:
            pass
    return {
        "generator_version": None,
        "profile": ds.get("profile", "small"),
        "seed": ds.get("seed", 0),
        "root": f"dataset options of {run.key}",
    }


def _opened_root(dataset: str, options: Mapping[str, Any]) -> Path | None:
    """The folder the dataset plugin opens with ``options`` (its source's ``root``), or None."""
    try:
        from harness.plugins import get_host

        spec = get_host().dataset(dataset)
        opts = {k: v for k, v in options.items() if k != "root"}
        source = spec.open(options.get("root"), **opts)
        root = getattr(source, "root", None)
        return Path(root) if root is not None else None
    except Exception:  # no plugin here, or options it does not take: nothing to say about the data folder
        return None


def check_matched(refs: ReferenceSet, runs: Iterable[Any]) -> list[str]:
    """Check the user's ``runs`` of the reference dataset against ``refs``; raise ``ReferenceMismatchError`` when any
    was trained or scored on other samples (or recorded no digest), naming the runs, what differs, the package
    versions that differ and the command that installs the locked environment. Returns notes: runs of folds or
    encodings the references do not hold (compared on their aligned samples), and runs whose samples differ from the
    references' only within the tolerance of a library release (``harness.cache.fingerprint``), each labelled with
    the measured difference and the package versions that differ."""
    runs = list(runs)
    mismatched: list[tuple[Any, str]] = []
    undigested: list[str] = []
    notes: list[str] = []
    for run in runs:
        k = run.key
        if k.dataset != refs.dataset or k.detector.startswith(PREFIX):
            continue
        got = _digests(run.metrics)
        if got is None:
            undigested.append(str(k))
            continue
        want = refs.held_out_digest(k.fold, k.encoding)
        have = got.get("held_out")
        what = f"held-out samples of fold {k.fold} with encoding {k.encoding}"
        if want is None:  # an encoding the references do not hold: the aligned samples must still agree
            want, have = refs.aligned_digest(k.fold), (got.get("aligned") or {}).get("held_out")
            what = f"aligned held-out samples of fold {k.fold}"
            if want is None:
                notes.append(f"{k}: fold {k.fold} is not in the reference results")
                continue
        if want != have:
            mismatched.append((run, f"{k}: {what} digest {str(have)[:12]}, references {str(want)[:12]}"))
    if undigested:
        raise ReferenceMismatchError(
            f"cannot verify that {len(undigested)} run(s) used the reference results' samples: they were stored "
            f"before runs recorded their samples' digest ({', '.join(undigested[:4])}"
            f"{' ...' if len(undigested) > 4 else ''}); rerun them with --force, or leave out --reference-results"
        )
    if not mismatched:
        return notes
    tolerated, refused, measured = _within_tolerance(refs, [r for r, _ in mismatched])
    notes += tolerated
    mismatched = [(r, text) for r, text in mismatched if str(r.key) in refused]
    if not mismatched:
        return notes
    gen = None
    for run in runs:
        if not run.key.detector.startswith(PREFIX) and run.key.dataset == refs.dataset:
            gen = _generator_of(run)
            if gen:
                break
    ref_gen = refs.manifest.get("generator") or {}
    differs = ""
    if gen and ref_gen:
        diffs = [
            f"{name} {gen.get(key)} vs {ref_gen.get(ref_key)}"
            for name, key, ref_key in (
                ("generator version", "generator_version", "version"),
                ("profile", "profile", "profile"),
                ("seed", "seed", "seed"),
            )
            if gen.get(key) is not None and gen.get(key) != ref_gen.get(ref_key)
        ]
        if diffs:
            differs = f" Your data ({gen['root']}) differs from the references' in: {', '.join(diffs)}."
    versions = _version_differences(refs, [r for r, _ in mismatched])
    shown = [text + (f" ({refused[str(r.key)]})" if refused.get(str(r.key)) else "") for r, text in mismatched]
    raise ReferenceMismatchError(
        f"the reference results ({refs.describe()}) were trained and scored on other samples than "
        f"{len(mismatched)} of your run(s): "
        + "; ".join(shown[:4])
        + (" ..." if len(shown) > 4 else "")
        + "."
        + differs
        + (
            f" Package versions that differ from the references': {', '.join(versions)}; install the locked "
            f"environment ({LOCK_COMMAND}) and prepare again (`harness prepare --force`)."
            if versions
            else ""
        )
        + (f" {measured}" if measured else "")
        + " A comparison needs the same samples: generate the default synthetic set "
        "(`harness synth`, seed 0) and prepare it with default sensing options, or leave out --reference-results."
    )


#: The one command that installs the locked environment the shipped references were made in.
LOCK_COMMAND = "`make venv` in a checkout of the harness: the versions pinned in requirements.lock"
#: The fingerprint of the references' samples (``harness.cache.fingerprint``), beside the manifest.
FINGERPRINT = "samples.npz"


def _version_differences(refs: ReferenceSet, runs: Sequence[Any]) -> list[str]:
    """``["OpenCV 5.1.0, references 5.0.0"]``: sample- or training-shaping packages whose versions differ between
    the runs' environment (or this one, for runs that recorded none) and the references'."""
    from harness import provenance

    theirs = {**(refs.manifest.get("environment") or {}), **(refs.manifest.get("samples_environment") or {})}
    keys = [*provenance.SAMPLE_PACKAGES, *provenance.TRAINING_PACKAGES]
    out: list[str] = []
    for run in runs:
        env = run.metrics.get("environment") if isinstance(run.metrics, dict) else None
        mine = env if isinstance(env, dict) and env else provenance.package_versions()
        for d in provenance.differences(mine, theirs, keys, "references"):
            if d not in out:
                out.append(d)
    return out


def prepared_folder(run: Any) -> Path | None:
    """The prepared-data folder ``run`` read its samples from (recorded in its metrics, or found in the cache by its
    ``meta.prepared_key``), when it is still there."""
    from harness.cache.forms import FORMS
    from harness.cache.key import cache_root, form_folder

    recorded = (run.metrics.get("samples") or {}).get("prepared") if isinstance(run.metrics, dict) else None
    candidates = [Path(recorded)] if recorded else []
    meta = (run.config.get("meta") or {}) if isinstance(run.config, dict) else {}
    key = meta.get("prepared_key")
    if key:
        candidates += [form_folder(cache_root(None), run.key.dataset, str(key), form) for form in FORMS]
    return next((c for c in candidates if (c / "manifest.json").is_file()), None)


def _within_tolerance(refs: ReferenceSet, runs: Sequence[Any]) -> tuple[list[str], dict[str, str], str]:
    """Measure the samples of ``runs`` (whose digests differ from the references') against the references'
    fingerprint: (notes for the runs within ``fingerprint.TOLERANCE``, ``{run key: why not}`` for the others, one
    sentence on what was measured)."""
    from harness.cache import fingerprint as FP

    loaded: dict[Path, Any] = {}
    measured: dict[tuple[str, str, str], tuple[FP.Difference | None, str]] = {}
    refused: dict[str, str] = {}
    accepted: dict[str, list[str]] = {}
    for run in runs:
        path = fingerprint_path(refs.root, refs.manifest, run.key.fold)
        if path not in loaded:
            try:
                loaded[path] = FP.load(path) if path.is_file() else None
            except (OSError, ValueError) as exc:
                log.warning("reference results: %s", exc)
                loaded[path] = None
        if loaded[path] is None:
            refused[str(run.key)] = ""
            continue
        diff, why = measure_samples(run, loaded[path], measured)
        if diff is None or not diff.within(FP.TOLERANCE):
            refused[str(run.key)] = (f"measured: {diff.describe()}" if diff is not None else "") or why
            continue
        accepted.setdefault(diff.describe(), []).append(str(run.key).removeprefix(f"{refs.dataset}/"))
    notes = []
    versions = _version_differences(refs, [r for r in runs if str(r.key) not in refused])
    for text, keys in accepted.items():
        notes.append(
            f"Compared within the tolerance of a library release, not on identical samples: {len(keys)} run(s) "
            f"({', '.join(keys[:3])}{' ...' if len(keys) > 3 else ''}) used samples that differ from the references' "
            f"as measured: {text} (tolerance: {FP.TOLERANCE.describe()})."
            + (f" Package versions that differ: {', '.join(versions)}." if versions else "")
        )
    summary = ""
    if refused and any(refused.values()):
        summary = f"Beyond the tolerance of a library release ({FP.TOLERANCE.describe()})."
    return notes, refused, summary


def measure_samples(
    run: Any, ref_fp: dict[str, Any], memo: dict[tuple[str, str, str], tuple[Any, str]]
) -> tuple[Any, str]:
    """(the fingerprint difference of ``run``'s samples from the references', or None, and why none); ``memo``: the
    measurements of this call's prepared folders, kept across calls."""
    from harness.cache import fingerprint as FP
    from harness.cache.reader import PreparedDataset
    from harness.errors import HarnessError
    from harness.plugins import get_host

    folder = prepared_folder(run)
    if folder is None:
        return None, "its prepared data is no longer in the cache, so the difference cannot be measured"
    cfg = run.config if isinstance(run.config, dict) else {}
    params = dict((cfg.get("encoding") or {}).get(run.key.encoding) or {})
    memo_key = (str(folder), run.key.encoding, json.dumps(params, sort_keys=True, default=str))
    if memo_key not in memo:
        try:
            prepared = PreparedDataset(folder)
            enc = get_host().encoding(run.key.encoding)
            meta = cfg.get("meta") or {}
            held_out = prepared.indices(list(meta.get("val_groups") or []))
            if prepared.content_digest(held_out, enc, params) != (run.metrics.get("samples") or {}).get("held_out"):
                memo[memo_key] = (None, f"the prepared data in {folder} no longer holds the samples it was run on")
            else:
                fp = FP.compute(prepared, [(enc, params)])
                planes = ["rgb", "aligned"] + ([f"enc:{enc.name}"] if f"enc:{enc.name}/hash" in ref_fp else [])
                memo[memo_key] = (FP.compare(fp, ref_fp, planes), "")
        except (HarnessError, OSError, ValueError, KeyError) as exc:
            memo[memo_key] = (None, f"its samples could not be measured ({exc})")
    return memo[memo_key]


def write_fingerprint(
    root: str | Path,
    prepared: Any,
    encodings: Sequence[str] | None = None,
    folds: Iterable[str] | None = None,
    name: str = FINGERPRINT,
) -> dict[str, Any]:
    """Write the fingerprint of the reference results' samples (``name``, default ``FINGERPRINT``) and the
    sample-shaping package versions (``samples_environment``) into the reference store at ``root``, from ``prepared``
    (a ``PreparedDataset``) after checking that it holds exactly the samples every digest of the manifest names.

    ``folds``: only the digests of these folds are checked, and the manifest's ``fingerprints`` records that ``name``
    holds their samples (``fingerprint_path``): a dataset prepared once per annotation source (RGBT-Tiny's thermal and
    visible boxes) gets one fingerprint per preparation."""
    from harness import provenance
    from harness.cache import fingerprint as FP
    from harness.cache.folds import resolve_folds
    from harness.plugins import get_host

    refs = load_references(root)
    host = get_host()
    spec = host.dataset(refs.dataset)
    folds = {f.name: f for f in resolve_folds(spec, prepared, {"protocol": _protocol_of(refs)})}
    only = set(folds) if folds is not None else None
    samples = {k: v for k, v in (refs.manifest.get("samples") or {}).items() if only is None or k.split("/")[0] in only}
    if only is not None and not samples:
        raise StoreError(f"{refs.root}: the references record no samples of fold(s) {', '.join(sorted(only))}")
    names = encodings or sorted({key.split("/")[1] for key in samples})
    wrong = []
    for key, want in samples.items():
        fold, enc_name = key.split("/")
        f = folds.get(fold)
        if f is None:
            wrong.append(f"{key}: fold not in the prepared data")
            continue
        enc = host.encoding(enc_name)
        have = prepared.content_digest(prepared.indices(list(f.val_groups)), enc, {})
        if have != want.get("held_out"):
            wrong.append(f"{key}: held-out digest {have[:12]}, references {str(want.get('held_out'))[:12]}")
    if wrong:
        raise ReferenceMismatchError(
            f"{prepared.folder}: not the samples of the reference results at {refs.root} ({'; '.join(wrong[:4])}); "
            f"the fingerprint is written only from the references' own samples"
        )
    fp = FP.compute(prepared, [(host.encoding(n), {}) for n in names])
    FP.save(refs.root / name, fp)
    manifest = dict(refs.manifest)
    if only is not None:
        manifest["fingerprints"] = {**(manifest.get("fingerprints") or {}), name: sorted(only)}
    manifest["samples_environment"] = provenance.sample_environment()
    ran_with = str((manifest.get("environment") or {}).get("torch") or "")
    if ran_with and ran_with == provenance.package_versions().get("torch"):
        # the BLAS, LAPACK and oneDNN builds of the torch build the runs record (read from that same build here)
        manifest["torch_build"] = provenance.torch_build()
    (refs.root / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=False) + "\n", encoding="utf-8")
    return {"fingerprint": str(refs.root / name), "bytes": (refs.root / name).stat().st_size}


def fingerprint_path(root: str | Path, manifest: Mapping[str, Any], fold: str) -> Path:
    """The fingerprint file of the reference results at ``root`` that holds the samples of ``fold`` (the manifest's
    ``fingerprints``; ``FINGERPRINT`` for references with one preparation)."""
    for name, folds in (manifest.get("fingerprints") or {}).items():
        if fold in folds:
            return Path(root) / name
    return Path(root) / FINGERPRINT


def _protocol_of(refs: ReferenceSet) -> dict[str, Any]:
    """The folds of the references' runs (``protocol`` of a run's config)."""
    from harness.config import load_config

    for cfg_path in sorted(refs.root.rglob("config.yaml"))[:1]:
        import yaml

        cfg = yaml.safe_load(cfg_path.read_text(encoding="utf-8")) or {}
        return dict(cfg.get("protocol") or {})
    return dict(load_config().get("protocol") or {})


def training_of(run: Any) -> dict[str, Any]:
    """What the references' ``training`` record holds, for one run (its config)."""
    cfg = run.config if isinstance(run.config, dict) else {}
    return {
        "imgsz": (cfg.get("protocol") or {}).get("imgsz"),
        "epochs": (cfg.get("protocol") or {}).get("epochs"),
        "scale": (cfg.get("model") or {}).get("scale"),
        "threads": (cfg.get("train") or {}).get("threads"),
        "selection": (cfg.get("protocol") or {}).get("selection"),
        "profile": (cfg.get("meta") or {}).get("profile"),
    }


def _training_record(runs: Sequence[Any]) -> dict[str, Any]:
    """The references' ``training`` record: the first run's settings, and the epochs of every detector (the benchmark
    profile gives each detector its own budget, chosen from learning curves)."""
    record = training_of(runs[0])
    record.pop("profile", None)  # the manifest's own "profile"
    own: dict[str, Any] = {}
    for r in runs:
        own.setdefault(r.key.detector.removeprefix(PREFIX), training_of(r).get("epochs"))
    record["epochs_by_detector"] = dict(sorted(own.items()))
    return record


def same_training(refs: ReferenceSet, runs: Sequence[Any]) -> bool:
    """Whether every one of ``runs`` was trained at the references' budget, so that a comparison of accuracy is one of
    detectors at one budget and not of two budgets: the references' image size and model selection, and

    * for a detector the references trained, its epochs there;
    * for another detector, the references' profile (its epochs are the profile's, or its own config's, and its
      plateau record says whether they sufficed), or the epochs of one of the reference detectors;
    * references that record one number of epochs for every run: that number."""
    t = refs.manifest.get("training") or {}
    own = t.get("epochs_by_detector") or {}

    def same(r: Any) -> bool:
        got = training_of(r)
        if got.get("imgsz") != t.get("imgsz"):
            return False
        if t.get("selection") is not None and got.get("selection") != t.get("selection"):
            return False
        if not own:
            return bool(got.get("epochs") == t.get("epochs"))
        det = str(r.key.detector).removeprefix(PREFIX)
        if det in own:
            return bool(got.get("epochs") == own[det])
        at_profile = got.get("profile") is not None and got.get("profile") == refs.manifest.get("profile")
        return bool(at_profile or got.get("epochs") in own.values())

    return bool(runs) and all(same(r) for r in runs)


# ------------------------------------------------------------------------------------------------- export
def _gzip_copy(src: Path, dst: Path) -> None:
    data = src.read_bytes()
    with open(dst, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=9) as f:
        f.write(data)


def export_references(
    store: str | Path,
    out: str | Path,
    cells: Sequence[Any],
    benchmark: Mapping[str, Any] | None = None,
    generator: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the reference store of ``cells`` (``harness.sweep.JobResult``-like: ``.run`` is the run key text, or
    ``RunKey``) from ``store`` into ``out``. Every cell must be finished and carry its samples' digests, and every
    run of a (fold, encoding) must have used the same samples; the result must fit in ``MAX_BYTES``, and together
    with the other shipped folders (``SHIPPED_FOLDERS``) beside ``out`` in ``MAX_TOTAL_BYTES``."""
    from harness.report.reader import StoreView, read_run
    from harness.store import Run, RunKey

    store, out = Path(store), Path(out)
    view = StoreView(store)
    keys: list[RunKey] = []
    for c in cells:
        if isinstance(c, RunKey):
            keys.append(c)
        else:
            ds, det, enc, fold, seed = str(getattr(c, "run", c)).split("/")
            keys.append(RunKey(ds, det, enc, fold, int(seed.removeprefix("seed"))))
    runs = []
    missing = []
    for k in keys:
        r = Run(view.root, k)
        if not r.is_finished():
            missing.append(str(k))
            continue
        runs.append(read_run(r))
    if missing:
        raise StoreError(
            f"{store}: {len(missing)} benchmark cell(s) not finished ({', '.join(missing[:4])}"
            f"{' ...' if len(missing) > 4 else ''}); run `harness benchmark run` first"
        )
    samples: dict[str, dict[str, str]] = {}
    aligned: dict[str, dict[str, str]] = {}
    conflicts: list[str] = []
    for r in runs:
        d = _digests(r.metrics)
        if d is None:
            raise StoreError(f"{r.path}: its metrics.json records no samples digest; rerun {r.key} with --force")
        for table, key, rec in (
            (samples, f"{r.key.fold}/{r.key.encoding}", {k: d[k] for k in ("train", "held_out")}),
            (aligned, r.key.fold, d.get("aligned") or {}),
        ):
            if table.setdefault(key, rec) != rec:
                conflicts.append(f"{r.key} ({key})")
    if conflicts:
        raise StoreError(
            f"{store}: runs of the same fold and encoding used different samples: " + ", ".join(conflicts[:4])
        )
    datasets = sorted({k.dataset for k in keys})
    if len(datasets) != 1:
        raise StoreError(f"reference results hold one dataset; the cells name {', '.join(datasets)}")
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    for r in runs:
        dst = Run(tmp, r.key).path
        dst.mkdir(parents=True)
        for name in COPIED:
            if (r.path / name).is_file():
                shutil.copyfile(r.path / name, dst / name)
        for name in PACKED:
            src = r.path / name
            if not src.is_file():
                raise StoreError(f"{src}: missing; the bootstrap needs it (rerun {r.key} with --force)")
            if name == DETECTIONS and (packed := pack_detections(read_json(src))) is not None:
                (dst / Path(name).with_suffix(".npz").name).write_bytes(packed)  # exact, a third of the gzip size
                continue
            _gzip_copy(src, dst / f"{name}.gz")
        for name in PACKED_IF_ANY:
            if (r.path / name).is_file():
                _gzip_copy(r.path / name, dst / f"{name}.gz")
    ds_file = store / datasets[0] / "_dataset.json"
    if ds_file.is_file():
        shutil.copyfile(ds_file, tmp / datasets[0] / "_dataset.json")
    first = runs[0]
    manifest = {
        "schema": MANIFEST_SCHEMA,
        "dataset": datasets[0],
        "profile": (first.config.get("meta") or {}).get("profile"),
        "generator": dict(generator) if generator else _generator_record(first),
        "samples": dict(sorted(samples.items())),
        "aligned": dict(sorted(aligned.items())),
        "cells": sorted(str(k).removeprefix(f"{datasets[0]}/") for k in keys),
        "training": _training_record(runs),
        "environment": first.metrics.get("environment") or {},
        "benchmark": dict(benchmark) if benchmark else None,
    }
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=False) + "\n", encoding="utf-8")
    folders: dict[Path, set[str]] = {}  # each preparation of the runs, with the folds it holds
    for r in runs:
        if (f := prepared_folder(r)) is not None:
            folders.setdefault(f, set()).add(r.key.fold)
    if len(folders) == 1 and prepared_folder(first) is not None:  # one preparation: every digest checked on it
        from harness.cache.reader import PreparedDataset

        write_fingerprint(tmp, PreparedDataset(next(iter(folders))))
        manifest = load_references(tmp).manifest
    elif folders:  # what matching across library releases measures against: one fingerprint per preparation
        from harness.cache.reader import PreparedDataset

        covered: set[str] = set()
        for n, (folder, its_folds) in enumerate(folders.items()):
            if its_folds <= covered:
                continue
            name = FINGERPRINT if n == 0 else f"samples-{'+'.join(sorted(its_folds - covered))}.npz"
            write_fingerprint(tmp, PreparedDataset(folder), folds=its_folds - covered, name=name)
            covered |= its_folds
        manifest = load_references(tmp).manifest
    else:
        log.warning("%s: the prepared data of the runs is gone; the references get no sample fingerprint", store)
    size = sum(p.stat().st_size for p in tmp.rglob("*") if p.is_file())
    if size > MAX_BYTES:
        shutil.rmtree(tmp, ignore_errors=True)
        raise StoreError(
            f"the reference store would take {size / 2**20:.1f} MiB, over the {MAX_BYTES / 2**20:.0f} MiB "
            f"the project ships"
        )
    beside = {
        name: sum(p.stat().st_size for p in (out.parent / name).rglob("*") if p.is_file())
        for name in SHIPPED_FOLDERS
        if name != out.name and (out.parent / name).is_dir()
    }
    if size + sum(beside.values()) > MAX_TOTAL_BYTES:
        shutil.rmtree(tmp, ignore_errors=True)
        others = ", ".join(f"{n} {b / 1e6:.2f} MB" for n, b in beside.items())
        raise StoreError(
            f"the reference store would take {size / 1e6:.2f} MB, and with the reference folders beside it in "
            f"{out.parent} ({others}) {(size + sum(beside.values())) / 1e6:.2f} MB, over the "
            f"{MAX_TOTAL_BYTES / 1e6:.0f} MB the project ships together"
        )
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    manifest["bytes"] = size
    return manifest


def _generator_record(run: Any) -> dict[str, Any] | None:
    gen = _generator_of(run)
    if not gen:
        return None
    return {
        "name": run.key.dataset,
        "version": gen.get("generator_version"),
        "profile": gen.get("profile"),
        "seed": gen.get("seed"),
    }


__all__ = [
    "MANIFEST",
    "PREFIX",
    "SHIPPED",
    "SHIPPED_FOLDERS",
    "ReferenceMismatchError",
    "ReferenceSet",
    "check_matched",
    "export_references",
    "fingerprint_path",
    "load_references",
    "measure_samples",
    "resolve",
    "same_training",
    "shipped_root",
]
