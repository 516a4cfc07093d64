"""The evaluator against plain pycocotools, edge cases pycocotools gets wrong, and the precision/recall operating
point."""

from __future__ import annotations

import contextlib
import copy
import io

import numpy as np
import pytest

from evaluation_fixtures import canonical, nullable, pycocotools_reference, random_coco
from harness.evaluation import ENGINES, EvaluationError, evaluate, max_f1_operating_point

CASES = {
    "mixed": dict(seed=0),
    "crowd-heavy": dict(seed=1, crowd=0.2),
    "no-absent-category": dict(seed=2, absent_cat=False, empty_images=0, dense_image=False),
}


def _assert_matches_reference(result, ref_stats, ref_cat, gt):
    assert result["metrics"]["coco_stats"] == pytest.approx(nullable(ref_stats), abs=1e-12)
    names = {c["id"]: c["name"] for c in gt["categories"]}
    for cid, (ap50, ap) in ref_cat.items():
        got = result["per_category"][names[cid]]
        assert got["AP50"] == (pytest.approx(ap50, abs=1e-12) if ap50 is not None else None)
        assert got["AP50_95"] == (pytest.approx(ap, abs=1e-12) if ap is not None else None)
    assert result["metrics"]["mAP50"] == nullable(ref_stats)[1]
    assert result["metrics"]["mAP50_95"] == nullable(ref_stats)[0]


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("engine", ENGINES)
def test_equals_pycocotools_on_randomized_fixtures(case, engine):
    gt, dets = random_coco(**CASES[case])
    ref_stats, ref_cat = pycocotools_reference(gt, dets)
    gt_before, dets_before = copy.deepcopy(gt), copy.deepcopy(dets)
    result = evaluate(gt, dets, engine=engine)
    _assert_matches_reference(result, ref_stats, ref_cat, gt)
    assert gt == gt_before and dets == dets_before, "inputs must not be modified"
    assert 0 < result["metrics"]["mAP50_95"] < result["metrics"]["mAP50"] < 1


@pytest.mark.parametrize("engine", ENGINES)
def test_detections_in_any_order_score_the_same(engine):
    """pycocotools matches detections of equal score in the order they are listed, so another codebase's order
    changes the numbers; the evaluator scores the canonical order, whatever order it is given."""
    gt, dets = random_coco(seed=21)
    for d in dets:
        d["score"] = round(d["score"], 1)  # many equal scores within an image and category
    rng = np.random.default_rng(3)
    orders = [dets, dets[::-1], *([dets[i] for i in rng.permutation(len(dets))] for _ in range(3))]
    raw = {tuple(pycocotools_reference(gt, o, in_canonical_order=False)[0]) for o in orders}
    assert len(raw) > 1, "the fixture must make plain pycocotools order-dependent"
    results = [evaluate(gt, o, engine=engine) for o in orders]
    assert all(r == results[0] for r in results[1:])
    ref_stats, ref_cat = pycocotools_reference(gt, dets)  # the reference: pycocotools on the canonical order
    _assert_matches_reference(results[0], ref_stats, ref_cat, gt)


def test_support_and_categories_without_gt():
    gt, dets = random_coco(seed=3)
    r = evaluate(gt, dets)
    non_crowd = [a for a in gt["annotations"] if not a["iscrowd"]]
    assert r["support"]["images"] == len(gt["images"])
    assert r["support"]["instances"] == len(non_crowd)
    assert sum(r["support"]["categories"].values()) == len(non_crowd)
    assert len(r["support"]["image_ids_sha1"]) == 40
    absent = r["per_category"]["cat4"]  # the fixture's last category has detections but no GT
    assert absent == {"AP50": None, "AP50_95": None, "instances": 0, "precision": None, "recall": None}
    # the absent category does not pull the mean down: mAP50 is the mean over the three categories with GT
    present = [r["per_category"][f"cat{k}"]["AP50"] for k in (1, 2, 3)]
    assert r["metrics"]["mAP50"] == pytest.approx(np.mean(present), abs=1e-12)


