"""Fold aggregation (absent categories excluded), the sample-matched guard, and the detectron2-style evaluator."""

from __future__ import annotations

import statistics

import numpy as np
import pytest

from evaluation_fixtures import random_coco
from harness.evaluation import EvaluationError, SampleMismatchError, aggregate_folds, check_sample_matched, evaluate
from harness.store import RunKey, Store


def _fold(name, map50, cats, images=10, instances=None, sha="a" * 40):
    per_cat = {
        n: {"AP50": ap, "AP50_95": None if ap is None else ap / 2, "instances": 0 if ap is None else 5}
        for n, ap in cats.items()
    }
    inst = instances if instances is not None else sum(v["instances"] for v in per_cat.values())
    return {
        "run": {"dataset": "m3t", "detector": "ours", "encoding": "c2", "fold": name, "seed": 0},
        "support": {
            "images": images,
            "instances": inst,
            "image_ids_sha1": sha,
            "categories": {n: v["instances"] for n, v in per_cat.items()},
        },
        "metrics": {"mAP50": map50, "mAP50_95": map50 / 2, "precision": 0.5, "recall": 0.4},
        "per_category": per_cat,
    }


def test_absent_category_is_excluded_from_its_mean_not_counted_as_zero():
    folds = [
        _fold("P1", 0.6, {"crack": 0.5, "window": 0.9}),
        _fold("P2", 0.8, {"crack": None, "window": 0.8}),  # no crack in the held-out projects of P2
        _fold("P3", 0.7, {"crack": 0.7, "window": 0.7}),
    ]
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


def test_the_runners_path_from_model_outputs_scores_exactly_what_evaluate_scores():
    """A run turns the detector's eval-mode outputs (xyxy tensors, 0-based labels) into COCO results with
    ``detections_to_coco`` and scores them with ``evaluate``: the same numbers, to the last bit, as ``evaluate`` on
    those detections written by hand; predictions on an image outside the ground truth are refused there."""
    import torch

    from harness.engine.predict import detections_to_coco

    gt, dets = random_coco(seed=33, dense_image=False)
    by_image: dict[int, list] = {}
    for d in dets:
        by_image.setdefault(d["image_id"], []).append(d)
    converted, by_hand = [], []
    for im in gt["images"]:
        ds = by_image.get(im["id"], [])
        xyxy = np.array([[x, y, x + w, y + h] for x, y, w, h in (d["bbox"] for d in ds)], np.float32).reshape(-1, 4)
        scores = np.array([d["score"] for d in ds], np.float32)
        out = {
            "boxes": torch.from_numpy(xyxy),
            "scores": torch.from_numpy(scores),
            "labels": torch.tensor([d["category_id"] - 1 for d in ds], dtype=torch.int64),
        }
        converted += detections_to_coco(out, im["id"], None, len(gt["categories"]))
        by_hand += [
            {
                "image_id": im["id"],
                "category_id": d["category_id"],
                "score": float(s),
                "bbox": [float(b[0]), float(b[1]), float(b[2]) - float(b[0]), float(b[3]) - float(b[1])],
            }
            for d, b, s in zip(ds, xyxy, scores)
        ]
    assert len(converted) == len(dets) == len(by_hand)
    assert evaluate(gt, converted) == evaluate(gt, by_hand)
    stray = {**converted[0], "image_id": 99999}
    with pytest.raises(EvaluationError, match="not in the ground truth"):
        evaluate(gt, converted + [stray], strict=True)
