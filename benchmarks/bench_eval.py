"""Evaluation speed on an RGBT-Tiny-sized result set: the harness's ``evaluate`` against plain pycocotools.

Synthetic, seeded: 12,590 images of 640x512, 7 categories, ~15 GT boxes per image (~189k, tiny-object sizes,
1 % crowd), ~100 detections per image (~1.26M: jittered true positives, wrong-class copies, random false
positives). The anchor is pycocotools 2.x used the documented way (``COCO`` index, ``loadRes``, ``evaluate``,
``accumulate``, ``summarize``, per-category AP from ``eval["precision"]``), timed in the same process. The harness
is timed end to end (input checks, engine, per-category AP, operating point), ``--repeats`` times, then once more
with each phase timed (where the time goes). Both sets of statistics are compared; they must be identical.
CPU (process) time is the measure: on a shared machine wall time depends on the other jobs. Target: the harness
>= 12x faster than pycocotools in CPU time.

    .venv/bin/python benchmarks/bench_eval.py            # full size (about 3 minutes of CPU, ~3 GB peak RSS)
    .venv/bin/python benchmarks/bench_eval.py --scale 0.1 --anchor-repeats 1
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import gc
import io
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine_lines  # noqa: E402

TARGET = 12.0

CATEGORIES = ("ship", "car", "cyclist", "pedestrian", "bus", "drone", "plane")


def synthesize(n_images: int, gt_per_image: float, dets_per_image: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    W, H, K = 640, 512, len(CATEGORIES)
    n_gt = rng.poisson(gt_per_image, n_images)
    img_of_gt = np.repeat(np.arange(1, n_images + 1), n_gt)
    G = len(img_of_gt)
    side = np.exp(rng.normal(np.log(12), 0.7, G)).clip(2, 200)  # tiny objects, median 12 px
    aspect = np.exp(rng.normal(0, 0.3, G))
    w, h = side * aspect, side / aspect
    x, y = rng.uniform(0, W - w), rng.uniform(0, H - np.minimum(h, H - 1))
    cat = rng.integers(1, K + 1, G)
    crowd = rng.uniform(size=G) < 0.01
    anns = [
        {
            "id": i + 1,
            "image_id": int(im),
            "category_id": int(c),
            "bbox": [float(a), float(b), float(c_), float(d)],
            "area": float(c_ * d),
            "iscrowd": int(cr),
        }
        for i, (im, c, a, b, c_, d, cr) in enumerate(zip(img_of_gt, cat, x, y, w, h, crowd))
    ]
    # detections: 0-2 jittered copies of each GT (10 % wrong class), then random false positives up to ~100 per image
    copies = rng.integers(0, 3, G)
    src = np.repeat(np.arange(G), copies)
    j = rng.normal(0, 0.15, (len(src), 4))
    tp_boxes = np.stack(
        [x[src] + j[:, 0] * w[src], y[src] + j[:, 1] * h[src], w[src] * np.exp(j[:, 2]), h[src] * np.exp(j[:, 3])],
        axis=1,
    )
    tp_cat = np.where(rng.uniform(size=len(src)) < 0.9, cat[src], rng.integers(1, K + 1, len(src)))
    tp_img = img_of_gt[src]
    tp_score = rng.uniform(0.2, 1.0, len(src))
    per_img_tp = np.bincount(tp_img, minlength=n_images + 1)[1:]
    n_fp = np.maximum(dets_per_image - per_img_tp, 0)
    fp_img = np.repeat(np.arange(1, n_images + 1), n_fp)
    F = len(fp_img)
    fs = np.exp(rng.normal(np.log(12), 0.8, F)).clip(2, 200)
    fp_boxes = np.stack(
        [rng.uniform(0, W - fs), rng.uniform(0, H - fs), fs, fs * np.exp(rng.normal(0, 0.3, F))], axis=1
    )
    fp_cat = rng.integers(1, K + 1, F)
    fp_score = rng.uniform(0.0, 0.8, F)
    boxes = np.concatenate([tp_boxes, fp_boxes]).round(2)
    imgs = np.concatenate([tp_img, fp_img])
    cats = np.concatenate([tp_cat, fp_cat])
    scores = np.concatenate([tp_score, fp_score]).round(5)
    order = np.lexsort((rng.uniform(size=len(imgs)), imgs))  # grouped by image, as a predictor writes them
    dets = [
        {"image_id": int(i), "category_id": int(c), "bbox": b, "score": float(s)}
        for i, c, b, s in zip(imgs[order].tolist(), cats[order].tolist(), boxes[order].tolist(), scores[order].tolist())
    ]
    gt = {
        "info": {"description": "synthetic RGBT-Tiny-sized set"},
        "images": [{"id": i, "width": W, "height": H, "file_name": f"{i:05d}.jpg"} for i in range(1, n_images + 1)],
        "annotations": anns,
        "categories": [{"id": k + 1, "name": n} for k, n in enumerate(CATEGORIES)],
    }
    return gt, dets


def run_pycocotools(gt, dets):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        g = COCO()
        g.dataset = gt
        g.createIndex()
        d = g.loadRes(dets)
        return _summary(COCOeval(g, d, "bbox"))


def _summary(ev: Any) -> tuple[list[float], dict[int, tuple[float, float]]]:
    """Run a COCOeval-like evaluator; its 12 summary stats and, per category, (AP50, AP) over all areas."""
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    per_cat = {}
    for k, cid in enumerate(ev.params.catIds):
        p = ev.eval["precision"][:, :, k, 0, -1]
        per_cat[cid] = (float(p[0][p[0] > -1].mean()), float(p[p > -1].mean()))
    return [float(s) for s in ev.stats[:12]], per_cat


def run_library(gt, dets):
    """faster-coco-eval used the documented way (its own preparation, C++ matching, full C++ accumulation)."""
    from faster_coco_eval.core.coco import COCO
    from faster_coco_eval.core.faster_eval_api import COCOeval_faster

    def quiet(*_: Any, **__: Any) -> None:
        return None

    g = COCO(gt, print_function=quiet)
    return _summary(COCOeval_faster(g, g.loadRes(dets), "bbox", print_function=quiet))


def peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """``(result, CPU s, wall s)`` of one call, after a full garbage collection."""
    gc.collect()
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - t0


#: The harness's phases, as (label, module, function): each is timed in CPU seconds by a wrapper in one extra run.
PHASES = (
    ("input checks (prepare)", "harness.evaluation.coco", "prepare"),
    ("pair layout", "harness.evaluation.engines", "pair_layout"),
    ("IoU of the pairs", "harness.evaluation.engines", "iou_values"),
    ("matching (10 IoU x 4 areas)", "harness.evaluation.engines", "match_all"),
    ("accumulation", "harness.evaluation.engines", "accumulate"),
    ("operating point", "harness.evaluation.coco", "max_f1_operating_point"),
    ("operating point inputs", "harness.evaluation.engines", "_fill_operating_inputs"),
    ("per-category AP", "harness.evaluation.coco", "_per_category"),
)


def phase_times(run: Callable[[], Any]) -> tuple[dict[str, float], float]:
    """CPU seconds per phase of one ``run()``, and its total."""
    import importlib

    spent: dict[str, float] = {}
    saved = []
    for label, module, name in PHASES:
        mod = importlib.import_module(module)
        fn = getattr(mod, name)

        def wrapper(*a: Any, _fn: Any = fn, _label: str = label, **k: Any) -> Any:
            c0 = time.process_time()
            try:
                return _fn(*a, **k)
            finally:
                spent[_label] = spent.get(_label, 0.0) + time.process_time() - c0

        saved.append((mod, name, fn))
        setattr(mod, name, wrapper)
    try:
        _, cpu, _ = timed(run)
    finally:
        for mod, name, fn in saved:
            setattr(mod, name, fn)
    return spent, cpu


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="fraction of the 12,590 images")
    ap.add_argument("--engine", default="faster-coco-eval")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of the harness")
    ap.add_argument("--anchor-repeats", type=int, default=2, help="timed runs of pycocotools (about 1 CPU-minute each)")
    ap.add_argument(
        "--library",
        action="store_true",
        help="also run faster-coco-eval the documented way (its own C++ path) and compare bit for bit",
    )
    args = ap.parse_args()

    from harness.evaluation import evaluate

    n_images = max(1, round(12590 * args.scale))
    t0 = time.perf_counter()
    gt, dets = synthesize(n_images, 15.0, 100, args.seed)
    print(
        f"synthetic set: {n_images:,} images, {len(gt['annotations']):,} GT boxes, {len(dets):,} detections "
        f"(generated in {time.perf_counter() - t0:.1f} s)"
    )
    for line in machine_lines():
        print(line)

    cpu_h, wall_h = [], []
    result = None
    for _ in range(max(1, args.repeats)):
        result, c, w = timed(lambda: evaluate(gt, dets, engine=args.engine))
        cpu_h.append(c)
        wall_h.append(w)
    spent, cpu_p = phase_times(lambda: evaluate(gt, dets, engine=args.engine))

    cpu_a, wall_a = [], []
    ref_stats: list[float] = []
    ref_cat: dict[int, tuple[float, float]] = {}
    for _ in range(max(1, args.anchor_repeats)):
        copies = copy.deepcopy((gt, dets))  # loadRes mutates its input; not timed
        (ref_stats, ref_cat), c, w = timed(lambda: run_pycocotools(*copies))
        copies = None  # freed before the next copy is made
        cpu_a.append(c)
        wall_a.append(w)

    assert result is not None
    ours = [(-1.0 if s is None else s) for s in result["metrics"]["coco_stats"]]
    stat_diff = float(np.max(np.abs(np.array(ours) - np.array(ref_stats))))
    names = {c["id"]: c["name"] for c in gt["categories"]}
    cat_diff = max(
        max(abs(result["per_category"][names[c]]["AP50"] - a50), abs(result["per_category"][names[c]]["AP50_95"] - a))
        for c, (a50, a) in ref_cat.items()
    )
    identical = stat_diff == 0.0 and cat_diff == 0.0
    # pycocotools divides by TP + FP + 2.2e-16, faster-coco-eval (and so the harness) by TP + FP: the last bits of
    # a mean can differ on some sets
    agree = max(stat_diff, cat_diff) <= 1e-12
    print(f"  {'':<34} {'runs':>4} {'CPU min':>9} {'CPU median':>11} {'wall median':>12}")
    for label, cpu, wall in (
        (f"harness evaluate ({args.engine})", cpu_h, wall_h),
        ("pycocotools, as documented", cpu_a, wall_a),
    ):
        print(
            f"  {label:<34} {len(cpu):>4} {min(cpu):>7.2f} s {statistics.median(cpu):>9.2f} s "
            f"{statistics.median(wall):>10.2f} s"
        )
    print("  (pycocotools: index, loadRes, evaluate, accumulate, summarize, per-category AP)")
    print(f"where the harness's CPU time goes (one more run with each phase timed: {cpu_p:.2f} s CPU):")
    for label, _, _ in PHASES:
        if label in spent:
            print(f"  {label:<30} {spent[label]:6.2f} s  {100 * spent[label] / cpu_p:5.1f} %")
    other = cpu_p - sum(spent.values())
    print(f"  {'other (summarize, results)':<30} {other:6.2f} s  {100 * other / cpu_p:5.1f} %")
    print("stats (harness):     " + " ".join(f"{s:.5f}" for s in ours))
    print("stats (pycocotools): " + " ".join(f"{s:.5f}" for s in ref_stats))
    verdict = "IDENTICAL" if identical else ("equal to 1e-12 (last bits)" if agree else "DIFFERENT")
    print(f"max |diff|: 12 stats {stat_diff:.3g}, per-category AP50 and AP50:95 {cat_diff:.3g} -> {verdict}")
    if args.library:
        (lib_stats, lib_cat), c, _ = timed(lambda: run_library(copy.deepcopy(gt), copy.deepcopy(dets)))
        same = lib_stats == ours and all(
            (result["per_category"][names[k]]["AP50"], result["per_category"][names[k]]["AP50_95"]) == v
            for k, v in lib_cat.items()
        )
        said = "bit for bit the harness's" if same else "DIFFERENT from the harness's"
        print(f"faster-coco-eval's own path ({c:.2f} s CPU): stats and per-category AP {said}")
        agree = agree and same
    m = result["metrics"]
    print(f"operating point: conf {m['conf_threshold']:.4f}, precision {m['precision']:.4f}, recall {m['recall']:.4f}")
    ratio = statistics.median(cpu_a) / statistics.median(cpu_h)
    print(
        f"speed-up vs pycocotools (same run): {ratio:.2f}x CPU time (medians; {min(cpu_a) / min(cpu_h):.2f}x "
        f"the minima), {statistics.median(wall_a) / statistics.median(wall_h):.2f}x wall"
    )
    print(
        f"target: >= {TARGET:g}x in CPU time, statistics pycocotools' -> "
        f"{'met' if ratio >= TARGET and agree else 'NOT met'}"
    )
    print(f"peak RSS: {peak_rss_gib():.2f} GiB (the whole process, pycocotools included)")
    return 0 if agree else 1


if __name__ == "__main__":
    sys.exit(main())
