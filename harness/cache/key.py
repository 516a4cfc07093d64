"""Where a prepared dataset lives and what names it: the cache root, the key, the form's folder.

``<cache>/<dataset>/<key>/`` (compact form) or ``<cache>/<dataset>/<key>-raw/``, where ``<cache>`` is the
``cache_root`` argument, else ``$HARNESS_CACHE``, else ``./cache``, and::

    key = sha1({dataset, fingerprint, sensing, PREPARE_VERSION, plugin code})[:16]

The source's fingerprint changes with the input files (names, sizes, modification times, annotation and
registration contents) and the dataset's options; ``sensing`` is the part of the config's ``sensing`` section that
can change prepared samples; the plugin code is the Python source the dataset plugin comes from
(``plugin_code_files``: for a built-in plugin its own modules and those of ``adapters`` it imports, directly or
through another; for a third-party plugin its package or distribution; never the harness's), so a changed input, a
changed sensing setting or an edited plugin prepares again and never reuses stale samples, while moving code inside
the harness, or adding another built-in dataset, keeps every user's cache. The same files key a detector plugin's
code (``detector_code``), which a run records as ``meta.detector_code``.
"""

from __future__ import annotations

import ast
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


#: The top-level package of the built-in plugins (``adapters``): a built-in plugin is keyed by its own modules and
#: the modules of this package it imports (``import_closure``), never the whole package, so editing one detector, or
#: adding a dataset module, leaves the keys of the others alone.
BUILTIN_PACKAGE = "adapters"


def plugin_code_fingerprint(dataset: str) -> str:
    """sha1 of the Python source the registered dataset plugin comes from (``plugin_code_files``), so editing any
    module of it, imported directly or not, prepares again ("" for an unregistered name). Modules of the harness
    itself are never part of it."""
    try:
        from harness.plugins import get_host

        opener = get_host().dataset(dataset).open
    except Exception:  # noqa: BLE001 - a name no plugin registers (tests, analyses of a cache) has no code to key
        return ""
    home = inspect.getmodule(opener)
    if home is None:
        return ""
    h = hashlib.sha1()
    for name, digest in _file_digests(plugin_code_files(home)).items():
        h.update(name.encode() + b"\0" + digest)
    return h.hexdigest()


#: Hex digits of ``meta.detector_code`` and of each file's digest in ``meta.detector_code_files``.
CODE_DIGITS, FILE_DIGITS = 16, 8


def detector_code(detector: str) -> tuple[str, dict[str, str]]:
    """(digest, {file: digest}) of the Python source the registered detector plugin comes from: the files of
    ``plugin_code_files`` for the module of its ``build`` and for the plugin module that registered it (``("", {})``
    for an unregistered name, or a detector whose code is all the harness's). A run records them as
    ``meta.detector_code`` (part of its identity) and ``meta.detector_code_files`` (which files changed)."""
    try:
        from harness.plugins import get_host

        host = get_host()
        spec = host.detector(detector)
        owner = host.pm.get_plugin(host.owner("detector", detector))
    except Exception:  # noqa: BLE001 - a name no plugin registers has no code to key
        return "", {}
    homes = [inspect.getmodule(spec.build), owner if inspect.ismodule(owner) else inspect.getmodule(type(owner))]
    files: dict[str, Path] = {}
    for home in homes:
        if home is not None:
            files.update(plugin_code_files(home))
    digests = _file_digests(sorted(files.items()))
    if not digests:
        return "", {}
    h = hashlib.sha1()
    for name, digest in digests.items():
        h.update(name.encode() + b"\0" + digest)
    return h.hexdigest()[:CODE_DIGITS], {n: d.hex()[:FILE_DIGITS] for n, d in digests.items()}


def changed_code_files(old: Mapping[str, str] | None, new: Mapping[str, str] | None) -> list[str]:
    """The files whose digest differs between two ``meta.detector_code_files`` records (added and removed too)."""
    a, b = dict(old or {}), dict(new or {})
    return sorted(n for n in a.keys() | b.keys() if a.get(n) != b.get(n))


