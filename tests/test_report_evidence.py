"""The report's error analysis: TIDE error types, confusion matrices, PR curves, AP per size bin and the galleries'
choice of samples, all from the analyses stored with the runs; runs without one say so in place."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("harness.evaluation")

from harness.evaluation.analysis import ERROR_TYPES, NO_ANALYSIS  # noqa: E402
from harness.report import build_report  # noqa: E402
from harness.report.evidence import collect, confusion, pr_curves  # noqa: E402
from harness.report.gallery import choose, disagreements, worst_picks  # noqa: E402
from harness.report.reader import StoreView  # noqa: E402
from harness.store import RunKey  # noqa: E402
from report_fixtures import CATEGORIES, make_detections, synthetic_store, write_run  # noqa: E402

FOLDS = ("P1", "P2")


@pytest.fixture(scope="module")
def evidence_store(tmp_path_factory):
    """alpha (two seeds per fold), beta and gamma (one), on two folds; delta's runs were stored before the analysis
    existed, and gamma's P2 run lost its analysis."""
    root = tmp_path_factory.mktemp("evidence")
    store = synthetic_store(
        root / "store", folds=FOLDS, per_fold=8, detectors={"alpha": "strong", "beta": "weak", "gamma": "medium"}
    )
    for f in FOLDS:
        gt = json.loads(store.run(RunKey("synth", "alpha", "c2", f, 0)).gt_path.read_text())
        write_run(
            store,
            RunKey("synth", "alpha", "c2", f, 1),
            gt,
            make_detections(gt, np.random.default_rng([5, int(f[1])]), recall=0.8, false_positives=1.0),
        )
        write_run(
            store,
            RunKey("synth", "delta", "c2", f, 0),
            gt,
            make_detections(gt, np.random.default_rng([6, int(f[1])]), recall=0.6),
            analysis=False,
        )
    store.run(RunKey("synth", "gamma", "c2", "P2", 0)).analysis_path.unlink()
    out = root / "report"
    return store, out, build_report(store, out=out, resamples=0)


def _analyses(store, det):
    """fold -> the stored analyses of ``det``'s seeds (read here directly: the test checks the reader's sums)."""
    out = {}
    for f in FOLDS:
        for seed in (0, 1):
            run = store.run(RunKey("synth", det, "c2", f, seed))
            if run.path.exists() and run.analysis_path.exists():
                out.setdefault(f, []).append(run.read_analysis())
    return out


def test_error_types_are_the_fold_means_of_each_folds_seed_mean(evidence_store):
    store, _, report = evidence_store
    table = next(t for t in report.tables if t.name == "synth-errors")
    rows = {r["detector"]: r for r in table.rows}
    assert list(rows) == ["alpha", "beta", "delta", "gamma"]
    alpha = _analyses(store, "alpha")
    for t in ERROR_TYPES:
        per_fold = [np.mean([a["tide"]["dAP50"][t] for a in alpha[f]]) for f in FOLDS]
        assert rows["alpha"][t].mean == pytest.approx(np.mean(per_fold), abs=1e-12)
        assert rows["alpha"][t].n == 2
    assert rows["alpha"]["mAP50"].mean == pytest.approx(
        np.mean([np.mean([a["tide"]["mAP50"] for a in alpha[f]]) for f in FOLDS])
    )
    # gamma: only P1 has an analysis, so its numbers are P1's (n = 1), and a note names the run left out
    gamma = _analyses(store, "gamma")
    assert rows["gamma"]["missed"].n == 1 and rows["gamma"]["missed"].mean == gamma["P1"][0]["tide"]["dAP50"]["missed"]
    assert f"gamma: {NO_ANALYSIS} (run P2/seed0; left out here)" in table.notes
    # delta: no analysis at all; the table says so in place of its numbers
    assert rows["delta"]["mAP50"] == NO_ANALYSIS
    assert table.cell(rows["delta"], table.columns[2]) == NO_ANALYSIS
    assert f"delta: {NO_ANALYSIS} (every run; left out here)" in table.notes


