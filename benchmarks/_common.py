"""What several benchmarks share: the repository on the import path, a median timer, and the reference arrays of the
real DJI samples.

Imported as ``from _common import ...`` (a benchmark runs with ``benchmarks/`` as its script folder).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parent.parent
#: The shared data beside the repository (real DJI files and their reference arrays).
SHARED_DATA = REPO.parent / "shared" / "data"


def on_path(*folders: str) -> None:
    """Put the repository (and ``folders`` of it, e.g. ``tests`` for its fixtures) first on the import path."""
    for folder in reversed(("", *folders)):
        path = str(REPO / folder) if folder else str(REPO)
        if path not in sys.path:
            sys.path.insert(0, path)


def median_time(fn: Callable[[], Any], repeat: int, warmup: int = 1) -> float:
    """Median wall seconds of ``repeat`` calls of ``fn`` after ``warmup`` calls (page cache filled, lazy work done)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def reference_arrays(argv: list[str] | None, description: str, data: Path, pattern: str) -> list[Path]:
    """The ``--data`` option (default ``data``) parsed from ``argv``, and the reference arrays matching ``pattern``
    in that folder, sorted; none is a one-line message on stderr and ``SystemExit(1)``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--data", type=Path, default=data)
    args = ap.parse_args(argv)
    found = sorted(args.data.glob(pattern))
    if not found:
        print(f"no reference arrays ({pattern}) in {args.data}", file=sys.stderr)
        raise SystemExit(1)
    return found
