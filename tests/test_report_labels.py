"""Every report table carries the labels and the support of the runs it shows: the error-type and object-size tables
mark numbers resting on approximate temperatures, say when their rows saw different samples (one instances row per
entry), and say when a column averages fewer seeds than the runs have; external runs get galleries and the remedy
that fits them; ``harness show RUN_DIR`` names the commands that show a run."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("harness.evaluation")

from harness.report import build_report  # noqa: E402
from harness.store import RunKey  # noqa: E402
from report_fixtures import make_detections, make_gt, synthetic_store, write_run  # noqa: E402

FOLDS = ("P1", "P2")


def _approximate(store, det):
    """Label every run of ``det`` as resting on approximate temperatures, as a run on such samples is stored."""
    for f in FOLDS:
        run = store.run(RunKey("synth", det, "c2", f, 0))
        m = run.read_metrics()
        m["temperatures"] = {"label": "approximate temperatures", "bound_c": 0.6, "approximations": ["no SDK"]}
        run.metrics_path.write_text(json.dumps(m))


def test_error_type_and_size_tables_mark_approximate_temperatures(tmp_path):
    store = synthetic_store(tmp_path / "store", folds=FOLDS, per_fold=6)
    _approximate(store, "beta")
    report = build_report(store, out=None, resamples=0, gallery=False)
    tables = [t for t in report.tables if t.name in ("synth-errors", "synth-size-ap-coco")]
    assert len(tables) == 2
    for table in tables:
        rows = {r["detector"]: r for r in table.rows}
        assert rows["beta"].get("_marks") and set(rows["beta"]["_marks"].values()) == {"~"}, table.name
        assert not rows["alpha"].get("_marks")
        assert any(n.startswith("~ measured on approximate temperatures") for n in table.notes), table.name
        assert "~" in table.to_markdown()


def test_size_tables_of_runs_on_different_samples_show_each_ones_objects_and_say_so(tmp_path):
    store = synthetic_store(tmp_path / "store", folds=("P1",), per_fold=6, detectors={"alpha": "strong"})
    gt = make_gt(4, np.random.default_rng(3), first_id=100)  # other images, other objects, under the same fold
    write_run(
        store, RunKey("synth", "external/other", "external", "P1", 0), gt, make_detections(gt, np.random.default_rng(4))
    )
    report = build_report(store, out=None, resamples=0, gallery=False)
    table = next(t for t in report.tables if t.name == "synth-size-ap-coco")
    support = [r["detector"] for r in table.rows if r.get("_summary")]
    assert support == ["instances (alpha)", "instances (external/other)"]
    assert table.warning and table.warning.startswith("NOT sample-matched")
    assert any("different objects per bin" in n for n in table.notes)
    errors = next(t for t in report.tables if t.name == "synth-errors")
    assert errors.warning and errors.warning.startswith("NOT sample-matched")


def test_a_tide_column_averaging_fewer_seeds_is_said(tmp_path):
    store = synthetic_store(tmp_path / "store", folds=FOLDS, per_fold=6, detectors={"alpha": "strong"}, seeds=(0, 1, 2))
    run = store.run(RunKey("synth", "alpha", "c2", "P1", 2))
    analysis = json.loads(run.analysis_path.read_text())
    analysis["tide"]["dAP50"]["missed"] = None  # this seed stored no value for Miss
    run.analysis_path.write_text(json.dumps(analysis))
    report = build_report(store, out=None, resamples=0, gallery=False)
    table = next(t for t in report.tables if t.name == "synth-errors")
    assert any("alpha: Miss averages fewer seeds" in n and "P1 (2 of 3)" in n for n in table.notes)
    assert not any("FN averages" in n for n in table.notes)


def test_a_store_of_scored_runs_is_told_to_rescore_with_params_not_to_rerun(tmp_path):
    from harness.store import Store

    store = Store(tmp_path / "store")  # only runs of `harness score`
    gt = make_gt(6, np.random.default_rng(1))
    write_run(
        store, RunKey("synth", "external/yolo", "external", "P1", 0), gt, make_detections(gt, np.random.default_rng(2))
    )
    report = build_report(store, out=None, resamples=0, gallery=False)
    sec = next(s for s in report.sections if s.key == "accuracy-gflops" or "GFLOPs" in s.title)
    assert "harness score ... --params M --gflops G --force" in sec.absent
    assert "harness run" not in sec.absent


def test_show_given_a_run_folder_names_the_commands_that_show_a_run(tmp_path, cli_runner):
    store = synthetic_store(tmp_path / "store", folds=("P1",), per_fold=4, detectors={"alpha": "strong"})
    run = store.run(RunKey("synth", "alpha", "c2", "P1", 0))
    res = cli_runner(["show", str(run.path)])
    assert res.exit_code == 2
    text = res.stderr
    assert "is a run folder" in text and f"harness report --store {store.root} --dataset synth --print" in text
    assert "Missing option" not in text
