"""Progress of long work, on stderr only: one helper for every bar, and the overall one-line progress of run and sweep.

Bars. Every progress bar of the harness comes from ``bar()`` (a rich bar on stderr, so stdout carries only a
command's output). A bar shows only when three things hold: its caller enabled it, progress is switched on for this
invocation (the CLI's ``--no-progress`` switches it off, see ``switched_off()``), and stderr is a terminal: in a log
file or a pipe a bar would be noise, so it prints nothing there. Library code asks for a bar where it has work to
count and leaves these decisions here::

    from harness.progress import bar

    with bar("decoding", total=len(files), enabled=progress) as b:
        for f in files:
            ...
            b.advance()

Lines. ``harness run`` prints ``OverallProgress`` after every epoch (``run 2/4 ours/c2/P2 epoch 3/6 | 9/24 epochs |
0:41 elapsed, ETA 1:10``) and ``harness sweep`` prints ``SweepProgress`` after every run (``sweep 3/16 runs (1
failed) | 2:05 elapsed, ETA 9:00``), beside the per-epoch bar; ``harness benchmark run`` prints
``BenchmarkProgress`` over its lanes (``benchmark 14/57 cells (2 running) | 41:05 elapsed, ETA 1:32:10``).
These are log lines: they go to stderr also when it is not a terminal (a Slurm log keeps them), and
``--no-progress`` silences them too. The ETA assumes the remaining
epochs (or runs) take as long as those done so far in this call; early stopping can only make it shorter.
``enabled=False`` (any process but the first under ``torchrun``) prints nothing.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextvars import ContextVar, Token
from dataclasses import dataclass
from typing import Any, TextIO

#: Whether progress is shown in this invocation (``--no-progress`` sets it to False for the command it runs).
_SWITCH: ContextVar[bool] = ContextVar("harness_progress", default=True)


def progress_on() -> bool:
    """False after ``--no-progress`` (or inside ``switched_off()``): no bars and no progress lines."""
    return _SWITCH.get()


def switch_off() -> Token[bool]:
    """Switch progress off until ``switch_back(token)`` (what ``--no-progress`` does for one command)."""
    return _SWITCH.set(False)


def switch_back(token: Token[bool]) -> None:
    _SWITCH.reset(token)


@contextlib.contextmanager
def switched_off() -> Iterator[None]:
    """No bars and no progress lines inside the ``with`` block."""
    token = switch_off()
    try:
        yield
    finally:
        switch_back(token)


_CONSOLE: Any = None


def console() -> Any:
    """The one rich console on stderr that bars and log lines share (so logs print above a live bar, and a bar
    started inside another one stays silent instead of fighting it)."""
    global _CONSOLE
    if _CONSOLE is None:
        from rich.console import Console

        _CONSOLE = Console(stderr=True)
    return _CONSOLE


def stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


class Bar:
    """One progress bar on stderr, or nothing (see the module docstring for when it shows).

    ``eta`` adds the time remaining, ``note`` a free text after the bar (the trainer's running losses), and
    ``transient=False`` leaves the finished bar on the terminal. ``restart()`` replaces the counted task with a new
    one in the same display (one bar per epoch).
    """

    def __init__(
        self,
        description: str,
        total: float | None = None,
        *,
        enabled: bool = True,
        eta: bool = False,
        note: bool = False,
        transient: bool = True,
    ):
        self.description, self.total = description, total
        self.shown = bool(enabled) and progress_on() and stderr_is_terminal()
        self._eta, self._note, self._transient = eta, note, transient
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> Bar:
        if self.shown:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                ProgressColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            columns: list[ProgressColumn] = [
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
            ]
            if self._eta:
                columns.append(TimeRemainingColumn())
            if self._note:
                columns.append(TextColumn("{task.fields[note]}"))
            from rich.errors import LiveError

            progress = Progress(*columns, console=console(), transient=self._transient)
            try:
                progress.start()
            except LiveError:  # another bar is showing (a nested one): this one stays silent
                self.shown = False
                return self
            self._progress = progress
            self._task = self._progress.add_task(self.description, total=self.total, note="")
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def advance(self, k: float = 1, note: str | None = None) -> None:
        if self._progress is not None:
            self._progress.update(self._task, advance=k, **({} if note is None else {"note": note}))

    def update(
        self,
        *,
        completed: float | None = None,
        total: float | None = None,
        description: str | None = None,
        note: str | None = None,
    ) -> None:
        if self._progress is not None:
            fields = {} if note is None else {"note": note}
            self._progress.update(self._task, completed=completed, total=total, description=description, **fields)

    def restart(self, description: str, total: float | None = None) -> None:
        """Count a new task (``description``, ``total``) in place of the current one."""
        self.description, self.total = description, total
        if self._progress is not None:
            self._progress.remove_task(self._task)
            self._task = self._progress.add_task(description, total=total, note="")


#: A progress bar on stderr (a context manager): ``with bar("preparing m3t", total=n) as b: ... b.advance()``.
bar = Bar


def clock(seconds: float | None) -> str:
    """``83.2`` -> ``"1:23"``, ``3725`` -> ``"1:02:05"``; ``None`` -> ``"?"``."""
    if seconds is None:
        return "?"
    s = max(int(round(seconds)), 0)
    h, rest = divmod(s, 3600)
    m, sec = divmod(rest, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


class OverallProgress:
    """Progress over the runs of one ``harness run`` (``runs`` to do, ``epochs`` each at most)."""

    def __init__(
        self,
        runs: int,
        epochs: int,
        enabled: bool = True,
        stream: TextIO | None = None,
        now: Callable[[], float] | None = None,
    ):
        self.runs, self.epochs_per_run = int(runs), int(epochs)
        self.enabled = enabled and runs > 0
        self.stream = stream
        self._now = now or time.perf_counter
        self.t0 = self._now()
        self.done_runs = 0
        self.done_epochs = 0  # epochs no longer to do: trained, or left out by early stopping
        self.trained_epochs = 0  # epochs trained in this call (the rate the ETA uses)
        self._run_epochs = 0  # epochs of the current run counted so far
        self.label = ""

    @property
    def total_epochs(self) -> int:
        return self.runs * self.epochs_per_run

    def start_run(self, label: str) -> None:
        self.label = label
        self._run_epochs = 0

    def eta(self) -> float | None:
        """Seconds left: the mean time per epoch trained so far times the epochs left (``None`` before the first)."""
        if self.trained_epochs <= 0:
            return None
        elapsed = self._now() - self.t0
        left = max(self.total_epochs - self.done_epochs, 0)
        return elapsed / self.trained_epochs * left

    def line(self, epoch: int | None = None, epochs: int | None = None) -> str:
        run_no = min(self.done_runs + 1, self.runs)
        head = f"run {run_no}/{self.runs} {self.label}"
        if epoch is not None:
            head += f" epoch {epoch}/{epochs}"
        return (
            f"{head} | {self.done_epochs}/{self.total_epochs} epochs | {clock(self._now() - self.t0)} elapsed, "
            f"ETA {clock(self.eta())}"
        )

    def _print(self, text: str) -> None:
        if self.enabled and progress_on():
            stream = self.stream or sys.stderr
            print(text, file=stream, flush=True)

    def epoch_done(self, epoch: int, epochs: int) -> None:
        """After epoch ``epoch`` (1-based) of the current run; a resumed run counts the epochs it had done before."""
        new = max(int(epoch) - self._run_epochs, 0)
        self._run_epochs = int(epoch)
        self.done_epochs += new
        self.trained_epochs += 1
        self._print(self.line(epoch, epochs))

    def finish_run(self) -> None:
        """The current run ended; epochs it skipped (early stopping) no longer count as to do."""
        self.done_epochs += max(self.epochs_per_run - self._run_epochs, 0)
        self.done_runs += 1
        self._run_epochs = 0


class SweepProgress:
    """Progress over the jobs of a sweep: one line after each job."""

    def __init__(
        self, jobs: int, enabled: bool = True, stream: TextIO | None = None, now: Callable[[], float] | None = None
    ):
        self.jobs, self.enabled, self.stream = int(jobs), enabled and jobs > 0, stream
        self._now = now or time.perf_counter
        self.t0 = self._now()
        self.done = 0
        self.failed = 0

    def eta(self) -> float | None:
        if self.done <= 0:
            return None
        return (self._now() - self.t0) / self.done * max(self.jobs - self.done, 0)

    def line(self) -> str:
        failed = f" ({self.failed} failed)" if self.failed else ""
        return (
            f"sweep {self.done}/{self.jobs} runs{failed} | {clock(self._now() - self.t0)} elapsed, "
            f"ETA {clock(self.eta())}"
        )

    def job_done(self, ok: bool = True) -> None:
        self.done += 1
        self.failed += 0 if ok else 1
        if self.enabled and progress_on():
            print(self.line(), file=self.stream or sys.stderr, flush=True)


@dataclass
class _Lane:
    job: Any
    started: float
    epochs_done: int = 0  # epochs logged so far (a resumed cell starts with those of its earlier attempt)
    epochs: int = 0
    start_epochs: int = 0


class BenchmarkProgress:
    """Overall progress of the benchmark over all lanes, on stderr: cells done, running, failed, elapsed and ETA.

    The ETA sums the epochs left (of the cells running and of those waiting) times each detector's seconds per epoch
    measured in this call (its first epochs), or, before a detector has been timed, the mean of the others scaled by
    ``relative_cost`` (``harness.benchmark.RELATIVE_COST``); divided by the lanes. Early stopping can only make it
    shorter."""

    def __init__(
        self,
        jobs: Sequence[Any],
        epochs: int,
        lanes: int,
        skipped: int = 0,
        enabled: bool = True,
        stream: TextIO | None = None,
        now: Callable[[], float] | None = None,
        relative_cost: Mapping[str, float] | None = None,
    ):
        self.relative_cost = dict(relative_cost or {})
        self.pending = list(jobs)
        self.epochs, self.lanes, self.skipped = int(epochs), max(1, int(lanes)), int(skipped)
        self.total = len(self.pending) + self.skipped
        self.enabled, self.stream = enabled, stream
        self._now = now or time.perf_counter
        self.t0 = self._now()
        self.done = 0
        self.failed = 0
        self.running: dict[str, _Lane] = {}
        self._epoch_s: dict[str, list[float]] = {}  # detector -> seconds per epoch of each timed lane
        self._lock = threading.Lock()
        self._last_line = 0.0

    def started(self, job: Any, epochs_done: int = 0) -> None:
        with self._lock:
            self.pending = [j for j in self.pending if str(j) != str(job)]
            self.running[str(job)] = _Lane(job, self._now(), epochs_done, self.epochs, epochs_done)

    def epoch(self, job: Any, epochs_done: int, epochs: int | None = None) -> None:
        with self._lock:
            lane = self.running.get(str(job))
            if lane is None or epochs_done <= lane.epochs_done:
                return
            elapsed = self._now() - lane.started
            lane.epochs_done = epochs_done
            if epochs:
                lane.epochs = int(epochs)
            trained = epochs_done - lane.start_epochs  # in this call, start-up included
            if trained > 0 and elapsed > 0:
                self._epoch_s.setdefault(job.detector, []).append(elapsed / trained)
        self.print_line(force=False)

    def finished(self, job: Any, ok: bool) -> None:
        with self._lock:
            self.running.pop(str(job), None)
            self.done += 1
            self.failed += 0 if ok else 1
        self.print_line(force=True)

    def seconds_per_epoch(self, detector: str) -> float | None:
        timed = {d: v[-1] for d, v in self._epoch_s.items() if v}
        if detector in timed:
            return timed[detector]
        if not timed:
            return None
        unit = sum(s / self.relative_cost.get(d, 1.0) for d, s in timed.items()) / len(timed)
        return unit * self.relative_cost.get(detector, 1.0)

    def eta(self) -> float | None:
        with self._lock:
            left = 0.0
            for lane in self.running.values():
                spe = self.seconds_per_epoch(lane.job.detector)
                if spe is None:
                    return None
                left += spe * max(lane.epochs - lane.epochs_done, 0)
            for job in self.pending:
                spe = self.seconds_per_epoch(job.detector)
                if spe is None:
                    return None
                left += spe * self.epochs
        return left / self.lanes

    def line(self) -> str:
        running = len(self.running)
        failed = f", {self.failed} failed" if self.failed else ""
        done = self.done + self.skipped
        return (
            f"benchmark {done}/{self.total} cells ({running} running{failed}) | "
            f"{clock(self._now() - self.t0)} elapsed, ETA {clock(self.eta())}"
        )

    def print_line(self, force: bool = True) -> None:
        if not (self.enabled and progress_on()):
            return
        now = self._now()
        if not force and now - self._last_line < 30.0:  # at most one line per 30 s between cell ends
            return
        self._last_line = now
        print(self.line(), file=self.stream or sys.stderr, flush=True)
