"""The report's tables, built from small results stores scored by the one evaluator."""

from __future__ import annotations

import math
import re
import statistics

import numpy as np
import pytest

pytest.importorskip("harness.evaluation")

from harness.report.plots import LABEL_SLOTS, _short_labels, pareto_front, pareto_steps, place_labels  # noqa: E402
from harness.report.reader import StoreView  # noqa: E402
from harness.report.tables import (  # noqa: E402
    Column,
    Interval,
    Stat,
    Table,
    ablation_tables,
    category_table,
    displacement_table,
    format_value,
    project_table,
    records_csv,
    registration_table,
    text_table,
)
from harness.store import RunKey  # noqa: E402
from report_fixtures import make_detections, make_gt, synthetic_store, write_run  # noqa: E402


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return synthetic_store(
        tmp_path_factory.mktemp("tables"),
        folds=("P1", "P2", "P10"),
        per_fold=5,
        detectors={"alpha": "strong", "beta": "weak"},
        encodings={"alpha": ["ir8", "none"]},
        profiles={"alpha": (3_210_000, 8.2), "beta": (1_100_000, 2.5)},
    )


def test_cells_format_fractions_as_percent_and_missing_as_dash():
    assert format_value(0.4567, "pct") == "45.7"
    assert format_value(Stat(0.5, 0.0123, 3), "pct") == "50.0 ± 1.2"
    assert format_value(Stat(0.5, None, 1), "pct") == "50.0"
    assert format_value(Stat(None), "pct") == "-"
    assert format_value(None, "pct") == "-" and format_value(float("nan"), "float") == "-"
    assert format_value(Interval(0.031, -0.002, 0.07), "pp") == "+3.1 [-0.2, +7.0]"
    assert format_value(12345, "int") == "12,345"
    assert format_value(3.21, "float", 2) == "3.21"


def test_text_tables_line_up():
    text = text_table(["name", "value"], [["a", "1.0"], ["longer name", "123.45"]])
    lines = text.splitlines()
    assert lines[1] == "-----------  ------"
    assert [len(line) for line in lines] == [len(lines[1])] * 4
    assert lines[3].endswith("123.45") and lines[2].endswith("   1.0")


def test_pareto_front_keeps_points_no_cheaper_point_beats():
    costs = [1.0, 2.0, 3.0, 4.0, 2.0, 5.0]
    values = [0.2, 0.5, 0.4, 0.6, 0.1, 0.6]
    assert pareto_front(costs, values) == [0, 1, 3]  # 2 and 4 are beaten by 1; 5 ties 3 at a higher cost
    xs, ys = pareto_steps(costs, values, x_max=10.0)
    assert xs == [1.0, 2.0, 4.0, 10.0] and ys == [0.2, 0.5, 0.6, 0.6]
    assert pareto_front([], []) == []


def test_figure_labels_of_close_points_take_slots_that_do_not_cover_each_other():
    # two markers 6 pt apart, labels 40 x 10 pt: the second label cannot sit right-above like the first one
    slots = place_labels([(100.0, 100.0), (104.0, 95.0)], [(40.0, 10.0), (40.0, 10.0)])
    assert slots[0] == LABEL_SLOTS[0] and slots[1] != LABEL_SLOTS[0]
    # far apart, both keep the preferred slot
    assert place_labels([(0.0, 0.0), (300.0, 0.0)], [(40.0, 10.0)] * 2) == [LABEL_SLOTS[0]] * 2
    # a point with no free slot takes the one covering least (here: any; the result is still one slot per point)
    crowded = place_labels([(0.0, 0.0)] * 6, [(40.0, 10.0)] * 6)
    assert len(crowded) == 6 and set(crowded) <= set(LABEL_SLOTS)


def test_figure_labels_drop_model_options_unless_two_would_read_the_same():
    short = _short_labels(["ours [scale=n]", "icafusion [scale=n, tokens=[8, 4, 2]]", "eme"])
    assert short == {"ours [scale=n]": "ours", "icafusion [scale=n, tokens=[8, 4, 2]]": "icafusion", "eme": "eme"}
    both = _short_labels(["ours [scale=n]", "ours [scale=s]"])
    assert both == {"ours [scale=n]": "ours [scale=n]", "ours [scale=s]": "ours [scale=s]"}


