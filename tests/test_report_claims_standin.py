"""The claims read as tests on the stand-in data: what every report says they are about, the architecture-only part of
claim 6 judged at the paper's sizes, low-AP parts not tested on runs that learned nothing, and reference results in
blocks of their own."""

from __future__ import annotations

import html

import numpy as np
import pytest

from harness.report.claims import NOT_TESTED, SUPPORTED, evaluate_claims
from harness.report.reader import StoreView
from harness.report.stats import BootstrapScorer
from harness.report.tables import Column, Table
from harness.store import RunKey, Store
from report_fixtures import make_gt, synthetic_store, write_run

DETS = {"ours": "strong", "eme": "medium", "icafusion": "medium", "cmadet": "weak"}
# the models trained here: EME the fewest GFLOPs (as the benchmark's n-size models); the paper's sizes say ours
PROFILES = {"ours": (8.0e6, 8.12), "eme": (2.0e6, 4.51), "icafusion": (3.0e6, 7.28), "cmadet": (4.0e6, 8.80)}
ABLATION = {"ours": ["none", "ir8", "linear16"]}


@pytest.fixture(scope="module")
def benchmark_like(tmp_path_factory):
    """A store laid out as the benchmark's (four detectors on two folds, the ablation on P4+P5), m3t-synth."""
    root = tmp_path_factory.mktemp("standin")
    synthetic_store(root, "m3t-synth", ("P1", "P4+P5"), 8, DETS, encodings=ABLATION, profiles=PROFILES, seeds=(0, 1, 2))
    return root


_CLAIMS: dict[str, list] = {}


def _claims(root):
    if str(root) in _CLAIMS:
        return _CLAIMS[str(root)]
    view = StoreView(root)
    cats = list(view.entries("m3t-synth")[0].folds["P4+P5"].metrics["per_category"])
    _CLAIMS[str(root)] = evaluate_claims(view, "m3t-synth", BootstrapScorer(10, categories=cats))[0]
    return _CLAIMS[str(root)]


@pytest.mark.slow
def test_every_report_says_the_verdicts_concern_the_stand_in_and_the_benchmark_sizes(benchmark_like, tmp_path):
    from harness.report import build_report

    report = build_report(benchmark_like, out=tmp_path / "r", resamples=0, gallery=False)
    text = report.to_text()
    for rendered in (
        text,
        report.to_markdown(),
        html.unescape((tmp_path / "r" / "report.html").read_text(encoding="utf-8")),
    ):
        flat = " ".join(rendered.split())
        assert "tested on the synthetic stand-in" in flat
        assert "synthetic stand-in data (m3t-synth)" in flat and "benchmark's model sizes" in flat
        assert "neither confirms nor refutes the paper's numbers on the real M3T data" in flat


def test_fewest_gflops_is_judged_at_the_papers_sizes_not_the_models_trained(benchmark_like):
    six = _claims(benchmark_like)[5]
    judged = next(e for e in six.evidence if e.startswith("fewest GFLOPs"))
    assert "paper's sizes" in judged and "ours 28.50" in judged and "eme 109.20" in judged
    assert judged.endswith("(fewest: ours)")
    trained = next(e for e in six.evidence if e.startswith("not judged"))
    assert "eme 4.51" in trained and trained.endswith("(fewest: eme)")
    assert any(e.startswith("accuracy at the sizes trained") for e in six.evidence)


def test_paper_sizes_are_the_detectors_published_figures():
    """The claims' paper sizes are the ``Reference`` figures the built-in detectors print beside their profiles."""
    from harness.plugins import get_host
    from harness.report.claims import PAPER_COMPLEXITY

    host = get_host()
    for name, (params, gflops) in PAPER_COMPLEXITY.items():
        ref = host.detector(name).reference
        assert ref is not None and ref.params_m == pytest.approx(params) and ref.gflops == pytest.approx(gflops)


