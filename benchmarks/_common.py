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


def add_set_arguments(ap: argparse.ArgumentParser) -> None:
    """``--prepared``, ``--coco`` and ``--repeat``: the datasets an input-guard measurement runs on (``measured_sets``)
    and how often the check is timed."""
    ap.add_argument("--prepared", type=Path, nargs="*", default=[], help="prepared dataset folders (manifest.json)")
    ap.add_argument("--coco", type=int, nargs="*", default=[], help="make_coco_rgbt folders of N pairs")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs of the check per correct set")


def measured_sets(coco: list[int], prepared: list[Path], tmp: Path) -> list[tuple[str, Any]]:
    """(name, prepared dataset) of the tests' ``make_coco_rgbt`` folders of N pairs (``coco``, prepared into ``tmp``
    with every input-guard finding accepted: they are measured, not refused) and of the prepared folders named."""
    on_path("tests")
    from coco_rgbt_helpers import make_coco_rgbt, prepare_coco_rgbt
    from harness.cache.reader import PreparedDataset

    sets = [
        (f"coco-rgbt n={n}", prepare_coco_rgbt(make_coco_rgbt(tmp / f"coco-{n}", n=n), tmp / "cache", "all"))
        for n in coco
    ]
    for path in prepared:
        data = PreparedDataset(path)
        sets.append((f"{data.name} {len(data)}", data))
    return sets
