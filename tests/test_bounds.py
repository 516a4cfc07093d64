"""Bounds on the settings that can exhaust the machine (``harness.config.check_bounds``): an image size x batch whose
memory exceeds what the machine has, worker counts beyond a few per core, and non-positive or non-integer values
stop before any work with the numbers; worker processes leave Ctrl-C to the parent (``harness.workers``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from harness import config
from harness.errors import ConfigError


def test_an_image_size_that_cannot_fit_is_refused_with_the_memory_it_needs():
    with pytest.raises(ConfigError) as err:
        config.load_config(profile="smoke", overrides=["protocol.imgsz=64000"])
    text = str(err.value)
    need = config.TRAIN_BYTES_PER_PIXEL * 64000**2 * 4
    assert text.startswith("--set protocol.imgsz=64000: protocol.imgsz=64000 with train.batch=4 needs at least")
    assert f"{need / 2**40:.1f} TiB" in text and "MemAvailable" in text and "lower protocol.imgsz (at most" in text


def test_the_bound_follows_the_memory_there_is(monkeypatch):
    cfg = config.load_config(profile="smoke")
    need = config.memory_needed(cfg)
    assert need["train"] == config.TRAIN_BYTES_PER_PIXEL * 160 * 160 * 4
    assert need["eval"] == config.EVAL_BYTES_PER_PIXEL * 160 * 160 * 8
    monkeypatch.setattr(config, "available_memory", lambda device="auto": (need["train"] - 1, "the memory here"))
    with pytest.raises(ConfigError, match=r"needs at least .* the memory here is"):
        config.check_bounds(cfg)
    monkeypatch.setattr(config, "available_memory", lambda device="auto": (need["train"], "the memory here"))
    config.check_bounds(cfg)
    monkeypatch.setattr(config, "available_memory", lambda device="auto": (0, "unknown"))
    config.check_bounds({**cfg, "protocol": {"imgsz": 10**6}})  # unknown memory: no bound


def test_available_memory_reads_the_host_on_a_cpu_run():
    have, where = config.available_memory("cpu")
    assert have > 0 and "MemAvailable" in where


@pytest.mark.parametrize(
    "item, said",
    [
        ("protocol.imgsz=0", "protocol.imgsz=0 must be an integer >= 1"),
        ("protocol.imgsz=-64", "protocol.imgsz=-64 must be an integer >= 1"),
        ("train.batch=0", "train.batch=0 must be an integer >= 1"),
        ("eval.batch=-1", "eval.batch=-1 must be an integer >= 1"),
        ("protocol.imgsz=2.5", "expects int"),
        ("train.workers=-1", "train.workers=-1 must be an integer >= 0"),
        ("train.workers=100000", "asks for more worker processes than"),
    ],
)
def test_bad_sizes_batches_and_workers_are_refused_by_name(item, said):
    with pytest.raises(ConfigError, match=f"--set {item}") as err:
        config.load_config(profile="smoke", overrides=[item])
    assert said in str(err.value)


def test_a_run_with_an_impossible_image_size_stops_before_any_work(cli_runner, tmp_path):
    t0 = time.perf_counter()
    res = cli_runner(
        ["run", "--dataset", "m3t-synth", "--detector", "ours", "--profile", "smoke", "--store", str(tmp_path / "s"),
         "--set", "protocol.imgsz=64000", "--no-progress"]
    )  # fmt: skip
    assert res.exit_code == 2 and "needs at least" in res.output and "MemAvailable" in res.output, res.output
    assert time.perf_counter() - t0 < 20 and not (tmp_path / "s").exists()


def test_workers_of_a_command_are_bounded(cli_runner, tmp_path):
    res = cli_runner(["sensing", "decode", str(tmp_path), "--out", str(tmp_path / "o"), "--workers", "100000"])
    assert res.exit_code == 2 and "--workers" in res.output and str(config.worker_cap()) in res.output


POOL = """
import multiprocessing as mp, signal, sys, time
from concurrent.futures import ProcessPoolExecutor
from harness.workers import worker_pool
# Ctrl-C as in a terminal: a process started in the background by a non-interactive shell (as a CI job may be)
# inherits SIGINT ignored, and Python then raises no KeyboardInterrupt
signal.signal(signal.SIGINT, signal.default_int_handler)
ctx = mp.get_context("spawn")
pool = worker_pool(2, mp_context=ctx) if sys.argv[1] == "quiet" else ProcessPoolExecutor(2, mp_context=ctx)
for f in [pool.submit(time.sleep, 0.01) for _ in range(4)]:
    f.result()
print("ready", flush=True)
try:  # the parent busy (a model predicting), the workers waiting for captures
    busy = pool.submit(time.sleep, 1.0)  # one worker busy, the other waiting
    time.sleep(30)
except KeyboardInterrupt:
    pool.shutdown(wait=True, cancel_futures=True)
    print("interrupted: stopped", file=sys.stderr)
    sys.exit(130)
"""


def _interrupted(kind: str) -> tuple[int, str, float]:
    """(exit status, stderr, seconds from Ctrl-C to exit) of a pool of two workers (one busy, one waiting),
    interrupted as a terminal does (SIGINT to the whole process group) while the parent is busy."""
    proc = subprocess.Popen(
        [sys.executable, "-c", POOL, kind],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        time.sleep(0.3)
        t0 = time.perf_counter()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        return proc.returncode, err, time.perf_counter() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_ctrl_c_stops_the_workers_without_tracebacks_within_seconds():
    code, err, seconds = _interrupted("quiet")
    assert code == 130 and err.strip() == "interrupted: stopped" and seconds < 5, err
    code, err, _ = _interrupted("plain")  # a plain pool's waiting workers each print a KeyboardInterrupt traceback
    assert err.count("KeyboardInterrupt") >= 1 and "Traceback" in err, err


def test_every_worker_starts_while_ctrl_c_is_ignored():
    """A spawning pool starts a worker per task as tasks come; ``worker_pool`` starts all of them at once, while
    SIGINT is ignored, so none is still importing (and raising KeyboardInterrupt) when Ctrl-C comes later."""
    import multiprocessing as mp

    from harness.workers import worker_pool

    pool = worker_pool(3, mp_context=mp.get_context("spawn"))
    try:
        assert len(pool._processes) == 3  # noqa: SLF001 - how many processes the pool has started
    finally:
        pool.shutdown(wait=True)
