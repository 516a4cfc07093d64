"""SAFit against hand-computed values, and as a matching measure inside the evaluator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.evaluation import ENGINES, evaluate, iou_xywh, nwd_xywh, safit_weight, safit_xywh


def sigmoid(x: float) -> float:
    return 1 / (1 + math.exp(-x))


@pytest.mark.parametrize(
    "gt, dt, iou, nwd, w, safit",
    [
        # 8x8 GT, prediction shifted 2 px diagonally: overlap 6x6 = 36, union 92; W2 = sqrt(2^2 + 2^2)
        ((100, 100, 8, 8), (102, 102, 8, 8), 36 / 92, math.exp(-math.sqrt(8) / 32), sigmoid(-24 / 32), None),
        ((100, 100, 32, 32), (102, 102, 32, 32), 900 / 1148, math.exp(-math.sqrt(8) / 32), 0.5, None),
        (
            (100, 100, 100, 100),
            (102, 102, 100, 100),
            9604 / 10396,
            math.exp(-math.sqrt(8) / 32),
            sigmoid(68 / 32),
            None,
        ),
        ((100, 100, 8, 8), (200, 200, 8, 8), 0.0, math.exp(-math.sqrt(2 * 100**2) / 32), sigmoid(-24 / 32), None),
    ],
)
def test_worked_values(gt, dt, iou, nwd, w, safit):
    expected = w * iou + (1 - w) * nwd
    for anchor in ("center", "topleft"):  # same-size boxes: both anchors agree
        assert nwd_xywh([dt], [gt], anchor=anchor)[0, 0] == pytest.approx(nwd, abs=1e-12)
        assert safit_xywh([dt], [gt], anchor=anchor)[0, 0] == pytest.approx(expected, abs=1e-12)
    assert iou_xywh([dt], [gt])[0, 0] == pytest.approx(iou, abs=1e-12)
    assert safit_weight(gt[2] * gt[3]) == pytest.approx(w, abs=1e-12)


def test_the_papers_example_rounded():
    assert round(float(iou_xywh([[102, 102, 8, 8]], [[100, 100, 8, 8]])[0, 0]), 3) == 0.391
    assert round(float(safit_xywh([[102, 102, 8, 8]], [[100, 100, 8, 8]])[0, 0]), 3) == 0.747
    assert round(float(safit_xywh([[102, 102, 32, 32]], [[100, 100, 32, 32]])[0, 0]), 3) == 0.850
    assert round(float(safit_xywh([[102, 102, 100, 100]], [[100, 100, 100, 100]])[0, 0]), 3) == 0.923
    assert round(float(safit_xywh([[200, 200, 8, 8]], [[100, 100, 8, 8]])[0, 0]), 3) == 0.008


def test_weight_limits():
    assert safit_weight(32 * 32) == 0.5
    assert safit_weight(0) == pytest.approx(sigmoid(-1))  # 0.269 for vanishing boxes
    assert safit_weight(1e8) > 0.99


def test_anchor_changes_nwd_when_sizes_differ():
    # same top-left corner, prediction twice the size of the 8x8 GT
    gt, dt = [[100, 100, 8, 8]], [[100, 100, 16, 16]]
    topleft = math.exp(-math.sqrt(0**2 + 0**2 + 4**2 + 4**2) / 32)  # official code: corners coincide
    center = math.exp(-math.sqrt(4**2 + 4**2 + 4**2 + 4**2) / 32)  # centres (104,104) vs (108,108)
    assert nwd_xywh(dt, gt, anchor="topleft")[0, 0] == pytest.approx(topleft)
    assert nwd_xywh(dt, gt, anchor="center")[0, 0] == pytest.approx(center)
    w = sigmoid(-24 / 32)
    assert safit_xywh(dt, gt, anchor="center")[0, 0] == pytest.approx(w * 0.25 + (1 - w) * center)
    with pytest.raises(ValueError, match="anchor"):
        nwd_xywh(dt, gt, anchor="middle")


def test_integer_boxes_are_not_floored_or_modified():
    gt = np.array([[0, 0, 9, 9]], dtype=np.int64)
    dt = np.array([[0, 0, 8, 8]], dtype=np.int64)
    expected = math.exp(-math.sqrt(0.5**2 * 2) / 32)  # (9 - 8) / 2 = 0.5 per side; flooring would give NWD 1
    assert nwd_xywh(dt, gt, anchor="topleft")[0, 0] == pytest.approx(expected)
    assert gt.tolist() == [[0, 0, 9, 9]] and dt.tolist() == [[0, 0, 8, 8]]


def test_crowd_gt_uses_coco_crowd_iou():
    gt, dt = [[0, 0, 100, 100]], [[10, 10, 20, 20]]
    assert iou_xywh(dt, gt, iscrowd=[True])[0, 0] == 1.0  # intersection over the detection's own area
    assert iou_xywh(dt, gt, iscrowd=[False])[0, 0] == pytest.approx(400 / 10000)


def test_matrix_shapes_and_empty_inputs():
    assert safit_xywh(np.zeros((3, 4)) + [0, 0, 5, 5], [[0, 0, 5, 5], [1, 1, 5, 5]]).shape == (3, 2)
    assert safit_xywh(np.zeros((0, 4)), [[0, 0, 5, 5]]).shape == (0, 1)


def _one_box(dt_box, gt_box=(100, 100, 8, 8)):
    gt = {
        "images": [{"id": 1, "width": 640, "height": 512}],
        "annotations": [
            {
                "id": 1,
                "image_id": 1,
                "category_id": 1,
                "bbox": list(gt_box),
                "area": gt_box[2] * gt_box[3],
                "iscrowd": 0,
            }
        ],
        "categories": [{"id": 1, "name": "person"}],
    }
    return gt, [{"image_id": 1, "category_id": 1, "bbox": list(dt_box), "score": 0.9}]


@pytest.mark.parametrize("engine", ENGINES)
def test_safit_is_reported_beside_standard_map(engine):
    # same size, shifted 9 px: no overlap (IoU 0) but SAFit = (1 - w) exp(-9/32) = 0.513 >= 0.5, < 0.55
    gt, dets = _one_box((109, 100, 8, 8))
    assert 0.5 <= safit_xywh([dets[0]["bbox"]], [gt["annotations"][0]["bbox"]])[0, 0] < 0.55
    r = evaluate(gt, dets, engine=engine, matching="safit")
    assert r["metrics"]["mAP50"] == 0.0  # standard IoU numbers are unchanged
    s = r["metrics"]["safit"]
    assert s["mAP50"] == pytest.approx(1.0) and s["mAP50_95"] == pytest.approx(0.1) and s["AP75"] == 0.0
    assert s["anchor"] == "center" and s["C"] == 32.0
    assert r["per_category"]["person"]["SAFit_AP50"] == pytest.approx(1.0)
    assert r["per_category"]["person"]["AP50"] == 0.0
    assert "safit" not in evaluate(gt, dets, engine=engine)["metrics"]


@pytest.mark.parametrize("engine", ENGINES)
def test_size_bins_are_chosen_by_area_range(engine):
    gt, dets = _one_box((100, 100, 6, 6), gt_box=(100, 100, 6, 6))  # area 36: extremely tiny only
    s = evaluate(gt, dets, engine=engine, matching="safit")["metrics"]["safit"]
    assert s["AP_et"] == pytest.approx(1.0)
    assert s["AP_t"] is None and s["AP_s"] is None and s["AP_m"] is None and s["AP_l"] is None
    assert s["area_ranges"]["tiny"] == [64.0, 256.0]


def test_anchor_option_reaches_the_evaluator():
    # prediction shares the GT's 8x8 top-left corner but is 20x20: IoU 64/400; W2 = sqrt(6^2 + 6^2) from the
    # corner (official code) or sqrt(4 * 6^2) from the centres (104,104) vs (110,110)
    gt, dets = _one_box((100, 100, 20, 20))
    w = sigmoid(-24 / 32)
    tl = w * 0.16 + (1 - w) * math.exp(-math.sqrt(72) / 32)  # 0.572
    ce = w * 0.16 + (1 - w) * math.exp(-12 / 32)  # 0.518
    assert 0.50 < ce < 0.55 < tl < 0.60
    r_tl = evaluate(gt, dets, matching="safit", safit_anchor="topleft")["metrics"]["safit"]
    r_ce = evaluate(gt, dets, matching="safit", safit_anchor="center")["metrics"]["safit"]
    # a TP at 0.50 only for the centre form (1 of 10 thresholds), at 0.50 and 0.55 for the top-left form (2 of 10)
    assert r_ce["mAP50_95"] == pytest.approx(0.1) and r_tl["mAP50_95"] == pytest.approx(0.2)
    assert r_tl["anchor"] == "topleft"


def test_engines_agree_under_safit():
    from evaluation_fixtures import random_coco

    gt, dets = random_coco(seed=21)
    a, b = (evaluate(gt, dets, engine=e, matching="safit") for e in ENGINES)
    keys = ("mAP50", "mAP50_95", "AP75", "AP_et", "AP_t", "AP_s", "AP_m", "AP_l")
    sa, sb = a["metrics"]["safit"], b["metrics"]["safit"]
    assert all((sa[k] is None) == (sb[k] is None) for k in keys)
    assert [sa[k] for k in keys if sa[k] is not None] == pytest.approx(
        [sb[k] for k in keys if sb[k] is not None], abs=1e-12
    )
    assert sa["mAP50"] > a["metrics"]["mAP50"]  # tiny, loosely placed boxes score higher under SAFit
    assert {k: v.get("SAFit_AP50_95") for k, v in a["per_category"].items()} == pytest.approx(
        {k: v.get("SAFit_AP50_95") for k, v in b["per_category"].items()}, abs=1e-12
    )


def test_config_selects_engine_matching_and_anchor():
    from harness.config import load_config
    from harness.evaluation import evaluate_with_config

    cfg = load_config(overrides=["eval.matching=safit", "eval.safit_anchor=topleft", "eval.engine=pycocotools"])
    gt, dets = _one_box((100, 100, 20, 20))
    m = evaluate_with_config(gt, dets, cfg)["metrics"]
    assert (m["engine"], m["matching"], m["safit"]["anchor"]) == ("pycocotools", "safit", "topleft")
    assert m["safit"]["mAP50_95"] == pytest.approx(0.2)
    default = evaluate_with_config(gt, dets, load_config())["metrics"]
    assert (default["engine"], default["matching"]) == ("faster-coco-eval", "iou") and "safit" not in default
