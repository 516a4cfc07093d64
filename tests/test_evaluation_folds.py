"""Fold aggregation (absent categories excluded), the sample-matched guard, and the detectron2-style evaluator."""

from __future__ import annotations

import statistics

import numpy as np
import pytest

from evaluation_fixtures import random_coco
from harness.evaluation import (COCOEvaluator, EvaluationError, SampleMismatchError, aggregate_folds,
                                check_sample_matched, evaluate)
from harness.store import RunKey, Store


def _fold(name, map50, cats, images=10, instances=None, sha="a" * 40):
    per_cat = {n: {"AP50": ap, "AP50_95": None if ap is None else ap / 2, "instances": 0 if ap is None else 5}
               for n, ap in cats.items()}
    inst = instances if instances is not None else sum(v["instances"] for v in per_cat.values())
    return {"run": {"dataset": "m3t", "detector": "ours", "encoding": "c2", "fold": name, "seed": 0},
            "support": {"images": images, "instances": inst, "image_ids_sha1": sha,
                        "categories": {n: v["instances"] for n, v in per_cat.items()}},
            "metrics": {"mAP50": map50, "mAP50_95": map50 / 2, "precision": 0.5, "recall": 0.4},
            "per_category": per_cat}


def test_absent_category_is_excluded_from_its_mean_not_counted_as_zero():
    folds = [_fold("P1", 0.6, {"crack": 0.5, "window": 0.9}),
             _fold("P2", 0.8, {"crack": None, "window": 0.8}),  # no crack in the held-out projects of P2
             _fold("P3", 0.7, {"crack": 0.7, "window": 0.7})]
    agg = aggregate_folds(folds)
    crack = agg["per_category"]["crack"]["AP50"]
    assert crack["values"] == [0.5, None, 0.7]
    assert crack["mean"] == pytest.approx(0.6)  # counting the absent fold as zero would give 0.4
    assert crack["sd"] == pytest.approx(statistics.stdev([0.5, 0.7]))
    assert crack["n"] == 2
    assert agg["per_category"]["crack"]["folds_present"] == 2
    assert agg["per_category"]["crack"]["instances"] == 10
    m = agg["metrics"]["mAP50"]
    assert m["mean"] == pytest.approx(0.7) and m["sd"] == pytest.approx(0.1) and m["n"] == 3
    assert agg["folds"] == ["P1", "P2", "P3"]
    assert agg["support"]["images"] == 30 and agg["support"]["categories"]["crack"] == 10


def test_single_fold_has_no_sd_and_empty_input_is_an_error():
    agg = aggregate_folds([_fold("all", 0.5, {"crack": 0.5})])
    assert agg["metrics"]["mAP50"]["sd"] is None and agg["metrics"]["mAP50"]["mean"] == 0.5
    with pytest.raises(EvaluationError, match="no fold results"):
        aggregate_folds([])


def test_aggregate_real_evaluations_with_safit():
    results = []
    for seed in (30, 31):
        gt, dets = random_coco(seed=seed)
        results.append(evaluate(gt, dets, matching="safit"))
    agg = aggregate_folds(results)
    assert agg["metrics"]["mAP50"]["mean"] == pytest.approx(np.mean([r["metrics"]["mAP50"] for r in results]))
    assert agg["metrics"]["safit_mAP50"]["n"] == 2
    assert agg["per_category"]["cat4"]["AP50"]["n"] == 0 and agg["per_category"]["cat4"]["AP50"]["mean"] is None


def test_guard_accepts_matched_and_refuses_unmatched_naming_the_difference():
    a = _fold("P1", 0.6, {"crack": 0.5})
    b = dict(_fold("P1", 0.7, {"crack": 0.6}), run={**a["run"], "detector": "eme"})
    assert check_sample_matched([a, b]) is None
    c = _fold("P1", 0.7, {"crack": 0.6}, images=9, instances=7, sha="b" * 40)
    c["run"] = {**a["run"], "detector": "icafusion"}
    with pytest.raises(SampleMismatchError) as err:
        check_sample_matched([a, b, c])
    msg = str(err.value)
    assert "fold 'P1'" in msg and "image-id hash" in msg and "image count: 10" in msg and "vs 9" in msg
    assert "instance count: 5" in msg and "m3t/icafusion/c2/P1/0" in msg and "allow=True" in msg
    label = check_sample_matched([a, b, c], allow=True)
    assert label == "NOT sample-matched: image-id hash, image count, instance count differ"


def test_guard_compares_within_a_fold_only():
    a = _fold("P1", 0.6, {"crack": 0.5})
    other = _fold("P2", 0.6, {"crack": 0.5}, images=50, instances=80, sha="c" * 40)
    assert check_sample_matched([a, other]) is None  # different folds hold different images by design
    assert check_sample_matched({"x": a}) is None


def test_guard_reads_runs_from_the_store(tmp_path):
    store = Store(tmp_path)
    gt, dets = random_coco(seed=32)
    full = evaluate(gt, dets)
    fewer = dict(gt, images=gt["images"][:-3])
    fewer["annotations"] = [x for x in gt["annotations"] if x["image_id"] in {im["id"] for im in fewer["images"]}]
    part = evaluate(fewer, dets)
    runs = []
    for det, res in (("ours", full), ("eme", part)):
        run = store.run(RunKey("m3t-synth", det, "c2", "P1", 0))
        run.write_metrics(res)
        run.set_status("finished")
        runs.append(run)
    with pytest.raises(SampleMismatchError, match=r"image count: 40 \(m3t-synth/ours/c2/P1/seed0\) vs 37"):
        check_sample_matched(runs)


@pytest.mark.parametrize("as_tensor", [False, True])
def test_coco_evaluator_process_equals_evaluate(as_tensor):
    import torch

    gt, dets = random_coco(seed=33, dense_image=False)
    ev = COCOEvaluator(gt)
    ev.reset()
    by_image = {}
    for d in dets:
        by_image.setdefault(d["image_id"], []).append(d)
    ids = [im["id"] for im in gt["images"]]
    for start in range(0, len(ids), 8):  # batches of 8 images
        batch_ids, outputs = ids[start:start + 8], []
        for i in batch_ids:
            ds = by_image.get(i, [])
            boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (d["bbox"] for d in ds)]).reshape(-1, 4)
            out = {"boxes": boxes, "scores": np.array([d["score"] for d in ds]),
                   "labels": np.array([d["category_id"] - 1 for d in ds], dtype=np.int64)}
            if as_tensor:
                out = {k: torch.as_tensor(v) for k, v in out.items()}
            outputs.append(out)
        ev.process(batch_ids, outputs)
    got = ev.evaluate()
    # xyxy -> xywh round trip changes the last bits of the boxes, so compare to a tolerance
    assert got["metrics"]["coco_stats"] == pytest.approx(evaluate(gt, dets)["metrics"]["coco_stats"], abs=1e-9)
    assert got["metrics"]["unprocessed_images"] == 0
    assert len(ev.detections) == len(dets)
    with pytest.raises(EvaluationError, match="processed twice"):
        ev.process([ids[0]], [outputs[0]])
    with pytest.raises(EvaluationError, match="not in the ground truth"):
        ev.process([99999], [outputs[0]])
    ev.reset()
    assert ev.evaluate()["metrics"]["unprocessed_images"] == len(ids)