def test_low_ap_parts_are_not_tested_on_runs_that_learned_nothing(tmp_path):
    """Untrained runs (no detection at all: every AP 0) do not "support" that hard categories stay near zero."""
    store = Store(tmp_path / "untrained")
    rng = np.random.default_rng(0)
    gts = {f: make_gt(8, rng, first_id=1 + 8 * i) for i, f in enumerate(("P1", "P4+P5"))}
    for det in DETS:
        for f, gt in gts.items():
            for s in (0, 1, 2):
                write_run(store, RunKey("m3t-synth", det, "c2", f, s), gt, [], analysis=False)
    for enc in ABLATION["ours"]:
        for s in (0, 1, 2):
            write_run(store, RunKey("m3t-synth", "ours", enc, "P4+P5", s), gts["P4+P5"], [], analysis=False)
    claims = _claims(store.root)
    five, four = claims[4], claims[3]
    assert five.verdict == NOT_TESTED and any("learned nothing" in e for e in five.evidence)
    assert four.verdict == NOT_TESTED and all("not tested" in e for e in four.evidence)
    assert claims[0].verdict != SUPPORTED


def test_trained_runs_are_tested_on_low_ap(benchmark_like):
    five = _claims(benchmark_like)[4]
    assert five.verdict != NOT_TESTED and not any("learned nothing" in e for e in five.evidence)


def test_reference_rows_form_their_own_block_with_their_own_best():
    cols = [Column("detector", "Detector"), Column("map", "mAP50", "pct", best="max")]
    rows = [
        {"detector": "ref:ours", "map": 0.30},
        {"detector": "mine", "map": 0.10},
        {"detector": "ref:eme", "map": 0.20},
        {"detector": "yours", "map": 0.15},
    ]
    t = Table("t", "t", cols, rows)
    t.split_blocks(lambda r: r["detector"].startswith("ref:"), "this store's runs", "reference results")
    assert [r["detector"] for r in t.rows] == ["mine", "yours", "ref:ours", "ref:eme"]
    assert t.best_rows(cols[1]) == {1, 2}  # yours is the store's best, though below both references
    text = t.to_text()
    assert text.index("-- this store's runs") < text.index("mine") < text.index("-- reference results")
    md = t.to_markdown()
    assert "**15.0**" in md and "**30.0**" in md and "| *reference results* |" in md
    from harness.report.html import render_table

    page = render_table(t)
    assert page.count('<tr class="block">') == 2 and page.count('class="r best"') == 2


def test_a_table_of_one_kind_has_no_blocks():
    cols = [Column("detector", "Detector"), Column("map", "mAP50", "pct", best="max")]
    t = Table("t", "t", cols, [{"detector": "a", "map": 0.1}, {"detector": "b", "map": 0.2}])
    t.split_blocks(lambda r: r["detector"].startswith("ref:"), "own", "refs")
    assert "-- own" not in t.to_text() and t.best_rows(cols[1]) == {1}


def test_a_bound_within_its_monte_carlo_error_of_the_threshold_decides_nothing():
    """The verdict of "above 0" on resamples whose 2.5th percentile lies just above 0 would flip with the bootstrap
    seed: it is inconclusive; clear of 0 by the percentile's Monte-Carlo error, it is supported for every seed."""
    from harness.report.claims import INCONCLUSIVE, Interval, above, bound_bands
    from harness.report.stats import percentile_ci

    def verdict(shift: float, seed: int, n: int) -> str:
        v = np.random.default_rng(seed).normal(size=n) + shift
        return above(Interval(float(v.mean()), *percentile_ci(v), *bound_bands(v)), 0.0)

    edge = 1.96  # the 2.5th percentile of N(1.96, 1) is 0
    assert {verdict(edge + 0.02, s, 200) for s in range(20)} == {INCONCLUSIVE}
    assert {verdict(edge + 0.02, s, 2000) for s in range(20)} == {INCONCLUSIVE}
    assert {verdict(edge + 1.5, s, 200) for s in range(20)} == {SUPPORTED}
    # without the bands the same resamples flip between the two
    plain = {
        above(Interval(0.0, *percentile_ci(np.random.default_rng(s).normal(size=200) + edge + 0.02)), 0.0)
        for s in range(20)
    }
    assert plain == {SUPPORTED, INCONCLUSIVE}
