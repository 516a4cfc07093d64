"""Loading throughput: prepared (memory-mapped) samples vs decoding the raw files each time.

Anchor (measured in the same run): ``raw decode`` = read the wide RGB JPEG (OpenCV) and decode the thermal R-JPEG
(``read_thermal``) for every pair, without any alignment. Also measured: ``raw + align`` = the whole sensing
pipeline per pair (what every epoch would cost without the cache), and ``prepared`` = one ``PreparedDataset[i]``
per sample with its arrays copied out of the memory map (RGB, temperature, preview, boxes, labels).

    .venv/bin/python benchmarks/bench_prepared_loading.py                 # m3t-synth small (generated if absent)
    .venv/bin/python benchmarks/bench_prepared_loading.py --profile tiny --repeat 5

Prints samples/s for each and the ratios to the anchor. Numbers are noisy on a shared machine; the ratio is what
to compare between runs.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from _common import median_time, on_path

on_path()


#: Loading a prepared sample against decoding its raw files (41x and 63x when the cache was introduced).
TARGET = 20.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", default="small", choices=["tiny", "small", "full"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--root", type=Path, default=None, help="m3t-synth folder (default: generated data dir)")
    ap.add_argument("--cache", type=Path, default=None, help="cache folder (default: $HARNESS_CACHE or ./cache)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--max-samples", type=int, default=None)
    args = ap.parse_args()

    import cv2

    from harness.api import PrepareReport
    from harness.cache import open_source, prepare
    from harness.config import load_config
    from harness.sensing.radiometry import read_thermal

    cv2.setNumThreads(1)
    cfg = load_config(protocol="m3t-4fold")
    cfg["dataset"] = {"profile": args.profile, "seed": args.seed}
    if args.root is not None:
        cfg["dataset"]["root"] = str(args.root)
    ds = prepare("m3t-synth", cfg, cache_root=args.cache, progress=False, form="raw")
    _, source = open_source("m3t-synth", cfg)
    n = min(len(ds), args.max_samples or len(ds))
    records = source.records[:n]
    pairs = [(source.base / r.file_name, source.thermal_partner(r)) for r in records]

    def raw_decode() -> None:
        for rgb_path, th_path in pairs:
            rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
            temp, _ = read_thermal(th_path)
            assert rgb is not None and temp.size

    def raw_align() -> None:
        source.records = records
        for _ in source.samples(PrepareReport()):
            pass

    def prepared() -> None:
        for i in range(n):
            s = ds[i]
            for a in (s.rgb, s.thermal, s.ir8, s.boxes, s.labels):
                np.array(a)  # copy out of the memory map: the bytes a data loader hands on

    t_anchor = median_time(raw_decode, args.repeat)
    t_align = median_time(raw_align, max(1, args.repeat - 1))
    t_prep = median_time(prepared, args.repeat)
    s0 = ds[0]
    rh, rw = cv2.imread(str(pairs[0][0])).shape[:2]
    print(
        f"m3t-synth {args.profile}: {n} samples; raw: RGB {rw}x{rh} JPEG + thermal {pairs[0][1].suffix} file; "
        f"prepared: {s0.width}x{s0.height} (rgb u8, thermal f32, ir8 u8); {os.cpu_count()} CPU(s), "
        f"median of {args.repeat} passes"
    )
    rows = [("raw decode (anchor)", t_anchor), ("raw + align", t_align), ("prepared (memmap)", t_prep)]
    width = max(len(r[0]) for r in rows)
    print(f"{'loader':<{width}}  {'samples/s':>10}  {'x anchor':>9}")
    for name, t in rows:
        print(f"{name:<{width}}  {n / t:>10,.1f}  {t_anchor / t:>9.1f}")
    print(f"target: prepared >= {TARGET:g}x the raw decode -> {'met' if t_anchor / t_prep >= TARGET else 'NOT met'}")


if __name__ == "__main__":
    main()
