"""The example plugin in plugins/harness-tinydet installs as a package, is found through its entry point, and runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

# the whole job needs the dataset cache and the evaluation (skipped cleanly on a checkout without them)
pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")
pytest.importorskip("setuptools")  # the plugin is built without build isolation, with the environment's setuptools

from engine_helpers import install_plugin, run_plugin_tests, write_plugin_dir


def _env(site, **extra):
    env = dict(os.environ)
    env.pop("HARNESS_DISABLE_PLUGIN_AUTOLOAD", None)
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["HARNESS_LOAD_PLUGINS"] = "harness-tinydet"  # only this distribution, whatever else is installed
    env.update({k: str(v) for k, v in extra.items()})
    return env


def _harness(args, env, timeout=300):
    return subprocess.run(
        [sys.executable, "-m", "harness", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=env.get("HARNESS_TEST_CWD"),
    )


@pytest.mark.slow
def test_example_plugin_installs_lists_and_runs(tmp_path):
    src, site = install_plugin("harness-tinydet", tmp_path)
    assert (site / "harness_tinydet" / "plugin.py").exists()

    env = _env(
        site,
        HARNESS_PLUGINS_DIR=write_plugin_dir(tmp_path / "dir_plugins"),
        HARNESS_CACHE=tmp_path / "cache",
        HARNESS_TEST_CWD=tmp_path,
    )
    listed = _harness(["list", "--format", "json"], env)
    assert listed.returncode == 0, listed.stderr
    detectors = {d["name"]: d for d in json.loads(listed.stdout)["detectors"]}
    assert detectors["tinydet"]["plugin"] == "tinydet" and detectors["tinydet"]["input_kind"] == "single"
    assert detectors["tinydet-dual"]["input_kind"] == "dual"

    plugins = json.loads(_harness(["plugins", "--external"], env).stdout)["plugins"]
    mine = next(p for p in plugins if p["name"] == "tinydet")
    assert mine["distribution"] == "harness-tinydet" and mine["version"] == "0.1.0"

    store = tmp_path / "store"
    sets = [
        "protocol.imgsz=64",
        "protocol.epochs=2",
        "train.batch=8",
        "train.nominal_batch=8",
        "train.threads=1",
        "train.warmup_min_iters=0",
        "train.device=cpu",
    ]
    ran = _harness(
        [
            "run",
            "--detector",
            "tinydet",
            "--dataset",
            "shapes",
            "--encoding",
            "test-ir8",
            "--folds",
            "A",
            "--store",
            str(store),
            "--no-progress",
            *[a for s in sets for a in ("--set", s)],
        ],
        env,
    )
    assert ran.returncode == 0, ran.stderr[-3000:]
    assert "tinydet on shapes, encoding test-ir8" in ran.stdout
    metrics = json.loads((store / "shapes" / "tinydet" / "test-ir8" / "A" / "seed0" / "metrics.json").read_text())
    assert metrics["train"]["epochs_run"] == 2 and metrics["support"]["images"] == 8

    own = run_plugin_tests(src, _env(site))  # its own tests, with the fixtures the harness ships
    assert own.returncode == 0 and "3 passed" in own.stdout, own.stdout[-3000:] + own.stderr[-2000:]
