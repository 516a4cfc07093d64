"""Cost of the paired bootstrap over images: time per re-scored resample, and the speed-up of worker processes.

Anchor: ``BootstrapScorer(workers=1)`` scoring one run's resamples in this process, measured in the same run as the
worker variants on the same store. The store is synthetic but scored by the one evaluator: ``--images`` held-out
images per fold with 1-4 objects and ``--dets`` detections per image (a low confidence threshold keeps many). The
numbers of every variant are checked to be identical to the anchor's.

    .venv/bin/python benchmarks/bench_bootstrap.py [--images 100] [--dets 60] [--resamples 40] [--workers 2,4]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=100, help="held-out images of the fold")
    ap.add_argument("--dets", type=float, default=60.0, help="false-positive detections per image (mean)")
    ap.add_argument("--resamples", type=int, default=40)
    ap.add_argument("--workers", default="2", help="comma-separated worker counts to compare with the anchor")
    args = ap.parse_args()

    from harness.report.reader import StoreView
    from harness.report.stats import BootstrapScorer
    from harness.store import RunKey, Store
    from report_fixtures import make_detections, make_gt, write_run

    with tempfile.TemporaryDirectory() as tmp:
        store = Store(tmp)
        rng = np.random.default_rng(0)
        gt = make_gt(args.images, rng)
        dets = make_detections(gt, rng, recall=0.8, jitter=2.0, false_positives=args.dets)
        write_run(store, RunKey("bench", "det", "c2", "F1", 0), gt, dets)
        run = next(iter(StoreView(store).entries("bench")[0].folds["F1"].runs))
        print(
            f"fold: {args.images} images, {len(gt['annotations'])} instances, {len(dets)} detections; "
            f"{args.resamples} resamples + the original images"
        )

        def timed(workers: int) -> tuple[float, np.ndarray]:
            scorer = BootstrapScorer(args.resamples, seed=0, workers=workers)
            t0 = time.perf_counter()
            out = scorer.run_scores("bench", "F1", run)
            return time.perf_counter() - t0, out

        anchor_s, anchor = timed(1)
        per_eval = 1000 * anchor_s / (1 + args.resamples)
        print(f"anchor  workers=1: {anchor_s:7.2f} s  ({per_eval:.1f} ms per re-scored resample)")
        all_same = True
        for w in (int(x) for x in args.workers.split(",") if x.strip()):
            s, out = timed(w)
            same = np.array_equal(np.nan_to_num(out, nan=-1), np.nan_to_num(anchor, nan=-1))
            all_same = all_same and same
            print(f"        workers={w}: {s:7.2f} s  speed-up x{anchor_s / s:.2f} vs anchor; identical numbers: {same}")
        print(
            f"target: identical numbers with any number of workers -> {'met' if all_same else 'NOT met'} "
            f"(workers pay off once the resamples outweigh their start-up, about a second each)"
        )


if __name__ == "__main__":
    main()