def test_confusion_matrices_sum_the_folds_and_keep_the_background(evidence_store):
    store, out, report = evidence_store
    view = StoreView(store)
    ev = {e.name: e for e in collect(view.entries("synth"), {})}
    labels, matrix, seeds = confusion(ev["beta/c2"])
    assert labels == [*CATEGORIES, "background"] and seeds == 1
    beta = _analyses(store, "beta")
    assert np.array_equal(matrix, sum(np.array(beta[f][0]["confusion"]["matrix"]) for f in FOLDS))
    # every ground-truth object is in its column: found, confused or missed (the background row)
    instances = [sum(beta[f][0]["pr"]["categories"][c]["instances"] for f in FOLDS) for c in CATEGORIES]
    assert matrix[:, :-1].sum(axis=0).tolist() == instances
    assert matrix[-1, -1] == 0 and matrix[:-1, -1].sum() > 0  # false positives on background
    labels, matrix, seeds = confusion(ev["alpha/c2"])  # two seeds: each fold's matrix is their mean
    alpha = _analyses(store, "alpha")
    expected = sum(np.mean([a["confusion"]["matrix"] for a in alpha[f]], axis=0) for f in FOLDS)
    assert seeds == 2 and np.allclose(matrix, expected)
    sec = next(s for s in report.sections if s.key == "confusion")
    (fig,) = sec.figures
    assert "beta" in fig.svg and "alpha (mean of 2 seeds)" in fig.svg and "delta" not in fig.svg
    assert (out / "figures" / "confusion_synth.png").stat().st_size > 5_000


def test_pr_curves_put_every_detector_on_one_plot_per_category_and_average_to_the_table_ap(evidence_store):
    store, _, report = evidence_store
    view = StoreView(store)
    entries = view.entries("synth")
    curves = pr_curves([e for e in collect(entries, {}) if not e.empty])
    assert list(curves) == list(CATEGORIES)
    by_name = {e.label: e for e in entries}
    for cat in CATEGORIES:
        names = [c.name for c in curves[cat]]
        # gamma's only analysed fold (P1) has no water seepage: it has no curve there, rather than a zero one
        assert names == ["alpha/c2", "beta/c2"] + (["gamma/c2"] if cat != "water_seepage" else [])
        for c in curves[cat]:
            # the curve's mean is the mean over the folds that contain the category of each fold's seed-mean AP50
            e = by_name[c.name]
            folds = [f for f in FOLDS if f in e.folds and not (c.name == "gamma/c2" and f == "P2")]
            aps = [e.folds[f].metrics["per_category"][cat]["AP50"] for f in folds]
            aps = [a for a in aps if a is not None]
            assert c.ap50 == pytest.approx(np.mean(aps), abs=1e-5) and c.folds == len(aps)
            assert len(c.recall) == 101 and c.recall[0] == 0.0 and c.recall[-1] == 1.0
    sec = next(s for s in report.sections if s.key == "pr")
    (fig,) = sec.figures
    for cat in CATEGORIES:  # one panel per category, titled with it
        assert f"<!-- {cat} -->" in fig.svg


def test_ap_per_size_bin(evidence_store):
    store, _, report = evidence_store
    tables = [t for t in report.tables if t.name.startswith("synth-size-ap")]
    # the fixture's objects (12-40 px) are mostly COCO-small, so SAFit's bins were stored and get a table too
    assert [t.name for t in tables] == ["synth-size-ap-coco", "synth-size-ap-safit"]
    table = tables[0]
    assert [c.short for c in tables[1].columns[2:7]] == ["extremely_tiny", "tiny", "small", "medium", "large"]
    rows = {r["detector"]: r for r in table.rows}
    beta = _analyses(store, "beta")
    for b in ("small", "medium"):
        values = [beta[f][0]["sizes"]["coco"]["AP50"][b] for f in FOLDS]
        values = [v for v in values if v is not None]
        assert rows["beta"][f"AP50:{b}"].mean == pytest.approx(np.mean(values))
    support = rows["instances"]
    assert support["_summary"] and int(support["AP50:small"].replace(",", "")) == sum(
        beta[f][0]["sizes"]["coco"]["instances"]["small"] for f in FOLDS
    )
    sizes = next(s for s in report.sections if s.key == "sizes")
    assert all(t in sizes.tables for t in tables)


def test_every_format_carries_the_evidence(evidence_store):
    _, out, report = evidence_store
    html = (out / "report.html").read_text()
    for key in ("errors", "confusion", "pr"):
        section = html.split(f'<section id="synth-{key}">', 1)[1].split("</section>", 1)[0]
        assert "<svg" in section, key
    md = (out / "report.md").read_text()
    assert "figures/errors_synth.png" in md and "figures/confusion_synth.png" in md and "figures/pr_synth.png" in md
    assert "error types (TIDE" in report.to_text()
    # without prepared samples the galleries say why, with the rest of the report intact
    gallery = next(s for s in report.sections if s.key == "gallery")
    assert gallery.absent and "prepared data" in gallery.absent


