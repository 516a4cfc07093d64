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
    assert "strong/c2 (A) vs weak/c2 (B)" in text and "40 resamples" in text


def test_a_one_seed_comparison_says_so_and_gives_no_significance_verdict(pair_store, scorer):
    """One training run per fold: the interval over images holds the trained models fixed, so however far it is
    from 0 there is no verdict, in the text, the JSON and the report's table (it used to print "CI excludes 0 ...
    yes")."""
    from harness.report.tables import paired_table

    comp = _compare(pair_store, "strong", "weak", scorer)
    assert comp.bootstrap["mAP50"].excludes_zero  # a clear difference between these two trained models ...
    assert comp.training_runs == 1 and not comp.verdict_allowed
    assert comp.verdict("mAP50") is None and comp.verdict("mAP50_95") is None  # ... and still no verdict
    text = comp.to_text()
    flat = " ".join(text.split())
    assert "One training seed per fold: this compares trained models, not detectors" in flat
    assert "no significance verdict" in flat and "--seeds 0,1,2" in flat
    assert "the trained models fixed" in flat and "Δ 95% CI (images)" in flat
    assert "CI excludes 0" not in text and "yes" not in text.split() and "P(" not in text
    data = json.loads(json.dumps(comp.to_dict()))
    assert data["verdict"] is None and data["training_runs"] == 1 and "compares trained models" in data["seed_note"]
    assert data["bootstrap"]["mAP50"]["level"] == "images" and data["bootstrap"]["mAP50"]["p_a_beats_b"] is None
    table = paired_table([comp], "t", "t")
    (row,) = table.rows
    assert row["verdict"] == "none: 1 seed per fold" and row["seeds"] == "1/1" and "p_beats" not in row
    assert not {"p_beats", "needed"} & {c.key for c in table.columns}  # nothing about new training runs
    assert "yes" not in table.to_text().split()
    assert any("compares trained models, not detectors, and gives no significance verdict" in n for n in table.notes)


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
    res = cli_runner(
        [
            "compare-detectors",
            "strong",
            "weak/c2",
            "--dataset",
            "synth",
            "--store",
            str(pair_store.root),
            "--resamples",
            "20",
        ]
    )
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert any(line.startswith("mean ± SD") for line in lines)
    assert "20 resamples (20 valid), seed 0" in res.output
    res = cli_runner(
        [
            "compare-detectors",
            "strong",
            "weak",
            "--dataset",
            "synth",
            "--store",
            str(pair_store.root),
            "--resamples",
            "0",
            "--format",
            "json",
        ]
    )
    data = json.loads(res.output)
    assert data["bootstrap"] is None and data["folds"] == ["P1", "P2"]
    res = cli_runner(["compare-detectors", "strong", "nope", "--dataset", "synth", "--store", str(pair_store.root)])
    assert res.exit_code == 2 and "no finished runs of 'nope'" in res.output


# ------------------------------------------------------------------------------------------------ training seeds
def test_two_level_bootstrap_by_hand():
    """One fold, images without effect (every resample scores each run as on the original images): the spread is the
    seeds' alone. A's seeds score 0.5, 0.6, 0.7 and B's 0.4 each: every resampled difference is the mean of three
    draws of A minus 0.4, a new run of A always beats one of B, and with V_img = 0 two seeds per fold resolve the
    difference in 80 % of benchmarks ((1.96 + 0.84)^2 var(A) / delta^2 = 7.85 * 0.01 / 0.04 = 1.96)."""
    from harness.report.stats import seeds_needed, two_level

    resamples = 400
    a = np.repeat(np.array([0.5, 0.6, 0.7])[:, None, None], 1 + resamples, axis=1)
    b = np.full((3, 1 + resamples, 1), 0.4)
    (lv,) = two_level([a], [b], ["P1"], seed=0)
    d = lv["a"] - lv["b"]
    assert d.min() >= 0.1 - 1e-12 and d.max() <= 0.3 + 1e-12 and d.std() > 0.02  # seeds resampled, not fixed
    assert set(np.round(lv["single"], 9)) == {0.1, 0.2, 0.3}  # one new run: one seed of each side
    assert np.allclose(lv["fixed"], 0.2) and lv["v_seed"] == pytest.approx(0.01)
    assert lv["seed_sd"]["a"] == pytest.approx(0.1) and lv["seed_sd"]["b"] == pytest.approx(0.0, abs=1e-12)
    assert seeds_needed(0.2, 0.0, lv["v_seed"]) == (2, None)
    # a difference of 0.05 with the same spread: ceil(7.85 * 0.01 / 0.05^2) = 32 seeds per fold; at 50 % power
    # (the interval just excluding 0 at the observed difference) ceil(1.96^2 * 0.01 / 0.05^2) = 16
    assert seeds_needed(0.05, 0.0, 0.01) == (32, None)
    assert seeds_needed(0.05, 0.0, 0.01, power=0.5) == (16, None)
    # with image spread: 0.01 / ((0.05 / 2.8016)^2 - 0.01^2) = 45.8
    assert seeds_needed(0.05, 0.01**2, 0.01) == (46, None)
    # the images alone (SD 0.03) cover 0.05: no number of seeds resolves it
    n, why = seeds_needed(0.05, 0.03**2, 0.01)
    assert n is None and "more images are needed" in why
    # seeds that are copies of one run: the two levels reduce to the image bootstrap (seeds held at their mean)
    rng = np.random.default_rng(0)
    one = rng.uniform(0, 1, (1, 1 + resamples, 2))
    (lv50, _) = two_level([np.repeat(one, 3, axis=0)], [np.zeros((3, 1 + resamples, 2))], ["P1"], seed=0)
    assert np.allclose(lv50["a"], one[0, 1:, 0]) and np.allclose(lv50["fixed"], one[0, 1:, 0])


