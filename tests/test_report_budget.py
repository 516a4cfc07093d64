"""The report's training budget (epochs, selection protocol, plateau per detector) and its note on weights chosen on
the held-out fold (the seed's protocol), in text, Markdown, HTML and CSV, for the store's runs and reference results
apart."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import pytest

from report_fixtures import synthetic_store

DATASET = "synth"
HELD_OUT = "Weights chosen on the held-out fold (the seed's protocol) for:"


def _plateau(slope: float, metric: str = "held-out fitness, logged only") -> dict[str, Any]:
    return {"slope_per_epoch": slope, "epochs": 10, "reached": slope < 0.2, "threshold": 0.2, "metric": metric}


def _rewrite(store: Path, change: Any) -> None:
    """Apply ``change(detector, fold, seed, metrics)`` to every run's ``metrics.json`` of ``store``."""
    for path in sorted(store.glob(f"{DATASET}/*/*/*/seed*/metrics.json")):
        det, fold, seed = path.parts[-5], path.parts[-3], int(path.parts[-2].removeprefix("seed"))
        metrics = json.loads(path.read_text())
        change(det, fold, seed, metrics)
        path.write_text(json.dumps(metrics))


def _digest(store: Path) -> None:
    """The same samples for every run (so the references are shown and paired beside the store's runs)."""

    def change(det: str, fold: str, seed: int, m: dict[str, Any]) -> None:
        m["samples"] = {"encoding": "c2", "train": "d-train", "held_out": "d-held-out"}
        m["samples"]["aligned"] = {"train": "d-train", "held_out": "d-held-out"}

    _rewrite(store, change)


#: the store's runs, protocol ``last``: ours on the plateau; eme rising in one of its two runs
SLOPES = {("ours", "P1"): 0.05, ("ours", "P2"): -0.1, ("eme", "P1"): 0.43, ("eme", "P2"): 0.12}
EPOCHS = {"ours": 30, "eme": 80}


def _last_protocol(det: str, fold: str, seed: int, m: dict[str, Any]) -> None:
    n = EPOCHS[det] - (fold == "P2")  # epochs differ between runs: the table gives the range
    m["selection"] = {"protocol": "last", "weights": "last", "best_epoch": None, "epochs_run": n}
    m["selection"]["validation_groups"] = []
    m["train"] = {**m["train"], "epochs_run": n, "plateau": _plateau(SLOPES[(det, fold)])}


def _stored_before(det: str, fold: str, seed: int, m: dict[str, Any]) -> None:
    """A run stored before selection and plateau records: best epoch on the held-out fold, no plateau."""
    m["train"] = {**m["train"], "epochs_run": 20, "best_epoch": 14}


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    """One report of a store with selection/plateau records beside reference results without them."""
    from harness.references import export_references, load_references
    from harness.report.build import build_report
    from harness.store import Store

    root = tmp_path_factory.mktemp("budget")
    bench = root / "bench"
    synthetic_store(bench, dataset=DATASET, detectors={"ours": "medium", "cmadet": "weak"})
    _rewrite(bench, _stored_before)
    _digest(bench)
    refs = root / "refs"
    export_references(bench, refs, [r.key for r in Store(bench).runs(dataset=DATASET)])
    user = root / "user"
    synthetic_store(user, dataset=DATASET, detectors={"ours": "strong", "eme": "weak"}, analysis=False)
    _rewrite(user, _last_protocol)
    _digest(user)
    out = root / "report"
    report = build_report(
        user, [DATASET], out, resamples=0, gallery=False, references=load_references(refs), title="budget"
    )
    return report, out


def _section(report: Any, key: str) -> Any:
    return next(s for s in report.sections if s.key == key and s.dataset == DATASET)


def test_the_budget_table_has_one_row_per_detector_in_labelled_blocks(reports):
    report, _ = reports
    sec = _section(report, "budget")
    keys = [s.key for s in report.sections if s.dataset == DATASET]
    assert keys.index("budget") == keys.index("folds") + 1
    rows = {r["detector"]: r for r in sec.tables[0].rows}
    assert [r["_block"] for r in sec.tables[0].rows] == [
        "this store's runs",
        "this store's runs",
        "reference results (ref:DETECTOR)",
        "reference results (ref:DETECTOR)",
    ]
    assert rows["eme"]["epochs"] == "79-80" and rows["ours"]["epochs"] == "29-30"
    assert rows["eme"]["selection"] == "last" and rows["eme"]["reached"] == "1 of 2"
    assert rows["ours"]["reached"] == "2 of 2"
    assert rows["eme"]["slope_mean"] == pytest.approx((0.43 + 0.12) / 2) and rows["eme"]["slope_max"] == 0.43
    assert rows["eme"]["metric"] == "held-out fitness, logged only"
    ref = rows["ref:ours"]
    assert ref["selection"] == "held-out" and ref["epochs"] == "20" and ref["reached"] == "not recorded"
    assert ref["slope_mean"] is None and ref["metric"] == "-"


