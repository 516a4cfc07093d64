"""The error analysis stored with every run: TIDE errors, confusion matrix, PR curves, size bins, per-image evidence."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evaluation_fixtures import canonical, random_coco
from harness.evaluation import analysis as A
from harness.evaluation import evaluate
from harness.evaluation.analysis import NO_ANALYSIS, analyse, analysis_of, store_analysis
from harness.evaluation.inputs import prepare
from harness.store import RunKey, Store


def _hand_fixture():
    """Two categories A (1) and B (2), two images; every value below is computed by hand in the tests.

    image 1: GT g1 A [0,0,10,10], g2 A [50,50,10,10], g3 B [20,20,10,10]; image 2: GT g4 B [0,0,20,20].
    d1 A .9 = g1 (TP); d2 A .8 = g1 (duplicate); d3 B .7 = g2 (classification); d4 A .6 on nothing (background);
    d5 B .5 = g3 (TP); d6 B .4 [0,0,20,8] on g4, IoU 0.4 (localisation); d7 A .3 = g4 (classification, but d6
    scores higher on g4, so fixing classification removes d7 rather than matching it).
    """
    gt = {
        "images": [{"id": 1, "width": 100, "height": 100}, {"id": 2, "width": 100, "height": 100}],
        "categories": [{"id": 1, "name": "A"}, {"id": 2, "name": "B"}],
        "annotations": [
            {"id": 11, "image_id": 1, "category_id": 1, "bbox": [0, 0, 10, 10], "area": 100, "iscrowd": 0},
            {"id": 12, "image_id": 1, "category_id": 1, "bbox": [50, 50, 10, 10], "area": 100, "iscrowd": 0},
            {"id": 13, "image_id": 1, "category_id": 2, "bbox": [20, 20, 10, 10], "area": 100, "iscrowd": 0},
            {"id": 14, "image_id": 2, "category_id": 2, "bbox": [0, 0, 20, 20], "area": 400, "iscrowd": 0},
        ],
    }
    dets = [
        (1, 1, 0.9, [0, 0, 10, 10]),
        (1, 1, 0.8, [0, 0, 10, 10]),
        (1, 2, 0.7, [50, 50, 10, 10]),
        (1, 1, 0.6, [80, 80, 10, 10]),
        (1, 2, 0.5, [20, 20, 10, 10]),
        (2, 2, 0.4, [0, 0, 20, 8]),
        (2, 1, 0.3, [0, 0, 20, 20]),
    ]
    return gt, [{"image_id": i, "category_id": c, "score": s, "bbox": b} for i, c, s, b in dets]


# hand-computed: AP_A = 51/101 (precision 1 up to recall 0.5), AP_B = 25.5/101 (interpolated precision 0.5)
BASE = (51 / 101 + 25.5 / 101) / 2
# classification fixed: d3 becomes A's TP on g2 -> AP_A = (51 + 50 * 2/3) / 101, AP_B = 51 / 101
CLS = ((51 + 50 * 2 / 3) / 101 + 51 / 101) / 2
# localisation fixed: d6 becomes B's TP on g4 -> AP_B = 2/3 at every recall point
LOC = (51 / 101 + 2 / 3) / 2


def test_hand_computed_tide_errors():
    gt, dets = _hand_fixture()
    an = analyse(gt, dets)
    t = an["tide"]
    assert t["mAP50"] == pytest.approx(BASE, abs=1e-12)
    assert t["counts"] == {
        "classification": 2,
        "localisation": 1,
        "both": 0,
        "duplicate": 1,
        "background": 1,
        "missed": 0,
    }
    assert t["dAP50"]["classification"] == pytest.approx(CLS - BASE, abs=1e-12)
    assert t["dAP50"]["localisation"] == pytest.approx(LOC - BASE, abs=1e-12)
    # removing d2 (duplicate) or d4 (background) leaves A at precision 1 up to recall 0.5: nothing gained
    assert t["dAP50"]["duplicate"] == t["dAP50"]["background"] == t["dAP50"]["both"] == t["dAP50"]["missed"] == 0
    assert list(t["dAP50"]) == list(A.ERROR_TYPES)
    assert t["counts_per_category"]["A"]["classification"] == 1 and t["counts_per_category"]["B"]["localisation"] == 1


def test_hand_computed_confusion_matrix_and_operating_point():
    gt, dets = _hand_fixture()
    an = analyse(gt, dets)
    # mean F1 over A and B is highest (0.45) keeping scores >= 0.5
    assert an["conf_threshold"] == 0.5 == evaluate(gt, dets)["metrics"]["conf_threshold"]
    c = an["confusion"]
    assert c["labels"] == ["A", "B", "background"] and c["rows"] == "predicted"
    # rows predicted A, B, background; columns GT A, B, background. d1 and d5 on the diagonal; d3 (B) on g2 (A);
    # d2 (on g1, already found) and d4 go to background; g4 is missed (d6, d7 are below the threshold)
    assert c["matrix"] == [[1, 0, 2], [1, 1, 0], [0, 1, 0]]
    assert an["images"] == {"image_id": [1, 2], "gt": [3, 1], "tp": [2, 0], "fp": [3, 0], "fn": [1, 1]}
    assert an["gt_found"] == [1, 0, 1, 0]


def test_hand_computed_pr_curves():
    gt, dets = _hand_fixture()
    pr = analyse(gt, dets)["pr"]
    assert pr["recall"] == [round(k / 100, 2) for k in range(101)]
    a, b = pr["categories"]["A"], pr["categories"]["B"]
    # A: d1 TP, then three FPs: precision 1 (score 0.9) up to recall 0.5, nothing beyond
    assert a["precision"] == [1.0] * 51 + [0.0] * 50 and a["scores"] == [0.9] * 51 + [0.0] * 50
    # B: d3 FP, d5 TP, d6 FP: interpolated precision 0.5; recall 0 is reached at d3 (0.7), the rest at d5 (0.5)
    assert b["precision"] == [0.5] * 51 + [0.0] * 50 and b["scores"] == [0.7] + [0.5] * 50 + [0.0] * 50
    assert (a["AP50"], b["AP50"]) == (pytest.approx(51 / 101), pytest.approx(25.5 / 101))
    assert a["max_recall"] == b["max_recall"] == 0.5 and (a["detections"], b["detections"]) == (4, 3)


def test_hand_computed_worst_misses_and_false_positives():
    gt, dets = _hand_fixture()
    worst = analyse(gt, dets)["worst"]
    fa = worst["A"]["false_positives"]
    assert [(f["score"], f["error"]) for f in fa] == [(0.8, "duplicate"), (0.6, "background"), (0.3, "classification")]
    assert fa[2]["gt_category"] == "B" and fa[2]["annotation_id"] == 14 and not fa[2]["kept"]
    assert [(f["score"], f["error"], f["gt_category"]) for f in worst["B"]["false_positives"]] == [
        (0.7, "classification", "A"),
        (0.4, "localisation", "B"),
    ]
    # g2 is confused with d3 (a B box); nothing at the operating point came near g4
    assert [(m["annotation_id"], m["reason"]) for m in worst["A"]["misses"]] == [(12, "classification")]
    assert [(m["annotation_id"], m["reason"], m["bbox"]) for m in worst["B"]["misses"]] == [
        (14, "missed", [0.0, 0.0, 20.0, 20.0])
    ]


def _pycocotools_eval(gt, dets):
    import contextlib
    import copy
    import io

    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        g = COCO()
        g.dataset = copy.deepcopy(gt)
        g.createIndex()
        ev = COCOeval(g, g.loadRes(copy.deepcopy(canonical(dets))), "bbox")
        ev.evaluate()
        ev.accumulate()
    return ev.eval


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_analysis_uses_the_evaluator_s_matching_and_numbers(seed):
    gt, dets = random_coco(seed)  # crowd GT, a category without GT, ties, more than 100 detections on one image
    ev = evaluate(gt, dets)
    an = analyse(gt, dets)
    assert an["tide"]["mAP50"] == ev["metrics"]["mAP50"]  # the same number, to the last bit
    assert an["conf_threshold"] == ev["metrics"]["conf_threshold"]
    prep = prepare(gt, dets)
    coco = _pycocotools_eval(gt, dets)  # plain COCOeval's precision and score arrays [T, R, K, A, M]
    for k, cid in enumerate(prep.cat_ids):
        name = prep.cat_names[cid]
        assert an["pr"]["categories"][name]["AP50"] == ev["per_category"][name]["AP50"]
        if ev["per_category"][name]["AP50"] is not None:  # stored to 6 decimals
            np.testing.assert_allclose(
                an["pr"]["categories"][name]["precision"], coco["precision"][0, :, k, 0, -1], atol=6e-7
            )
            np.testing.assert_allclose(
                an["pr"]["categories"][name]["scores"], coco["scores"][0, :, k, 0, -1], atol=6e-7
            )
    # confusion matrix: the diagonal is the operating point's true positives, columns sum to the instances,
    # and diagonal / row sum is each category's precision at the operating point
    mat = np.array(an["confusion"]["matrix"])
    k = len(prep.cat_ids)
    assert mat[:k, :k].trace() == sum(an["images"]["tp"])
    assert mat[:, :k].sum(axis=0).tolist() == [prep.n_gt[c] for c in prep.cat_ids]
    for i, cid in enumerate(prep.cat_ids):
        p = ev["per_category"][prep.cat_names[cid]]["precision"]
        if p is not None and mat[i].sum():
            assert mat[i, i] / mat[i].sum() == pytest.approx(p)
    # COCO's size bins: AP50:95 per bin is COCO's APs, APm, APl
    sizes = an["sizes"]["coco"]["AP50_95"]
    assert [sizes[b] for b in ("small", "medium", "large")] == ev["metrics"]["coco_stats"][3:6]
    assert sum(an["images"]["fp"]) == mat[:k].sum() - mat[:k, :k].trace()  # every other kept detection


def _rounded(obj, digits=12):
    if isinstance(obj, dict):
        return {k: _rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rounded(v, digits) for v in obj]
    return round(obj, digits) if isinstance(obj, float) else obj


def test_size_bins_engines_agree_and_tiny_datasets_get_safit_bins():
    gt, dets = random_coco(3)
    fast = analyse(gt, dets, tiny=True)["sizes"]
    ref = analyse(gt, dets, tiny=True, engine="pycocotools")["sizes"]
    assert _rounded(fast) == _rounded(ref)  # C++ and Python sums may differ in the last bit
    assert set(fast["safit"]["AP50"]) == {"extremely_tiny", "tiny", "small", "medium", "large"}
    assert sum(fast["safit"]["instances"].values()) >= sum(fast["coco"]["instances"].values())

    # automatic: a dataset whose GT is mostly COCO-small (below 32 x 32) is a tiny-object one
    def sized(side):
        return {
            **gt,
            "annotations": [
                {**a, "bbox": [*a["bbox"][:2], side, side], "area": side * side} for a in gt["annotations"]
            ],
        }

    assert "safit" in analyse(sized(20), dets)["sizes"]
    assert "safit" not in analyse(sized(40), dets)["sizes"]
    assert "safit" in analyse(sized(40), dets, matching="safit")["sizes"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tide_errors_equal_the_tidecv_package(seed, monkeypatch):
    tidecv = pytest.importorskip("tidecv")
    # tidecv's conditions: no crowd GT, every category with predictions has GT, distinct scores
    gt, dets = random_coco(seed, absent_cat=False, crowd=0.0, dense_image=False)
    rng = np.random.default_rng(100 + seed)
    for d in dets:
        d["score"] = float(d["score"] + rng.uniform(0, 1e-3))
    g, p = tidecv.Data("gt"), tidecv.Data("pred")
    for a in gt["annotations"]:
        g.add_ground_truth(a["image_id"], a["category_id"], a["bbox"])
    for im in gt["images"]:  # images without GT too: TIDE visits only the images it knows
        g.add_image(im["id"], im["file_name"])
    for d in dets:
        p.add_detection(d["image_id"], d["category_id"], d["score"], d["bbox"])
    tide = tidecv.TIDE()
    run = tide.evaluate(g, p, mode=tidecv.TIDE.BOX)
    theirs = tide.get_main_errors()["pred"]
    special = tide.get_special_errors()["pred"]
    names = {
        "Cls": "classification",
        "Loc": "localisation",
        "Both": "both",
        "Dupe": "duplicate",
        "Bkg": "background",
        "Miss": "missed",
    }
    counts = {names[e.short_name]: n for e, n in run.count_errors().items()}

    ours = analyse(gt, dets)["tide"]
    assert ours["counts"] == counts
    assert 100 * ours["mAP50"] == pytest.approx(run.ap, abs=1e-9)
    for short, name in names.items():
        assert 100 * ours["dAP50"][name] == pytest.approx(theirs[short], abs=0.1)
    # the one difference is the recall grid: COCO's np.linspace points (0.30000000000000004) against tidecv's
    # k / 100; with tidecv's grid every number is tidecv's own
    monkeypatch.setattr(A, "RECALL_POINTS", np.array([k / 100 for k in range(101)]))
    exact = analyse(gt, dets)["tide"]
    for short, name in names.items():
        assert 100 * exact["dAP50"][name] == pytest.approx(theirs[short], abs=1e-9)
    assert 100 * exact["special"]["false_positives"] == pytest.approx(special["FalsePos"], abs=1e-9)
    assert 100 * exact["special"]["false_negatives"] == pytest.approx(special["FalseNeg"], abs=1e-9)


def test_no_detections_and_no_ground_truth_are_analysed_not_crashed():
    gt, _ = _hand_fixture()
    empty = analyse(gt, [])
    assert empty["tide"]["mAP50"] == 0.0 and empty["tide"]["counts"]["missed"] == 4
    assert empty["confusion"]["matrix"] == [[0, 0, 0], [0, 0, 0], [2, 2, 0]]
    assert empty["conf_threshold"] is None
    no_gt = {**gt, "annotations": []}
    an = analyse(no_gt, _hand_fixture()[1])
    assert an["tide"]["mAP50"] is None and an["tide"]["dAP50"]["background"] is None
    assert an["tide"]["counts"]["background"] == 7 and an["confusion"]["matrix"][0][2] == 4
    json.dumps(an, allow_nan=False)  # stored as plain JSON: no NaN anywhere


def test_runs_without_an_analysis_still_load_and_say_so(tmp_path):
    run = Store(tmp_path).run(RunKey("d", "det", "enc", "F1", 0))
    run.path.mkdir(parents=True)
    run.write_metrics({"support": {}, "metrics": {"mAP50": 0.5}, "per_category": {}})
    run.set_status("finished")
    assert run.read_metrics()["metrics"]["mAP50"] == 0.5
    assert analysis_of(run) == (None, NO_ANALYSIS) == (None, "no error analysis stored; rerun with --force")
    run.analysis_path.write_text(json.dumps({"schema": 99}))
    data, why = analysis_of(run)
    assert data is None and "schema 99" in why and "--force" in why
    gt, dets = _hand_fixture()
    assert store_analysis(run, gt, dets, {"eval": {"engine": "faster-coco-eval", "matching": "iou"}}, 0.5)
    data, why = analysis_of(run)
    assert why is None and data["run"]["fold"] == "F1" and data["tide"]["mAP50"] == pytest.approx(BASE)


def test_a_failing_analysis_is_recorded_and_the_run_stands(tmp_path, monkeypatch, caplog):
    run = Store(tmp_path).run(RunKey("d", "det", "enc", "F1", 0))
    run.path.mkdir(parents=True)

    def broken(*_, **__):
        raise ValueError("boom")

    monkeypatch.setattr(A, "analyse", broken)
    gt, dets = _hand_fixture()
    assert store_analysis(run, gt, dets, {}, None) is False
    assert "error analysis failed" in caplog.text
    data, why = analysis_of(run)
    assert data is None and why == "error analysis failed: ValueError: boom"
