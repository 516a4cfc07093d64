"""Paired statistics: resampling with duplicates, the bootstrap's intervals, per-fold differences, refusals."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("harness.evaluation")

from harness.errors import HarnessError, StoreError  # noqa: E402
from harness.report.stats import (  # noqa: E402
    BootstrapScorer,
    bootstrap_indices,
    compare_detectors,
    percentile_ci,
    resample_coco,
)
from harness.store import RunKey, Store  # noqa: E402
from report_fixtures import make_detections, make_gt, synthetic_store, write_run  # noqa: E402


def _two_image_case():
    """Image 1 has one object, found (score 0.9); image 2 has one object, missed."""
    gt = {
        "images": [{"id": 1, "width": 100, "height": 100}, {"id": 2, "width": 100, "height": 100}],
        "annotations": [
            {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "area": 400, "iscrowd": 0},
            {"id": 2, "image_id": 2, "category_id": 1, "bbox": [50, 50, 20, 20], "area": 400, "iscrowd": 0},
        ],
        "categories": [{"id": 1, "name": "crack"}],
    }
    dets = [{"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.9}]
    return gt, dets


def test_resampled_images_get_new_unique_ids_so_duplicates_count_twice():
    from harness.evaluation import evaluate

    gt, dets = _two_image_case()
    rgt, rdets = resample_coco(gt, [1, 1, 2], dets)
    assert [im["id"] for im in rgt["images"]] == [1, 2, 3]
    assert [im["source_id"] for im in rgt["images"]] == [1, 1, 2]
    assert [a["id"] for a in rgt["annotations"]] == [1, 2, 3]
    assert [a["image_id"] for a in rgt["annotations"]] == [1, 2, 3]
    assert [d["image_id"] for d in rdets] == [1, 2]
    assert gt["images"][0]["id"] == 1 and dets[0]["image_id"] == 1  # inputs untouched
    # 3 instances, 2 found at precision 1: COCO's 101-point AP = 67/101 (recall thresholds 0..0.66).
    # Collapsing the duplicate would give 2 instances, 1 found: 51/101.
    m = evaluate(rgt, rdets)["metrics"]
    assert m["mAP50"] == pytest.approx(67 / 101, abs=1e-9)
    assert evaluate(gt, dets)["metrics"]["mAP50"] == pytest.approx(51 / 101, abs=1e-9)


def test_resampling_an_unknown_image_is_an_error():
    gt, dets = _two_image_case()
    with pytest.raises(StoreError, match="image id 7"):
        resample_coco(gt, [1, 7], dets)


def test_bootstrap_indices_are_seeded_per_fold():
    a = bootstrap_indices(10, 5, seed=3, stream="P1")
    assert a.shape == (5, 10) and a.min() >= 0 and a.max() < 10
    assert np.array_equal(a, bootstrap_indices(10, 5, seed=3, stream="P1"))
    assert not np.array_equal(a, bootstrap_indices(10, 5, seed=4, stream="P1"))
    assert not np.array_equal(a, bootstrap_indices(10, 5, seed=3, stream="P2"))


def test_percentile_ci_of_known_values():
    lo, hi = percentile_ci(np.arange(101, dtype=float))
    assert (lo, hi) == pytest.approx((2.5, 97.5))
    assert percentile_ci(np.array([np.nan, np.nan])) == (None, None)


@pytest.fixture(scope="module")
def pair_store(tmp_path_factory):
    """strong vs weak on two folds, an exact copy of strong ('twin'), and two independent draws of one medium
    quality ('medium', 'peer')."""
    root = tmp_path_factory.mktemp("pairs")
    store = synthetic_store(root, folds=("P1", "P2"), per_fold=8, detectors={"strong": "strong", "weak": "weak"})
    medium = {"recall": 0.75, "jitter": 2.0, "false_positives": 1.0, "label_noise": 0.1}
    for f in ("P1", "P2"):
        src = store.run(RunKey("synth", "strong", "c2", f, 0))
        gt = json.loads(src.gt_path.read_text())
        write_run(store, RunKey("synth", "twin", "c2", f, 0), gt, json.loads(src.predictions_path.read_text()))
        for k, name in enumerate(("medium", "peer")):
            rng = np.random.default_rng([99, k, int(f[1])])
            write_run(store, RunKey("synth", name, "c2", f, 0), gt, make_detections(gt, rng, **medium))
    return store


@pytest.fixture(scope="module")
def scorer():
    """One scorer for the module: each run is re-scored once per resample, whatever the pairs."""
    return BootstrapScorer(RESAMPLES, seed=0)


RESAMPLES = 40


def _compare(store, a, b, scorer):
    from harness.report.reader import StoreView
    from harness.report.stats import paired_comparison

    view = StoreView(store)
    return paired_comparison(view.entry("synth", a), view.entry("synth", b), RESAMPLES, 0, scorer)


def test_identical_detectors_give_an_interval_containing_zero(pair_store, scorer):
    comp = _compare(pair_store, "strong", "twin", scorer)
    for key in ("mAP50", "mAP50_95"):
        b = comp.bootstrap[key]
        assert b.delta == 0.0 and b.ci_low == 0.0 and b.ci_high == 0.0
        assert not b.excludes_zero and b.valid == 40
        assert comp.fold_differences[key].diffs == [0.0, 0.0]


def test_detectors_of_the_same_quality_give_an_interval_containing_zero(pair_store, scorer):
    comp = _compare(pair_store, "medium", "peer", scorer)
    for key in ("mAP50", "mAP50_95"):
        b = comp.bootstrap[key]
        assert b.ci_low <= 0.0 <= b.ci_high, (key, b)
        assert b.ci_low < 0.0 < b.ci_high and b.ci_high - b.ci_low > 0.02  # a real spread, not a degenerate one


def test_a_clearly_better_detector_excludes_zero_and_the_observed_delta_is_the_table_difference(pair_store, scorer):
    comp = _compare(pair_store, "strong", "weak", scorer)
    view_metrics = {
        det: [pair_store.run(RunKey("synth", det, "c2", f, 0)).read_metrics()["metrics"] for f in ("P1", "P2")]
        for det in ("strong", "weak")
    }
    for key in ("mAP50", "mAP50_95"):
        b = comp.bootstrap[key]
        assert b.ci_low > 0.05 and b.excludes_zero and b.p_not_better == 0.0
        # the statistic on the original images is the stored mean over folds (re-scoring is consistent)
        stored = {d: sum(m[key] for m in ms) / 2 for d, ms in view_metrics.items()}
        assert b.a == pytest.approx(stored["strong"], abs=1e-9) and b.b == pytest.approx(stored["weak"], abs=1e-9)
        assert b.delta == pytest.approx(stored["strong"] - stored["weak"], abs=1e-9)
        assert b.a_ci[0] <= b.a <= b.a_ci[1]
        fd = comp.fold_differences[key]
        assert fd.diffs == pytest.approx(
            [view_metrics["strong"][i][key] - view_metrics["weak"][i][key] for i in range(2)]
        )
        assert fd.stat.mean == pytest.approx(sum(fd.diffs) / 2)
        assert fd.stat.sd == pytest.approx(abs(fd.diffs[0] - fd.diffs[1]) / math.sqrt(2))
    swapped = _compare(pair_store, "weak", "strong", scorer)
    assert swapped.bootstrap["mAP50"].ci_high == pytest.approx(-comp.bootstrap["mAP50"].ci_low)
    text = comp.to_text()
    assert "strong/c2 (A) vs weak/c2 (B)" in text and "40 resamples" in text and "yes" in text


def test_same_seed_same_interval_and_scores_are_cached(pair_store):
    calls = []
    scorer = BootstrapScorer(10, 5, progress=calls.append)
    from harness.report.reader import StoreView
    from harness.report.stats import paired_comparison

    view = StoreView(pair_store)
    a, b, c = (view.entry("synth", n) for n in ("strong", "weak", "twin"))
    assert scorer.evaluations([a, b], ["P1", "P2"]) == 4 * 11
    first = paired_comparison(a, b, 10, 5, scorer)
    n_first = len(calls)
    paired_comparison(a, c, 10, 5, scorer)
    assert n_first == 4 * 11 and len(calls) == n_first + 2 * 11  # strong was scored once
    again = compare_detectors(pair_store, "synth", "strong", "weak", resamples=10, seed=5)
    assert again.bootstrap["mAP50_95"].ci_low == first.bootstrap["mAP50_95"].ci_low


def test_worker_processes_give_the_same_numbers(pair_store):
    one = compare_detectors(pair_store, "synth", "medium", "weak", resamples=11, seed=2)
    two = compare_detectors(pair_store, "synth", "medium", "weak", resamples=11, seed=2, workers=2)
    assert one.bootstrap == two.bootstrap


def test_pairs_scored_on_different_samples_are_refused(tmp_path):
    from harness.evaluation import SampleMismatchError

    store = synthetic_store(tmp_path, folds=("P1",), per_fold=5, detectors={"a": "strong"})
    rng = np.random.default_rng(1)
    gt = make_gt(4, rng)  # other images
    write_run(store, RunKey("synth", "b", "c2", "P1", 0), gt, make_detections(gt, rng))
    with pytest.raises(SampleMismatchError, match="image count"):
        compare_detectors(store, "synth", "a", "b", resamples=5)


def test_missing_predictions_and_bad_names_are_clear_errors(tmp_path):
    store = synthetic_store(tmp_path, folds=("P1",), per_fold=4)
    store.run(RunKey("synth", "beta", "c2", "P1", 0)).predictions_path.unlink()
    with pytest.raises(StoreError, match="predictions.json: missing"):
        compare_detectors(store, "synth", "alpha", "beta", resamples=3)
    with pytest.raises(StoreError, match="no finished runs of 'gamma'.*available: alpha/c2, beta/c2"):
        compare_detectors(store, "synth", "gamma", "beta")
    with pytest.raises(StoreError, match="same runs"):
        compare_detectors(store, "synth", "alpha", "alpha/c2")
    write_run(
        store,
        RunKey("synth", "alpha", "ir8", "P1", 0),
        json.loads(store.run(RunKey("synth", "alpha", "c2", "P1", 0)).gt_path.read_text()),
        [],
    )
    with pytest.raises(HarnessError, match="several encodings"):
        compare_detectors(Store(tmp_path), "synth", "alpha", "beta")


def test_a_stored_number_that_re_scoring_does_not_reproduce_is_noted(tmp_path):
    store = synthetic_store(tmp_path, folds=("P1",), per_fold=4)
    run = store.run(RunKey("synth", "alpha", "c2", "P1", 0))
    m = run.read_metrics()
    m["metrics"]["mAP50_95"] = 0.01
    run.write_metrics({k: v for k, v in m.items() if k not in ("schema", "run")})
    comp = compare_detectors(store, "synth", "alpha", "beta", resamples=3)
    assert any("re-scored mAP50_95 of alpha/c2" in n and "0.0100" in n for n in comp.notes)
    assert not any("beta" in n for n in comp.notes)


def test_compare_detectors_command(cli_runner, pair_store):
    res = cli_runner(["compare-detectors", "strong", "weak/c2", "--dataset", "synth", "--store", str(pair_store.root),
                      "--resamples", "20"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert any(line.startswith("mean ± SD") for line in lines)
    assert "20 resamples (20 valid), seed 0" in res.output
    res = cli_runner(["compare-detectors", "strong", "weak", "--dataset", "synth", "--store", str(pair_store.root),
                      "--resamples", "0", "--format", "json"])
    data = json.loads(res.output)
    assert data["bootstrap"] is None and data["folds"] == ["P1", "P2"]
    res = cli_runner(["compare-detectors", "strong", "nope", "--dataset", "synth", "--store", str(pair_store.root)])
    assert res.exit_code == 2 and "no finished runs of 'nope'" in res.output