def test_runs_still_rising_and_runs_without_a_record_are_said_under_the_table(reports):
    report, out = reports
    rising = (
        "eme: 1 of 2 runs still rising (slope up to 0.43 point/epoch over the last 10 epochs): its numbers may rise "
        "with more epochs."
    )
    unrecorded = (
        "Plateau not recorded for ref:cmadet, ref:ours: runs made before plateau records, or without per-epoch scores."
    )
    assert _section(report, "budget").notes == [rising, unrecorded]
    text = " ".join((out / "report.txt").read_text().split())
    md = (out / "report.md").read_text()
    html = (out / "report.html").read_text()
    for doc in (text, md):
        assert rising in doc and unrecorded in doc
    assert "training budget (plateau slope in points/epoch)" in text
    assert "| eme | c2 | 2 | 79-80 | last | 1 of 2 | 0.28 | 0.43 | held-out fitness, logged only |" in md
    assert "*reference results (ref:DETECTOR)*" in md.split("training budget")[1]
    assert "eme: 1 of 2 runs still rising" in html and "Plateau not recorded for ref:cmadet, ref:ours" in html
    assert "Plateau reached</th>" in html


def test_the_budget_table_is_written_as_csv(reports):
    _, out = reports
    rows = list(csv.DictReader(io.StringIO((out / "csv" / "synth-budget.csv").read_text())))
    by = {r["Detector"]: r for r in rows}
    assert set(by) == {"ours", "eme", "ref:ours", "ref:cmadet"}
    assert by["eme"]["Plateau reached"] == "1 of 2" and float(by["eme"]["Slope max"]) == 0.43
    assert by["ref:cmadet"]["Selection"] == "held-out" and by["ref:cmadet"]["Slope max"] == ""
    tidy = list(csv.DictReader(io.StringIO((out / "tidy.csv").read_text())))
    slope = [r for r in tidy if r["table"] == "synth-budget" and r["metric"] == "plateau_slope_max"]
    assert {r["detector"]: r["value"] for r in slope}["eme"] == "0.43"
    assert all(r["unit"] == "points/epoch" for r in slope)


def test_the_held_out_note_names_held_out_runs_and_not_last_runs(reports):
    report, out = reports
    folds = _section(report, "folds").tables[0]
    paired = _section(report, "paired").tables[0]
    notes = [n for t in (folds, paired) for n in t.notes if n.startswith(HELD_OUT)]
    assert len(notes) == 2
    for note in notes:
        named = note.split(HELD_OUT)[1].split(";")[0]
        assert "ref:ours" in named and "ref:cmadet" in named and "eme" not in named and " ours" not in named
        assert "added up to 5.1 points of mAP50:95 over the last epoch" in note
        assert "docs/learning-curves/README.md" in note
    text = " ".join((out / "report.txt").read_text().split())
    md = (out / "report.md").read_text()
    html = (out / "report.html").read_text()
    for doc in (text, md, html):
        assert HELD_OUT.replace("'", "&#x27;" if doc is html else "'") in doc


def test_no_held_out_note_when_every_run_chose_its_last_epoch(tmp_path):
    from harness.report.build import build_report

    store = tmp_path / "store"
    synthetic_store(store, dataset=DATASET, detectors={"ours": "strong", "eme": "weak"})
    _rewrite(store, _last_protocol)
    report = build_report(store, [DATASET], None, resamples=0, gallery=False)
    notes = [n for t in report.tables for n in t.notes] + [n for s in report.sections for n in s.notes]
    assert not [n for n in notes if "held-out fold (the seed's protocol)" in n]
    assert _section(report, "budget").tables[0].rows[0]["selection"] == "last"
    assert "Plateau not recorded" not in report.to_text()


def test_runs_without_records_count_as_the_seeds_protocol(tmp_path):
    from harness.report.build import build_report

    store = tmp_path / "store"
    synthetic_store(store, dataset=DATASET, detectors={"ours": "strong", "eme": "weak"})
    report = build_report(store, [DATASET], None, resamples=0, gallery=False)
    folds = _section(report, "folds").tables[0]
    assert any(n.startswith(f"{HELD_OUT} eme, ours;") for n in folds.notes)
    sec = _section(report, "budget")
    assert {r["reached"] for r in sec.tables[0].rows} == {"not recorded"}
    assert sec.notes == [
        "Plateau not recorded for eme, ours: runs made before plateau records, or without per-epoch scores."
    ]


@pytest.mark.parametrize(
    ("map50", "map5095", "slope", "rising"),
    [
        (0.05, 0.019, 0.15, True),  # fitness 2.2 points: a slope of 0.15 is 7 % of it per epoch, barely started
        (0.05, 0.019, 0.08, False),  # 3.6 %: flat enough
        (0.45, 0.24, 0.15, False),  # fitness 26 points: the absolute threshold decides alone
        (0.05, 0.019, -0.15, False),  # falling is not rising
        (0.0, 0.0, 0.01, True),  # nothing learnt yet and moving: not a plateau
    ],
)
def test_a_slope_under_the_threshold_still_rises_when_it_is_large_for_the_runs_level(map50, map5095, slope, rising):
    from harness.report.tables import _rising_for_its_level

    assert _rising_for_its_level({"metrics": {"mAP50": map50, "mAP50_95": map5095}}, slope) is rising
    assert _rising_for_its_level({}, slope) is False  # no held-out score: the absolute rule alone
