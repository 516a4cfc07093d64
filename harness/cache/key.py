"""Where a prepared dataset lives and what names it: the cache root, the key, the form's folder.

``<cache>/<dataset>/<key>/`` (compact form) or ``<cache>/<dataset>/<key>-raw/``, where ``<cache>`` is the
``cache_root`` argument, else ``$HARNESS_CACHE``, else ``./cache``, and::

    key = sha1({dataset, fingerprint, sensing, PREPARE_VERSION, plugin code})[:16]

The source's fingerprint changes with the input files (names, sizes, modification times, annotation and
registration contents) and the dataset's options; ``sensing`` is the part of the config's ``sensing`` section that
can change prepared samples; the plugin code is all the Python source of the package or distribution the dataset
plugin comes from (``plugin_code_files``: a module it imports only through another counts too; never the
harness's), so a changed input, a changed sensing setting or an edited plugin prepares again and never reuses stale
samples (nor a finished run: a run's identity holds the key), while moving code inside the harness keeps every
user's cache.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import sys
from pathlib import Path
from typing import Any, Mapping

from harness.cache.forms import DEFAULT_FORM, ENV_FORM, check_form

#: Bumped whenever preparation changes what it writes for the same inputs (part of every cache key).
PREPARE_VERSION = 2
ENV_CACHE = "HARNESS_CACHE"
#: ``sensing`` sub-sections that only steer analyses of prepared data, not preparation (left out of the key).
ANALYSIS_ONLY_SENSING = ("displacement",)


def cache_root(root: str | Path | None = None) -> Path:
    """Where prepared datasets live: ``root``, else ``$HARNESS_CACHE``, else ``./cache``."""
    if root is not None:
        return Path(root)
    return Path(os.environ.get(ENV_CACHE) or "cache")


def cache_form(form: str | None = None) -> str:
    """The cache form: ``form``, else ``$HARNESS_CACHE_FORM``, else ``compact`` (see ``harness.cache.forms``)."""
    return check_form(form or os.environ.get(ENV_FORM) or DEFAULT_FORM)


def form_folder(root: Path, dataset: str, key: str, form: str) -> Path:
    """``<root>/<dataset>/<key>`` (compact) or ``<root>/<dataset>/<key>-raw``: both forms can sit side by side."""
    return root / dataset / (key if form == DEFAULT_FORM else f"{key}-{form}")


def preparation_sensing(sensing: Mapping[str, Any] | None) -> dict[str, Any]:
    """The part of the ``sensing`` section that can change prepared samples."""
    return {k: v for k, v in dict(sensing or {}).items() if k not in ANALYSIS_ONLY_SENSING}


def cache_key(fingerprint: str, sensing: Mapping[str, Any] | None, dataset: str) -> str:
    """``sha1({dataset, fingerprint, sensing, PREPARE_VERSION, plugin code})`` as 16 hex digits (analysis-only
    sensing keys, such as the displacement study's shifts, are left out)."""
    payload = json.dumps(
        {
            "dataset": dataset,
            "fingerprint": fingerprint,
            "sensing": preparation_sensing(sensing),
            "version": PREPARE_VERSION,
            "code": plugin_code_fingerprint(dataset),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha1(payload.encode()).hexdigest()[:16]


#: The package of the built-in dataset plugins: its whole source keys their caches (the detectors beside it do not).
BUILTIN_DATASETS = "adapters.datasets"


def plugin_code_fingerprint(dataset: str) -> str:
    """sha1 of all the Python source of the package or distribution the registered dataset plugin comes from
    (``plugin_code_files``), so editing any module of it, imported directly or not, prepares again ("" for an
    unregistered name). Modules of the harness itself are never part of it."""
    try:
        from harness.plugins import get_host

        opener = get_host().dataset(dataset).open
    except Exception:  # noqa: BLE001 - a name no plugin registers (tests, analyses of a cache) has no code to key
        return ""
    home = inspect.getmodule(opener)
    if home is None:
        return ""
    h = hashlib.sha1()
    for name, path in plugin_code_files(home):
        try:
            data = path.read_bytes()
        except OSError:  # a file removed meanwhile: keyed by its absence
            continue
        h.update(name.encode() + b"\0" + hashlib.sha1(data).digest())
    return h.hexdigest()


def plugin_code_files(module: Any) -> list[tuple[str, Path]]:
    """(name, path) of every ``.py`` file of the code a plugin module comes from, in a fixed order:

    * the built-in dataset plugins (``adapters.datasets``): every module of that package;
    * a module of an installed distribution (a wheel, not an editable install): every ``.py`` file the
      distribution installed;
    * a module of a package (an editable install, a folder on ``sys.path``): every ``.py`` file below its
      top-level package's folder;
    * a lone module (a ``--plugins-dir`` file, a top-level ``.py`` on ``sys.path``): itself and the ``.py`` files
      beside it, which it may import.

    ``__pycache__`` is skipped; nothing of the harness is ever part of it."""
    name = getattr(module, "__name__", "") or ""
    top = name.split(".")[0]
    if not name or top == "harness":
        return []
    if name == BUILTIN_DATASETS or name.startswith(BUILTIN_DATASETS + "."):
        return _tree(sys.modules.get(BUILTIN_DATASETS), BUILTIN_DATASETS)
    own = getattr(module, "__file__", None)
    if own and top in _distributions():
        files = _distribution_files(_distributions()[top], Path(own))
        if files:
            return files
    package = sys.modules.get(top)
    if package is not None and getattr(package, "__path__", None):
        return _tree(package, top)
    if own and Path(own).is_file():
        folder = Path(own).parent
        return [(p.name, p) for p in sorted(folder.glob("*.py")) if p.is_file()]
    return []


def _tree(package: Any, label: str) -> list[tuple[str, Path]]:
    out: list[tuple[str, Path]] = []
    for base in [Path(p) for p in getattr(package, "__path__", None) or []]:
        for path in sorted(base.rglob("*.py")):
            if "__pycache__" not in path.parts and path.is_file():
                out.append((f"{label}/{path.relative_to(base).as_posix()}", path))
    return out


def _distributions() -> dict[str, list[str]]:
    """Top-level import name -> distributions providing it (``importlib.metadata.packages_distributions``)."""
    global _DISTRIBUTIONS
    if _DISTRIBUTIONS is None:
        from importlib.metadata import packages_distributions

        try:
            _DISTRIBUTIONS = dict(packages_distributions())
        except Exception:  # noqa: BLE001 - a broken metadata folder must not stop preparation: key by folders
            _DISTRIBUTIONS = {}
    return _DISTRIBUTIONS


_DISTRIBUTIONS: dict[str, list[str]] | None = None


def _distribution_files(names: list[str], own: Path) -> list[tuple[str, Path]]:
    """The ``.py`` files of the distribution among ``names`` that installed ``own``; empty when none lists it (an
    editable install lists a path hook, not its sources)."""
    from importlib.metadata import PackageNotFoundError, distribution

    own = own.resolve()
    for dist_name in names:
        try:
            dist = distribution(dist_name)
        except PackageNotFoundError:
            continue
        paths = [(str(f), Path(str(dist.locate_file(f))).resolve()) for f in dist.files or [] if str(f).endswith(".py")]
        if any(p == own for _, p in paths):
            return sorted((f"{dist_name}/{n}", p) for n, p in paths if "__pycache__" not in Path(n).parts)
    return []
