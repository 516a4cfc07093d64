"""``harness sweep``: expansion against the results store, and two-run sweeps executed by Ray (a local cluster of
two CPUs) and by submitit (its local executor), each run in a worker process writing into the same store."""

from __future__ import annotations

import json
import os
import sys

import pytest

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from harness.errors import ConfigError, StoreError
from scale_helpers import TINY, plugin_dir, plugins_dir_in_process


@pytest.fixture
def plugins(host, tmp_path, monkeypatch):
    """The test plugins here (for planning) and, through HARNESS_* variables, in every worker process."""
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    folder = plugin_dir(tmp_path / "plugins")
    monkeypatch.setenv("HARNESS_PLUGINS_DIR", str(folder))
    monkeypatch.setenv("HARNESS_DISABLE_PLUGIN_AUTOLOAD", "1")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    with plugins_dir_in_process(folder):
        yield host


def spec(tmp_path, **kw):
    from harness.sweep import SweepSpec

    base = dict(
        detectors=("tinydet",),
        datasets=("shapes",),
        folds="all",
        seeds=(0,),
        overrides=tuple(TINY),
        store=str(tmp_path / "store"),
    )
    base.update(kw)
    return SweepSpec(**base)


def _finished_runs(store):
    from harness.store import Store

    return sorted(str(r.key) for r in Store(store).runs())


def test_expansion_covers_the_grid_and_leaves_out_impossible_combinations(plugins, tmp_path):
    from harness.sweep import expand

    planned = expand(
        spec(tmp_path, detectors=("tinydet", "tinydet-dual"), encodings=("test-ir8", "test-none"), seeds=(0, 1))
    )
    names = sorted(str(j) for j in planned.jobs)
    assert len(names) == 2 * 2 * 3 == len(set(names))  # (fold A, B) x (seed 0, 1) x 3 valid combinations
    assert "shapes/tinydet-dual/test-ir8/B/seed1" in names and "shapes/tinydet/test-none/A/seed0" in names
    assert len(planned.invalid) == 1 and "tinydet-dual x test-none" in planned.invalid[0]
    job = planned.jobs[0]
    assert os.path.isabs(job.store) and dict(job.env)["HARNESS_CACHE"] == str((tmp_path / "cache").resolve())
    assert dict(job.env)["HARNESS_PLUGINS_DIR"] == str(tmp_path / "plugins")
    with pytest.raises(ConfigError, match="no runnable combination"):
        expand(spec(tmp_path, detectors=("tinydet-dual",), encodings=("test-none",)))
    with pytest.raises(ConfigError, match="--executor 'nope'"):
        from harness.sweep import sweep

        sweep(spec(tmp_path), executor="nope")


def test_a_missing_executor_package_is_a_clear_error(plugins, tmp_path, monkeypatch):
    from harness.sweep import ExecutorError, execute, expand

    job = expand(spec(tmp_path, folds="A")).jobs[0]
    for module, executor in (("ray", "ray"), ("submitit", "slurm")):
        monkeypatch.setitem(sys.modules, module, None)  # `import ray` now raises ImportError
        with pytest.raises(
            ExecutorError, match=rf"--executor {executor} needs the Python package '{module}'.*pip install"
        ):
            execute([job], executor)
    assert _finished_runs(tmp_path / "store") == []