@pytest.mark.parametrize("engine", ENGINES)
def test_empty_detections_score_zero_where_pycocotools_crashes(engine):
    from pycocotools.coco import COCO

    gt, _ = random_coco(seed=4)
    with contextlib.redirect_stdout(io.StringIO()):
        g = COCO()
        g.dataset = copy.deepcopy(gt)
        g.createIndex()
        with pytest.raises(IndexError):
            g.loadRes([])  # the pycocotools behaviour the harness guards against
    r = evaluate(gt, [], engine=engine)
    assert r["metrics"]["mAP50"] == 0.0 and r["metrics"]["mAP50_95"] == 0.0
    assert r["metrics"]["precision"] == 0.0 and r["metrics"]["recall"] == 0.0
    assert r["metrics"]["conf_threshold"] is None
    assert r["per_category"]["cat1"]["AP50"] == 0.0
    assert r["per_category"]["cat4"]["AP50"] is None
    assert r["metrics"]["detections"] == 0


@pytest.mark.parametrize("engine", ENGINES)
def test_unknown_categories_and_images_are_dropped_and_counted(engine, caplog):
    gt, dets = random_coco(seed=5)
    extra = [dict(dets[0], category_id=99), dict(dets[1], category_id=99), dict(dets[2], image_id=12345)]
    ref_stats, ref_cat = pycocotools_reference(gt, dets + extra[:2])  # pycocotools silently drops category 99 ...
    with pytest.raises(AssertionError):
        pycocotools_reference(gt, dets + extra)  # ... and asserts on an unknown image
    r = evaluate(gt, dets + extra, engine=engine)
    _assert_matches_reference(r, ref_stats, ref_cat, gt)
    assert r["metrics"]["dropped_detections"] == {"unknown_category": 2, "unknown_image": 1}
    assert r["metrics"]["detections"] == len(dets)
    assert "category_id 99" in caplog.text and "12345" in caplog.text
    with pytest.raises(EvaluationError, match="categories not in the ground truth"):
        evaluate(gt, dets + extra[:1], engine=engine, strict=True)


def test_int_and_str_image_ids_are_the_same_image():
    gt, dets = random_coco(seed=6)
    ref = evaluate(gt, dets)
    str_dets = [dict(d, image_id=str(d["image_id"])) for d in dets]
    assert evaluate(gt, str_dets)["metrics"]["coco_stats"] == ref["metrics"]["coco_stats"]
    str_gt = copy.deepcopy(gt)
    for im in str_gt["images"]:
        im["id"] = str(im["id"])
    for a in str_gt["annotations"][::2]:
        a["image_id"] = str(a["image_id"])
    mixed = [dict(d, image_id=d["image_id"] if i % 2 else float(d["image_id"])) for i, d in enumerate(dets)]
    r = evaluate(str_gt, mixed)
    assert r["metrics"]["coco_stats"] == ref["metrics"]["coco_stats"]
    assert r["support"]["image_ids_sha1"] == ref["support"]["image_ids_sha1"]
    # non-numeric string ids work too and give the same numbers as the integer ids they stand for
    named_gt = copy.deepcopy(gt)
    for im in named_gt["images"]:
        im["id"] = f"frame_{im['id']:04d}"
    for a in named_gt["annotations"]:
        a["image_id"] = f"frame_{a['image_id']:04d}"
    named_dets = [dict(d, image_id=f"frame_{d['image_id']:04d}") for d in dets]
    assert evaluate(named_gt, named_dets)["metrics"]["coco_stats"] == ref["metrics"]["coco_stats"]
    dup = copy.deepcopy(gt)
    dup["images"].append(dict(dup["images"][0], id=str(dup["images"][0]["id"])))
    with pytest.raises(EvaluationError, match="appears more than once"):
        evaluate(dup, dets)


