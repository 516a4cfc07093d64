"""Parameters and GFLOPs of the baseline detectors at 640 x 640, batch 1, both inputs, nc = 8, BatchNorm folded,
beside the seed paper's figures; then CPU train-step time at 256 px, batch 8, at a reduced size, as ratios to EME.

    .venv/bin/python benchmarks/baselines_complexity.py [--steps 3] [--scale n] [--threads 1] [--no-timing]

Counts come from models built on the meta device and the harness profiler (``harness.profiling``): "paper"
GFLOPs are thop 0.1.1's module rules on the BN-folded model, x2 (the seed's convention); "exact" is torch
FlopCounterMode (all matmuls, incl. attention); "unused" are parameters the forward never reaches (ICAFusion's
checkpoint-only modules). Timings are noisy on a shared machine: compare the ratios, which share one run.
"""

from __future__ import annotations

import argparse
import time

import torch

from adapters.detectors import cmadet, eme, icafusion
from harness.profiling.flops import exact_flops, paper_flops
from harness.profiling.params import reachable_parameters

SEED = {"icafusion": (120.24, 191.68), "eme": (46.15, 109.20), "cmadet": (33.47, 33.67)}
#: The rebuilt baselines' parameters and paper-convention GFLOPs against the seed's table (relative difference).
TARGET_DIFF = 0.01
BUILD = {"icafusion": icafusion.build, "eme": eme.build, "cmadet": cmadet.build}


def complexity() -> None:
    print(
        f"{'detector':<10} {'params (M)':>11} {'seed':>7} {'diff':>7} {'GFLOPs paper':>13} {'seed':>7} {'diff':>7} "
        f"{'GFLOPs exact':>13} {'unused (M)':>11}"
    )
    worst = 0.0
    for name, build in BUILD.items():
        with torch.device("meta"):
            model = build(8).eval().fuse()
            x = (torch.zeros(1, 3, 640, 640), torch.zeros(1, 3, 640, 640))
        params = sum(p.numel() for p in model.parameters()) / 1e6
        paper = paper_flops(model, x).gflops
        exact = exact_flops(model, x).gflops
        unused = reachable_parameters(model, x).unreachable_count / 1e6
        sp, sg = SEED[name]
        print(
            f"{name:<10} {params:>11.3f} {sp:>7.2f} {100 * (params / sp - 1):>+6.2f}% {paper:>13.3f} {sg:>7.2f} "
            f"{100 * (paper / sg - 1):>+6.2f}% {exact:>13.3f} {unused:>11.3f}"
        )
        worst = max(worst, abs(params / sp - 1), abs(paper / sg - 1))
    print(
        f"target: params and paper GFLOPs within {TARGET_DIFF:.0%} of the seed's -> "
        f"{'met' if worst <= TARGET_DIFF else 'NOT met'} (largest difference {100 * worst:.2f} %)"
    )


def timing(steps: int, scale: str) -> None:
    torch.manual_seed(0)
    b, size = 8, 256
    x = (torch.rand(b, 3, size, size), torch.rand(b, 3, size, size))
    targets = [
        {"boxes": torch.tensor([[20.0, 30.0, 80.0, 100.0], [120.0, 40.0, 200.0, 90.0]]), "labels": torch.tensor([1, 3])}
        for _ in range(b)
    ]
    results = {}
    for name, build in (("eme", BUILD["eme"]), ("icafusion", BUILD["icafusion"]), ("cmadet", BUILD["cmadet"])):
        model = build(8, scale=scale).train()
        opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9)
        times = []
        for i in range(steps + 1):
            t = time.perf_counter()
            loss = sum(model(x, targets).values())
            opt.zero_grad()
            loss.backward()
            opt.step()
            if i:  # the first step warms up
                times.append(time.perf_counter() - t)
        results[name] = (sorted(times)[len(times) // 2], sum(p.numel() for p in model.parameters()) / 1e6)
    anchor = results["eme"][0]
    print(
        f"\ntrain step, {size} px, batch {b}, scale {scale!r}, CPU threads {torch.get_num_threads()}, "
        f"median of {steps} (anchor: eme)"
    )
    print(f"{'detector':<10} {'params (M)':>11} {'s/step':>8} {'x eme':>7}")
    for name, (t, p) in results.items():
        print(f"{name:<10} {p:>11.3f} {t:>8.3f} {t / anchor:>7.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--scale", default="n")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--no-timing", action="store_true")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    complexity()
    if not args.no_timing:
        timing(args.steps, args.scale)


if __name__ == "__main__":
    main()
