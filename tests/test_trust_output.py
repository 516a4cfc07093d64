"""Output hygiene: machine-readable stdout, logs on stderr, located plugin failures, exit codes, no stray files."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BROKEN = """from harness import DatasetSpec, hookimpl


@hookimpl
def register_datasets(register):
    raise RuntimeError("the plugin is broken here")
"""


def test_plugins_prints_json_only_and_locates_a_broken_plugin(tmp_path):
    (tmp_path / "plug").mkdir()
    path = tmp_path / "plug" / "broken_plugin.py"
    path.write_text(BROKEN)
    env = {
        **os.environ,
        "HARNESS_PLUGINS_DIR": str(tmp_path / "plug"),
        "HARNESS_DISABLE_PLUGIN_AUTOLOAD": "1",
        "COLUMNS": "100",
    }
    res = subprocess.run(
        [sys.executable, "-m", "harness", "-vv", "plugins"], capture_output=True, text=True, env=env, timeout=120
    )
    assert res.returncode == 0, res.stderr
    data = json.loads(res.stdout)  # nothing but the JSON on stdout
    problem = next(p for p in data["problems"] if p["plugin"] == "broken_plugin")
    assert f"{path}:6" in problem["message"]
    assert "the plugin is broken here" in res.stderr and "Traceback" in res.stderr  # -vv: the traceback, on stderr


def test_ctrl_c_exits_130(cli_runner, monkeypatch):
    import harness.commands.core as core

    def interrupted(host):
        raise KeyboardInterrupt

    monkeypatch.setattr(core, "listing", interrupted)
    assert cli_runner(["list"]).exit_code == 130


def test_report_print_writes_the_report_folder_only_with_out(tmp_path, cli_runner):
    pytest.importorskip("harness.evaluation")
    sys.path.insert(0, str(Path(__file__).parent))
    from report_fixtures import synthetic_store

    store = synthetic_store(tmp_path / "s", folds=("P1", "P2"), per_fold=3)
    res = cli_runner(
        ["report", "--print", "--store", str(store.root), "--out", str(tmp_path / "rep"), "--resamples", "0"]
    )
    assert res.exit_code == 0, res.output
    assert "project-grouped folds" in res.output and (tmp_path / "rep" / "report.md").is_file()
    assert f"-> {tmp_path / 'rep' / 'report.md'}" in res.output  # said, not silent
    res = cli_runner(["report", "--print", "--store", str(store.root), "--resamples", "0"])
    assert res.exit_code == 0 and "project-grouped folds" in res.output and "-> " not in res.output


def test_a_dataset_with_only_invalid_samples_names_the_reasons_with_counts(host, tmp_path, monkeypatch):
    pytest.importorskip("harness.cache")
    from engine_helpers import CATEGORIES, ShapesSource
    from harness import DatasetSpec
    from harness.cache import prepare
    from harness.errors import DataError

    class FloatRGB(ShapesSource):
        def samples(self, report):
            for s in super().samples(report):
                yield dataclasses.replace(s, rgb=s.rgb.astype(np.float32))

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    spec = DatasetSpec(name="float-rgb", open=lambda root=None, **o: FloatRGB(), categories=CATEGORIES)
    with pytest.raises(DataError) as err:
        prepare(spec, {}, progress=False)
    assert "16 skipped" in str(err.value)
    assert "field 'rgb': expected dtype uint8, got float32: 16" in str(err.value)


def test_a_sweep_checks_its_settings_per_detector_when_planning(host, tmp_path, monkeypatch):
    pytest.importorskip("harness.cache")
    from engine_helpers import ShapesPlugin, tinydet_module
    from harness.errors import ConfigError
    from harness.sweep import SweepSpec, expand
    from harness.testing import temporary_plugin

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    tinydet_module()
    import harness_tinydet.plugin as tinydet_plugin

    with (
        temporary_plugin(ShapesPlugin(), name="shapes-sweep-plan"),
        temporary_plugin(tinydet_plugin, name="tinydet-sweep-plan"),
    ):
        spec = SweepSpec(
            ("tinydet",), ("shapes",), store=str(tmp_path / "store"), overrides=("protocol.imgsz=64", "model.widht=8")
        )
        with pytest.raises(ConfigError, match="tinydet.*widht"):
            expand(spec)
        assert len(expand(dataclasses.replace(spec, overrides=("protocol.imgsz=64", "model.width=8"))).jobs) == 2