def test_project_table_reports_each_fold_the_mean_and_sample_sd_and_the_profile(store):
    view = StoreView(store)
    table = project_table(view, "synth", pareto={"alpha/c2"})
    assert table.warning is None
    rows = {r["detector"]: r for r in table.rows}
    assert [c.label for c in table.columns][2:4] == ["P1 mAP50", "P1 mAP50:95"]  # natural fold order P1, P2, P10
    assert [c.label for c in table.columns][6:8] == ["P10 mAP50", "P10 mAP50:95"]
    folds = {f: store.run(RunKey("synth", "alpha", "c2", f, 0)).read_metrics() for f in ("P1", "P2", "P10")}
    for f, m in folds.items():
        assert rows["alpha"][f"{f}:mAP50_95"] == m["metrics"]["mAP50_95"]
    values = [m["metrics"]["mAP50_95"] for m in folds.values()]
    assert rows["alpha"]["mAP50_95"].mean == pytest.approx(statistics.fmean(values))
    assert rows["alpha"]["mAP50_95"].sd == pytest.approx(statistics.stdev(values))
    assert rows["alpha"]["params"] == pytest.approx(3.21) and rows["alpha"]["gflops"] == 8.2
    assert rows["alpha"]["images"] == 15 == sum(m["support"]["images"] for m in folds.values())
    assert rows["alpha"]["instances"] == sum(m["support"]["instances"] for m in folds.values())
    assert rows["alpha"]["pareto"] == "yes" and rows["beta"]["pareto"] == ""
    support = rows["support"]
    assert support["P1:mAP50"] == "5 img" and support["P1:mAP50_95"] == f"{folds['P1']['support']['instances']} inst"
    assert any("alpha/ir8 [P10]" in n for n in table.notes)  # the ablation runs are named, not mixed in
    text = table.to_text()
    lines = text.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("Detector"))
    spans = [m.span() for m in re.finditer(r"-+", lines[head + 1])]
    for line in lines[head + 2 : head + 5]:  # every right-aligned cell ends under the end of its rule
        for (a, b), col in zip(spans[:-1], table.columns[:-1]):
            if col.align == "r":
                assert line[b - 1] != " " and (b == len(line) or line[b] == " "), (line, col.label)
    best = table.best_rows(next(c for c in table.columns if c.key == "mAP50_95"))
    assert [table.rows[i]["detector"] for i in best] == ["alpha"]
    assert "**" in table.to_markdown()
    recs = [r for r in table.records if r["detector"] == "alpha" and r["metric"] == "mAP50_95" and r["fold"] == "P2"]
    assert len(recs) == 1 and recs[0]["images"] == 5 and recs[0]["value"] == folds["P2"]["metrics"]["mAP50_95"]
    csv = table.to_csv().splitlines()
    assert csv[0].startswith("Detector,Encoding,P1 mAP50,P1 mAP50:95") and "mAP50 mean ± SD sd" in csv[0]


def test_category_means_skip_folds_without_the_category(store):
    table = category_table(StoreView(store), "synth")
    row = next(r for r in table.rows if r["category"] == "water_seepage")
    per_fold = [
        store.run(RunKey("synth", "alpha", "c2", f, 0)).read_metrics()["per_category"]["water_seepage"]
        for f in ("P1", "P2", "P10")
    ]
    assert per_fold[0]["instances"] == 0 and per_fold[0]["AP50"] is None  # the fixture leaves it out of P1
    present = [p["AP50"] for p in per_fold[1:]]
    assert row["folds"] == "2/3" and row["instances"] == sum(p["instances"] for p in per_fold)
    assert row["alpha/c2:AP50"].mean == pytest.approx(statistics.fmean(present)) and row["alpha/c2:AP50"].n == 2


def test_ablation_table_rows_are_encodings_with_the_thermal_defects(store):
    tables, notes = ablation_tables(StoreView(store), "synth", categories=("delamination", "Water Seepage", "mould"))
    assert notes == [] and len(tables) == 1
    t = tables[0]
    assert [r["encoding"] for r in t.rows] == ["c2", "ir8", "none"]
    assert [c.label for c in t.columns][-2:] == ["AP50 delamination", "AP50 water_seepage"]
    assert any("mould" in n for n in t.notes)
    m = store.run(RunKey("synth", "alpha", "none", "P10", 0)).read_metrics()
    none = t.rows[2]
    assert (
        none["recall"] == m["metrics"]["recall"]
        and none["cat:water_seepage"] == m["per_category"]["water_seepage"]["AP50"]
    )
    assert none["images"] == 5 and "P10" in t.title


