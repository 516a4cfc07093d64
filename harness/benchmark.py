"""The reference benchmark: the four detectors x four folds x three seeds and the encoding ablation, at the
``benchmark`` profile on the small ``m3t-synth`` set, run in lanes (one run per core) and resumed where it stopped.

``plan_benchmark(BenchmarkSpec(...))`` lists the benchmark's cells and asks the results store which are left to do,
through the sweep's planning (``harness.sweep.expand``): a finished cell with the same configuration is skipped, a
finished cell with another configuration stops everything before anything trains, and an interrupted cell resumes
from its ``last.pt`` when it runs again. ``run_benchmark`` then runs the cells left in ``lanes`` worker processes at
a time (``harness run`` for one fold and seed, one torch thread each, its log in ``<store>/_benchmark/logs``),
longest first, and prints the overall progress with an ETA after every epoch of any lane (``BenchmarkProgress``).
A cell that fails is listed at the end; the others go on. With ``executor="ray"`` or ``"slurm"`` the same cells run
through the sweep's executors instead (``run_on_executor``: one Ray task per cell with one GPU where the cluster has
GPUs, or one submitit job array, submitit's local executor where there is no Slurm), each as a lane runs it
(``run_cell``), into the same store with the same logs and the same resume.

The cells:

* every detector of ``DETECTORS`` on every fold of the dataset, with the dataset's encoding (``c2``), seeds 0, 1, 2,
  each with ``configs/benchmark/<detector>.yaml`` on top of the profile (not at the ``paper`` profile, where the
  detectors keep their own, published sizes);
* the encoding ablation: ``ours`` with each of ``ENCODINGS`` on ``P4+P5`` (the seed's ablation split), seeds 0, 1, 2
  (its ``c2`` cells are the detector grid's own).

The shipped reference results (``harness.references``) are this benchmark's store, exported.

A second suite, ``rgbt-tiny-synth`` (``SUITES``, ``--suite``), runs the same machinery on the RGBT-Tiny-like stand-in
(``harness synth --family rgbt-tiny``, read by the ``rgbt-tiny`` adapter): every detector of ``DETECTORS`` with each
annotation source (``dataset.gt`` thermal or visible: folds ``test-T`` and ``test-RGB``, the release's own split by
sequence), seeds 0, 1, 2, and ``ours`` with ``none``, ``proxy8`` and ``ir8`` on the thermal-source annotations. It
runs at the ``benchmark`` profile with its own layer and per-detector files (``configs/benchmark-rgbt-tiny/``), into
``results/benchmark-rgbt-tiny``; its references go to ``references/rgbt-tiny-synth-benchmark``. A suite is data
(``Suite``): what differs between the two is there; the planning, lanes, resume, export and rerun are the same code.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence, TextIO

from harness.errors import ConfigError
from harness.progress import BenchmarkProgress
from harness.provenance import KERNEL_VARIABLES
from harness.sweep import ExecutorOptions, JobResult, SweepJob, SweepSpec

log = logging.getLogger(__name__)

DATASET = "m3t-synth"
PROFILE = "benchmark"
DETECTORS = ("ours", "eme", "icafusion", "cmadet")
SEEDS = (0, 1, 2)
ABLATION_DETECTOR = "ours"
ABLATION_FOLD = "P4+P5"
ENCODINGS = ("none", "ir8", "linear16", "c2")
#: Default results store of ``harness benchmark run`` and ``make benchmark``.
DEFAULT_STORE = Path("results") / PROFILE
#: Relative CPU time of one epoch per detector at the benchmark's sizes (ours = 1; measured side by side on one
#: 2-core machine, docs/benchmark.md); only used to order the cells (longest first, so the lanes end together) and
#: for the ETA before a detector's first epoch has been timed in this call.
RELATIVE_COST = {"ours": 1.0, "eme": 0.8, "icafusion": 1.9, "cmadet": 2.3}


#: Profiles at which the detectors run at their own, published sizes (``s``) and options: the benchmark's per-detector
#: files (``n`` sizes for 192 px) are not applied.
OWN_SIZES_PROFILES = ("paper",)


def detector_config(detector: str, profile: str | None = PROFILE, folder: str = "benchmark") -> Path | None:
    """``configs/<folder>/<detector>.yaml`` when it exists (the per-detector options of the benchmark; ``folder`` is
    the suite's ``Suite.detector_configs``), except at a profile of ``OWN_SIZES_PROFILES``."""
    from harness.config import config_dir

    if profile in OWN_SIZES_PROFILES:
        return None
    path = config_dir() / folder / f"{detector}.yaml"
    return path if path.is_file() else None


# ------------------------------------------------------------------------------------------------- suites
@dataclass(frozen=True)
class Suite:
    """One reference benchmark: its dataset and data, its cells, its profile, store and reference folder.

    ``variants``: the dataset options that make each set of cells, as ``(name, --set overrides)`` (the RGBT-Tiny
    suite's two annotation sources; one unnamed variant without overrides for ``m3t-synth``); every detector runs on
    ``folds`` of every variant. The ablation runs ``ablation_detector`` with each of ``encodings`` on
    ``ablation_fold`` of the variant named ``ablation_variant``; ``grid_encoding`` is the ablation detector's
    encoding in the detector grid. ``data``: the command that writes the suite's data folder, ``data_root`` that
    folder (``None``: the dataset plugin makes its data itself), read through ``dataset.root``."""

    name: str
    dataset: str
    profile: str
    detectors: tuple[str, ...] = DETECTORS
    seeds: tuple[int, ...] = SEEDS
    folds: str = "all"
    variants: tuple[tuple[str, tuple[str, ...]], ...] = (("", ()),)
    ablation_detector: str = ABLATION_DETECTOR
    ablation_fold: str = ABLATION_FOLD
    ablation_variant: str = ""
    encodings: tuple[str, ...] = ENCODINGS
    grid_encoding: str = "c2"
    detector_configs: str = "benchmark"
    references: str = "m3t-synth-benchmark"
    data: tuple[str, ...] = ()
    data_root: str | None = None
    #: the suite's own layers on top of the profile, under ``configs/`` (before each detector's file)
    config_files: tuple[str, ...] = ()
    #: the default results store's folder under ``results/`` (default: the profile's, the one rule of ``--store``)
    store_name: str | None = None

    @property
    def store(self) -> Path:
        """The default results store: ``results/<store_name or profile>``."""
        return Path("results") / (self.store_name or self.profile)

    def layers(self) -> tuple[str, ...]:
        """``config_files`` as paths of the configuration folder."""
        from harness.config import config_dir

        return tuple(str(config_dir() / f) for f in self.config_files)

    def variant_overrides(self, name: str) -> tuple[str, ...]:
        return dict(self.variants)[name]

    def data_overrides(self) -> tuple[str, ...]:
        """``dataset.root=<the data folder>`` when the suite reads a generated folder (a location: not part of a
        run's identity), else nothing."""
        return (f"dataset.root={self.data_folder()}",) if self.data_root else ()

    def data_folder(self) -> Path | None:
        """The suite's data folder, under ``$HARNESS_DATA`` (default ``./data``), resolved."""
        if not self.data_root:
            return None
        return (Path(os.environ.get("HARNESS_DATA") or "data") / self.data_root).resolve()


#: The suites ``harness benchmark --suite`` knows; the first is the default.
SUITES: dict[str, Suite] = {
    s.name: s
    for s in (
        Suite("m3t-synth", DATASET, PROFILE),
        Suite(
            "rgbt-tiny-synth",
            "rgbt-tiny",
            PROFILE,
            variants=(("thermal", ("dataset.gt=thermal",)), ("visible", ("dataset.gt=visible",))),
            ablation_fold="test-T",
            ablation_variant="thermal",
            encodings=("none", "proxy8", "ir8"),
            grid_encoding="proxy8",
            detector_configs="benchmark-rgbt-tiny",
            references="rgbt-tiny-synth-benchmark",
            data=("synth", "--family", "rgbt-tiny", "--size", "small-320", "--seed", "0"),
            data_root="rgbt-tiny-synth-small-320-seed0",
            config_files=("benchmark-rgbt-tiny/suite.yaml",),
            store_name="benchmark-rgbt-tiny",
        ),
    )
}
DEFAULT_SUITE = "m3t-synth"


def get_suite(name: str | None) -> Suite:
    """The suite called ``name`` (``None``: the default); an unknown name is a ``ConfigError`` listing the known."""
    if name is None:
        return SUITES[DEFAULT_SUITE]
    if name not in SUITES:
        raise ConfigError(f"--suite {name!r}: unknown benchmark suite; choose one of {', '.join(SUITES)}")
    return SUITES[name]


def suite_spec(suite: str | Suite | None = None, **kwargs: Any) -> "BenchmarkSpec":
    """The ``BenchmarkSpec`` of ``suite`` (its dataset, profile, store, detectors, seeds and encodings), with
    ``kwargs`` on top."""
    s = suite if isinstance(suite, Suite) else get_suite(suite)
    base: dict[str, Any] = dict(
        suite=s.name,
        dataset=s.dataset,
        profile=s.profile,
        store=s.store,
        detectors=s.detectors,
        seeds=s.seeds,
        encodings=s.encodings,
    )
    return BenchmarkSpec(**{**base, **kwargs})


def ensure_data(suite: Suite, stream: TextIO | None = None) -> Path | None:
    """Write the suite's data folder with its command (``harness synth ...``, in a child process, its output on
    stderr) when it is not there yet; the folder, or None for a suite whose dataset plugin makes its own data."""
    folder = suite.data_folder()
    if folder is None:
        return None
    if (folder / "synth.json").is_file():
        return folder
    cmd = [sys.executable, "-m", "harness", *suite.data, "--out", str(folder)]
    log.info("benchmark %s: writing its data folder %s (%s)", suite.name, folder, " ".join(cmd[2:]))
    proc = subprocess.run(cmd, stdout=stream or sys.stderr, stderr=stream or sys.stderr)
    if proc.returncode != 0 or not (folder / "synth.json").is_file():
        raise ConfigError(
            f"benchmark {suite.name}: could not write its data folder {folder} (exit {proc.returncode}); run "
            f"`harness {' '.join(suite.data)} --out {folder}` to see why"
        )
    return folder


@dataclass(frozen=True)
class BenchmarkSpec:
    """What to run; the defaults are the reference benchmark."""

    store: str | Path = DEFAULT_STORE
    detectors: tuple[str, ...] = DETECTORS
    folds: str = "all"
    seeds: tuple[int, ...] = SEEDS
    ablation: bool = True
    encodings: tuple[str, ...] = ENCODINGS
    dataset: str = DATASET
    profile: str = PROFILE
    config_files: tuple[str, ...] = ()  # applied after each detector's configs/benchmark/<detector>.yaml
    overrides: tuple[str, ...] = ()
    force: bool = False
    suite: str = DEFAULT_SUITE  # what the cells are (``SUITES``); ``suite_spec`` fills the rest from it

    @property
    def suite_def(self) -> Suite:
        return get_suite(self.suite)


@dataclass
class BenchmarkPlan:
    store: Path
    jobs: list[SweepJob] = field(default_factory=list)  # cells left to do, longest first
    skipped: list[JobResult] = field(default_factory=list)  # finished earlier with the same configuration
    invalid: list[str] = field(default_factory=list)

    @property
    def cells(self) -> int:
        return len(self.jobs) + len(self.skipped)


def _specs(spec: BenchmarkSpec) -> list[SweepSpec]:
    suite = spec.suite_def
    out = []
    for det in spec.detectors:
        cfg = detector_config(det, spec.profile, suite.detector_configs)
        for variant, options in suite.variants:
            common = dict(
                datasets=(spec.dataset,),
                seeds=tuple(spec.seeds),
                profile=spec.profile,
                config_files=suite.layers() + ((str(cfg),) if cfg else ()) + tuple(spec.config_files),
                overrides=suite.data_overrides() + tuple(options) + tuple(spec.overrides),
                store=str(spec.store),
                force=spec.force,
            )
            out.append(SweepSpec(detectors=(det,), folds=spec.folds, **common))  # type: ignore[arg-type]
            if spec.ablation and det == suite.ablation_detector and variant == suite.ablation_variant:
                out.append(
                    SweepSpec(detectors=(det,), folds=suite.ablation_fold, encodings=tuple(spec.encodings), **common)  # type: ignore[arg-type]
                )
    return out


def plan_benchmark(spec: BenchmarkSpec) -> BenchmarkPlan:
    """The benchmark's cells, checked against the results store (see the module docstring)."""
    from harness.sweep import expand

    if not spec.seeds:
        raise ConfigError("the benchmark needs at least one seed (--seeds)")
    if len(set(spec.seeds)) != len(spec.seeds):
        raise ConfigError(f"--seeds {','.join(map(str, spec.seeds))}: a seed is listed twice")
    ensure_data(spec.suite_def)
    plan = BenchmarkPlan(store=Path(spec.store).resolve())
    seen: set[str] = set()
    for sweep_spec in _specs(spec):
        part = expand(sweep_spec)
        plan.invalid.extend(part.invalid)
        for job in part.jobs:
            if str(job) not in seen:
                seen.add(str(job))
                plan.jobs.append(job)
        for done in part.skipped:
            if done.run not in seen:
                seen.add(done.run)
                plan.skipped.append(done)
    plan.jobs.sort(
        key=lambda j: (
            -RELATIVE_COST.get(j.detector, 1.0),
            DETECTORS.index(j.detector) if j.detector in DETECTORS else len(DETECTORS),
            j.fold,
            j.encoding,
            j.seed,
        )
    )
    return plan


def finished_cells(spec: BenchmarkSpec) -> tuple[list[Any], list[str]]:
    """(the finished runs of the benchmark's cells in ``spec.store``, the cells not finished there).

    Read from the store alone (no plugin, no planning), so a finished benchmark can be exported after a change that
    moves the prepared data's cache key: what ties the results to their samples is the samples' digest. A
    detector's grid is the encoding its runs used on every fold (one encoding per detector)."""
    from harness.store import Store

    suite = spec.suite_def
    abl_det, abl_fold, grid = suite.ablation_detector, suite.ablation_fold, suite.grid_encoding
    runs = {r.key: r for r in Store(spec.store).runs(dataset=spec.dataset)}
    want_folds = None if spec.folds == "all" else set(spec.folds.split(","))
    found: list[Any] = []
    missing: list[str] = []
    for det in spec.detectors:
        mine = [k for k in runs if k.detector == det]
        if not mine:
            missing.append(f"{det}: no runs")
            continue
        encodings = sorted({k.encoding for k in mine})
        if det == abl_det and spec.ablation and len(encodings) > 1:  # its grid: the dataset's encoding (c2)
            encodings = [grid] if grid in encodings else sorted({k.encoding for k in mine if k.fold != abl_fold})
        if len(encodings) != 1:
            missing.append(f"{det}: one encoding on every fold expected, found {encodings or 'none'}")
            continue
        folds = sorted({k.fold for k in mine if k.encoding == encodings[0]})
        if want_folds is not None:
            folds = sorted(want_folds)
        for fold in folds:
            for seed in spec.seeds:
                key = next((k for k in mine if (k.encoding, k.fold, k.seed) == (encodings[0], fold, seed)), None)
                (found.append(key) if key is not None else missing.append(f"{det}/{encodings[0]}/{fold}/seed{seed}"))
    if spec.ablation:
        for enc in spec.encodings:
            for seed in spec.seeds:
                key = next(
                    (k for k in runs if (k.detector, k.encoding, k.fold, k.seed) == (abl_det, enc, abl_fold, seed)),
                    None,
                )
                if key is None:
                    missing.append(f"{abl_det}/{enc}/{abl_fold}/seed{seed}")
                elif key not in found:
                    found.append(key)
    return found, missing


# ------------------------------------------------------------------------------------------------- lanes
def job_command(job: SweepJob) -> list[str]:
    """The ``harness run`` command line of one cell."""
    cmd = [
        sys.executable,
        "-m",
        "harness",
        "run",
        "--detector",
        job.detector,
        "--dataset",
        job.dataset,
        "--encoding",
        job.encoding,
        "--folds",
        job.fold,
        "--seeds",
        str(job.seed),
        "--store",
        job.store,
        "--no-progress",
    ]
    if job.profile:
        cmd += ["--profile", job.profile]
    for c in job.config_files:
        cmd += ["--config", c]
    for o in job.overrides:
        cmd += ["--set", o]
    if job.force:
        cmd.append("--force")
    return cmd


def _log_path(store: Path, job: SweepJob) -> Path:
    name = f"{job.detector}_{job.encoding}_{job.fold}_seed{job.seed}.log".replace("/", "-")
    return store / "_benchmark" / "logs" / name


def _epochs_logged(store: Path, job: SweepJob) -> int:
    from harness.store import Run, RunKey

    path = Run(store, RunKey(job.dataset, job.detector, job.encoding, job.fold, job.seed)).log_path
    try:
        with open(path, "rb") as f:
            return sum(1 for line in f if line.strip())
    except OSError:
        return 0


def _result(store: Path, job: SweepJob, rc: int, elapsed: float, log_file: Path, resumed: bool) -> JobResult:
    from harness.report.reader import read_run
    from harness.store import Run, RunKey

    run = Run(store, RunKey(job.dataset, job.detector, job.encoding, job.fold, job.seed))
    if rc == 0 and run.is_finished():
        m = read_run(run).metrics.get("metrics", {})
        return JobResult(
            str(job),
            "resumed" if resumed else "trained",
            str(run.path),
            m.get("mAP50"),
            m.get("mAP50_95"),
            round(elapsed, 1),
        )
    tail = ""
    try:
        lines = [ln for ln in log_file.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
        tail = " | ".join(lines[-3:])
    except OSError:
        pass
    return JobResult(
        str(job), "failed", str(run.path), time_s=round(elapsed, 1), error=f"exit {rc}: {tail[-400:]} (log: {log_file})"
    )


def run_lanes(
    jobs: Sequence[SweepJob], lanes: int, store: Path, progress: BenchmarkProgress, poll_s: float = 2.0
) -> list[JobResult]:
    """Run ``jobs`` as ``harness run`` processes, ``lanes`` at a time, in order; the results in order of ending.

    Each process gets one thread per library (``OMP_NUM_THREADS=1``; the profile sets torch's). On an interrupt
    (Ctrl-C, SIGTERM) the running cells are stopped the way ``harness run`` stops (their status says interrupted and
    ``last.pt`` holds their last epoch), and the interrupt is raised again once they have exited."""
    queue = list(jobs)
    running: dict[str, tuple[SweepJob, subprocess.Popen[bytes], float, Path, bool, Any]] = {}
    results: list[JobResult] = []
    env = _cell_env()
    try:
        while queue or running:
            while queue and len(running) < lanes:
                job = queue.pop(0)
                log_file = _log_path(store, job)
                log_file.parent.mkdir(parents=True, exist_ok=True)
                before = _epochs_logged(store, job)
                fh = open(log_file, "ab")
                fh.write(f"\n$ {' '.join(job_command(job))}\n".encode())
                fh.flush()
                proc = subprocess.Popen(
                    job_command(job), stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True
                )
                running[str(job)] = (job, proc, time.perf_counter(), log_file, before > 0, fh)
                progress.started(job, before)
            time.sleep(poll_s)
            for key in list(running):
                job, proc, t0, log_file, resumed, fh = running[key]
                progress.epoch(job, _epochs_logged(store, job))
                rc = proc.poll()
                if rc is None:
                    continue
                fh.close()
                del running[key]
                res = _result(store, job, rc, time.perf_counter() - t0, log_file, resumed)
                results.append(res)
                if res.state == "failed":
                    log.error("benchmark: %s failed: %s", res.run, res.error)
                progress.finished(job, res.state != "failed")
    except BaseException:
        for job, proc, _, _, _, fh in running.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)  # as Ctrl-C: the run records "interrupted" and keeps last.pt
        deadline = time.perf_counter() + 60
        for job, proc, _, _, _, fh in running.values():
            try:
                proc.wait(timeout=max(deadline - time.perf_counter(), 0.1))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
            fh.close()
        raise
    return results


def _cell_env(threads: int = 1, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment of a cell's ``harness run`` process: ``threads`` threads per library."""
    n = str(max(1, int(threads)))
    env = {**(os.environ if base is None else base), "OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n}
    env["OPENBLAS_NUM_THREADS"] = n
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return env


def _stop_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """In a cell's process: be interrupted (as Ctrl-C) when the worker that started it dies (Linux)."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGINT)  # PR_SET_PDEATHSIG
    except Exception:
        pass


#: ``SweepJob.env`` entry that carries the threads of a cell run by an executor (``ExecutorOptions.cpus_per_run``).
THREADS_ENV = "HARNESS_BENCHMARK_THREADS"


def run_cell(job: SweepJob) -> JobResult:
    """One cell in a worker of an executor (a Ray task, a submitit job), run as a local lane runs it: ``harness run``
    in a child process, its output appended to ``<store>/_benchmark/logs/<cell>.log``, one thread per library (or
    ``THREADS_ENV``). A cell interrupted earlier resumes from its ``last.pt``. When the worker is stopped (Ray's
    cancel, submitit's or Slurm's signals) or dies, the child is interrupted as Ctrl-C interrupts a lane: its status
    says interrupted and ``last.pt`` keeps its last epoch, for the next ``benchmark run``."""
    import resource
    import socket

    env = dict(os.environ)
    env.update(job.env)
    threads = int(env.pop(THREADS_ENV, "1") or 1)
    store = Path(job.store)
    log_file = _log_path(store, job)
    log_file.parent.mkdir(parents=True, exist_ok=True)
    before = _epochs_logged(store, job)
    cmd = job_command(job)
    usage0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log_file, "ab") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n".encode())
        fh.flush()
        proc = subprocess.Popen(
            cmd,
            stdout=fh,
            stderr=subprocess.STDOUT,
            env=_cell_env(threads, env),
            start_new_session=True,
            preexec_fn=_stop_with_parent if sys.platform.startswith("linux") else None,
        )
        try:
            rc = proc.wait()
        except BaseException:
            with contextlib.suppress(OSError):
                os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
            raise
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    res = _result(store, job, rc, time.perf_counter() - t0, log_file, before > 0)
    res.worker = f"{socket.gethostname()}:{os.getpid()}"
    res.cpu_s = round(usage.ru_utime + usage.ru_stime - usage0.ru_utime - usage0.ru_stime, 1)
    return res


def run_on_executor(
    jobs: Sequence[SweepJob],
    executor: str,
    options: ExecutorOptions,
    store: Path,
    progress: BenchmarkProgress,
    poll_s: float = 5.0,
) -> list[JobResult]:
    """Run ``jobs`` with the sweep's ``executor`` (``ray``: one task per cell, one GPU each where the cluster has
    GPUs; ``slurm``: one submitit job array), each cell by ``run_cell``; the results in order of ``jobs``.

    The cells write into ``store`` (a folder every worker reaches); progress and ETA are read from it, as for the
    lanes, by a thread that looks at the cells' logs every ``poll_s`` seconds. A submitit job array's own logs go to
    ``options.log_dir`` [default: ``<store>/_sweeps/<time>``, as a sweep's]."""
    import dataclasses
    import threading

    from harness.sweep import execute

    threads = ((THREADS_ENV, str(max(1, options.cpus_per_run))),)
    jobs = [dataclasses.replace(job, env=(*job.env, *threads)) for job in jobs]
    ended: set[str] = set()
    sizes = {str(job): _log_size(store, job) for job in jobs}
    epochs0 = {str(job): _epochs_logged(store, job) for job in jobs}
    stop = threading.Event()

    def watch() -> None:
        while not stop.wait(poll_s):
            for job in jobs:
                key = str(job)
                if key in ended:
                    continue
                if key not in progress.running and _log_size(store, job) > sizes[key]:
                    progress.started(job, epochs0[key])
                    progress.lanes = max(progress.lanes, len(progress.running))
                progress.epoch(job, _epochs_logged(store, job))

    def on_result(res: JobResult) -> None:
        job = next((j for j in jobs if str(j) == res.run), None)
        ended.add(res.run)
        if res.state == "failed":
            log.error("benchmark: %s failed: %s", res.run, res.error)
        if job is not None:
            progress.finished(job, res.state != "failed")

    watcher = threading.Thread(target=watch, name="benchmark-progress", daemon=True)
    watcher.start()
    try:
        return execute(jobs, executor, options, progress=False, on_result=on_result, task=run_cell)
    finally:
        stop.set()
        watcher.join(timeout=poll_s + 5)


def _log_size(store: Path, job: SweepJob) -> int:
    try:
        return _log_path(store, job).stat().st_size
    except OSError:
        return 0


def default_lanes() -> int:
    """One lane per core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class BenchmarkSummary:
    store: Path
    results: list[JobResult]
    invalid: list[str]
    wall_s: float
    cpu_s: float  # of the cells trained in this call
    executor: str = "local"
    lanes: int = 1  # local: the lanes; ray, slurm: the most cells seen running at once

    @property
    def failed(self) -> list[JobResult]:
        return [r for r in self.results if r.state == "failed"]


def run_benchmark(
    spec: BenchmarkSpec,
    lanes: int | None = None,
    progress: bool = True,
    stream: TextIO | None = None,
    executor: str = "local",
    options: ExecutorOptions | None = None,
) -> BenchmarkSummary:
    """Plan the benchmark and run the cells left to do: ``local``, in ``lanes`` processes (default: one per core);
    ``ray`` or ``slurm``, with the sweep's executors (``run_on_executor``, ``options`` their resources and cluster
    settings). Either way the store, its logs and the resume are the same."""
    from harness.config import load_config
    from harness.sweep import EXECUTORS

    if executor not in EXECUTORS:
        raise ConfigError(f"--executor {executor!r}: choose one of {', '.join(EXECUTORS)}")
    if executor != "local" and lanes is not None:
        raise ConfigError(f"--lanes is for --executor local; with --executor {executor} the cluster decides")
    lanes = lanes or (default_lanes() if executor == "local" else 1)
    plan = plan_benchmark(spec)
    epochs = int(
        load_config(profile=spec.profile, files=spec.suite_def.layers(), overrides=list(spec.overrides))["protocol"][
            "epochs"
        ]
    )
    log.info(
        "benchmark: %d cells, %d finished earlier, %d to run %s; store %s",
        plan.cells,
        len(plan.skipped),
        len(plan.jobs),
        f"in {lanes} lane(s)" if executor == "local" else f"with --executor {executor}",
        plan.store,
    )
    bar = BenchmarkProgress(
        plan.jobs,
        epochs,
        lanes,
        skipped=len(plan.skipped),
        enabled=progress,
        stream=stream,
        relative_cost=RELATIVE_COST,
    )
    t0, c0 = time.perf_counter(), _children_cpu()
    if not plan.jobs:
        results: list[JobResult] = []
    elif executor == "local":
        results = run_lanes(plan.jobs, lanes, plan.store, bar)
    else:
        results = run_on_executor(plan.jobs, executor, options or ExecutorOptions(), plan.store, bar)
    wall = time.perf_counter() - t0
    if executor == "local":
        cpu = _children_cpu() - c0
    else:  # the cells ran in workers: the CPU time each measured of its own process
        cpu = sum(r.cpu_s or 0.0 for r in results)
        lanes = bar.lanes
    return BenchmarkSummary(plan.store, [*plan.skipped, *results], plan.invalid, wall, cpu, executor, lanes)


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``) and the instruction set torch's kernels use, e.g. ``AMD EPYC 9B14
    (torch CPU capability AVX2)``."""
    name = ""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
            if line.lower().startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    name = name or __import__("platform").processor() or "unknown CPU"
    try:
        import torch

        cap = torch.backends.cpu.get_cpu_capability()
        return f"{name} (torch CPU capability {cap})"
    except Exception:
        return name


def timing_path(store: Path) -> Path:
    return Path(store) / "_benchmark" / "timing.json"


def read_timing(store: Path) -> dict[str, Any] | None:
    """The benchmark's accumulated wall and CPU time in ``store`` (``write_timing``), or None."""
    from harness.io import read_json

    path = timing_path(store)
    return read_json(path) if path.is_file() else None


def write_timing(summary: BenchmarkSummary, lanes: int | None = None) -> dict[str, Any]:
    """Add this call's wall and CPU time to ``<store>/_benchmark/timing.json`` (a resumed benchmark adds up its
    calls); the calls are listed with their executor, lanes (``summary.lanes`` unless given), cells and the CPU
    of this machine."""
    from harness.io import atomic_write_json

    old = read_timing(summary.store) or {"wall_s": 0.0, "cpu_s": 0.0, "calls": []}
    trained = [r for r in summary.results if r.state in ("trained", "resumed")]
    call = {
        "wall_s": round(summary.wall_s, 1),
        "cpu_s": round(summary.cpu_s, 1),
        "executor": summary.executor,
        "lanes": int(summary.lanes if lanes is None else lanes),
        "cells": len(trained),
        "failed": len(summary.failed),
        "cpu": cpu_name(),
        "isa_env": {k: os.environ[k] for k in KERNEL_VARIABLES if k in os.environ},
        "ended": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    out = {
        "wall_s": round(float(old.get("wall_s", 0.0)) + summary.wall_s, 1),
        "cpu_s": round(float(old.get("cpu_s", 0.0)) + summary.cpu_s, 1),
        "calls": [*old.get("calls", []), call],
    }
    if trained or not old.get("calls"):
        timing_path(summary.store).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(timing_path(summary.store), out)
    return out


#: What ``rerun_cell`` compares: the metrics.json sections that hold numbers of the evaluation.
RERUN_SECTIONS = ("support", "metrics", "per_category")
#: Configuration keys that name where the prepared samples lie or how they are cached, not what training computes:
#: when the samples' digests match (or differ within the tolerance of a library release, said as such), they are not
#: differences of the rerun.
RERUN_NEUTRAL_KEYS = ("meta.prepared_fingerprint", "meta.prepared_key", "meta.prepared_samples")


def _short(v: Any) -> str:
    """A number with 4 significant digits; another value as it is written (a list or mapping by its size)."""
    if isinstance(v, bool) or v is None:
        return repr(v)
    if isinstance(v, (int, float)):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return f"[{len(v)} values]"
    if isinstance(v, dict):
        return f"{{{len(v)} fields}}"
    return repr(v)


def section_difference(a: Any, b: Any, most: int = 4) -> str:
    """What differs between two metrics.json sections, reference ``a`` against rerun ``b``, in a line a person
    reads: each differing field as ``name A vs B``, mAP50 and mAP50_95 first (numbers to 4 significant digits, a list
    by how many of its values differ, a per-category record by its AP50 or its first differing field), at most
    ``most``, then how many more."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return "differs"
    first = [k for k in ("mAP50", "mAP50_95") if k in a or k in b]  # the headline numbers lead
    keys = [k for k in (*first, *sorted({*a, *b} - set(first))) if a.get(k) != b.get(k)]
    parts = []
    for k in keys[:most]:
        x, y = a.get(k), b.get(k)
        if isinstance(x, dict) and isinstance(y, dict):
            inner = [f for f in ("AP50", *sorted({*x, *y})) if x.get(f) != y.get(f)]
            parts.append(f"{k} {inner[0]} {_short(x.get(inner[0]))} vs {_short(y.get(inner[0]))}")
        elif isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
            parts.append(f"{k} ({sum(u != v for u, v in zip(x, y))} of {len(x)} values)")
        else:
            parts.append(f"{k} {_short(x)} vs {_short(y)}")
    more = f", and {len(keys) - most} more field(s)" if len(keys) > most else ""
    return (", ".join(parts) + more) or "differs"


def rerun_cell(
    refs: Any,
    detector: str,
    encoding: str,
    fold: str,
    seed: int,
    store: Path,
    progress: bool = False,
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """Train one reference cell again into ``store`` with the reference run's own configuration and compare it with
    the reference run.

    Before anything trains (``check_rerun``): the samples (the content digests of the cell's training and held-out
    samples as prepared here, against those the reference run recorded; digests that differ are measured against the
    references' sample fingerprint, and beyond the tolerance of a library release the rerun stops at once with
    ``ReferenceMismatchError``), the configuration that changes training, and the environment (every recorded fact
    that differs, and those the reference did not record). After training: the evaluation's numbers
    (``RERUN_SECTIONS``) and the predictions; a rerun that is not identical gets a verdict against the references'
    training variance (``harness.verdict.judge``: the cell's seeds in the reference store)."""
    from harness.io import read_json
    from harness.report.reader import read_run
    from harness.runner import run
    from harness.store import Run, RunKey
    from harness.verdict import judge

    request, ref = rerun_request(refs, detector, encoding, fold, seed, store, progress, overrides)
    checked = check_rerun(refs, ref, request)
    run(request)
    new_run = read_run(Run(Path(store), RunKey(refs.dataset, detector, encoding, fold, seed)))
    differences: list[str] = []
    for section in RERUN_SECTIONS:
        a, b = ref.metrics.get(section), new_run.metrics.get(section)
        if a != b:
            differences.append(f"metrics.json {section}: {section_difference(a, b)}")
    same_predictions = read_json(ref.predictions_path) == read_json(new_run.predictions_path)
    if not same_predictions:
        differences.append("predictions differ")
    ref_m, new_m = ref.metrics.get("metrics") or {}, new_run.metrics.get("metrics") or {}
    verdict = judge(
        {k: ref_m.get(k) for k in ("mAP50", "mAP50_95")},
        {k: new_m.get(k) for k in ("mAP50", "mAP50_95")},
        reference_seeds(refs, detector, encoding, fold),
        identical=not differences,
    )
    env = checked["environment"]
    return {
        "cell": f"{detector}/{encoding}/{fold}/seed{seed}",
        "reference": str(ref.path),
        "rerun": str(new_run.path),
        "identical": not differences,
        "verdict": verdict.to_dict(),
        "differences": differences,
        "samples": checked["samples"],
        "config_differences": checked["config_differences"],
        "environment": env,
        "environment_differences": [f"{d['label']}: {d['reference']!r} vs {d['here']!r}" for d in env["differ"]],
        "check_s": checked["check_s"],
        "mAP50": [ref_m.get("mAP50"), new_m.get("mAP50")],
        "mAP50_95": [ref_m.get("mAP50_95"), new_m.get("mAP50_95")],
    }


def rerun_request(
    refs: Any,
    detector: str,
    encoding: str,
    fold: str,
    seed: int,
    store: Path,
    progress: bool = False,
    overrides: Sequence[str] = (),
) -> tuple[Any, Any]:
    """(the ``RunRequest`` that trains reference cell ``detector/encoding/fold/seed`` again into ``store``, the
    reference run as read by the store's reader). The reference run's own configuration is the last layer, so the
    rerun resolves to the same settings whatever the checkout's profiles say (its locations and its record of the run
    left out); ``overrides``: locations on top (a suite's ``dataset.root``)."""
    import yaml

    from harness.io import atomic_write_text
    from harness.report.reader import read_run
    from harness.runner import RunRequest
    from harness.store import Run, RunKey

    ref_run = Run(refs.root, RunKey(refs.dataset, detector, encoding, fold, seed))
    if not ref_run.is_finished():
        cells = ", ".join((refs.manifest.get("cells") or [])[:3])
        raise ConfigError(
            f"{detector}/{encoding}/{fold}/seed{seed} is not a cell of the reference results in "
            f"{refs.root} (cells look like {cells} ...)"
        )
    ref = read_run(ref_run)
    layer = {k: v for k, v in ref.config.items() if k != "meta"}
    for section, key in (("dataset", "root"), ("train", "init")):
        if isinstance(layer.get(section), dict):
            layer[section].pop(key, None)
    cfg_file = Path(store) / "_rerun" / f"{detector}_{encoding}_{fold}_seed{seed}.yaml"
    cfg_file.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(cfg_file, yaml.safe_dump(layer, sort_keys=True))
    request = RunRequest(
        detector=detector,
        dataset=refs.dataset,
        encoding=encoding,
        folds=fold,
        seeds=[seed],
        profile=(ref.config.get("meta") or {}).get("profile"),
        config_files=[str(cfg_file)],
        overrides=list(overrides),
        store=store,
        force=True,
        progress=progress,
    )
    return request, ref


def check_rerun(refs: Any, ref: Any, request: Any) -> dict[str, Any]:
    """What ``rerun_cell`` checks before it trains: plan ``request`` as the run will (its prepared samples, folds and
    configuration), then compare with the reference run ``ref``:

    * ``samples``: the content digests of the training and held-out samples with the cell's encoding (and of the
      aligned samples), here and in the reference run's ``metrics.json``; ``state`` is ``identical``, ``within
      tolerance`` (digests differ, the measured difference from the references' sample fingerprint is within
      ``harness.cache.fingerprint.TOLERANCE``: ``measured`` says by how much) or ``not recorded`` (the reference run
      holds no digests). Beyond the tolerance, or not measurable, it raises ``ReferenceMismatchError`` naming the
      digests, the measured difference, the package versions that differ and the command that installs the locked
      environment, and the seconds it took to find out;
    * ``config_differences``: the settings of the run identity that differ (``identity_diff``), without the keys of
      ``RERUN_NEUTRAL_KEYS`` when the samples match;
    * ``environment``: ``harness.verdict.environment_differences`` of the reference run's record and this machine's
      (the threads the configuration sets, the instruction-set caps of the environment).

    Also returns ``check_s``, the seconds the checks took."""
    import time as _time

    from harness.runner import fold_indices, identity_diff, plan

    t0 = _time.perf_counter()
    p = plan(request)
    planned = p.runs[0]
    prepared, enc = p.prepared, p.encoding
    train_idx, val_idx = fold_indices(prepared, planned.fold)
    params = dict((planned.config.get("encoding") or {}).get(enc.name) or {})
    here = {
        "train": prepared.content_digest(train_idx, enc, params),
        "held_out": prepared.content_digest(val_idx, enc, params),
        "aligned": {"train": prepared.content_digest(train_idx), "held_out": prepared.content_digest(val_idx)},
    }
    theirs = ref.metrics.get("samples") if isinstance(ref.metrics.get("samples"), dict) else {}
    samples = _compare_samples(refs, ref, planned, prepared, here, theirs, t0)
    neutral = samples["state"] in ("identical", "within tolerance")
    config_diff = [
        d
        for d in identity_diff(ref.config, planned.config, limit=10**6)
        if not (neutral and d.split(":", 1)[0] in RERUN_NEUTRAL_KEYS)
    ]
    env = _environment_check(refs, ref, planned.config)
    return {
        "samples": samples,
        "config_differences": config_diff,
        "environment": env.to_dict(),
        "check_s": round(_time.perf_counter() - t0, 2),
    }


def _compare_samples(
    refs: Any,
    ref: Any,
    planned: Any,
    prepared: Any,
    here: Mapping[str, Any],
    theirs: Mapping[str, Any],
    t0: float,
) -> dict[str, Any]:
    """The samples part of ``check_rerun``."""
    import time as _time
    from types import SimpleNamespace

    from harness import provenance
    from harness.cache import fingerprint as FP
    from harness.references import LOCK_COMMAND, ReferenceMismatchError, fingerprint_path, measure_samples

    rows = [
        ("train", here.get("train"), theirs.get("train")),
        ("held-out", here.get("held_out"), theirs.get("held_out")),
        ("aligned train", (here.get("aligned") or {}).get("train"), (theirs.get("aligned") or {}).get("train")),
        (
            "aligned held-out",
            (here.get("aligned") or {}).get("held_out"),
            (theirs.get("aligned") or {}).get("held_out"),
        ),
    ]
    out: dict[str, Any] = {"here": dict(here), "reference": dict(theirs), "measured": None}
    if not theirs.get("held_out"):
        out["state"] = "not recorded"
        return out
    differ = [f"{name} {str(a)[:12]} vs {str(b)[:12]}" for name, a, b in rows if b is not None and a != b]
    if not differ:
        out["state"] = "identical"
        return out
    run = SimpleNamespace(
        key=planned.run.key,
        config=planned.config,
        metrics={"samples": {**here, "prepared": str(prepared.folder)}, "environment": provenance.package_versions()},
    )
    fp_path = fingerprint_path(refs.root, refs.manifest, planned.run.key.fold)
    diff, why = None, f"the references in {refs.root} hold no sample fingerprint ({fp_path.name}) to measure against"
    if fp_path.is_file():
        try:
            diff, why = measure_samples(run, FP.load(fp_path), {})
        except (OSError, ValueError) as exc:
            why = f"the references' sample fingerprint could not be read ({exc})"
    if diff is not None:
        out["measured"] = diff.describe()
        if diff.within(FP.TOLERANCE):
            out["state"] = "within tolerance"
            return out
    theirs_env = {**(refs.manifest.get("environment") or {}), **(refs.manifest.get("samples_environment") or {})}
    versions = provenance.differences(
        provenance.package_versions(),
        {**theirs_env, **(ref.metrics.get("environment") or {})},
        [*provenance.SAMPLE_PACKAGES, *provenance.TRAINING_PACKAGES],
        "reference",
    )
    measured = (
        f"measured against the references' sample fingerprint: {diff.describe()}, beyond the tolerance of a library "
        f"release ({FP.TOLERANCE.describe()})"
        if diff is not None
        else f"the difference could not be measured: {why}"
    )
    raise ReferenceMismatchError(
        f"{planned.run.key}: stopped before training: the samples prepared here are not the reference run's "
        f"(digests here vs reference: {'; '.join(differ)}); {measured}. "
        + (
            f"Package versions that differ from the reference's: {', '.join(versions)}. "
            if versions
            else "No sample- or training-shaping package version differs from the reference's: check the dataset's "
            f"source folder and options (the samples prepared here: {prepared.folder}). "
        )
        + f"Install the locked environment ({LOCK_COMMAND}), prepare again (`harness prepare --force`) and rerun. "
        f"(Checked in {_time.perf_counter() - t0:.1f} s, nothing trained.)"
    )


def _environment_check(refs: Any, ref: Any, cfg: Mapping[str, Any]) -> Any:
    """``harness.verdict.environment_differences`` of the reference run's recorded environment (completed by what the
    reference manifest records: the sample-shaping package versions, and of the benchmark that made it the CPU model
    and the instruction-set caps) and this
    machine's, with the threads the configuration sets."""
    from harness.engine.runtime import environment
    from harness.verdict import environment_differences

    theirs = dict(ref.metrics.get("environment") or {})
    calls = ((refs.manifest.get("benchmark") or {}).get("calls") or [{}])[-1:]
    call = calls[0] if calls else {}
    if "cpu" not in theirs and call.get("cpu"):  # "AMD EPYC (torch CPU capability AVX2)"
        theirs["cpu"] = {"model": str(call["cpu"]).split(" (torch CPU capability")[0]}
    packages = dict(theirs.get("packages") or {})
    for k, v in (refs.manifest.get("samples_environment") or {}).items():  # the versions that made its samples
        if k != "python" and k not in theirs:
            packages.setdefault(k, v)
    if packages:
        theirs["packages"] = packages
    isa = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")
    if call.get("isa_env") is not None:
        theirs["isa_env"] = {k: call["isa_env"].get(k, "<unset>") for k in isa}
    here = dict(environment(None))
    threads = (cfg.get("train") or {}).get("threads")
    if threads:
        here["threads"] = int(threads)
    here["isa_env"] = {k: os.environ.get(k, "<unset>") for k in isa}
    return environment_differences(theirs, here, ignore=("harness", "platform"))


def reference_seeds(refs: Any, detector: str, encoding: str, fold: str) -> dict[int, dict[str, Any]]:
    """``{seed: {"mAP50": .., "mAP50_95": ..}}`` of every finished reference run of ``detector/encoding/fold``."""
    from harness.report.reader import read_run
    from harness.store import Run, RunKey

    out: dict[int, dict[str, Any]] = {}
    prefix = f"{detector}/{encoding}/{fold}/seed"
    for cell in refs.manifest.get("cells") or []:
        if not str(cell).startswith(prefix):
            continue
        try:
            s = int(str(cell).removeprefix(prefix))
        except ValueError:
            continue
        r = Run(refs.root, RunKey(refs.dataset, detector, encoding, fold, s))
        if r.is_finished():
            m = read_run(r).metrics.get("metrics") or {}
            out[s] = {"mAP50": m.get("mAP50"), "mAP50_95": m.get("mAP50_95")}
    return out


def rerun_text(result: Mapping[str, Any]) -> str:
    """``rerun_cell``'s result as text, under 100 columns."""
    import textwrap

    from harness.verdict import EnvironmentComparison, Verdict, verdict_lines

    def wrap(text: str, indent: str = "  ") -> list[str]:
        return textwrap.wrap(text, 100, initial_indent=indent, subsequent_indent=indent + "  ")

    lines = [*wrap(f"cell {result['cell']}: reference {result['reference']}", ""), *wrap(f"rerun {result['rerun']}")]
    s = result.get("samples") or {}
    state = s.get("state")
    if state == "identical":
        lines.append("samples: identical (train, held-out and aligned digests equal the reference run's)")
    elif state == "within tolerance":
        lines += wrap(f"samples: differ within the tolerance of a library release, measured: {s.get('measured')}", "")
    elif state:
        lines.append(f"samples: {state} by the reference run (not checked)")
    if result["identical"]:
        lines.append("identical: metrics, per-category AP, support and predictions equal the reference run's")
    else:
        lines += wrap("DIFFERENT: " + "; ".join(result["differences"]), "")
    v = result.get("verdict")
    if v:
        from harness.verdict import Interval, MetricVerdict

        rows = [
            MetricVerdict(**{**m, "interval": Interval(**m["interval"]) if m.get("interval") else None})
            for m in v["metrics"]
        ]
        lines += verdict_lines(Verdict(v["result"], list(v["seeds"]), rows, v.get("why", "")))
    if result["config_differences"]:
        lines += wrap("configuration differs: " + "; ".join(result["config_differences"]), "")
    else:
        lines.append("configuration: every setting that changes training equals the reference run's")
    env = result.get("environment")
    if env:
        lines += EnvironmentComparison(env["differ"], env["unknown"], env["same"]).lines()
    lines.append(f"checked before training in {result.get('check_s', 0):.1f} s")
    return "\n".join(lines)


def _children_cpu() -> float:
    t = os.times()
    return t.children_user + t.children_system


__all__ = [
    "ABLATION_DETECTOR",
    "ABLATION_FOLD",
    "BenchmarkPlan",
    "BenchmarkProgress",
    "BenchmarkSpec",
    "BenchmarkSummary",
    "DATASET",
    "DEFAULT_SUITE",
    "DETECTORS",
    "ENCODINGS",
    "PROFILE",
    "SEEDS",
    "SUITES",
    "Suite",
    "default_lanes",
    "ensure_data",
    "get_suite",
    "cpu_name",
    "detector_config",
    "job_command",
    "plan_benchmark",
    "read_timing",
    "rerun_cell",
    "rerun_text",
    "run_benchmark",
    "run_cell",
    "run_lanes",
    "run_on_executor",
    "suite_spec",
    "write_timing",
]
