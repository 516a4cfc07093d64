"""Start-up cost of the ``harness`` command line: wall time and import time of light commands.

    .venv/bin/python benchmarks/bench_cli_startup.py [--repeats 7] [--cmd="--help" --cmd="run --help" ...]

Each command runs ``--repeats`` times in a fresh interpreter (``python -X importtime -m harness ...``, installed
plugins not auto-loaded, byte code cached after a first untimed run); the table gives the best wall time, the best
sum of top-level import times, and the heavy modules the command imported (numpy, torch, cv2, rich, ...). The best
of several runs is the figure to compare: on a busy machine single runs vary by 2x. ``python -c pass`` is the floor.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEAVY = (
    "numpy",
    "torch",
    "cv2",
    "scipy",
    "rich",
    "yaml",
    "PIL",
    "pycocotools",
    "faster_coco_eval",
    "onnx",
    "onnxruntime",
    "matplotlib",
    "safetensors",
    "pandas",
)
DEFAULT = ("--help", "--version", "run --help", "sensing decode --help", "list", "plugins")
LINE = re.compile(r"import time:\s+(\d+) \|\s+(\d+) \|( +)(\S+)")


def measure(args: list[str], env: dict[str, str]) -> tuple[float, float, list[str]]:
    """(wall seconds, seconds of top-level imports, heavy top-level packages imported) of one run."""
    cmd = [sys.executable, "-X", "importtime", "-m", "harness", *args]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    imports, heavy = 0, []
    for line in res.stderr.splitlines():
        m = LINE.match(line)
        if not m:
            continue
        if len(m[3]) == 1:  # a top-level import: its cumulative time
            imports += int(m[2])
        name = m[4]
        if name in HEAVY and name not in heavy:
            heavy.append(name)
    return wall, imports / 1e6, heavy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument(
        "--cmd",
        action="append",
        default=None,
        help="A command line to time, e.g. --cmd='run --help' (repeatable) [default: a set of light ones].",
    )
    opts = ap.parse_args()
    with tempfile.TemporaryDirectory() as pyc:
        env = {
            **os.environ,
            "HARNESS_DISABLE_PLUGIN_AUTOLOAD": "1",
            "PYTHONPYCACHEPREFIX": pyc,
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
        }
        env.pop("PYTHONDONTWRITEBYTECODE", None)  # a real installation has its byte code cached
        floor = min(_time([sys.executable, "-c", "pass"], env) for _ in range(opts.repeats))
        print(f"python -c pass: {floor * 1e3:.0f} ms (best of {opts.repeats})")
        print(f"{'command':<28} {'wall ms':>8} {'imports ms':>10}  heavy modules imported")
        for text in opts.cmd or DEFAULT:
            args = shlex.split(text)
            measure(args, env)  # first run writes the byte code
            runs = [measure(args, env) for _ in range(opts.repeats)]
            wall = min(r[0] for r in runs)
            imports = min(r[1] for r in runs)
            print(f"{'harness ' + text:<28} {wall * 1e3:>8.0f} {imports * 1e3:>10.0f}  {', '.join(runs[0][2]) or '-'}")


def _time(cmd: list[str], env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True)
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
