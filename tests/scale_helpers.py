"""Helpers for the scale-out tests: a plugin folder that gives another process (torchrun, Ray or submitit workers,
a killed and restarted run) the test dataset, the test encodings and the example TinyDet detector, and the
environment such a process needs."""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path
from typing import Iterator

from engine_helpers import PLUGIN_SRC, write_plugin_dir

TESTS = Path(__file__).resolve().parent

TINYDET_FILE = '''
"""Test plugin loaded through HARNESS_PLUGINS_DIR: the example TinyDet detectors from the source tree."""
import sys
sys.path.insert(0, {src!r})
from harness_tinydet.plugin import register_detectors
'''

#: A run that takes a few seconds on one CPU core: 64 px images, 8 training and 8 held-out images per fold.
TINY = [
    "protocol.imgsz=64",
    "protocol.epochs=2",
    "protocol.patience=10",
    "train.batch=4",
    "train.nominal_batch=4",
    "train.warmup_epochs=0.5",
    "train.warmup_min_iters=0",
    "train.close_mosaic=1",
    "train.threads=1",
    "train.device=cpu",
    "eval.batch=8",
]


def plugin_dir(folder: Path) -> Path:
    """A folder of plugin files (shapes dataset + test encodings + TinyDet) for ``HARNESS_PLUGINS_DIR``."""
    write_plugin_dir(folder)
    (folder / "tinydet_plugin.py").write_text(TINYDET_FILE.format(src=str(PLUGIN_SRC)))
    return folder


@contextlib.contextmanager
def plugins_dir_in_process(folder: Path) -> Iterator[None]:
    """The plugin files of ``folder`` registered in this process as ``HARNESS_PLUGINS_DIR`` registers them in a worker
    (the same modules, names and files), for a ``with`` block: planning here then sees the code the workers run, which
    is part of a run's identity (``meta.detector_code``)."""
    import importlib.util

    from harness.testing import temporary_plugin

    with contextlib.ExitStack() as stack:
        for path in sorted(folder.glob("*.py")):
            name = f"harness_plugins_dir.{path.stem}"
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
            sys.modules[name] = module
            spec.loader.exec_module(module)  # type: ignore[union-attr]
            stack.enter_context(temporary_plugin(module, name=f"{path.stem}-in-process"))
        yield


def subprocess_env(tmp_path: Path, **extra: str) -> dict[str, str]:
    """The environment of a harness process started by a test: only the test plugins, a private cache, one thread."""
    env = dict(os.environ)
    env.update(
        HARNESS_DISABLE_PLUGIN_AUTOLOAD="1",
        HARNESS_PLUGINS_DIR=str(plugin_dir(tmp_path / "plugins")),
        HARNESS_CACHE=str(tmp_path / "cache"),
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        PYTHONPATH=os.pathsep.join([str(TESTS), env.get("PYTHONPATH", "")]).rstrip(os.pathsep),
    )
    env.pop("HARNESS_LOAD_PLUGINS", None)
    env.update(extra)
    return env


def harness_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "harness", *args]
