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
