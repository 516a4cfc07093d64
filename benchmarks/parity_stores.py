"""Do two results stores hold the same results? The before/after check of a speed-up.

Compares every run present in both stores (``<dataset>/<detector>/<encoding>/<fold>/seed<N>``): the stored
metrics (overall, per category, support, best epoch and fitness, complexity), every prediction (image, category,
box, score) and the per-epoch records of ``log.jsonl`` (losses, held-out metrics, fitness, learning rates).
Timings, paths and the environment record are not compared. A value differs when it is not equal within
``--tol`` (absolute, default 0: bit for bit as stored). Prints one line per run and exits 1 if any run differs or
is missing from one store::

    .venv/bin/python benchmarks/parity_stores.py results/demo-before results/demo
    .venv/bin/python benchmarks/parity_stores.py A B --tol 1e-6      # allow float noise
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Iterator

#: keys that record when, where or how fast a run ran, not what it computed
IGNORED = {
    "time_s",
    "predict_s",
    "predict_images_per_s",
    "images_per_s",
    "environment",
    "best_path",
    "last_path",
    "device",
    "resumed_from",
    "created",
    "finished",
    "started",
    "elapsed_s",
}


def runs(store: Path) -> dict[str, Path]:
    return {str(p.parent.relative_to(store)): p.parent for p in sorted(store.rglob("metrics.json"))}


def diffs(a: Any, b: Any, path: str, tol: float) -> Iterator[tuple[str, Any, Any]]:
    """``(where, a, b)`` for every leaf that differs (numbers within ``tol`` are equal; NaN equals NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k in IGNORED:
                continue
            if k not in a or k not in b:
                yield f"{path}.{k}", a.get(k, "<missing>"), b.get(k, "<missing>")
            else:
                yield from diffs(a[k], b[k], f"{path}.{k}", tol)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            yield f"{path}[len]", len(a), len(b)
            return
        for i, (x, y) in enumerate(zip(a, b)):
            yield from diffs(x, y, f"{path}[{i}]", tol)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        if math.isnan(a) and math.isnan(b):
            return
        if not abs(a - b) <= tol:
            yield path, a, b
    elif a != b:
        yield path, a, b


def compare_run(a: Path, b: Path, tol: float) -> list[tuple[str, Any, Any]]:
    out: list[tuple[str, Any, Any]] = []
    for name in ("metrics.json", "predictions.json"):
        out += diffs(json.loads((a / name).read_text()), json.loads((b / name).read_text()), name, tol)
    logs = []
    for d in (a, b):
        p = d / "log.jsonl"
        logs.append([json.loads(line) for line in p.read_text().splitlines() if line.strip()] if p.exists() else [])
    out += diffs(logs[0], logs[1], "log.jsonl", tol)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--tol", type=float, default=0.0, help="absolute tolerance for numbers (default 0: identical)")
    p.add_argument("--show", type=int, default=3, help="differences shown per run")
    args = p.parse_args()
    ra, rb = runs(args.a), runs(args.b)
    if not ra or not rb:
        sys.exit(f"no finished runs in {args.a if not ra else args.b}")
    bad = 0
    for key in sorted(set(ra) | set(rb)):
        if key not in ra or key not in rb:
            print(f"{key:<48} only in {'A' if key in ra else 'B'}")
            bad += 1
            continue
        found = compare_run(ra[key], rb[key], args.tol)
        n_pred = len(json.loads((ra[key] / "predictions.json").read_text()))
        print(f"{key:<48} {'identical' if not found else f'{len(found)} differences'} ({n_pred} predictions)")
        for where, x, y in found[: args.show]:
            print(f"    {where}: {x!r} != {y!r}")
        bad += bool(found)
    print(f"{len(set(ra) & set(rb))} runs compared, {bad} differ or are missing (tolerance {args.tol:g})")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
