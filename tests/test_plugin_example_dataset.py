"""The example dataset plugin in plugins/harness-example-dataset installs with pip, is found through its entry
point, ships its own protocol YAML, and goes through ``harness prepare``, ``folds`` and ``run``."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")
pytest.importorskip("setuptools")  # the plugin is built without build isolation, with the environment's setuptools

from engine_helpers import install_plugin, run_plugin_tests  # noqa: E402


def _harness(args, env):
    return subprocess.run(
        [sys.executable, "-m", "harness", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=env["HARNESS_TEST_CWD"],
    )


@pytest.mark.slow
def test_example_dataset_plugin_installs_prepares_and_runs(tmp_path):
    src, site = install_plugin("harness-example-dataset", tmp_path)
    assert (site / "harness_example_dataset" / "protocol.yaml").exists()  # package data travels with the wheel

    env = dict(os.environ)
    env.pop("HARNESS_DISABLE_PLUGIN_AUTOLOAD", None)
    env.update(
        PYTHONPATH=os.pathsep.join([str(site), env.get("PYTHONPATH", "")]).rstrip(os.pathsep),
        HARNESS_LOAD_PLUGINS="harness-example-dataset",
        HARNESS_CACHE=str(tmp_path / "cache"),
        HARNESS_TEST_CWD=str(tmp_path),
    )

    listed = json.loads(_harness(["list", "--format", "json"], env).stdout)
    mine = next(d for d in listed["datasets"] if d["name"] == "example-folders")
    assert mine["plugin"] == "example-folders" and mine["protocol"] == "harness_example_dataset:protocol.yaml"

    made = _harness(["example-data", "data"], env)  # the plugin's own command
    assert made.returncode == 0, made.stderr
    prep = _harness(["prepare", "--dataset", "example-folders", "--root", "data"], env)
    assert prep.returncode == 0, prep.stderr
    assert "prepared example-folders: 12 aligned samples, 24 instances" in prep.stdout
    folds = _harness(["folds", "--dataset", "example-folders", "--root", "data"], env)
    assert folds.returncode == 0, folds.stderr
    assert [line.split()[0] for line in folds.stdout.splitlines() if line.startswith("site")] == [
        "site1",
        "site2",
        "site3",
    ]

    sets = ["protocol.epochs=1", "model.scale=n", "train.threads=1"]
    args = [
        "run",
        "--detector",
        "ours",
        "--dataset",
        "example-folders",
        "--root",
        "data",
        "--folds",
        "site2",
        "--profile",
        "smoke",
        "--store",
        "store",
        "--no-progress",
        *[a for s in sets for a in ("--set", s)],
    ]
    ran = _harness(args, env)
    assert ran.returncode == 0, ran.stderr[-3000:]
    run_dir = tmp_path / "store" / "example-folders" / "ours" / "c2" / "site2" / "seed0"
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["support"] == {**metrics["support"], "images": 4, "instances": 8}
    config = (run_dir / "config.yaml").read_text()
    # the protocol came from the plugin's package; the smoke profile's imgsz (160) overrides its 64
    assert "name: example-folders" in config and str(site / "harness_example_dataset" / "protocol.yaml") in config

    own = run_plugin_tests(src, env)  # its own tests, with the fixtures the harness ships
    assert own.returncode == 0 and "2 passed" in own.stdout, own.stdout[-3000:] + own.stderr[-2000:]
