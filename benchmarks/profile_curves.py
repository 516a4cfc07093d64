"""Learning curves of candidate benchmark profiles: the numbers behind ``configs/profiles/benchmark.yaml``.

Trains ``ours`` (YOLOv8n size, c2) on the seed's ablation split P4+P5 of the small m3t-synth set at each candidate
image size for the same number of epochs (the demo's optimiser), one torch thread per run, then prints per epoch the
held-out mAP50, mAP50:95 and the categories beyond windows with AP50 > 0, and each run's training time. Runs are kept
in ``--store`` (a finished one is reused), so ``--print-only`` reprints the table.

    python benchmarks/profile_curves.py --sizes 192,256,320 --epochs 30 --store results/profile-curves

The CPU is named in the output; candidates trained side by side share it, so compare their times within one call.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def train(size: int, epochs: int, store: Path) -> subprocess.Popen:
    from harness.benchmark import detector_config, job_command
    from harness.sweep import SweepJob

    cfg = detector_config("ours")
    job = SweepJob(
        "ours",
        "m3t-synth",
        "c2",
        "P4+P5",
        0,
        str(store / f"imgsz{size}"),
        profile="benchmark",
        config_files=(str(cfg),) if cfg else (),
        overrides=(f"protocol.imgsz={size}", f"protocol.epochs={epochs}", f"protocol.patience={epochs}"),
    )
    return subprocess.Popen(job_command(job), stdout=subprocess.DEVNULL)


def curve(store: Path, size: int) -> list[dict]:
    logs = sorted((store / f"imgsz{size}").glob("m3t-synth/ours/c2/P4+P5/seed0/log.jsonl"))
    return [json.loads(line) for line in logs[0].read_text().splitlines() if line.strip()] if logs else []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="192,256,320")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--store", type=Path, default=Path("results/profile-curves"))
    ap.add_argument("--every", type=int, default=5, help="print every Nth epoch")
    ap.add_argument("--print-only", action="store_true")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    if not args.print_only:
        procs = [train(s, args.epochs, args.store) for s in sizes]
        if any(p.wait() for p in procs):
            sys.exit("a candidate run failed; see its status.json in --store")
    from harness.benchmark import cpu_name

    print(f"# ours (n), c2, fold P4+P5, 1 thread per run; CPU: {cpu_name()}")
    print(f"{'imgsz':>5} {'epoch':>5} {'mAP50':>6} {'50:95':>6} {'>0':>3}  AP50 beyond windows")
    for s in sizes:
        rows = curve(args.store, s)
        for r in rows:
            if r["epoch"] % args.every and r["epoch"] != len(rows):
                continue
            m = r["metrics"]
            cats = {k: v for k, v in (m.get("AP50_per_category") or {}).items() if k != "window"}
            pos = sum(1 for v in cats.values() if v and v > 0)
            print(
                f"{s:>5} {r['epoch']:>5} {m['mAP50']:>6.3f} {m['mAP50_95']:>6.3f} {pos:>3}  "
                + " ".join(f"{k[:5]}={v:.2f}" for k, v in cats.items() if v)
            )
        if rows:
            print(f"{s:>5} total training time {sum(r['time_s'] for r in rows):.0f} s over {len(rows)} epochs")


if __name__ == "__main__":
    main()
