"""Learning curves of the reference detectors on the validation split: what chose the benchmark's epoch budget.

Trains each detector (``configs/benchmark/<detector>.yaml`` at the ``benchmark`` profile, 1 torch thread) on one
fold of m3t-synth under ``protocol.selection=validation`` for ``--epochs`` epochs without early stopping, with the
held-out fold scored each epoch for the log only (``eval.log_held_out``), at most ``--jobs`` runs at a time. Then,
per detector, prints a table (epoch, validation fitness, validation and held-out mAP50:95, epoch seconds) and a
summary: the epoch of the best validation fitness, the least-squares slope of the validation fitness over the
``--window`` epochs ending at each of ``--at`` epochs (points per epoch), and the inflation of the seed's protocol
(best-on-held-out minus last-epoch held-out mAP50:95). ``--json`` writes the curves and the summary.

    python benchmarks/learning_curves.py --store /tmp/curves --epochs 60,cmadet=40 \
        --json docs/learning-curves/p1-seed0.json --plot docs/learning-curves/p1-seed0.png
    python benchmarks/learning_curves.py --store /tmp/curves --read-only   # the tables of runs already made

``--suite rgbt-tiny-synth`` makes the curves of that benchmark suite (``harness.benchmark.SUITES``): its dataset
(``rgbt-tiny``) read from the suite's data folder under ``$HARNESS_DATA`` (written first when missing), its layer
``configs/benchmark-rgbt-tiny/suite.yaml`` and per-detector files, its ablation fold and annotation source (default
``--fold test-T`` with ``dataset.gt=thermal``). ``--set KEY=VALUE`` (repeatable) overrides every run after the
script's own settings, e.g. to compare image sizes (one ``--store`` per size):

    python benchmarks/learning_curves.py --suite rgbt-tiny-synth --store /tmp/curves320 --set protocol.imgsz=320 \
        --epochs 30,icafusion=24,cmadet=24 --json docs/learning-curves/rgbt-tiny-test-T-seed0.json

Each run's CPU seconds (its own and its children's, from ``wait4``) are printed when it ends and kept beside it in
``--store`` (``<detector>-<fold>-seed<seed>.usage.json``; the summary's ``cpu_s_per_epoch``): on a shared machine
they say more of a run's cost than its wall time. A run stopped early (``exit`` not 0) keeps its epochs so far: its
curve is read as far as it goes, and its CPU seconds per epoch count the epoch it was in.

Runs already finished in ``--store`` with the same configuration are reused (``harness run`` skips them). Set
``ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2`` as the benchmark does (``make benchmark``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _common import REPO, on_path

DETECTORS = ("ours", "eme", "icafusion", "cmadet")
DEFAULT_SUITE = "m3t-synth"


def command(det: str, args: argparse.Namespace) -> list[str]:
    sets = [
        "protocol.selection=validation",
        f"protocol.epochs={epochs_of(det, args.epochs)}",
        f"protocol.patience={epochs_of(det, args.epochs)}",
        "eval.log_held_out=true",
        "train.threads=1",
    ]
    if args.suite == DEFAULT_SUITE:
        dataset, configs = "m3t-synth", [REPO / "configs" / "benchmark" / f"{det}.yaml"]
    else:
        suite = suite_of(args.suite)
        own = detector_config(det, suite.profile, suite.detector_configs)
        dataset, configs = suite.dataset, [Path(c) for c in suite.layers()] + ([own] if own else [])
        # the suite's data folder and the annotation source of its ablation variant (the fold's own, e.g. thermal)
        sets = [*suite.data_overrides(), *suite.variant_overrides(suite.ablation_variant), *sets]
    cmd = [sys.executable, "-m", "harness", "run", "--detector", det, "--dataset", dataset, "--folds", args.fold]
    cmd += ["--seeds", str(args.seed), "--store", str(args.store), "--profile", "benchmark", "--no-progress"]
    for c in configs:
        cmd += ["--config", str(c)]
    for s in sets + list(args.set):
        cmd += ["--set", s]
    return cmd


def suite_of(name: str) -> Any:
    """The benchmark suite ``name`` (``harness.benchmark.SUITES``)."""
    on_path()
    from harness.benchmark import get_suite

    return get_suite(name)


def detector_config(det: str, profile: str, folder: str) -> Path | None:
    on_path()
    from harness.benchmark import detector_config as find

    return find(det, profile, folder)


def dataset_of(suite: str) -> str:
    """The dataset (the store's first folder) of the suite's runs."""
    return "m3t-synth" if suite == DEFAULT_SUITE else str(suite_of(suite).dataset)


def epochs_of(det: str, spec: str) -> int:
    """``--epochs``: ``60`` for every detector, or ``60,cmadet=40`` with per-detector exceptions."""
    default, own = 60, {}
    for part in str(spec).split(","):
        if "=" in part:
            k, v = part.split("=", 1)
            own[k.strip()] = int(v)
        elif part.strip():
            default = int(part)
    return own.get(det, default)


def slope(points: list[tuple[float, float]]) -> float | None:
    if len(points) < 2:
        return None
    mx = sum(x for x, _ in points) / len(points)
    my = sum(y for _, y in points) / len(points)
    sxx = sum((x - mx) ** 2 for x, _ in points)
    return sum((x - mx) * (y - my) for x, y in points) / sxx


def read_curve(
    store: Path, det: str, fold: str, seed: int, dataset: str = "m3t-synth", prefer: str | None = None
) -> dict[str, Any] | None:
    """The curve of ``det`` on ``fold``/``seed`` in ``store``; of several encodings (a benchmark store with the
    encoding ablation), ``prefer``'s, else the first by name."""
    logs = sorted((store / dataset / det).glob(f"*/{fold}/seed{seed}/log.jsonl"))
    if not logs:
        return None
    logs = [p for p in logs if p.parts[-4] == prefer] or logs
    rows = []
    for line in logs[0].read_text().splitlines():
        r = json.loads(line)
        m, o = r.get("metrics") or {}, r.get("observed") or {}
        rows.append(
            {
                "epoch": r["epoch"],
                "fitness": None if r.get("fitness") is None else round(100 * r["fitness"], 3),
                "val_mAP50_95": None if m.get("mAP50_95") is None else round(100 * m["mAP50_95"], 3),
                "held_out_mAP50_95": None if o.get("mAP50_95") is None else round(100 * o["mAP50_95"], 3),
                "time_s": r["time_s"],
            }
        )
    usage_file = store / f"{det}-{fold}-seed{seed}.usage.json"
    usage = json.loads(usage_file.read_text()) if usage_file.exists() else {}
    metrics_path = logs[0].parent / "metrics.json"
    final = json.loads(metrics_path.read_text()) if metrics_path.exists() else {}
    return {
        "detector": det,
        "encoding": logs[0].parts[-4],
        "fold": fold,
        "seed": seed,
        "rows": rows,
        "selection": final.get("selection"),
        **({"run_cpu_s": usage["cpu_s"], "run_wall_s": usage["wall_s"]} if usage else {}),
    }


def summarise(curve: dict[str, Any], windows: list[int], at: list[int]) -> dict[str, Any]:
    rows = curve["rows"]
    fit = [(float(r["epoch"]), r["fitness"]) for r in rows if r["fitness"] is not None]
    best = max(fit, key=lambda p: p[1]) if fit else None
    out: dict[str, Any] = {
        "epochs": len(rows),
        "best_validation_epoch": int(best[0]) if best else None,
        "mean_epoch_s": round(sum(r["time_s"] for r in rows) / max(len(rows), 1), 2),
        **({"cpu_s_per_epoch": round(curve["run_cpu_s"] / len(rows), 2)} if curve.get("run_cpu_s") and rows else {}),
        "slope": {},
    }
    out["plateau_epoch"] = {}
    for window in windows:
        for e in at:
            pts = [p for p in fit if e - window < p[0] <= e]
            s = slope(pts) if len(pts) == window else None
            out["slope"][f"{window}@{e}"] = None if s is None else round(s, 3)
        # the first epoch from which the validation-fitness slope over the window stays under each threshold
        for thr in (0.1, 0.2, 0.3):
            first = None
            for k in range(window, len(fit) + 1):
                s = slope(fit[k - window : k])
                if s is not None and s < thr:
                    if first is None:
                        first = int(fit[k - 1][0])
                else:
                    first = None
            out["plateau_epoch"][f"{window}<{thr}"] = first
    # the held-out score of the weights each protocol would keep (the held-out curve is logged, never used)
    held = [(r["epoch"], r["held_out_mAP50_95"]) for r in rows if r["held_out_mAP50_95"] is not None]
    if held:
        best_held = max(held, key=lambda p: p[1])
        last = held[-1]
        by_epoch = dict(held)
        out["held_out"] = {
            "best_epoch": best_held[0],
            "best": best_held[1],
            "last": last[1],
            "inflation_best_minus_last": round(best_held[1] - last[1], 3),
            "at_best_validation_epoch": by_epoch.get(out["best_validation_epoch"]),
            "mean_last_5": round(sum(v for _, v in held[-5:]) / len(held[-5:]), 3),
        }
    return out


def print_curve(curve: dict[str, Any], summary: dict[str, Any]) -> None:
    print(f"\n{curve['detector']}/{curve['encoding']} fold {curve['fold']} seed {curve['seed']}")
    print(f"{'epoch':>5}  {'val fitness':>11}  {'val mAP50:95':>12}  {'held-out mAP50:95':>17}  {'time s':>7}")
    for r in curve["rows"]:
        cells = [
            f"{r['epoch']:>5}",
            f"{r['fitness']:>11.2f}" if r["fitness"] is not None else f"{'-':>11}",
            f"{r['val_mAP50_95']:>12.2f}" if r["val_mAP50_95"] is not None else f"{'-':>12}",
            f"{r['held_out_mAP50_95']:>17.2f}" if r["held_out_mAP50_95"] is not None else f"{'-':>17}",
            f"{r['time_s']:>7.1f}",
        ]
        print("  ".join(cells))
    print(json.dumps(summary))


def plot(curves: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    validated = any(r["fitness"] is not None for c in curves for r in c["rows"])  # none under selection=last
    fig, axes = plt.subplots(1, 2 if validated else 1, figsize=(10 if validated else 5.5, 3.6), squeeze=False)
    ax_val, ax_held = (axes[0][0], axes[0][1]) if validated else (None, axes[0][0])
    for c in curves:
        e = [r["epoch"] for r in c["rows"]]
        label = f"{c['detector']}/{c['encoding']}"
        (line,) = ax_held.plot(e, [r["held_out_mAP50_95"] for r in c["rows"]], label=label)
        if ax_val is not None:
            ax_val.plot(e, [r["fitness"] for r in c["rows"]], color=line.get_color(), label=label)
    if ax_val is not None:
        ax_val.set_title("validation fitness (x100)")
    ax_held.set_title("held-out mAP50:95 (x100, logged only)")
    for ax in axes[0]:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    (ax_val or ax_held).legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", type=Path, required=True)
    p.add_argument("--detectors", default=",".join(DETECTORS))
    p.add_argument(
        "--suite",
        default=DEFAULT_SUITE,
        help="the benchmark suite whose data and configuration files the runs use (harness benchmark --suite)",
    )
    p.add_argument("--fold", help="the fold (default: P1 for m3t-synth, else the suite's ablation fold)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", default="60", help="epochs of each run: N, or N,detector=M,...")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time (one torch thread each)")
    p.add_argument("--window", default="5,10", help="epochs of the slope (comma-separated)")
    p.add_argument("--at", default="20,30,40,50,60", help="epochs at which the slope is reported")
    p.add_argument("--read-only", action="store_true", help="read the runs in --store, train nothing")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a configuration override of every run, after the script's own (e.g. protocol.imgsz=416); repeatable",
    )
    p.add_argument("--json", type=Path, help="write the curves and summaries here")
    p.add_argument("--plot", type=Path, help="write a PNG of the curves here")
    args = p.parse_args()
    dets = [d for d in args.detectors.split(",") if d]
    if args.fold is None:
        args.fold = "P1" if args.suite == DEFAULT_SUITE else suite_of(args.suite).ablation_fold
    if not args.read_only:
        args.store.mkdir(parents=True, exist_ok=True)
        if args.suite != DEFAULT_SUITE:
            on_path()
            from harness.benchmark import ensure_data

            ensure_data(suite_of(args.suite), sys.stderr)
        pending = list(dets)
        running: list[tuple[str, subprocess.Popen[bytes], float]] = []
        while pending or running:
            while pending and len(running) < args.jobs:
                det = pending.pop(0)
                with open(args.store / f"{det}.log", "wb") as log:
                    proc = subprocess.Popen(command(det, args), stdout=subprocess.DEVNULL, stderr=log)
                running.append((det, proc, time.perf_counter()))
                print(f"started {det}", file=sys.stderr)
            time.sleep(2)
            for item in list(running):
                det, proc, t0 = item
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    proc.returncode = os.waitstatus_to_exitcode(status)
                    running.remove(item)
                    wall, cpu = time.perf_counter() - t0, usage.ru_utime + usage.ru_stime
                    print(f"{det}: exit {proc.returncode} after {wall:.0f} s ({cpu:.0f} CPU s)", file=sys.stderr)
                    usage_file = args.store / f"{det}-{args.fold}-seed{args.seed}.usage.json"
                    if not usage_file.exists():  # the first run (a stopped one too), not a reuse of it
                        usage = {"exit": proc.returncode, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1)}
                        usage_file.write_text(json.dumps(usage) + "\n")
    at = [int(x) for x in args.at.split(",") if x]
    out = []
    for det in dets:
        curve = read_curve(
            args.store, det, args.fold, args.seed, dataset_of(args.suite), suite_of(args.suite).grid_encoding
        )
        if curve is None:
            print(f"{det}: no run in {args.store}", file=sys.stderr)
            continue
        summary = summarise(curve, [int(w) for w in args.window.split(",") if w], at)
        print_curve(curve, summary)
        out.append({**curve, "summary": summary})
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    if args.plot and out:
        plot(out, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