@pytest.fixture(scope="module")
def seeded_store(tmp_path_factory):
    """Three training seeds per fold (each seed an independent draw of the detector's quality): strong, weak, and
    two detectors of one medium quality (medium, peer); 'pair' has only two seeds."""
    root = tmp_path_factory.mktemp("seeds")
    store = synthetic_store(
        root,
        folds=("P1", "P2"),
        per_fold=8,
        seeds=(0, 1, 2),
        analysis=False,
        detectors={"strong": "strong", "weak": "weak", "medium": "medium", "peer": "medium"},
    )
    for f in ("P1", "P2"):
        gt = json.loads(store.run(RunKey("synth", "strong", "c2", f, 0)).gt_path.read_text())
        for s in (0, 1):
            write_run(
                store,
                RunKey("synth", "pair", "c2", f, s),
                gt,
                make_detections(gt, np.random.default_rng([7, s, int(f[1])]), recall=0.8),
                analysis=False,
            )
    return store


def test_three_seeds_give_the_two_level_intervals_and_a_verdict(seeded_store):
    from harness.report.reader import StoreView
    from harness.report.stats import SEEDS_IMAGES, paired_comparison
    from harness.report.tables import paired_table

    view = StoreView(seeded_store)
    scorer = BootstrapScorer(RESAMPLES, seed=0)
    strong, weak, medium, peer, pair = (view.entry("synth", n) for n in ("strong", "weak", "medium", "peer", "pair"))
    clear = paired_comparison(strong, weak, RESAMPLES, 0, scorer)
    assert clear.seeds == {"a": [3, 3], "b": [3, 3]} and clear.verdict_allowed and clear.seed_note is None
    for key in ("mAP50", "mAP50_95"):
        b = clear.bootstrap[key]
        assert b.level == SEEDS_IMAGES and b.valid == RESAMPLES and b.ci_low > 0.05
        assert clear.verdict(key) == "yes" and b.p_a_beats_b == 1.0 and b.seeds_needed == 1
        assert b.seed_sd["a"] > 0 and b.seed_sd["b"] > 0
        # the observed difference is still the stored mean over folds of the seed means
        stored = [sum(e.folds[f].metrics["metrics"][key] for f in ("P1", "P2")) / 2 for e in (strong, weak)]
        assert b.delta == pytest.approx(stored[0] - stored[1], abs=1e-9)
    # two detectors of the same quality: the interval holds 0, a new run of either wins about as often
    same = paired_comparison(medium, peer, RESAMPLES, 0, scorer)
    for key in ("mAP50", "mAP50_95"):
        b = same.bootstrap[key]
        assert b.ci_low < 0 < b.ci_high and same.verdict(key) == "no" and 0.1 < b.p_a_beats_b < 0.9
    # resampling the seeds widens the interval over the image bootstrap of the same (seed-averaged) runs
    images_only = scorer.scores(medium, ["P1", "P2"])[1:, 1] - scorer.scores(peer, ["P1", "P2"])[1:, 1]
    lo, hi = percentile_ci(images_only)
    assert same.bootstrap["mAP50_95"].ci_high - same.bootstrap["mAP50_95"].ci_low > hi - lo
    text = " ".join(clear.to_text().split())
    assert "two-level bootstrap (training seeds, then images, within each fold)" in text
    assert "P(A > B), new run" in text and "seeds needed" in text and "CI excludes 0" in text
    assert "3 training seed(s) per fold" in text and "compares trained models" not in text
    data = clear.to_dict()
    assert data["verdict"] == {"mAP50": "yes", "mAP50_95": "yes"} and data["training_runs"] == 3
    # two seeds are too few to estimate the spread: no verdict, said so
    few = paired_comparison(strong, pair, RESAMPLES, 0, scorer)
    assert not few.verdict_allowed and few.bootstrap["mAP50"].level == "images"
    assert "Only 2 training seeds per fold" in few.seed_note
    table = paired_table([clear, same, few], "t", "t")
    assert [r["verdict"] for r in table.rows] == [
        "mAP50 yes, mAP50:95 yes",
        "mAP50 no, mAP50:95 no",
        "none: 2 seeds per fold",
    ]
    assert [r["seeds"] for r in table.rows] == ["3/3", "3/3", "3/2"]
    assert table.rows[0]["p_beats"] == 1.0 and table.rows[0]["needed"] == "1"
    assert any(n.startswith("Three or more seeds per fold: two-level bootstrap") for n in table.notes)
    assert any(n.startswith("Fewer than three seeds per fold") for n in table.notes)
