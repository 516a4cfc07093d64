"""A run killed with SIGKILL in the middle of an epoch restarts from its last checkpoint and ends exactly where an
uninterrupted run with the same seed ends: same metrics, same predictions, same weights."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest
import torch

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from engine_helpers import set_args, shapes_run_args
from scale_helpers import TINY, harness_cmd, subprocess_env

# The tiny run with 32 training images in batches of 2 at 128 px (later overrides win): an epoch lasts long enough
# (about a second) to be killed in its middle
KILL = [
    *TINY,
    "dataset.per_group=32",
    "protocol.imgsz=128",
    "protocol.epochs=3",
    "train.batch=2",
    "eval.batch=16",
]


def _cmd(store):
    return harness_cmd(*shapes_run_args(store, *set_args(KILL)))


def _run_dir(store):
    return store / "shapes" / "tinydet" / "test-ir8" / "A" / "seed0"


def _wait_for(predicate, proc, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.01)
    return False


@pytest.mark.slow
def test_a_run_killed_mid_epoch_resumes_to_the_uninterrupted_result(tmp_path):
    env = subprocess_env(tmp_path)
    store = tmp_path / "store"
    run_dir = _run_dir(store)
    proc = subprocess.Popen(_cmd(store), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        # epoch 1 is checkpointed and logged; epoch 2 has started
        logged = _wait_for(
            lambda: (run_dir / "log.jsonl").exists() and (run_dir / "log.jsonl").read_text().count("\n") >= 1,
            proc,
            timeout=240,
        )
        assert logged, "the run ended before its first epoch was logged"
        first_epoch_s = json.loads((run_dir / "log.jsonl").read_text().splitlines()[0])["time_s"]
        time.sleep(0.3 * first_epoch_s)  # about a third into epoch 2, which lasts as long as epoch 1
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "running"  # SIGKILL leaves no chance to write anything else
    assert not (run_dir / "metrics.json").exists()
    last = torch.load(run_dir / "checkpoints" / "last.pt", weights_only=True)
    assert last["epoch"] == 0 and not last["done"]  # killed inside epoch 2: only epoch 1 is checkpointed

    # the uninterrupted run (the dataset cache is ready now) goes on beside the resumed one
    reference = subprocess.Popen(
        _cmd(tmp_path / "reference"), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    again = subprocess.run(_cmd(store), env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resumed" in again.stdout
    _, err = reference.communicate(timeout=300)
    assert reference.returncode == 0, err[-3000:]

    ref_dir = _run_dir(tmp_path / "reference")
    a, b = (json.loads((d / "metrics.json").read_text()) for d in (ref_dir, run_dir))
    assert b["train"]["resumed_from"] == 1 and a["train"]["resumed_from"] is None
    assert a["metrics"] == b["metrics"] and a["per_category"] == b["per_category"] and a["support"] == b["support"]
    assert a["train"]["best_epoch"] == b["train"]["best_epoch"]
    assert (ref_dir / "predictions.json").read_text() == (run_dir / "predictions.json").read_text()
    wa, wb = (torch.load(d / "checkpoints" / "last.pt", weights_only=True) for d in (ref_dir, run_dir))
    assert wa["model"].keys() == wb["model"].keys()
    assert all(torch.equal(wa["model"][k], wb["model"][k]) for k in wa["model"])
    assert all(torch.equal(wa["ema"]["module"][k], wb["ema"]["module"][k]) for k in wa["ema"]["module"])
    log = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
    ref_log = [json.loads(line) for line in (ref_dir / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [1, 2, 3]  # the killed epoch was not logged twice
    assert [r["loss"] for r in log] == [r["loss"] for r in ref_log]