@pytest.mark.slow
def test_ray_sweep_runs_each_run_as_a_task_on_a_local_cluster(plugins, tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    from harness.sweep import sweep, sweep_table

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        assert ray.cluster_resources()["CPU"] == 2
        summary = sweep(spec(tmp_path), executor="ray", progress=False)
        assert ray.is_initialized()  # a cluster the sweep did not start is left running
    finally:
        ray.shutdown()
    assert [r.state for r in summary.results] == ["trained", "trained"], sweep_table(summary)
    assert all(int(r.worker.rsplit(":", 1)[1]) != os.getpid() for r in summary.results)  # ran in Ray workers
    assert _finished_runs(tmp_path / "store") == ["shapes/tinydet/test-ir8/A/seed0", "shapes/tinydet/test-ir8/B/seed0"]
    for r in summary.results:
        metrics = json.loads(open(os.path.join(r.path, "metrics.json")).read())
        assert metrics["train"]["epochs_run"] == 2 and metrics["metrics"]["mAP50"] == r.mAP50


@pytest.mark.slow
def test_submitit_sweep_runs_a_job_array_and_a_second_sweep_skips_it(plugins, tmp_path):
    pytest.importorskip("submitit")
    from harness.sweep import ExecutorOptions, expand, sweep, sweep_table

    options = ExecutorOptions(cluster="local", log_dir=str(tmp_path / "logs"), timeout_min=10)
    summary = sweep(spec(tmp_path), executor="slurm", options=options, progress=False)
    assert [r.state for r in summary.results] == ["trained", "trained"], sweep_table(summary)
    assert all(int(r.worker.rsplit(":", 1)[1]) != os.getpid() for r in summary.results)  # ran as subprocesses
    assert _finished_runs(tmp_path / "store") == ["shapes/tinydet/test-ir8/A/seed0", "shapes/tinydet/test-ir8/B/seed0"]
    assert any((tmp_path / "logs").iterdir())  # submitit's job folders
    # the store decides what is left: nothing, and a changed configuration is refused before anything is submitted
    again = expand(spec(tmp_path))
    assert again.jobs == [] and [r.state for r in again.skipped] == ["skipped", "skipped"]
    assert [r.mAP50 for r in again.skipped] == [r.mAP50 for r in summary.results]
    with pytest.raises(StoreError, match="different configuration.*--force"):
        expand(spec(tmp_path, overrides=(*TINY, "train.lr0=0.02")))
    assert len(expand(spec(tmp_path, overrides=(*TINY, "train.lr0=0.02"), force=True)).jobs) == 2


def test_sweep_command_runs_locally_and_prints_the_table(plugins, tmp_path, cli_runner):
    args = [
        "sweep",
        "--detectors",
        "tinydet",
        "--datasets",
        "shapes",
        "--folds",
        "A",
        "--seeds",
        "3",
        "--store",
        str(tmp_path / "store"),
        "--no-progress",
        *[a for s in TINY for a in ("--set", s)],
    ]
    dry = cli_runner([*args, "--dry-run"])
    assert dry.exit_code == 0 and "run   shapes/tinydet/test-ir8/A/seed3" in dry.output
    assert _finished_runs(tmp_path / "store") == []
    ran = cli_runner(args)
    assert ran.exit_code == 0, ran.output
    assert "shapes/tinydet/test-ir8/A/seed3  trained" in ran.output
    assert _finished_runs(tmp_path / "store") == ["shapes/tinydet/test-ir8/A/seed3"]
    assert "shapes/tinydet/test-ir8/A/seed3  skipped" in cli_runner(args).output


FAKE_SBATCH = """#!/bin/sh
cp "$1" "$SBATCH_COPY"
echo "Submitted batch job 4242"
"""


def test_slurm_sweep_is_submitted_as_one_job_array_with_the_parameters(plugins, tmp_path, monkeypatch):
    """With fake ``srun``/``sbatch`` on the PATH: the batch script submitit writes for the sweep."""
    pytest.importorskip("submitit")
    from harness.sweep import ExecutorOptions, expand, run_job, submitit_executor

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, text in (("srun", "#!/bin/sh\nexit 0\n"), ("sbatch", FAKE_SBATCH)):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("SBATCH_COPY", str(tmp_path / "submitted.sh"))
    jobs = expand(spec(tmp_path, seeds=(0, 1, 2))).jobs
    options = ExecutorOptions(
        partition="gpu",
        account="proj",
        timeout_min=90,
        mem_gb=32,
        cpus_per_run=8,
        array_parallelism=4,
        slurm_setup=("source /opt/venv/bin/activate",),
        slurm_extra=(("constraint", "a100"),),
    )
    ex = submitit_executor(options, tmp_path / "logs" / "%j")
    assert ex.cluster == "slurm"
    submitted = ex.map_array(run_job, jobs)
    assert [j.job_id for j in submitted] == [f"4242_{i}" for i in range(6)]
    script = (tmp_path / "submitted.sh").read_text()
    for line in (
        "#SBATCH --array=0-5%4",
        "#SBATCH --partition=gpu",
        "#SBATCH --account=proj",
        "#SBATCH --time=90",
        "#SBATCH --mem=32GB",
        "#SBATCH --cpus-per-task=8",
        "#SBATCH --gpus-per-node=1",
        "#SBATCH --constraint=a100",
        "source /opt/venv/bin/activate",
        "submitit.core._submit",
    ):
        assert line in script, (line, script)
    assert _finished_runs(tmp_path / "store") == []