def _file_digests(files: list[tuple[str, Path]]) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    for name, path in files:
        try:
            out[name] = hashlib.sha1(path.read_bytes()).digest()
        except OSError:  # a file removed meanwhile: keyed by its absence
            continue
    return out


def plugin_code_files(module: Any) -> list[tuple[str, Path]]:
    """(name, path) of every ``.py`` file of the code a plugin module comes from, in a fixed order:

    * a built-in plugin (a module of ``BUILTIN_PACKAGE``): ``import_closure``, its own modules and those of the
      package it imports, directly or through another (a module of a sub-package such as
      ``adapters/datasets/synthetic/`` brings that whole sub-package);
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
    if top == BUILTIN_PACKAGE:
        return import_closure(name)
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


def import_closure(module: str) -> list[tuple[str, Path]]:
    """(name, path) of the ``.py`` files of ``module`` (a dotted name inside an imported top-level package) and of
    every module of that package it imports, transitively: the import statements are read from the source (at any
    depth, relative ones resolved), so a module imported only inside a function counts. The ``__init__.py`` of each
    package on the way is part of it (importing a module runs them). A module below a sub-package of the
    top-level package's first level (``top.kind.sub...``) brings every module of ``top.kind.sub``: its own code.
    Names are ``top.kind/relative/path.py``, as ``_tree`` writes them."""
    top = module.split(".")[0]
    package = sys.modules.get(top)
    roots = [Path(p) for p in getattr(package, "__path__", None) or []]
    if not roots:
        return []
    root = roots[0]
    todo, seen, files = [module], set(), {}
    parts = module.split(".")
    if len(parts) >= 3:
        own = _module_file(root, ".".join(parts[:3]))
        if own is not None and own.name == "__init__.py":  # the plugin's own sub-package
            todo += [_dotted(root, top, p) for p in sorted(own.parent.rglob("*.py")) if "__pycache__" not in p.parts]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = _module_file(root, name)
        if path is None:
            continue
        files[name] = path
        bits = name.split(".")
        todo += [".".join(bits[:i]) for i in range(1, len(bits))]  # the packages on the way
        todo += _imports(path, name, top)
    out = [(_label(root, top, path), path) for path in files.values()]
    return sorted(set(out))


def _module_file(root: Path, dotted: str) -> Path | None:
    rel = Path(*dotted.split(".")[1:]) if "." in dotted else Path()
    for candidate in (root / rel / "__init__.py", (root / rel).with_suffix(".py") if rel.parts else None):
        if candidate is not None and candidate.is_file():
            return candidate
    return None


def _dotted(root: Path, top: str, path: Path) -> str:
    rel = path.relative_to(root).with_suffix("").parts
    return ".".join([top, *(rel[:-1] if rel[-1] == "__init__" else rel)])


def _label(root: Path, top: str, path: Path) -> str:
    """``top.first/rest.py`` (``adapters.datasets/m3t.py``), or ``top/file.py`` for a module at the top level."""
    rel = path.relative_to(root).parts
    return f"{top}.{rel[0]}/{Path(*rel[1:]).as_posix()}" if len(rel) > 1 else f"{top}/{rel[0]}"


def _imports(path: Path, name: str, top: str) -> list[str]:
    """Dotted names within ``top`` that the module ``name`` (at ``path``) imports: the module and, for ``from X import
    y``, also ``X.y`` (which may be a module)."""
    try:
        tree = ast.parse(path.read_bytes(), filename=str(path))
    except (OSError, SyntaxError, ValueError):  # unreadable or broken: keyed by its bytes alone
        return []
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            out += [stem] + [f"{stem}.{a.name}" for a in node.names if a.name != "*"]
    return [n for n in out if n == top or n.startswith(top + ".")]


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