def test_gt_annotation_id_zero_is_renumbered():
    gt, dets = _box_case()
    ref_stats, _ = pycocotools_reference(gt, dets)
    zero = copy.deepcopy(gt)
    for a in zero["annotations"]:
        a["id"] -= 1  # ids 0 and 1: pycocotools reads a match to GT id 0 as "no match"
    naive_stats, _ = pycocotools_reference(zero, dets)
    assert naive_stats[1] < ref_stats[1]
    for engine in ENGINES:
        assert evaluate(zero, dets, engine=engine)["metrics"]["coco_stats"] == pytest.approx(
            nullable(ref_stats), abs=1e-12
        )


def test_missing_area_and_iscrowd_default_like_coco():
    gt, dets = random_coco(seed=8, crowd=0.0)
    bare = copy.deepcopy(gt)
    for a in bare["annotations"]:
        del a["area"], a["iscrowd"]
    assert evaluate(bare, dets)["metrics"]["coco_stats"] == evaluate(gt, dets)["metrics"]["coco_stats"]


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"bbox": [1, 2, 3]}, r"detections\[0\]: bbox has 3 numbers"),
        ({"bbox": [1, 2, -3, 4]}, r"detections\[0\]: bbox .* negative width"),
        ({"score": float("nan")}, r"detections\[0\]: score nan is not a finite number"),
        ({"image_id": True}, r"detections\[0\]: id True is a boolean"),
    ],
)
def test_malformed_detections_name_the_record(bad, message):
    gt, dets = random_coco(seed=9)
    with pytest.raises(EvaluationError, match=message):
        evaluate(gt, [dict(dets[0], **bad)] + dets[1:])


def test_malformed_ground_truth_names_the_record():
    gt, dets = random_coco(seed=9)
    broken = copy.deepcopy(gt)
    broken["annotations"][3]["category_id"] = 42
    with pytest.raises(EvaluationError, match=r"annotations\[3\].*category_id 42 is not in the ground truth"):
        evaluate(broken, dets)
    with pytest.raises(EvaluationError, match="field 'images' is missing"):
        evaluate({"annotations": [], "categories": []}, dets)
    with pytest.raises(EvaluationError, match="unknown evaluation engine 'coco'"):
        evaluate(gt, dets, engine="coco")


def test_no_ground_truth_at_all_is_undefined_not_a_crash():
    gt, dets = random_coco(seed=10)
    gt = dict(gt, annotations=[])
    r = evaluate(gt, dets)
    assert r["metrics"]["mAP50"] is None and r["metrics"]["precision"] is None
    assert all(s is None for s in r["metrics"]["coco_stats"])
    assert r["support"]["instances"] == 0


