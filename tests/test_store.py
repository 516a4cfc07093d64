"""The results store and atomic writes: a crash never leaves a truncated file."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from harness.errors import StoreError
from harness.io import atomic_write, atomic_write_json, read_json
from harness.store import RunKey, Store


def test_layout_one_folder_per_dataset_detector_encoding_fold_seed(tmp_path):
    store = Store(tmp_path)
    run = store.run(RunKey("m3t", "ours", "c2", "P4+P5", 2))
    assert run.path == tmp_path / "m3t" / "ours" / "c2" / "P4+P5" / "seed2"
    run.set_status("running", config_hash="abc")
    assert not run.is_finished()
    run.write_metrics({"metrics": {"mAP50": 0.5}, "support": {"images": 3, "instances": 9}})
    run.set_status("finished")
    assert run.is_finished()
    data = run.read_metrics()
    assert data["run"] == {"dataset": "m3t", "detector": "ours", "encoding": "c2", "fold": "P4+P5", "seed": 2}
    assert [r.key for r in store.runs()] == [run.key]
    assert list(store.runs(detector="eme")) == []
    assert run.status()["config_hash"] == "abc" and run.status()["state"] == "finished"


def test_unsafe_fold_names_are_refused(tmp_path):
    for bad in ("../x", "a/b", "..", "_sensing"):
        with pytest.raises(StoreError):
            Store(tmp_path).run(RunKey("d", "m", "e", bad, 0))


def test_log_lines_survive_a_partial_last_line(tmp_path):
    run = Store(tmp_path).run(RunKey("d", "m", "e", "f", 0))
    run.append_log({"epoch": 0, "loss": 1.0})
    run.append_log({"epoch": 1, "loss": 0.5})
    with open(run.log_path, "a") as f:
        f.write('{"epoch": 2, "lo')  # a crash in the middle of a line
    assert [r["epoch"] for r in run.read_log()] == [0, 1]


def test_failed_write_keeps_previous_file(tmp_path):
    target = tmp_path / "metrics.json"
    atomic_write_json(target, {"mAP50": 0.61})

    def crash_midway(f):
        f.write(b'{"mAP50": 0.7')
        raise KeyboardInterrupt("simulated crash")

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, crash_midway)
    assert read_json(target) == {"mAP50": 0.61}
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]  # no temporary left behind


def test_crash_before_rename_keeps_previous_file(tmp_path, monkeypatch):
    target = tmp_path / "m.json"
    atomic_write_json(target, {"v": 1})
    monkeypatch.setattr(os, "replace", lambda *a: (_ for _ in ()).throw(OSError("disk gone")))
    with pytest.raises(OSError):
        atomic_write_json(target, {"v": 2})
    monkeypatch.undo()
    assert read_json(target) == {"v": 1}


def test_sigkill_during_writes_never_leaves_a_truncated_file(tmp_path):
    target = tmp_path / "metrics.json"
    script = (
        "import sys\nfrom harness.io import atomic_write_json\n"
        "i = 0\n"
        "while True:\n"
        "    atomic_write_json(sys.argv[1], {'i': i, 'pad': 'x' * 200000})\n"
        "    i += 1\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script, str(target)])
    try:
        deadline = time.time() + 20
        while not target.exists() and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    data = json.loads(target.read_text())
    assert data["i"] >= 0 and len(data["pad"]) == 200000


def test_a_run_is_trained_by_one_process_at_a_time(tmp_path):
    from harness.store import RunBusyError

    run = Store(tmp_path).run(RunKey("m3t", "ours", "c2", "P1", 0))
    with run.exclusive():
        assert f"pid {os.getpid()}" in run.lock_path.read_text()
        with pytest.raises(RunBusyError, match=rf"m3t/ours/c2/P1/seed0.*another process \(pid {os.getpid()} on "):
            with run.exclusive():
                pass
    assert run.lock_path.read_text() == ""
    with run.exclusive():  # free again once released
        pass


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    from harness.store import RunBusyError

    run = Store(tmp_path).run(RunKey("m3t", "ours", "c2", "P1", 0))
    code = (
        "import sys, time; from pathlib import Path; from harness.store import Store, RunKey\n"
        f"r = Store(Path({str(tmp_path)!r})).run(RunKey('m3t', 'ours', 'c2', 'P1', 0))\n"
        "with r.exclusive():\n    print('locked', flush=True); time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(RunBusyError, match=f"pid {proc.pid}"):
            with run.exclusive():
                pass
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    with run.exclusive():  # the operating system released the dead holder's lock
        pass


def test_a_new_run_in_a_read_only_store_is_a_clear_error(tmp_path, monkeypatch):
    import errno
    from pathlib import Path

    store = Store(tmp_path / "store")
    run = store.run(RunKey("m3t-synth", "ours", "c2", "P9", 0))
    real_mkdir = Path.mkdir

    def read_only(self, *args, **kwargs):  # what a store on a read-only mount (or without write permission) does
        if str(self).startswith(str(store.root)):
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    with pytest.raises(
        StoreError,
        match=r"cannot write run m3t-synth/ours/c2/P9/seed0 into the results store: "
        r"Permission denied \(.*P9/seed0\); make the store writable or choose "
        r"another --store",
    ):
        with run.exclusive():
            pass
