"""What choosing the epoch on the held-out fold (the seed's protocol) would have added to a store's numbers.

A store trained under ``protocol.selection=last`` with ``eval.log_held_out`` on (the benchmark profile) logs the
held-out scores of every epoch's EMA weights in each run's ``log.jsonl`` (``observed``, ``observed_fitness``); they
choose nothing. For every finished run this reads them and compares the epoch the seed's protocol would keep (the
best ``observed_fitness``, 0.1 mAP50 + 0.9 mAP50:95, first of equals) with the last epoch, which the store reports.
Prints, per detector and encoding: runs, the mean of best-epoch minus last-epoch held-out mAP50:95 and mAP50 (points),
the largest, and how many runs would have reported an earlier epoch; ``--json`` writes the rows.

    .venv/bin/python benchmarks/selection_inflation.py STORE [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any


def run_inflation(log: Path) -> dict[str, Any] | None:
    """(epoch chosen on held-out, last epoch, mAP50:95 and mAP50 at each) of one run's log; None without a held-out
    curve."""
    rows = []
    from harness.io import read_packed_text

    for line in read_packed_text(log).splitlines():
        if not line.strip():
            continue
        rec = json.loads(line)
        obs, fit = rec.get("observed"), rec.get("observed_fitness")
        if isinstance(obs, dict) and fit is not None:
            rows.append((int(rec["epoch"]), float(fit), float(obs["mAP50_95"]), float(obs["mAP50"])))
    if not rows:
        return None
    best = max(rows, key=lambda r: r[1])  # max keeps the first of equal fitnesses, as the trainer does
    last = rows[-1]
    return {
        "best_epoch": best[0],
        "last_epoch": last[0],
        "d_map50_95": 100 * (best[2] - last[2]),
        "d_map50": 100 * (best[3] - last[3]),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for metrics in sorted(args.store.glob("*/*/*/*/seed*/metrics.json")):
        run = metrics.parent
        dataset, det, enc = run.parts[-5], run.parts[-4], run.parts[-3]
        from harness.store import packed_or_plain

        log = packed_or_plain(run / "log.jsonl")  # the shipped reference results keep it as log.jsonl.gz
        got = run_inflation(log) if log.is_file() else None
        if got is None:
            print(f"{run}: no held-out scores in log.jsonl (eval.log_held_out off?)", file=sys.stderr)
            continue
        groups[(f"{dataset}/{det}", enc)].append({"run": str(run.relative_to(args.store)), **got})
    if not groups:
        print(f"{args.store}: no finished run with a held-out curve", file=sys.stderr)
        return 1
    print(f"{'detector':<22} {'encoding':<9} {'runs':>4} {'d mAP50:95':>10} {'max':>6} {'d mAP50':>8} {'earlier':>8}")
    out = []
    for (det, enc), runs in sorted(groups.items()):
        d95 = [r["d_map50_95"] for r in runs]
        d50 = [r["d_map50"] for r in runs]
        earlier = sum(r["best_epoch"] < r["last_epoch"] for r in runs)
        row = {
            "detector": det,
            "encoding": enc,
            "runs": len(runs),
            "mean_d_map50_95": round(statistics.fmean(d95), 2),
            "max_d_map50_95": round(max(d95), 2),
            "mean_d_map50": round(statistics.fmean(d50), 2),
            "earlier_epoch": earlier,
            "per_run": runs,
        }
        out.append(row)
        print(
            f"{det:<22} {enc:<9} {len(runs):>4} {row['mean_d_map50_95']:>+10.2f} {row['max_d_map50_95']:>+6.2f} "
            f"{row['mean_d_map50']:>+8.2f} {earlier:>5}/{len(runs)}"
        )
    print("points of held-out mAP (best-on-held-out epoch minus last epoch), mean over runs", file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
