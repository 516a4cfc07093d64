"""Cost of the error analysis stored with every run, against the evaluation it follows, on an RGBT-Tiny-sized set.

The same synthetic result set as ``bench_eval.py`` (12,590 images, ~189k tiny GT, ~1.26M detections at full
size). Times ``evaluate`` (what every run pays already) and ``analyse`` (TIDE's error types with their dAP, the
confusion matrix, PR curves, AP per COCO and SAFit size bin, per-image evidence), wall and process CPU time, the
size of the analysis as compact JSON, and the peak RSS of the process.

    .venv/bin/python benchmarks/bench_analysis.py --scale 0.3
    .venv/bin/python benchmarks/bench_analysis.py            # full size
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_eval import peak_rss_gib, synthesize  # noqa: E402


def timed(fn, *args, **kwargs):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - w0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="fraction of the 12,590 images")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from harness.evaluation import evaluate
    from harness.evaluation.analysis import analyse
    from harness.io import dumps_json

    n_images = max(1, int(round(12590 * args.scale)))
    gt, dets = synthesize(n_images, 15.0, 100, args.seed)
    print(f"{n_images} images, {len(gt['annotations'])} GT, {len(dets)} detections")
    ev, ew, ec = timed(evaluate, gt, dets)
    an, aw, ac = timed(analyse, gt, dets, conf_threshold=ev["metrics"]["conf_threshold"])
    assert an["tide"]["mAP50"] == ev["metrics"]["mAP50"]
    size = len(dumps_json(an, indent=None).encode())
    print(f"evaluate: {ew:6.1f} s wall {ec:6.1f} s CPU")
    print(f"analyse:  {aw:6.1f} s wall {ac:6.1f} s CPU  ({aw / ew:.2f}x the evaluation's wall time)")
    print(f"analysis.json {size / 1e6:.1f} MB; peak RSS {peak_rss_gib():.2f} GiB")
    print("dAP50:", {k: round(100 * v, 2) for k, v in an["tide"]["dAP50"].items()})


if __name__ == "__main__":
    main()
