"""Sweeps: detectors x datasets x encodings x folds x seeds, run locally, on a Ray cluster, or as Slurm job arrays.

``expand(SweepSpec(...))`` turns a sweep into one job per run (one detector, dataset, encoding, fold and seed).
It resolves every combination through the runner's own planning (``harness.runner.plan``), so the dataset is
prepared once, before any job starts, and the results store decides what is left to do exactly as ``harness run``
does: a run that finished with the same configuration is skipped (unless ``force``), a run that finished with a
different configuration stops the whole sweep before anything is submitted (unless ``force``), and an interrupted
run resumes from its last checkpoint when its job runs.

``execute(jobs, executor, options)`` runs the jobs:

* ``local``: one after the other in this process;
* ``ray``: each job one Ray task (``num_gpus=1`` when the cluster has GPUs, ``num_cpus=options.cpus_per_run``),
  on the cluster at ``options.ray_address`` or a local one started for the sweep (and shut down after it);
* ``slurm``: a submitit job array (``AutoExecutor.map_array``; at most ``options.array_parallelism`` jobs at once).
  Where there is no Slurm, submitit's ``local`` executor runs the same jobs as subprocesses.

Each job calls ``harness.runner.run`` for its one (fold, seed), so every result lands in the same results store and
reports read it as soon as the job is done. A job that fails is reported with its error; the others go on.
Jobs carry plain values only (names, paths, overrides) and the ``HARNESS_*`` environment of the driver, so a worker
on another machine loads the same plugins and the same prepared-dataset cache.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from harness.errors import ConfigError, HarnessError
from harness.progress import bar as progress_bar

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray", "slurm")
#: Environment variables handed to every job (plugins, cache and config locations).
JOB_ENV_PREFIX = "HARNESS_"


class ExecutorError(HarnessError):
    """An executor cannot run the sweep (its package is missing, the cluster is unreachable)."""


@dataclass(frozen=True)
class SweepSpec:
    """What ``harness sweep`` asks for; ``seeds=None`` means the protocol's seeds, ``encodings=()`` the default."""

    detectors: tuple[str, ...]
    datasets: tuple[str, ...]
    folds: str = "all"
    seeds: tuple[int, ...] | None = None
    encodings: tuple[str, ...] = ()
    profile: str | None = "smoke"
    config_files: tuple[str, ...] = ()
    overrides: tuple[str, ...] = ()
    store: str | None = None
    force: bool = False


@dataclass(frozen=True)
class SweepJob:
    """One run of a sweep: everything a worker needs, as plain picklable values."""

    detector: str
    dataset: str
    encoding: str
    fold: str
    seed: int
    store: str
    profile: str | None = "smoke"
    config_files: tuple[str, ...] = ()
    overrides: tuple[str, ...] = ()
    force: bool = False
    env: tuple[tuple[str, str], ...] = ()

    def __str__(self) -> str:
        return f"{self.dataset}/{self.detector}/{self.encoding}/{self.fold}/seed{self.seed}"


@dataclass
class JobResult:
    """How a job ended: ``trained``, ``resumed``, ``skipped`` (finished earlier) or ``failed`` (with the error)."""

    run: str
    state: str
    path: str | None = None
    mAP50: float | None = None
    mAP50_95: float | None = None
    time_s: float | None = None
    error: str | None = None
    worker: str | None = None  # host:pid of the process that ran the job
    cpu_s: float | None = None  # CPU time of the job's own processes, where the worker measures it


@dataclass
class SweepPlan:
    jobs: list[SweepJob] = field(default_factory=list)  # runs left to do
    skipped: list[JobResult] = field(default_factory=list)  # finished earlier with the same configuration
    invalid: list[str] = field(default_factory=list)  # combinations that cannot run (e.g. dual-stream + RGB only)
    store: Path | None = None


@dataclass
class ExecutorOptions:
    """Resources and cluster settings of ``ray`` and ``slurm`` sweeps (see ``docs/scaling.md``)."""

    cpus_per_run: int = 1
    gpus_per_run: int | None = None  # None: 1 where GPUs exist, else 0
    ray_address: str | None = None  # None: $RAY_ADDRESS, else a local cluster for the sweep
    cluster: str | None = None  # submitit cluster: None (Slurm when available, else local), slurm, local, debug
    log_dir: str | None = None  # submitit logs [default: <store>/_sweeps/<time>]
    timeout_min: int = 24 * 60
    mem_gb: float | None = None
    partition: str | None = None
    account: str | None = None
    qos: str | None = None
    array_parallelism: int = 16
    slurm_setup: tuple[str, ...] = ()  # shell lines run before each job (module load, source venv)
    slurm_extra: tuple[tuple[str, str], ...] = ()  # further sbatch options, e.g. (("constraint", "a100"),)


