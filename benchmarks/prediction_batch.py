"""Held-out predictions against the prediction batch (``eval.batch``): what changes when the same model predicts the
same images 1, 2 or 8 at a time.

Each detector is trained briefly through the real engine (``harness run``: benchmark profile, its benchmark model
options, one fold, seed 0, ``--epochs`` epochs, one thread), then its final weights predict the held-out fold at
every batch of ``--batches``, through ``harness.engine.predict.predict`` as a run does. Against batch 1, per batch:
whether the detections are byte-identical, the largest score change and the largest box change (coordinates, in
thermal-frame pixels) of a detection and its counterpart (same image and category, nearest box), the detections
without a counterpart within 1 px, and the change of mAP50 and mAP50:95.

Every image is letterboxed on its own to the same ``imgsz x imgsz`` canvas whatever the batch, BatchNorm runs on its
running statistics in eval mode and NMS works per image: what a batch can change is only the arithmetic of the
kernels (a convolution's blocking chosen by the batch size), run the script under ``HARNESS_ONEDNN=0`` to see
torch's oneDNN kernels' part.

    .venv/bin/python benchmarks/prediction_batch.py                                  # every built-in detector
    .venv/bin/python benchmarks/prediction_batch.py --detectors ours,tinydet --epochs 6
    HARNESS_ONEDNN=0 .venv/bin/python benchmarks/prediction_batch.py --detectors ours

``tinydet`` (the example plugin under plugins/) is used from its source folder when it is not installed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import REPO, on_path
from _machine import machine_lines

BUILT_IN = ("ours", "eme", "icafusion", "cmadet")


def changes(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> dict[str, Any]:
    """``harness.engine.predict.detection_changes`` of two COCO result lists (image pixels): the largest score and
    box change of a detection and its counterpart, and the detections without one within 1 px."""
    import numpy as np

    from harness.engine.predict import detection_changes

    ids = sorted({r["image_id"] for r in a} | {r["image_id"] for r in b})

    def per_image(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        out = {i: [] for i in ids}
        for r in rows:
            out[r["image_id"]].append(r)
        dicts = []
        for i in ids:
            xywh = np.array([r["bbox"] for r in out[i]], dtype=np.float64).reshape(-1, 4)
            dicts.append(
                {
                    "boxes": np.concatenate((xywh[:, :2], xywh[:, :2] + xywh[:, 2:]), 1),
                    "scores": [r["score"] for r in out[i]],
                    "labels": [r["category_id"] for r in out[i]],
                }
            )
        return dicts

    ch = detection_changes(per_image(a), per_image(b))
    return {"score": ch.score, "box": ch.box, "unmatched": ch.unmatched}


def canonical(rows: list[dict[str, Any]]) -> list[tuple[Any, ...]]:
    return sorted((r["image_id"], r["category_id"], -r["score"], tuple(r["bbox"])) for r in rows)


def tinydet_available() -> bool:
    from harness.plugins import get_host

    if "tinydet" in get_host().detectors():
        return True
    src = REPO / "plugins" / "harness-tinydet" / "src"
    if not src.is_dir():
        return False
    sys.path.insert(0, str(src))
    from harness_tinydet import plugin

    from harness.plugins import register_plugin

    register_plugin(plugin, "harness_tinydet")
    return True


def measure(detector: str, args: argparse.Namespace, store: Path) -> list[dict[str, Any]]:
    from harness.engine import checkpoint as ckpt
    from harness.engine.data import SampleSource
    from harness.engine.predict import predict
    from harness.evaluation import evaluate_with_config
    from harness.plugins import get_host
    from harness.runner import RunRequest, build_model, fold_indices, plan, run

    config = REPO / "configs" / "benchmark" / f"{detector}.yaml"
    request = RunRequest(
        detector=detector,
        dataset="m3t-synth",
        folds=args.fold,
        seeds=[0],
        profile="benchmark",
        config_files=[str(config)] if config.exists() else [],
        overrides=[f"protocol.epochs={args.epochs}", f"protocol.patience={args.epochs}"],
        store=store,
        progress=False,
        keep_weights="final",
    )
    t0 = time.perf_counter()
    run(request)
    train_s = time.perf_counter() - t0
    p = plan(request)
    planned = p.runs[0]
    cfg, prepared, enc = planned.config, p.prepared, p.encoding
    det = get_host().detector(detector)
    _, val_idx = fold_indices(prepared, planned.fold)
    params = dict((cfg.get("encoding") or {}).get(enc.name) or {})
    source = SampleSource(prepared, val_idx, enc, params)
    weights = next(planned.run.checkpoint_dir.glob("*.pt"))
    model = build_model(det, len(prepared.categories), det.model_channels(source.channels), cfg.get("model") or {})
    model.load_state_dict(ckpt.load(weights)["model"])
    model.eval()
    gt = prepared.coco(val_idx)
    ev = cfg["eval"]
    conf = args.conf if args.conf is not None else ev["conf"]
    import torch

    rows = []
    for kernels in args.predict_kernels:
        torch.backends.mkldnn.enabled = kernels == "onednn"
        results: dict[int, tuple[list[dict[str, Any]], dict[str, Any]]] = {}
        for b in args.batches:
            dets = predict(
                model,
                source,
                int(cfg["protocol"]["imgsz"]),
                b,
                det.input_kind,
                det.thermal_channels,
                "cpu",
                conf,
                ev["iou"],
                ev["max_det"],
                len(prepared.categories),
                name=detector,
            )
            results[b] = (dets, evaluate_with_config(gt, dets, cfg)["metrics"])
        base_dets, base_m = results[args.batches[0]]
        for b in args.batches:
            dets, m = results[b]
            rows.append(
                {
                    "detector": detector,
                    "kernels": kernels,
                    "batch": b,
                    "detections": len(dets),
                    "identical": canonical(dets) == canonical(base_dets),
                    **changes(base_dets, dets),
                    "mAP50": m["mAP50"],
                    "mAP50_95": m["mAP50_95"],
                    "d_mAP50": m["mAP50"] - base_m["mAP50"],
                    "d_mAP50_95": m["mAP50_95"] - base_m["mAP50_95"],
                    "train_s": train_s,
                    "conf": conf,
                }
            )
    torch.backends.mkldnn.enabled = args.onednn
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--detectors", default=",".join((*BUILT_IN, "tinydet")))
    ap.add_argument("--fold", default="P1")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--batches", default="1,2,8", help="comma-separated; the first is the baseline")
    ap.add_argument("--conf", type=float, default=None, help="score threshold [default: the profile's eval.conf]")
    ap.add_argument(
        "--predict-kernels",
        default="onednn,aten",
        help="the convolution kernels predicting: onednn (torch's default) and/or aten (oneDNN off) [default: both]",
    )
    ap.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    args = ap.parse_args()
    args.batches = [int(b) for b in args.batches.split(",")]
    args.predict_kernels = args.predict_kernels.split(",")
    if set(args.predict_kernels) - {"onednn", "aten"}:
        sys.exit(f"--predict-kernels: onednn and/or aten, not {args.predict_kernels}")
    on_path()
    os.chdir(REPO)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    import torch

    from harness.engine.runtime import apply_onednn_setting

    torch.set_num_threads(1)
    onednn = args.onednn = apply_onednn_setting()
    names = args.detectors.split(",")
    if "tinydet" in names and not tinydet_available():
        print("tinydet: not installed and plugins/harness-tinydet not found; left out", file=sys.stderr)
        names.remove("tinydet")
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="prediction-batch-") as tmp:
        for name in names:
            print(f"{name}: training {args.epochs} epochs, predicting at batches {args.batches}", file=sys.stderr)
            rows += measure(name, args, Path(tmp))
    for line in machine_lines():
        print(line)
    print(
        f"m3t-synth fold {args.fold}, benchmark profile, {args.epochs} epochs (oneDNN {'on' if onednn else 'off'}), "
        f"seed 0, one thread, conf {rows[0]['conf'] if rows else '-'}; changes against batch {args.batches[0]}"
    )
    head = (
        f"{'detector':<9} {'kernels':<7} {'batch':>5} {'dets':>5} {'same':>4} {'dscore':>8} {'dbox px':>8} "
        f"{'unm':>3} {'mAP50':>7} {'mAP50:95':>8} {'dmAP50':>8} {'dmAP50:95':>9}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        print(
            f"{r['detector']:<9} {r['kernels']:<7} {r['batch']:>5} {r['detections']:>5} "
            f"{'yes' if r['identical'] else 'no':>4} {r['score']:>8.1e} {r['box']:>8.1e} {r['unmatched']:>3} "
            f"{r['mAP50']:>7.4f} {r['mAP50_95']:>8.4f} {r['d_mAP50']:>+8.1e} {r['d_mAP50_95']:>+9.1e}"
        )
    print("dscore, dbox: largest change of a detection against batch 1 (image pixels); unm: detections without a")
    print("counterpart within 1 px; kernels: oneDNN's convolutions (torch's default) or ATen's (HARNESS_ONEDNN=0)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