def test_rows_scored_on_different_samples_are_labelled_loudly(tmp_path):
    store = synthetic_store(tmp_path, folds=("P1", "P2"), per_fold=4, detectors={"alpha": "strong"})
    rng = np.random.default_rng(7)
    for f in ("P1", "P2"):
        gt = make_gt(3 if f == "P2" else 4, rng, first_id=100)
        write_run(store, RunKey("synth", "gamma", "c2", f, 0), gt, make_detections(gt, rng))
    view = StoreView(store)
    table = project_table(view, "synth")
    assert table.warning and table.warning.startswith("NOT sample-matched")
    assert "image-id hash" in table.warning and any("fold 'P2'" in d for d in table.warning_details)
    assert "!!! NOT SAMPLE-MATCHED" in table.to_text()
    assert "**⚠ NOT SAMPLE-MATCHED" in table.to_markdown()
    assert not any(r.get("detector") == "support" for r in table.rows)  # no shared support to show
    assert all(r["sample_matched"] is False for r in table.records if r["metric"].startswith("mAP"))
    assert category_table(view, "synth").warning


def test_sensing_tables_from_the_analyses(tmp_path):
    from harness.api import AlignedSample
    from harness.sensing.analyses import displacement_study, nan_to_none
    from harness.sensing.registration import registration_error

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 600, (12, 2))
    H = np.array([[0.5, 0.0, 10.0], [0.0, 0.5, -4.0], [0.0, 0.0, 1.0]])
    thermal = rgb * 0.5 + [10.0, -4.0] + rng.normal(0, 0.5, (12, 2))
    reg = nan_to_none(registration_error((rgb, thermal), H))
    t = registration_table(reg, "synth")
    overall = t.rows[-1]
    assert overall["scene"] == "all" and overall["n"] == 12
    assert overall["mean"] == pytest.approx(float(np.mean(np.linalg.norm(rgb * 0.5 + [10, -4] - thermal, axis=1))))

    yy, xx = np.mgrid[0:48, 0:64]
    temp = (25 + 3 * np.exp(-((xx - 20) ** 2 + (yy - 20) ** 2) / 8.0)).astype(np.float32)
    sample = AlignedSample(
        image_id=1,
        rgb=np.zeros((48, 64, 3), np.uint8),
        thermal=temp,
        ir8=np.zeros((48, 64), np.uint8),
        boxes=np.array([[16, 16, 24, 24]], np.float32),
        labels=np.array([0], np.int64),
        group="P1",
        meta={},
    )
    disp = nan_to_none(displacement_study([sample], ["crack", "vent"], shifts=(2, 5)))
    d = displacement_table(disp, "synth")
    assert [c.label for c in d.columns] == ["Class", "Boxes", "A(0)", "R(2 px) %", "R(5 px) %"]
    crack = d.rows[0]
    assert crack["boxes"] == 1 and crack["R2"] == pytest.approx(disp["classes"]["crack"]["R"][1])
    assert d.rows[1]["class"] == "vent" and "A0" not in d.rows[1]  # no boxes: '-'
    assert "1 images, 1 boxes" in " ".join(d.notes)
    assert d.to_text().count("\n") > 4


def test_tidy_records_carry_the_support(store):
    table = project_table(StoreView(store), "synth")
    text = records_csv(table.records)
    header = text.splitlines()[0].split(",")
    assert header[:8] == ["table", "dataset", "detector", "encoding", "fold", "category", "metric", "value"]
    assert "images" in header and "instances" in header
    row = next(r for r in table.records if r["fold"] == "P1" and r["metric"] == "mAP50")
    assert row["images"] == 5 and row["instances"] > 0 and row["seeds"] == "0"


def test_a_table_renders_in_every_format_without_rows():
    t = Table("empty", "Nothing", [Column("a", "A"), Column("b", "B", "pct", best="max")])
    assert "Nothing" in t.to_text() and "| A | B |" in t.to_markdown() and t.to_csv() == "A,B\n"
    assert math.isnan(float("nan"))  # formatting never raises on NaN
    t.rows.append({"a": "x", "b": float("nan")})
    assert t.to_text().splitlines()[-1].endswith("-")