def test_a_store_without_any_analysis_says_so_in_place(tmp_path):
    store = synthetic_store(tmp_path / "store", folds=("P1",), per_fold=4, analysis=False)
    report = build_report(store, out=None, resamples=0, formats=("md",))
    absent = {s.key: s.absent for s in report.sections if s.absent}
    for key in ("errors", "confusion", "pr", "gallery"):
        assert absent[key].startswith(NO_ANALYSIS), key
    assert "--force" in absent["errors"]


# ------------------------------------------------------------------------------------------------ galleries
def _ev(name, folds):
    """A stand-in for ``evidence.Evidence``: ``folds`` maps a fold to one analysis."""
    runs = {f: [SimpleNamespace(name=f"{f}/seed0")] for f in folds}
    return SimpleNamespace(name=name, runs=runs, folds={f: [a] for f, a in folds.items()}, empty=not folds)


def _analysis(found, fp, worst=None):
    return {"gt_found": found, "images": {"image_id": [1, 2, 3], "fp": fp}, "worst": worst or {}}


def test_galleries_start_where_the_detectors_disagree_most():
    # image 1: objects 1-2, image 2: objects 3-5, image 3: object 6 (a crowd region: never counted)
    gt = {"annotations": [{"image_id": i} for i in (1, 1, 2, 2, 2, 3)]}
    a = _ev("a", {"P1": _analysis([1, 1, 1, 0, 0, -1], [0, 0, 4])})
    b = _ev("b", {"P1": _analysis([1, 0, 0, 1, 1, -1], [0, 0, 1])})
    picks, problems = disagreements([a, b], {"P1": gt})
    assert problems == []
    # image 2: three objects split; image 1: one; image 3: none split but false positives 1-4
    assert [(p.image_id, p.kind) for p in picks] == [(2, "disagree"), (1, "disagree"), (3, "disagree")]
    assert "3 objects found by some detectors, missed by others" in picks[0].caption
    assert "false positives 1-4" in picks[2].caption
    assert disagreements([a], {"P1": gt}) == ([], [])  # one detector: nothing to disagree about
    short = _ev("c", {"P1": _analysis([1, 1], [0, 0, 0])})
    assert disagreements([a, short], {"P1": gt})[1] == [
        "fold P1: the runs' analyses do not cover the same ground truth; not compared"
    ]


def test_galleries_then_show_each_categorys_worst_miss_and_most_confident_kept_false_positive():
    worst = {
        "crack": {
            "misses": [
                {"image_id": 7, "bbox": [0, 0, 5, 5], "area": 25.0, "reason": "below_threshold", "best_iou": 0.9},
                {"image_id": 8, "bbox": [0, 0, 9, 9], "area": 81.0, "reason": "missed", "best_iou": 0.0},
                {"image_id": 9, "bbox": [0, 0, 3, 3], "area": 9.0, "reason": "missed", "best_iou": 0.0},
            ],
            "false_positives": [
                {"image_id": 4, "bbox": [1, 1, 2, 2], "score": 0.99, "error": "background", "kept": False},
                {"image_id": 5, "bbox": [1, 1, 2, 2], "score": 0.8, "error": "localisation", "kept": True},
            ],
        }
    }
    other = {
        "crack": {
            "misses": [{"image_id": 3, "bbox": [0, 0, 4, 4], "area": 16.0, "reason": "missed", "best_iou": 0.0}],
            "false_positives": [],
        }
    }
    ev = _ev("a", {"P1": _analysis([], [], worst), "P2": _analysis([], [], other)})
    picks = worst_picks(ev)
    misses = [(p.fold, p.image_id) for p in picks if p.kind == "miss"]
    # nothing near it first, then the largest; a miss only below the threshold last
    assert misses == [("P1", 8), ("P2", 3), ("P1", 9), ("P1", 7)]
    fps = [(p.image_id, p.score) for p in picks if p.kind == "false positive"]
    assert fps == [(5, 0.8)]  # the 0.99 one was not kept at the operating point: it is not drawn
    common = [SimpleNamespace(fold="P1", image_id=8, kind="disagree", category=None)]
    chosen = choose(common, picks, per_category=1, disagree=4)
    # the worst miss's image is already shown (it is where the detectors disagree): the next one is taken
    assert [(p.fold, p.image_id, p.kind) for p in chosen] == [
        ("P1", 8, "disagree"),
        ("P2", 3, "miss"),
        ("P1", 5, "false positive"),
    ]
