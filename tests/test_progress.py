"""The overall progress line of run and sweep: runs and epochs done, elapsed time and ETA, on stderr."""

from __future__ import annotations

import io

from harness.progress import OverallProgress, SweepProgress, clock


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_run_progress_counts_epochs_and_projects_the_rest():
    now, out = Clock(), io.StringIO()
    p = OverallProgress(runs=2, epochs=5, stream=out, now=now)
    assert p.eta() is None and "ETA ?" in p.line()
    p.start_run("ours/c2/P1")
    for e in (1, 2):
        now.t += 10
        p.epoch_done(e, 5)
    assert out.getvalue().splitlines()[-1] == "run 1/2 ours/c2/P1 epoch 2/5 | 2/10 epochs | 0:20 elapsed, ETA 1:20"
    p.finish_run()  # stopped early after 2 of 5 epochs: its 3 remaining epochs are no longer to do
    assert p.done_epochs == 5 and p.eta() == 50.0  # 10 s per trained epoch, 5 to do
    p.start_run("ours/c2/P2")
    now.t += 10
    p.epoch_done(3, 5)  # resumed after epoch 2: the first record it logs is epoch 3
    assert p.done_epochs == 8  # 5 of run 1, and run 2 had done epochs 1-2 before this call
    assert out.getvalue().splitlines()[-1].startswith("run 2/2 ours/c2/P2 epoch 3/5 | 8/10 epochs | 0:30 elapsed")


def test_progress_is_silent_when_disabled_and_sweeps_count_failures():
    out = io.StringIO()
    p = OverallProgress(runs=1, epochs=3, enabled=False, stream=out)
    p.start_run("x")
    p.epoch_done(1, 3)
    assert out.getvalue() == ""
    now = Clock()
    s = SweepProgress(4, stream=out, now=now)
    now.t = 30
    s.job_done(True)
    now.t = 60
    s.job_done(False)
    assert out.getvalue().splitlines() == [
        "sweep 1/4 runs | 0:30 elapsed, ETA 1:30",
        "sweep 2/4 runs (1 failed) | 1:00 elapsed, ETA 1:00",
    ]
    assert clock(3725) == "1:02:05" and clock(None) == "?"