# ------------------------------------------------------------------------------------------------- expansion
def job_env() -> tuple[tuple[str, str], ...]:
    """The ``HARNESS_*`` variables of this process, with the prepared-dataset cache as an absolute path."""
    from harness.cache import cache_root

    env = {k: v for k, v in os.environ.items() if k.startswith(JOB_ENV_PREFIX)}
    env["HARNESS_CACHE"] = str(cache_root().resolve())
    return tuple(sorted(env.items()))


def expand(spec: SweepSpec) -> SweepPlan:
    """The sweep's runs, checked against the results store (see the module docstring)."""
    from harness.report.reader import read_run
    from harness.runner import RunRequest, conflict_error, plan

    if not spec.detectors or not spec.datasets:
        raise ConfigError("a sweep needs at least one detector (--detectors) and one dataset (--datasets)")
    store = Path(spec.store or Path("results") / (spec.profile or "default")).resolve()
    config_files = tuple(str(Path(f).resolve()) for f in spec.config_files)
    env = job_env()
    out = SweepPlan(store=store)
    conflicts: list[str] = []
    for dataset in spec.datasets:
        for detector in spec.detectors:
            for encoding in spec.encodings or (None,):
                request = RunRequest(
                    detector=detector,
                    dataset=dataset,
                    encoding=encoding,
                    folds=spec.folds,
                    seeds=list(spec.seeds) if spec.seeds is not None else None,
                    profile=spec.profile,
                    config_files=config_files,
                    overrides=list(spec.overrides),
                    store=store,
                    force=spec.force,
                    progress=False,
                )
                try:
                    p = plan(request)
                except ConfigError as exc:
                    if encoding is None or "encoding" not in str(exc):
                        raise
                    out.invalid.append(f"{detector} x {encoding}: {exc}")  # e.g. a dual-stream detector, RGB only
                    log.warning("sweep: %s with encoding %s cannot run and is left out: %s", detector, encoding, exc)
                    continue
                conflicts.extend(p.conflicts())
                for planned in p.runs:
                    key = planned.run.key
                    if planned.state == "finished" and not spec.force:
                        m = read_run(planned.run).metrics.get("metrics", {})
                        out.skipped.append(
                            JobResult(str(key), "skipped", str(planned.run.path), m.get("mAP50"), m.get("mAP50_95"))
                        )
                        continue
                    out.jobs.append(
                        SweepJob(
                            detector=key.detector,
                            dataset=key.dataset,
                            encoding=key.encoding,
                            fold=key.fold,
                            seed=key.seed,
                            store=str(store),
                            profile=spec.profile,
                            config_files=config_files,
                            overrides=tuple(spec.overrides),
                            force=spec.force,
                            env=env,
                        )
                    )
    if conflicts and not spec.force:
        from harness.store import Store

        raise conflict_error(conflicts, Store(store))
    if not out.jobs and not out.skipped:
        raise ConfigError("the sweep expands to no runnable combination: " + "; ".join(out.invalid))
    return out


# ------------------------------------------------------------------------------------------------- one job
def run_job(job: SweepJob, progress: bool = False) -> JobResult:
    """Run one job with ``harness.runner.run`` (in a worker, or in this process); errors become a failed result."""
    import socket

    for k, v in job.env:
        os.environ[k] = v
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `harness run`: before torch is first imported
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from harness.runner import RunRequest, run

    t0 = time.perf_counter()
    host = f"{socket.gethostname()}:{os.getpid()}"
    try:
        summary = run(
            RunRequest(
                detector=job.detector,
                dataset=job.dataset,
                encoding=job.encoding,
                folds=job.fold,
                seeds=[job.seed],
                profile=job.profile,
                config_files=job.config_files,
                overrides=list(job.overrides),
                store=job.store,
                force=job.force,
                progress=progress,
            )
        )
    except Exception as exc:
        error = f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, HarnessError):  # a bug: keep the traceback in the report
            error += "\n" + "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)[-6:])
        return JobResult(str(job), "failed", error=error, worker=host, time_s=round(time.perf_counter() - t0, 2))
    r = summary.results[0]
    m = r.metrics.get("metrics", {})
    return JobResult(
        str(r.key),
        r.state,
        str(r.path),
        m.get("mAP50"),
        m.get("mAP50_95"),
        round(time.perf_counter() - t0, 2),
        worker=host,
    )


