"""The example dataset's own tests, written with the fixtures the harness ships for plugin authors
(``harness.testing``: a pytest plugin that installing the harness enables). Run them with ``pytest`` here."""

from __future__ import annotations

import harness_example_dataset.plugin as plugin

from harness.cache import prepare
from harness.config import load_config


def test_a_generated_folder_prepares_into_three_sites(harness_plugin, harness_host, tmp_path):
    harness_plugin(plugin, name="example-under-test")
    plugin.make_example(tmp_path / "data")
    spec = harness_host.dataset("example-folders")
    cfg = load_config(protocol=spec.protocol)
    cfg["dataset"] = {"root": str(tmp_path / "data")}
    ds = prepare("example-folders", cfg, cache_root=tmp_path / "cache", progress=False)
    assert len(ds) == 12 and sorted(set(ds.groups)) == ["site1", "site2", "site3"]
    assert ds.manifest["report"]["skipped"] == 0


def test_its_command_writes_the_example_folder(harness_plugin, harness_cli, tmp_path):
    harness_plugin(plugin)
    result = harness_cli(["example-data", str(tmp_path / "made")])
    assert result.exit_code == 0, result.output
    assert len(list((tmp_path / "made").glob("*/*.rgb.png"))) == 12
