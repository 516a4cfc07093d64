"""Where a prepared dataset lives and what names it: the cache root, the key, the form's folder.

``<cache>/<dataset>/<key>/`` (compact form) or ``<cache>/<dataset>/<key>-raw/``, where ``<cache>`` is the
``cache_root`` argument, else ``$HARNESS_CACHE``, else ``./cache``, and::

    key = sha1({dataset, fingerprint, sensing, PREPARE_VERSION, plugin code})[:16]

The source's fingerprint changes with the input files (names, sizes, modification times, annotation and
registration contents) and the dataset's options; ``sensing`` is the part of the config's ``sensing`` section that
can change prepared samples; the plugin code is the source of the dataset plugin's own modules (never the
harness's), so a changed input, a changed sensing setting or an edited plugin prepares again and never reuses stale
samples, while moving code inside the harness keeps every user's cache.
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


def plugin_code_fingerprint(dataset: str) -> str:
    """sha1 of the source of the registered dataset plugin: the module defining its ``open`` and the modules of
    the same package it imports names from, so an edited plugin prepares again ("" for an unregistered name).
    Modules of the harness itself are never part of it."""
    try:
        from harness.plugins import get_host

        opener = get_host().dataset(dataset).open
    except Exception:  # noqa: BLE001 - a name no plugin registers (tests, analyses of a cache) has no code to key
        return ""
    home = inspect.getmodule(opener)
    if home is None:
        return ""
    top = home.__name__.split(".")[0]
    names = {home.__name__} | {
        getattr(v, "__module__", None) or getattr(v, "__name__", "")
        for v in vars(home).values()
        if inspect.ismodule(v) or inspect.isclass(v) or inspect.isfunction(v)
    }
    h = hashlib.sha1()
    for name in sorted(n for n in names if n and n.split(".")[0] == top and top != "harness"):
        path = getattr(sys.modules.get(name), "__file__", None)
        if path and Path(path).is_file():
            h.update(name.encode() + b"\0" + Path(path).read_bytes())
    return h.hexdigest()
