"""Build time and folder size of ``harness report`` on a store shaped like the demo's, as ``make demo`` runs it.

The store (built once under ``--store``, reused after) has the demo's shape: the small synthetic M3T prepared as
``harness prepare --dataset m3t-synth`` does (112 held-out images over the four project-grouped folds), four
detectors on every fold and ours without a thermal channel on P1, each run with its ``config.yaml`` (naming the
prepared cache), ``gt.json``, ``predictions.json`` (up to 100 detections per image, as the demo keeps: a few found
objects among many low-confidence boxes, like a model trained for five epochs), ``metrics.json`` and
``analysis.json`` from the one evaluator, a five-epoch ``log.jsonl`` and a complexity record. The detections are
synthetic, not trained: the report reads the store, not the models, so its cost is the same.

Times ``build_report(store, out, resamples=50, workers=2)`` (the demo's ``harness report --resamples 50
--workers 2``), wall and CPU time of this process and its workers, and the size of the report folder (target: under
25 MB). ``--code DIR`` times another checkout of the harness (e.g. the previous commit) on the same store: the anchor;
run both in turn, several times, and compare CPU times (wall times follow a shared machine's load).

    HARNESS_DATA=... HARNESS_CACHE=... .venv/bin/python benchmarks/bench_report.py --store /tmp/demo-like \\
        --out /tmp/demo-report [--code /path/to/old/checkout]
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DETECTORS = {"ours": ("c2", 0.35), "eme": ("ir8", 0.45), "icafusion": ("ir8", 0.5), "cmadet": ("ir8", 0.4)}
EPOCHS = 5
TARGET_MB = 25.0  # the demo's report folder


def detections(gt: dict, rng: np.random.Generator, recall: float, per_image: int = 100) -> list[dict]:
    """A weak detector's output: each object found with probability ``recall`` (box jittered, category right 80 %
    of the time), the rest of the image's ``per_image`` boxes low-confidence background."""
    ncat = len(gt["categories"])
    by_image: dict[int, list[dict]] = {im["id"]: [] for im in gt["images"]}
    for a in gt["annotations"]:
        if rng.random() < recall:
            x, y, w, h = a["bbox"]
            j = 0.15 * max(w, h)
            cat = a["category_id"] if rng.random() < 0.8 else int(rng.integers(1, ncat + 1))
            by_image[a["image_id"]].append(
                {
                    "image_id": a["image_id"],
                    "category_id": cat,
                    "score": float(rng.uniform(0.05, 0.7)),
                    "bbox": [
                        x + rng.normal(0, j),
                        y + rng.normal(0, j),
                        max(2.0, w + rng.normal(0, j)),
                        max(2.0, h + rng.normal(0, j)),
                    ],
                }
            )
    sizes = {im["id"]: (im["width"], im["height"]) for im in gt["images"]}
    out = []
    for iid, dets in by_image.items():
        W, H = sizes[iid]
        for _ in range(per_image - len(dets)):
            w, h = float(rng.uniform(6, 60)), float(rng.uniform(6, 60))
            dets.append(
                {
                    "image_id": iid,
                    "category_id": int(rng.integers(1, ncat + 1)),
                    "score": float(rng.exponential(0.04)) + 0.001,
                    "bbox": [float(rng.uniform(0, W - w)), float(rng.uniform(0, H - h)), w, h],
                }
            )
        out += dets
    return out


