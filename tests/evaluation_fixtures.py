"""Seeded COCO fixtures and a plain-pycocotools reference, shared by the evaluation tests."""

from __future__ import annotations

import contextlib
import copy
import io
from typing import Any

import numpy as np


def random_coco(
    seed: int,
    n_images: int = 40,
    n_cats: int = 4,
    absent_cat: bool = True,
    crowd: float = 0.04,
    empty_images: int = 5,
    dense_image: bool = True,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """GT and detections with the cases COCO cares about.

    Sizes span small/medium/large; some GT are crowd; the last category has no GT but gets detections; a few
    images have no GT; one image has more than 100 detections of one category (maxDets truncation); some scores
    tie exactly.
    """
    rng = np.random.default_rng(seed)
    cats = [{"id": k + 1, "name": f"cat{k + 1}"} for k in range(n_cats)]
    gt_cats = n_cats - 1 if absent_cat else n_cats
    images = [{"id": i, "width": 640, "height": 512, "file_name": f"{i}.jpg"} for i in range(1, n_images + 1)]
    anns: list[dict[str, Any]] = []
    for im in images[: n_images - empty_images]:
        for _ in range(int(rng.integers(1, 9))):
            side = float(np.exp(rng.uniform(np.log(3), np.log(180))))
            w, h = side, side * float(rng.uniform(0.5, 2.0))
            x, y = float(rng.uniform(0, 640 - w)), float(rng.uniform(0, 512 - min(h, 500)))
            anns.append(
                {
                    "id": len(anns) + 1,
                    "image_id": im["id"],
                    "category_id": int(rng.integers(1, gt_cats + 1)),
                    "bbox": [x, y, w, h],
                    "area": w * h,
                    "iscrowd": int(rng.uniform() < crowd),
                }
            )
    dets: list[dict[str, Any]] = []
    for a in anns:
        for _ in range(int(rng.integers(0, 3))):
            x, y, w, h = a["bbox"]
            j = rng.normal(0, 0.12, 4)
            cat = a["category_id"] if rng.uniform() < 0.85 else int(rng.integers(1, n_cats + 1))
            dets.append(
                {
                    "image_id": a["image_id"],
                    "category_id": cat,
                    "bbox": [x + j[0] * w, y + j[1] * h, w * float(np.exp(j[2])), h * float(np.exp(j[3]))],
                    "score": round(float(rng.uniform(0.2, 1.0)), 2),
                }
            )  # rounding makes ties
    for im in images:
        for _ in range(int(rng.integers(0, 12))):
            s = float(rng.uniform(4, 120))
            dets.append(
                {
                    "image_id": im["id"],
                    "category_id": int(rng.integers(1, n_cats + 1)),
                    "bbox": [float(rng.uniform(0, 500)), float(rng.uniform(0, 400)), s, s * 0.8],
                    "score": round(float(rng.uniform(0.0, 0.8)), 2),
                }
            )
    if dense_image:
        for _ in range(130):
            s = float(rng.uniform(5, 60))
            dets.append(
                {
                    "image_id": 1,
                    "category_id": 1,
                    "bbox": [float(rng.uniform(0, 500)), float(rng.uniform(0, 400)), s, s],
                    "score": float(rng.uniform(0.0, 1.0)),
                }
            )
    order = rng.permutation(len(dets))
    dets = [dets[i] for i in order]
    return {"info": {}, "images": images, "annotations": anns, "categories": cats}, dets


def canonical(dets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The detections in the evaluator's canonical order (image, category, descending score, then x, y, w, h),
    sorted here independently of the harness's code. pycocotools matches equal scores in input order, so this is
    the order in which plain pycocotools is the reference."""
    return sorted(dets, key=lambda d: (d["image_id"], d["category_id"], -d["score"], *d["bbox"]))


def pycocotools_reference(
    gt: dict[str, Any], dets: list[dict[str, Any]], in_canonical_order: bool = True
) -> tuple[list[float], dict[int, tuple]]:
    """Stats and per-category (AP50, AP50:95) by plain pycocotools, the way its documentation uses it, on the
    detections in canonical order (or as given)."""
    if in_canonical_order:
        dets = canonical(dets)
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        g = COCO()
        g.dataset = copy.deepcopy(gt)
        g.createIndex()
        d = g.loadRes(copy.deepcopy(dets))
        ev = COCOeval(g, d, "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    prec = ev.eval["precision"]
    per_cat = {}
    for k, cid in enumerate(ev.params.catIds):
        p = prec[:, :, k, 0, -1]
        p50 = p[0]
        per_cat[cid] = (
            float(p50[p50 > -1].mean()) if (p50 > -1).any() else None,
            float(p[p > -1].mean()) if (p > -1).any() else None,
        )
    return [float(s) for s in ev.stats], per_cat


def nullable(stats: list[float]) -> list[float | None]:
    return [None if s < 0 else s for s in stats]
