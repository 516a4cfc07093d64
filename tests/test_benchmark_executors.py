"""``harness benchmark run --executor ray|slurm``: the benchmark's cells through the sweep's executors, into the same
store as the local lanes.

Two TinyDet cells (one fold, two seeds, one epoch at 64 px) run as Ray tasks on a local Ray instance of two CPUs;
one of them is removed and a second call through submitit's local executor (a job array) trains only that one and
skips the other; ``harness report`` reads the store.
"""

from __future__ import annotations

import json
import os
import re
import shutil

import pytest

from engine_helpers import set_args
from report_fixtures import TINY_RUN, TINYDET_SRC, cli, tinydet_on_path

for _module in ("harness.evaluation", "harness.runner", "harness.cache"):
    pytest.importorskip(_module)

CELLS = ["--detectors", "tinydet", "--folds", "P1", "--seeds", "0,1", "--no-ablation"]
SETS = set_args([*TINY_RUN, "dataset.profile=tiny"])


def _cell_results(output: str) -> dict[str, str]:
    """``run -> state`` from the table ``benchmark run`` prints."""
    out = {}
    for line in output.splitlines():
        parts = line.split()
        if parts and parts[0].startswith("m3t-synth/tinydet/"):
            out[parts[0]] = parts[1]
    return out


@pytest.mark.slow
def test_ray_then_submitit_fill_one_store_that_reports(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    pytest.importorskip("submitit")
    shim = tmp_path / "plugins"
    shim.mkdir()
    # the cells' `harness run` processes find the plugin the way an unpackaged plugin is found
    (shim / "tinydet_shim.py").write_text("from harness_tinydet.plugin import *  # noqa: F401,F403\n")
    from harness.testing import reset_plugins

    store = tmp_path / "store"
    args = ["benchmark", "run", "--store", str(store), *CELLS, *SETS, "--no-progress"]
    with tinydet_on_path(
        tmp_path,
        HARNESS_DATA=str(tmp_path / "data"),
        HARNESS_PLUGINS_DIR=str(shim),
        PYTHONPATH=os.pathsep.join([str(TINYDET_SRC), os.environ.get("PYTHONPATH", "")]),
        RAY_AUTH_MODE="disabled",
        OMP_NUM_THREADS="1",
    ):
        reset_plugins()
        try:
            ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
            try:
                first = cli([*args, "--executor", "ray"])
            finally:
                ray.shutdown()
            seed0, seed1 = "m3t-synth/tinydet/c2/P1/seed0", "m3t-synth/tinydet/c2/P1/seed1"
            assert _cell_results(first) == {seed0: "trained", seed1: "trained"}, first
            assert "this call (--executor ray)" in first
            runs = {seed: store / "m3t-synth" / "tinydet" / "c2" / "P1" / f"seed{seed}" for seed in (0, 1)}
            for run in runs.values():
                metrics = json.loads((run / "metrics.json").read_text())
                assert metrics["train"]["epochs_run"] == 1
            mtime0 = (runs[0] / "metrics.json").stat().st_mtime_ns
            # the lanes' layout: one log per cell, holding the cell's `harness run` command and its output
            logs = sorted(p.name for p in (store / "_benchmark" / "logs").glob("*.log"))
            assert logs == ["tinydet_c2_P1_seed0.log", "tinydet_c2_P1_seed1.log"]
            assert "-m harness run --detector tinydet" in (store / "_benchmark" / "logs" / logs[0]).read_text()

            shutil.rmtree(runs[1])
            second = cli(
                [*args, "--executor", "slurm", "--submitit-cluster", "local", "--log-dir", str(tmp_path / "sub")]
            )
            assert _cell_results(second) == {seed0: "skipped", seed1: "trained"}, second
            assert (runs[1] / "metrics.json").is_file()
            assert (runs[0] / "metrics.json").stat().st_mtime_ns == mtime0  # the finished cell was not touched
            assert any((tmp_path / "sub").iterdir())  # submitit's job folders

            timing = json.loads((store / "_benchmark" / "timing.json").read_text())
            calls = [(c["executor"], c["cells"]) for c in timing["calls"]]
            assert calls == [("ray", 2), ("slurm", 1)] and all(c["cpu_s"] > 0 for c in timing["calls"])

            cli(["report", "--store", str(store), "--out", str(tmp_path / "report")])
            text = (tmp_path / "report" / "report.txt").read_text()
            assert text.startswith("Benchmark report: m3t-synth") and re.search(r"^tinydet +c2 +\d", text, re.M), text
            assert "0 cell(s) to run, 2 finished" in cli([*args, "--dry-run"])
        finally:
            reset_plugins()


def test_lanes_are_for_the_local_executor_and_the_paper_profile_keeps_the_detectors_sizes(tmp_path):
    from harness import benchmark as B
    from harness.errors import ConfigError

    with pytest.raises(ConfigError, match="--lanes is for --executor local"):
        B.run_benchmark(B.BenchmarkSpec(store=tmp_path), lanes=2, executor="ray")
    with pytest.raises(ConfigError, match="--executor 'nope'"):
        B.run_benchmark(B.BenchmarkSpec(store=tmp_path), executor="nope")
    assert B.detector_config("ours", "paper") is None
    assert B.detector_config("ours").name == "ours.yaml"  # the benchmark profile: n sizes
    specs = B._specs(B.BenchmarkSpec(store=tmp_path, profile="paper"))
    assert specs and all(not s.config_files for s in specs)
    assert sum(len(s.seeds or ()) * len(s.encodings or ("",)) for s in specs) == 4 * 3 + 4 * 3
