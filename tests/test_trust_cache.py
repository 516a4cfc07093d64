"""The prepared-sample cache key covers the dataset plugin's code: an edited plugin prepares again."""

from __future__ import annotations

import importlib.util
import sys

import pytest

pytest.importorskip("harness.cache")

PLUGIN = """
from engine_helpers import CATEGORIES, ShapesSource
from harness import DatasetSpec, hookimpl


def open_shapes(root=None, sensing=None, **opts):
    return ShapesSource(**opts)


@hookimpl
def register_datasets(register):
    register(DatasetSpec(name="shapes-code", open=open_shapes, categories=CATEGORIES, default_encoding="test-ir8"))
"""


def test_an_edited_dataset_plugin_is_prepared_again(host, tmp_path, monkeypatch):
    from harness.cache import plugin_code_fingerprint, prepare
    from harness.testing import temporary_plugin

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "shapes_code_plugin.py"
    path.write_text(PLUGIN)
    spec = importlib.util.spec_from_file_location("shapes_code_plugin", path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "shapes_code_plugin", module)
    spec.loader.exec_module(module)
    with temporary_plugin(module, name="shapes-code-test"):
        before = plugin_code_fingerprint("shapes-code")
        assert before and prepare("shapes-code", {}, progress=False).from_cache is False
        assert prepare("shapes-code", {}, progress=False).from_cache is True
        path.write_text(PLUGIN.replace("**opts)\n", "**opts)  # samples now made differently\n", 1))
        assert plugin_code_fingerprint("shapes-code") != before
        assert prepare("shapes-code", {}, progress=False).from_cache is False
    assert plugin_code_fingerprint("no-such-dataset") == ""


PACKAGE = {
    "__init__.py": "",
    "plugin.py": """
from harness import DatasetSpec, hookimpl
from shapes_pkg_test.source import Source


def open_shapes(root=None, sensing=None, **opts):
    return Source(**opts)


@hookimpl
def register_datasets(register):
    register(DatasetSpec(name="shapes-pkg", open=open_shapes, categories=("window", "warm", "cold"),
                         default_encoding="test-ir8"))
""",
    "source.py": """
from engine_helpers import ShapesSource
from shapes_pkg_test import boxes


class Source(ShapesSource):
    def samples(self, report):
        for s in super().samples(report):
            yield boxes.adjust(s)
""",
    "boxes.py": """
def adjust(sample):
    return sample
""",
}


def test_a_module_the_plugin_imports_only_indirectly_is_part_of_the_key(host, tmp_path, monkeypatch):
    """plugin.py -> source.py -> boxes.py: editing boxes.py (which plugin.py never names) prepares again, and a
    finished run's identity (its prepared key) changes with it."""
    import importlib

    from harness.cache import plugin_code_fingerprint, prepare
    from harness.testing import temporary_plugin

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    pkg = tmp_path / "src" / "shapes_pkg_test"
    pkg.mkdir(parents=True)
    for name, text in PACKAGE.items():
        (pkg / name).write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path / "src"))
    for name in [m for m in sys.modules if m.startswith("shapes_pkg_test")]:
        monkeypatch.delitem(sys.modules, name)
    module = importlib.import_module("shapes_pkg_test.plugin")
    try:
        with temporary_plugin(module, name="shapes-pkg-test"):
            before = plugin_code_fingerprint("shapes-pkg")
            first = prepare("shapes-pkg", {}, progress=False)
            assert first.from_cache is False and prepare("shapes-pkg", {}, progress=False).from_cache is True
            (pkg / "boxes.py").write_text(PACKAGE["boxes.py"].replace("return sample", "return sample  # edited"))
            assert plugin_code_fingerprint("shapes-pkg") != before
            again = prepare("shapes-pkg", {}, progress=False)
            assert again.from_cache is False and again.key != first.key
    finally:
        for name in [m for m in sys.modules if m.startswith("shapes_pkg_test")]:
            sys.modules.pop(name, None)


def test_the_built_in_datasets_are_keyed_by_their_own_modules_and_what_they_import():
    """m3t-synth: its own sub-package and the modules of ``adapters`` it imports (m3t, the COCO helper), not the
    other datasets beside it, nor any detector."""
    import inspect

    from harness.cache.key import plugin_code_files
    from harness.plugins import get_host

    names = [n for n, _ in plugin_code_files(inspect.getmodule(get_host().dataset("m3t-synth").open))]
    assert "adapters.datasets/_coco.py" in names and "adapters.datasets/synthetic/rendering.py" in names
    assert "adapters.datasets/m3t.py" in names
    assert not any(n.startswith(("harness", "adapters.detectors", "adapters.datasets/synthetic_tiny")) for n in names)
    assert "adapters.datasets/llvip.py" not in names
