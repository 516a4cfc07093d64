"""DJI's correction by raw-count lookup table against the per-distinct-value correction, and R-JPEG decoding in
files per second against reading the same files' bytes, on real 640x512 R-JPEGs, in one run.

Timed per file, in an order rotating round by round:

* correction step (the file's parameters and APP5 table, ``raw14`` already read):
  anchor ``correct_temperature(blackbody_c(raw14))`` (the previous path: ``np.unique`` over the frame's float32
  blackbody temperatures, correct each value, scatter back) against ``correct_raw14(raw14)`` (correct each count
  between the frame's smallest and largest, index the table by the frame); the outputs are checked equal;
* whole decode: anchor ``Path.read_bytes()`` against ``read_rjpeg`` + ``rjpeg_temperature`` (segments, EXIF,
  APP3/APP4/APP5, correction); reported as files/s and as the ratio to reading the bytes;
* whole decode of the files with a correction step, per core: anchor ``read_rjpeg`` + the previous per-value
  correction against ``read_rjpeg`` + ``rjpeg_temperature`` (what a user's decode costs before and after).

    .venv/bin/python benchmarks/bench_dji_correction.py [--repeat 20] [--rounds 5] [FILE ...]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared" / "data"
DEFAULT_FILES = [SHARED / "dji-m3t-rjpeg" / f"m3t_{k}.jpg" for k in "abc"] + [
    SHARED / "dji-rjpeg-cameras" / "m2ea_iirp.jpg",
    SHARED / "dji-rjpeg-cameras" / "h20t_dirp.jpg",
]


def _time(fn, repeat: int) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


#: The correction step against the per-value path it replaced (6.9x and 8.5x when it was introduced).
TARGET = 5.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args(argv)
    files = [f for f in (args.files or DEFAULT_FILES) if f.exists()]
    if not files:
        print("no R-JPEG found; give files", file=sys.stderr)
        return 2
    from harness.sensing import dji_correction as dc
    from harness.sensing.radiometry import read_rjpeg, rjpeg_temperature

    def correction_args(rj) -> tuple:
        p = rj.correction_params()
        return rj.tau_table, p["emissivity"], p["distance"], p["humidity"], p["reflected"], p["atmosphere"]

    steps: dict[str, tuple] = {}
    for f in files:
        rj = read_rjpeg(f)
        if rj.tau_table is None:
            continue  # dirp files have no iirp correction step; they take part in the decode timing only
        args_ = correction_args(rj)
        old = dc.correct_temperature(rj.blackbody_c(), *args_)
        new = dc.correct_raw14(rj.raw14, *args_)
        if not np.array_equal(old, new, equal_nan=True):
            print(f"{f.name}: lookup table and per-value correction differ", file=sys.stderr)
            return 1
        steps[f.name] = (rj, args_)

    def previous_decode(f: Path) -> np.ndarray:
        rj = read_rjpeg(f)
        return dc.correct_temperature(rj.blackbody_c(), *correction_args(rj))

    corrected = [f for f in files if f.name in steps]

    runs = {
        "correction, anchor: np.unique per value": lambda: [
            dc.correct_temperature(rj.blackbody_c(), *a) for rj, a in steps.values()
        ],
        "correction, lookup table": lambda: [dc.correct_raw14(rj.raw14, *a) for rj, a in steps.values()],
        "decode, anchor: read the bytes": lambda: [f.read_bytes() for f in files],
        "decode, read_rjpeg + temperature": lambda: [rjpeg_temperature(read_rjpeg(f)) for f in files],
        "corrected decode, anchor: previous path": lambda: [previous_decode(f) for f in corrected],
        "corrected decode, read_rjpeg + temperature": lambda: [rjpeg_temperature(read_rjpeg(f)) for f in corrected],
    }
    names = list(runs)
    times: dict[str, list[float]] = {n: [] for n in names}
    for k in range(args.rounds):
        for name in names[k % len(names) :] + names[: k % len(names)]:
            times[name].append(_time(runs[name], args.repeat))
    med = {n: statistics.median(v) for n, v in times.items()}
    n_corr, n_dec = len(steps), len(files)
    print(
        f"{n_corr} file(s) with a correction step, {n_dec} decoded; median of {args.rounds} rounds x "
        f"{args.repeat} repeats, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}"
    )
    print(f"{'run':42s} {'ms/file':>9s} {'files/s':>9s}")
    for name in names:
        n = n_dec if name.startswith("decode") else n_corr
        print(f"{name:42s} {1000 * med[name] / n:9.2f} {n / med[name]:9.1f}")
    a, b = med[names[0]], med[names[1]]
    print(f"correction step: lookup table {a / b:.1f}x faster than the np.unique anchor")
    r, d = med[names[2]], med[names[3]]
    print(f"decode: {n_dec / d:.1f} files/s, {d / r:.0f}x the time of reading the bytes ({n_dec / r:.0f} files/s)")
    o, c = med[names[4]], med[names[5]]
    print(
        f"corrected decode: {o / c:.1f}x the previous path's files/s per core ({n_corr / c:.0f} against "
        f"{n_corr / o:.0f} files/s)"
    )
    print(f"target: lookup table >= {TARGET:g}x the np.unique anchor -> {'met' if a / b >= TARGET else 'NOT met'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