def _failed(job: SweepJob, exc: BaseException) -> JobResult:
    return JobResult(str(job), "failed", error=f"{type(exc).__name__}: {str(exc).strip()[-2000:]}")


# ------------------------------------------------------------------------------------------------- executors
def _require(module: str, executor: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ExecutorError(
            f"--executor {executor} needs the Python package {module!r}, which is not installed; install it with "
            f"`pip install 'rgbt-harness[scale]'` (or `pip install {module}`), or use --executor local"
        ) from None


@dataclass(frozen=True)
class ExecutorCall:
    """What ``execute`` hands an executor: the jobs, its options, whether to draw a progress bar, and a callback
    that hears each job's result as it comes in."""

    jobs: list[SweepJob]
    options: ExecutorOptions
    progress: bool = True
    on_result: Callable[[JobResult], None] | None = None
    #: What a worker runs for one job: ``run_job`` (the sweep's), or another module-level function of a job (the
    #: benchmark's ``harness.benchmark.run_cell``); Ray and submitit pickle it by reference.
    task: Callable[[SweepJob], JobResult] = run_job

    def deliver(self, result: JobResult) -> JobResult:
        """``result``, after handing it to ``on_result`` (when there is one)."""
        if self.on_result:
            self.on_result(result)
        return result


def run_local(call: ExecutorCall) -> list[JobResult]:
    results = []
    for i, job in enumerate(call.jobs, 1):
        log.info("sweep: run %d of %d: %s", i, len(call.jobs), job)
        results.append(call.deliver(run_job(job, progress=call.progress) if call.task is run_job else call.task(job)))
    return results


def run_ray(call: ExecutorCall) -> list[JobResult]:
    ray = _require("ray", "ray")
    options = call.options
    started = False
    if not ray.is_initialized():
        try:
            ray.init(address=options.ray_address, include_dashboard=False, log_to_driver=False)
        except Exception as exc:
            raise ExecutorError(
                f"cannot start or reach the Ray cluster (address {options.ray_address or 'local'}): "
                f"{type(exc).__name__}: {exc}"
            ) from None
        started = True
    try:
        gpus = options.gpus_per_run
        if gpus is None:
            gpus = 1 if ray.cluster_resources().get("GPU", 0) > 0 else 0
        task = ray.remote(num_cpus=options.cpus_per_run, num_gpus=gpus, max_retries=0)(call.task)
        refs = {task.remote(job): job for job in call.jobs}
        log.info("sweep: %d Ray tasks submitted (%d CPU, %d GPU each)", len(refs), options.cpus_per_run, gpus)
        by_ref: dict[Any, JobResult] = {}
        pending = list(refs)
        with progress_bar("sweep (ray)", len(refs), enabled=call.progress) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # the worker died (out of memory, killed node)
                        result = _failed(refs[ref], exc)
                    by_ref[ref] = call.deliver(result)
                    bar.advance()
        return [by_ref[ref] for ref in refs]
    finally:
        if started:
            ray.shutdown()


def submitit_executor(options: ExecutorOptions, folder: Path) -> Any:
    """A submitit ``AutoExecutor`` configured from ``options`` (Slurm when available, else local subprocesses)."""
    submitit = _require("submitit", "slurm")
    try:
        ex = submitit.AutoExecutor(folder=str(folder), cluster=options.cluster)
    except Exception as exc:
        raise ExecutorError(f"submitit cannot use cluster {options.cluster!r}: {exc}") from None
    if ex.cluster != "slurm":
        log.warning("sweep: no Slurm cluster here; submitit runs the jobs with its %r executor", ex.cluster)
    gpus = options.gpus_per_run
    if gpus is None:
        if ex.cluster == "slurm":
            gpus = 1
        else:
            import torch

            gpus = 1 if torch.cuda.is_available() else 0
    params: dict[str, Any] = {
        "name": "harness-sweep",
        "timeout_min": int(options.timeout_min),
        "nodes": 1,
        "tasks_per_node": 1,
        "cpus_per_task": int(options.cpus_per_run),
        "gpus_per_node": int(gpus),
        "mem_gb": options.mem_gb,
        "slurm_partition": options.partition,
        "slurm_account": options.account,
        "slurm_qos": options.qos,
        "slurm_array_parallelism": int(options.array_parallelism),
        "slurm_setup": list(options.slurm_setup) or None,
        "slurm_additional_parameters": dict(options.slurm_extra) or None,
    }
    try:
        ex.update_parameters(**{k: v for k, v in params.items() if v is not None})
    except (NameError, AssertionError, ValueError) as exc:
        raise ExecutorError(f"submitit refused the Slurm parameters: {exc}") from None
    return ex


def run_submitit(call: ExecutorCall) -> list[JobResult]:
    jobs, options = call.jobs, call.options
    if not jobs:
        return []
    store = Path(jobs[0].store)
    folder = Path(options.log_dir) if options.log_dir else store / "_sweeps" / time.strftime("%Y%m%d-%H%M%S")
    ex = submitit_executor(options, folder / "%j")
    submitted = ex.map_array(call.task, list(jobs))  # one Slurm job array
    log.info(
        "sweep: %d jobs submitted to %s (logs in %s): %s",
        len(submitted),
        ex.cluster,
        folder,
        ", ".join(str(j.job_id) for j in submitted[:5]) + (" ..." if len(submitted) > 5 else ""),
    )
    results: list[JobResult | None] = [None] * len(submitted)
    waiting = set(range(len(submitted)))
    try:
        with progress_bar(f"sweep ({ex.cluster})", len(submitted), enabled=call.progress) as bar:
            while waiting:
                for i in sorted(waiting):
                    if not submitted[i].done():
                        continue
                    try:
                        result = submitted[i].result()
                    except Exception as exc:  # the job crashed, timed out or was cancelled; submitit says why
                        result = _failed(jobs[i], exc)
                    waiting.discard(i)
                    results[i] = call.deliver(result)
                    bar.advance()
                if waiting:
                    time.sleep(0.5)
    except BaseException:  # Ctrl-C: the jobs left are cancelled (scancel), not left running without a driver
        for i in sorted(waiting):
            with contextlib.suppress(Exception):
                submitted[i].cancel(check=False)
        raise
    return [r for r in results if r is not None]


RUNNERS: dict[str, Callable[[ExecutorCall], list[JobResult]]] = {
    "local": run_local,
    "ray": run_ray,
    "slurm": run_submitit,
}


def execute(
    jobs: Sequence[SweepJob],
    executor: str = "local",
    options: ExecutorOptions | None = None,
    progress: bool = True,
    on_result: Callable[[JobResult], None] | None = None,
    task: Callable[[SweepJob], JobResult] = run_job,
) -> list[JobResult]:
    """Run ``jobs`` with ``executor`` (``task`` runs one job in a worker, see ``ExecutorCall``)."""
    if executor not in RUNNERS:
        raise ConfigError(f"--executor {executor!r}: choose one of {', '.join(EXECUTORS)}")
    return RUNNERS[executor](ExecutorCall(list(jobs), options or ExecutorOptions(), progress, on_result, task))


@dataclass
class SweepSummary:
    store: Path
    results: list[JobResult]
    invalid: list[str]

    @property
    def failed(self) -> list[JobResult]:
        return [r for r in self.results if r.state == "failed"]


def sweep(
    spec: SweepSpec, executor: str = "local", options: ExecutorOptions | None = None, progress: bool = True
) -> SweepSummary:
    """Expand ``spec`` and run what is left to do with ``executor``; see the module docstring."""
    if executor not in RUNNERS:
        raise ConfigError(f"--executor {executor!r}: choose one of {', '.join(EXECUTORS)}")
    planned = expand(spec)
    log.info(
        "sweep: %d runs to do, %d finished earlier, %d combinations left out",
        len(planned.jobs),
        len(planned.skipped),
        len(planned.invalid),
    )
    from harness.progress import SweepProgress

    overall = SweepProgress(len(planned.jobs), enabled=progress)
    results = (
        execute(
            planned.jobs,
            executor,
            options,
            progress=progress,
            on_result=lambda r: overall.job_done(r.state != "failed"),
        )
        if planned.jobs
        else []
    )
    assert planned.store is not None
    return SweepSummary(planned.store, [*planned.skipped, *results], planned.invalid)


def sweep_table(summary: SweepSummary) -> str:
    from harness.report.cells import format_value
    from harness.textable import text_table

    rows = [
        [
            r.run,
            r.state,
            format_value(r.mAP50, "float", 3),
            format_value(r.mAP50_95, "float", 3),
            "-" if r.time_s is None else f"{r.time_s:.1f}",
            (r.error or "").splitlines()[0][:80] if r.error else "",
        ]
        for r in sorted(summary.results, key=lambda r: r.run)
    ]
    return text_table(["run", "state", "mAP50", "mAP50:95", "time s", "error"], rows, align="llrrrl")


__all__ = [
    "EXECUTORS",
    "ExecutorError",
    "ExecutorOptions",
    "JobResult",
    "SweepJob",
    "SweepPlan",
    "SweepSpec",
    "SweepSummary",
    "execute",
    "expand",
    "run_job",
    "sweep",
    "sweep_table",
]
