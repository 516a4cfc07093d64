"""Run checkpoint reads under a memory limit in a forked worker, and report what each did.

``python tests/hostile_runner.py CASES.json`` reads ``[{"name", "path", "mode"[, "allowance"]}, ...]`` (mode ``import``:
``import_checkpoint``; ``cli``: ``harness weights import`` through the command line; ``plain``: what ``--init``
does, which is also how a run resumes from ``last.pt``), imports the harness once, then forks a worker that sets
``RLIMIT_AS`` to its address space plus ``--allowance`` bytes and runs the cases one after another. For each it
reports the outcome (``ok``, ``error`` for a ``HarnessError``, ``exception`` for anything else), the message, the
time and the peak resident memory above the resident memory the case started with (freed memory is handed back
with ``malloc_trim``, and Linux's peak, ``VmHWM`` = ``getrusage().ru_maxrss``, is reset through
``/proc/self/clear_refs`` before each case). A case still running after ``--timeout`` seconds is killed
(``hang``), one that kills the worker is a ``crash``; either way a new worker goes on with the next case. One JSON
list goes to stdout.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import select
import signal
import sys
import time
import traceback
from pathlib import Path

_LIBC = ctypes.CDLL("libc.so.6")


def _status() -> dict[str, int]:
    out = {}
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmSize", "VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) * 1024
    return out


def _case(case: dict) -> dict:
    from harness.errors import HarnessError

    _LIBC.malloc_trim(0)  # what earlier cases freed leaves the resident set, so this case's growth is its own
    with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
        f.write("5")  # resets the peak resident memory to the current one
    start = _status()
    t0 = time.perf_counter()
    result: dict = {"outcome": "ok"}
    try:
        path = Path(case["path"])
        if case["mode"] == "import":
            from harness.weights import import_checkpoint

            res = import_checkpoint(path, path.with_name(path.stem + ".out.safetensors"))
            result.update(sidecar_bytes=res.sidecar.stat().st_size, weights_bytes=res.weights.stat().st_size)
        elif case["mode"] == "cli":
            from click.testing import CliRunner

            from harness.cli import get_cli

            out = path.with_name(path.stem + ".cli.safetensors")
            res = CliRunner().invoke(get_cli(), ["weights", "import", str(path), "--out", str(out)])
            crashed = res.exception is not None and not isinstance(res.exception, SystemExit)
            result.update(
                outcome="exception" if crashed else ("ok" if res.exit_code == 0 else "error"),
                message=res.output,
                exit_code=res.exit_code,
                type=type(res.exception).__name__,
            )
        else:
            import torch

            from harness.engine import checkpoint as ckpt

            model = torch.nn.Module()
            model.w = torch.nn.Parameter(torch.zeros(4))  # the corpus's small state dicts hold 'w' of 4 floats
            result["loaded"] = ckpt.init_from(model, path)["loaded"]  # what --init does
    except HarnessError as exc:
        result.update(outcome="error", message=str(exc), type=type(exc).__name__)
    except BaseException as exc:  # what the test must never see
        result.update(
            outcome="exception",
            type=type(exc).__name__,
            message=str(exc)[:500],
            where=traceback.format_exc().splitlines()[-3:],
        )
    seconds = time.perf_counter() - t0
    peak = max(_status()["VmHWM"], resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    return {**case, **result, "seconds": seconds, "peak_bytes": max(peak - start["VmRSS"], 0)}


def _worker(cases: list[dict], allowance: int, w: int) -> None:
    limit = _status()["VmSize"] + allowance
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    for case in cases:
        soft = min(_status()["VmSize"] + case["allowance"], limit) if "allowance" in case else limit
        resource.setrlimit(resource.RLIMIT_AS, (soft, limit))  # a case may ask for less room than the others
        try:
            line = json.dumps(_case(case))
        except BaseException as exc:  # pragma: no cover
            line = json.dumps({**case, "outcome": "exception", "message": repr(exc)[:300]})
        os.write(w, line.encode() + b"\n")


def run(cases: list[dict], allowance: int, timeout: float) -> list[dict]:
    results: list[dict] = []
    while len(results) < len(cases):
        todo = cases[len(results) :]
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(r)
            _worker(todo, allowance, w)
            os._exit(0)
        os.close(w)
        buf, deadline, hung = b"", time.monotonic() + timeout, False
        while True:
            ready, _, _ = select.select([r], [], [], max(deadline - time.monotonic(), 0))
            if not ready:  # the current case hangs
                os.kill(pid, signal.SIGKILL)
                results.append({**todo[0], "outcome": "hang", "seconds": timeout})
                hung = True
                break
            chunk = os.read(r, 1 << 16)
            if not chunk:
                break
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                results.append(json.loads(line))
                todo = todo[1:]
                deadline = time.monotonic() + timeout
        os.close(r)
        _, status = os.waitpid(pid, 0)
        if not hung and len(results) < len(cases):  # the worker died in the middle of its current case
            results.append({**todo[0], "outcome": "crash", "message": f"worker died with status {status}"})
    return results


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("cases")
    ap.add_argument("--allowance", type=int, default=1 << 30, help="bytes of address space above the start")
    ap.add_argument("--timeout", type=float, default=20.0)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    import harness.engine.checkpoint  # noqa: F401  (imported once, before the forks)
    import harness.weights  # noqa: F401

    json.dump(run(json.loads(Path(args.cases).read_text()), args.allowance, args.timeout), sys.stdout)


if __name__ == "__main__":
    main()