def build_store(root: Path) -> None:
    from harness.cache import fold_indices, prepare, resolve_folds
    from harness.config import load_config
    from harness.evaluation import evaluate
    from harness.evaluation.analysis import store_analysis
    from harness.io import atomic_write_json
    from harness.runner import run_config
    from harness.store import RunKey, Store

    cfg = load_config(profile="demo")
    prepared = prepare("m3t-synth", cfg, progress=False)
    folds = resolve_folds("m3t-synth", prepared, cfg)
    store = Store(root)
    rng = np.random.default_rng(0)
    jobs = [(det, enc, recall, f) for det, (enc, recall) in DETECTORS.items() for f in folds]
    jobs.append(("ours", "none", 0.3, folds[0]))
    for det, enc, recall, fold in jobs:
        key = RunKey("m3t-synth", det, enc, fold.name, 0)
        run = store.run(key)
        run.path.mkdir(parents=True, exist_ok=True)
        run.set_status("running", config_hash="bench")
        run.write_config(
            run_config(
                cfg, key, {"prepared_fingerprint": prepared.manifest.get("fingerprint"), "prepared_key": prepared.key}
            )
        )
        _, val = fold_indices(prepared, fold)
        gt = prepared.coco(val)
        dets = detections(gt, rng, recall)
        ev = evaluate(gt, dets)
        atomic_write_json(run.gt_path, gt, indent=None)
        atomic_write_json(run.predictions_path, dets, indent=None)
        gflops = {"ours": 8.7, "eme": 5.1, "icafusion": 9.8, "cmadet": 11.2}[det]
        run.write_metrics(
            {
                **ev,
                "train": {"epochs": EPOCHS, "imgsz": 128},
                "environment": {"device": "cpu", "threads": 1, "torch": "bench"},
                "complexity": {
                    "schema": 1,
                    "model_options": {"scale": "n"},
                    "imgsz": 128,
                    "params": 3_000_000,
                    "params_fused": 3_000_000,
                    "bn_folded": True,
                    "unused_params": 0,
                    "gflops": {"640": {"paper": gflops, "exact": gflops * 1.01}},
                },
            }
        )
        store_analysis(run, gt, dets, cfg, ev["metrics"]["conf_threshold"])
        with open(run.log_path, "w", encoding="utf-8") as fh:
            for e in range(1, EPOCHS + 1):
                fh.write(
                    json.dumps(
                        {
                            "epoch": e,
                            "loss": {"box": 3.0 / e, "cls": 4.0 / e, "dfl": 2.0 / e},
                            "metrics": {"mAP50": 0.01 * e, "mAP50_95": 0.004 * e},
                        }
                    )
                    + "\n"
                )
        run.set_status("finished", config_hash="bench")
    atomic_write_json(
        store.dataset_path("m3t-synth"), {"dataset": "m3t-synth", "thermal": "radiometric", "sensing_stage": True}
    )
    print(f"store: {len(jobs)} runs in {root}")


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", type=Path, required=True, help="the demo-like store (built here when missing)")
    ap.add_argument("--out", type=Path, required=True, help="report folder")
    ap.add_argument("--code", type=Path, default=None, help="time this checkout of the harness instead (anchor)")
    ap.add_argument("--resamples", type=int, default=50)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    sys.path.insert(0, str(args.code or REPO))
    sys.path.insert(1, str(REPO / "benchmarks"))
    import torch

    torch.set_num_threads(1)
    import harness
    from _machine import machine_lines

    print("\n".join(machine_lines()))
    print(f"harness from {Path(harness.__file__).parent.parent}")
    if not (args.store / "m3t-synth").is_dir():
        build_store(args.store)
    from harness.report import build_report

    kwargs = {"resamples": args.resamples, "workers": args.workers}
    w0, c0 = time.perf_counter(), time.process_time()
    report = build_report(args.store, out=args.out, **kwargs)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    pictures = sum(len(g.thumbs) for s in report.sections for g in getattr(s, "galleries", []))
    print(
        f"build_report(resamples={args.resamples}, workers={args.workers}): {wall:.1f} s wall, {cpu:.1f} s CPU "
        f"here + {kids.ru_utime + kids.ru_stime:.1f} s CPU in workers; {len(report.tables)} tables, "
        f"{sum(len(s.figures) for s in report.sections)} figures, {pictures} pictures"
    )
    size = folder_bytes(args.out) / 1e6
    print(
        f"report folder {args.out}: {size:.2f} MB (report.html {(args.out / 'report.html').stat().st_size / 1e6:.2f} "
        f"MB)"
    )
    print(f"target: report folder < {TARGET_MB:g} MB: {'met' if size < TARGET_MB else 'NOT met'}")


if __name__ == "__main__":
    main()
