"""Overall progress of long work, as one line on stderr: runs done out of those to do, epochs, elapsed time, ETA.

``harness run`` prints it after every epoch (``run 2/4 ours/c2/P2 epoch 3/6 | 9/24 epochs | 0:41 elapsed, ETA
1:10``) and ``harness sweep`` after every run (``sweep 3/16 runs (1 failed) | 2:05 elapsed, ETA 9:00``), beside the
per-epoch bar. The ETA assumes the remaining epochs (or runs) take as long as those done so far in this call; early
stopping can only make it shorter. ``enabled=False`` (``--no-progress``, or any process but the first under
``torchrun``) prints nothing.
"""

from __future__ import annotations

import sys
import time
from typing import Callable, TextIO


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

    def __init__(self, runs: int, epochs: int, enabled: bool = True, stream: TextIO | None = None,
                 now: Callable[[], float] | None = None):
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
        return (f"{head} | {self.done_epochs}/{self.total_epochs} epochs | {clock(self._now() - self.t0)} elapsed, "
                f"ETA {clock(self.eta())}")

    def _print(self, text: str) -> None:
        if self.enabled:
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

    def __init__(self, jobs: int, enabled: bool = True, stream: TextIO | None = None,
                 now: Callable[[], float] | None = None):
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
        return (f"sweep {self.done}/{self.jobs} runs{failed} | {clock(self._now() - self.t0)} elapsed, "
                f"ETA {clock(self.eta())}")

    def job_done(self, ok: bool = True) -> None:
        self.done += 1
        self.failed += 0 if ok else 1
        if self.enabled:
            print(self.line(), file=self.stream or sys.stderr, flush=True)