def _box_case():
    """One category, two GT; detections: 0.9 hits GT1, 0.8 misses, 0.7 hits GT2, 0.6 duplicates GT1."""
    gt = {
        "images": [{"id": 1, "width": 100, "height": 100}],
        "annotations": [
            {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "area": 400, "iscrowd": 0},
            {"id": 2, "image_id": 1, "category_id": 1, "bbox": [60, 60, 20, 20], "area": 400, "iscrowd": 0},
        ],
        "categories": [{"id": 1, "name": "crack"}],
    }
    dets = [
        {"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.9},
        {"image_id": 1, "category_id": 1, "bbox": [40, 5, 10, 10], "score": 0.8},
        {"image_id": 1, "category_id": 1, "bbox": [61, 61, 20, 20], "score": 0.7},
        {"image_id": 1, "category_id": 1, "bbox": [11, 10, 20, 20], "score": 0.6},
    ]
    return gt, dets


@pytest.mark.parametrize("engine", ENGINES)
def test_operating_point_hand_computed(engine):
    # t=0.9: P 1, R 1/2, F1 2/3;  t=0.8: P 1/2, R 1/2, F1 1/2;  t=0.7: P 2/3, R 1, F1 0.8;  t=0.6: P 1/2, R 1, F1 2/3
    gt, dets = _box_case()
    m = evaluate(gt, dets, engine=engine)["metrics"]
    assert m["conf_threshold"] == 0.7
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == 1.0 and m["f1"] == pytest.approx(0.8)
    assert "maximising mean F1" in m["operating_point"]


def test_operating_point_averages_f1_over_categories_with_gt():
    # category 0: TP@0.9, FP@0.5 (1 GT); category 1: TP@0.5 (1 GT); category 2: no GT, its detections are ignored
    op = max_f1_operating_point(
        scores=[0.9, 0.5, 0.5, 0.95], labels=[0, 0, 1, 2], is_tp=[True, False, True, False], n_gt=[1, 1, 0]
    )
    # t=0.9: F1 = (1 + 0)/2 = 0.5;  t=0.5: F1 = (2/3 + 1)/2 = 0.8333
    assert op.conf_threshold == 0.5
    assert op.f1 == pytest.approx((2 / 3 + 1) / 2)
    assert op.precision == pytest.approx((0.5 + 1) / 2) and op.recall == 1.0
    assert set(op.per_category) == {0, 1}


def test_crowd_matches_are_ignored_by_the_operating_point():
    gt, dets = _box_case()
    gt["annotations"].append(
        {"id": 3, "image_id": 1, "category_id": 1, "bbox": [35, 0, 30, 30], "area": 900, "iscrowd": 1}
    )
    for engine in ENGINES:
        m = evaluate(gt, dets, engine=engine)["metrics"]
        # the 0.8 detection now falls in the crowd region: it is neither TP nor FP; t=0.7 gives P 1, R 1
        assert (m["conf_threshold"], m["precision"], m["recall"]) == (0.7, 1.0, 1.0)


def test_engines_agree_on_the_operating_point():
    gt, dets = random_coco(seed=11, crowd=0.1)
    a, b = (evaluate(gt, dets, engine=e)["metrics"] for e in ENGINES)
    for key in ("conf_threshold", "precision", "recall", "f1"):
        assert a[key] == b[key]


def test_operating_point_equals_brute_force_sweep():
    rng = np.random.default_rng(12)
    scores = np.round(rng.uniform(size=300), 2)
    labels = rng.integers(0, 4, size=300)
    is_tp = rng.uniform(size=300) < 0.4
    n_gt = np.array([40, 30, 0, 25])
    op = max_f1_operating_point(scores, labels, is_tp, n_gt)
    best = (-1.0, None)
    for t in sorted(set(scores.tolist())):
        f1s = []
        for k in (0, 1, 3):
            kept = (labels == k) & (scores >= t)
            tp = int((kept & is_tp).sum())
            p = tp / kept.sum() if kept.sum() else 0.0
            r = tp / n_gt[k]
            f1s.append(2 * p * r / (p + r) if p + r else 0.0)
        if np.mean(f1s) > best[0] + 1e-15:
            best = (float(np.mean(f1s)), t)
    assert op.conf_threshold == best[1]
    assert op.f1 == pytest.approx(best[0], abs=1e-12)


def _pycocotools_matches_at_50(gt, dets):
    """dt id -> gt id from plain pycocotools' evalImgs at IoU 0.50, area 'all' (detections numbered 1..N)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        g = COCO()
        g.dataset = copy.deepcopy(gt)
        g.createIndex()
        ev = COCOeval(g, g.loadRes(copy.deepcopy(dets)), "bbox")
        ev.evaluate()
    out = {}
    for e in ev.evalImgs:
        if e is not None and e["aRng"] == [0, 1e10]:
            out.update({d: int(m) for d, m in zip(e["dtIds"], e["dtMatches"][0]) if m > 0})
    return out


@pytest.mark.parametrize("seed", [13, 14])
def test_bulk_greedy_matching_equals_cocoeval(seed):
    from harness.evaluation.inputs import prepare
    from harness.evaluation.pairs import pair_layout
    from harness.evaluation.safit import iou_elementwise

    gt, dets = random_coco(seed=seed, crowd=0.15)
    # exact ties: a duplicated GT box (COCO gives the detection to the later one) and a crowd copy of a GT
    a = gt["annotations"][0]
    gt["annotations"] += [dict(a, id=10_001), dict(a, id=10_002, iscrowd=1)]
    exact = {"image_id": a["image_id"], "category_id": a["category_id"], "bbox": list(a["bbox"]), "score": 0.999}
    dets = canonical(dets + [exact])  # detections numbered 1..N in the evaluator's canonical order
    ref = _pycocotools_matches_at_50(gt, dets)
    renumbered = {x["id"]: k + 1 for k, x in enumerate(gt["annotations"])}  # the harness numbers GT 1..N in order
    ref = {d: renumbered[g] for d, g in ref.items()}
    prep = prepare(gt, dets)
    layout = pair_layout(prep, 100)
    got = layout.greedy_match(prep, layout.values(prep, iou_elementwise), threshold=0.5)
    assert len(ref) > 50 and got == ref
    # of two identical GT boxes, the later one (crowd comes last)
    assert got[dets.index(exact) + 1] == renumbered[10_001]


def test_bulk_iou_matrices_are_bitwise_cocoeval_s():
    from faster_coco_eval.core.coco import COCO
    from faster_coco_eval.core.faster_eval_api import COCOeval_faster

    from harness.evaluation.bulk import iou_values
    from harness.evaluation.inputs import prepare
    from harness.evaluation.pairs import pair_layout
    from harness.evaluation.safit import iou_elementwise

    gt, dets = random_coco(seed=15, crowd=0.15)
    prep = prepare(gt, dets)
    layout = pair_layout(prep, 100)
    ours = layout.matrices(layout.values(prep, iou_elementwise))
    ev = COCOeval_faster(COCO(copy.deepcopy(prep.gt)), COCO(copy.deepcopy(gt)).loadRes(canonical(dets)), iouType="bbox")
    ev.evaluate()  # the library's own per-pair IoU matrices, dense 1 image at a time
    theirs = {(int(i), int(c)): np.asarray(m) for (i, c), m in ev.ious.items() if len(m)}
    assert set(ours) == set(theirs) and len(ours) > 50
    assert all(np.array_equal(ours[k], theirs[k]) for k in ours)
    # the bulk path computes IoU only where boxes overlap horizontally: the same values, bit for bit
    values = layout.values(prep, iou_elementwise)
    assert np.array_equal(iou_values(layout, prep), values) and (values == 0).any() and (values > 0).any()


def test_stock_preparation_path_gives_the_same_numbers():
    """Without the bulk inputs the faster-coco-eval subclass falls back to the library's own preparation."""
    from faster_coco_eval.core.coco import COCO

    from harness.evaluation.engines import _faster_eval_class, _silent
    from harness.evaluation.inputs import prepare

    gt, dets = random_coco(seed=16, crowd=0.1)
    ref_stats, _ = pycocotools_reference(gt, dets)
    prep = prepare(gt, dets)
    dt = COCO(print_function=_silent)
    dt.dataset = {"images": prep.gt["images"], "categories": prep.gt["categories"], "annotations": prep.dets}
    ev = _faster_eval_class("iou", "center")(
        COCO(prep.gt, print_function=_silent), dt, iouType="bbox", print_function=_silent
    )
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    assert list(ev.stats) == pytest.approx(ref_stats, abs=1e-12)


def _library_evaluation(prep, gt, dets, matching, ranges=None):
    """faster-coco-eval's own evaluation (C++ matching and full accumulation) of the prepared inputs."""
    import faster_coco_eval.faster_eval_api_cpp as _C
    from faster_coco_eval.core.coco import COCO

    from harness.evaluation.engines import _faster_eval_class, _silent

    ev = _faster_eval_class(matching, "center")(
        COCO(copy.deepcopy(prep.gt), print_function=_silent),
        COCO(copy.deepcopy(gt), print_function=_silent).loadRes(copy.deepcopy(dets)),
        iouType="bbox",
        print_function=_silent,
        separate_eval=True,
        ranges=ranges,
    )
    ev.evaluate()  # no harness_inputs: the library's own path (SAFit matrices pair by pair)
    return ev, _C.COCOevalAccumulate(ev._paramsEval, ev._evalImgs_cpp)


@pytest.mark.parametrize("seed, matching, tiny", [(17, "iou", False), (19, "iou", False), (20, "safit", True)])
def test_bulk_matching_and_accumulation_equal_the_library_s_in_every_cell_it_computes(seed, matching, tiny):
    """The bulk path's precision, recall and scores are bitwise the library's C++ in every cell ``summarize()``
    reads (area "all" at every maxDets, the other ranges at the last); the cells it never reads hold -1."""
    from harness.evaluation.engines import _faster_eval_class, _silent
    from harness.evaluation.inputs import prepare
    from harness.evaluation.safit import TINY_AREA_RANGES

    gt, dets = random_coco(seed=seed, crowd=0.15)
    a = gt["annotations"][0]  # exact ties: a duplicated GT box and a crowd copy of it, a detection on it
    gt["annotations"] += [dict(a, id=10_001), dict(a, id=10_002, iscrowd=1)]
    dets.append({"image_id": a["image_id"], "category_id": a["category_id"], "bbox": list(a["bbox"]), "score": 0.999})
    prep = prepare(gt, dets)
    ranges = {k: list(v) for k, v in TINY_AREA_RANGES.items() if k != "all"} if tiny else None
    # the library reads the detections in the harness's canonical order (pycocotools-style engines break score
    # ties in input order; the fixture has exact ties)
    canonical = [{k: d[k] for k in ("image_id", "category_id", "bbox", "score")} for d in prep.dets]
    lib, full = _library_evaluation(prep, gt, canonical, matching, ranges)
    ev = _faster_eval_class(matching, "center")(None, None, iouType="bbox", print_function=_silent, ranges=ranges)
    ev.harness_inputs = prep
    ev.params.imgIds = [im["id"] for im in prep.gt["images"]]
    ev.params.catIds = list(prep.cat_ids)
    ev.evaluate()
    assert ev._harness_matches is not None  # the bulk path ran
    ours = ev.eval
    for key in ("precision", "recall", "scores"):
        assert ours[key].shape == full[key].shape
        assert np.array_equal(ours[key][..., :1, :], full[key][..., :1, :])  # area "all", every maxDets
        assert np.array_equal(ours[key][..., 1:, -1], full[key][..., 1:, -1])  # the other ranges at the last
        assert (ours[key][..., 1:, :-1] == -1).all()  # never read by summarize(): not computed
    assert (full["precision"][..., 1:, :-1] > -1).any() and (ours["precision"] > 0).any()
    ev.summarize()
    lib.eval = full
    lib.summarize()
    assert list(ev.stats) == list(lib.stats)
    if matching == "iou":  # the operating point's matches are the bulk matching's at 0.50, area "all"
        layout, values = ev._harness_layout, ev._harness_values
        d0, g0 = ev._harness_matches.at(0, 0)
        d1, g1 = layout.greedy_match_indices(values, threshold=0.5)
        assert sorted(zip(d0.tolist(), g0.tolist())) == sorted(zip(d1.tolist(), g1.tolist()))


def test_bulk_path_falls_back_to_the_library_s_own_when_its_parameters_move(monkeypatch, caplog):
    from harness.evaluation import engines

    gt, dets = random_coco(seed=18, crowd=0.1)
    ref_stats, _ = pycocotools_reference(gt, dets)
    expected = evaluate(gt, dets)

    def moved(*_args, **_kwargs):
        raise AttributeError("'Params' object has no attribute 'areaRng'")

    monkeypatch.setattr(engines, "gt_ignored", moved)
    with caplog.at_level("WARNING"):
        result = evaluate(gt, dets)
    assert "bulk evaluation unavailable" in caplog.text
    assert result["metrics"]["coco_stats"] == pytest.approx(nullable(ref_stats), abs=1e-12)
    assert result["metrics"]["coco_stats"] == expected["metrics"]["coco_stats"]
    assert result["metrics"]["precision"] == expected["metrics"]["precision"]
    assert result["per_category"] == expected["per_category"]
