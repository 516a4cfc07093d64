"""`harness compare` on a results store filled by real tiny runs (M3FD pretraining, RGBT-Tiny on both annotation
sources and two encodings); expected numbers are read back from the runs' own metrics.json, never written here."""

from __future__ import annotations

import json
import shutil

import pytest

from eightbit_fixtures import TINY_RUN, invoke
from harness.compare import build_table
from harness.io import read_json
from harness.store import RunKey, Store

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from eightbit_fixtures import trained_store

    return trained_store(tmp_path_factory)


def stored(trained, dataset, encoding, fold):
    return Store(trained["store"]).run(RunKey(dataset, "ours", encoding, fold, 0)).read_metrics()


def pct(x):
    return f"{100 * x:.1f}"


def _merged(text):
    """Header and rows of the text table, its panels (each repeating the first four columns) joined again."""
    panels, current = [], None
    for line in text.splitlines():
        if line.startswith("dataset "):
            current = [line.replace(" [", "[").split()]
            panels.append(current)
        elif current is not None and line and not line.startswith(("-", "AP in", "!")):
            current.append(line.replace(" [", "[").split())
    header, *rows = panels[0]
    for p in panels[1:]:
        header += p[0][4:]
        rows = [r + q[4:] for r, q in zip(rows, p[1:])]
    return header, rows


def test_table_lists_each_dataset_source_and_detector_with_support_and_map(trained):
    res = invoke(["compare", "--datasets", "m3fd,rgbt-tiny", "--store", str(trained["store"])])
    assert res.exit_code == 0, res.output
    header, rows = _merged(res.output)
    assert header == [
        "dataset",
        "GT",
        "detector",
        "encoding",
        "folds",
        "images",
        "instances",
        "mAP50",
        "mAP50:95",
        "SAFit-AP50",
        "SAFit-AP50:95",
    ]
    got = {(r[0], r[1], r[3]): r for r in rows}
    assert list(got) == [
        ("m3fd", "-", "ir8"),
        ("rgbt-tiny", "RGB", "proxy8"),
        ("rgbt-tiny", "T", "ir8"),
        ("rgbt-tiny", "T", "proxy8"),
    ]  # dataset order as asked, then source, then encoding
    for (ds, src, enc), r in got.items():
        fold = {"m3fd": "val", "T": "test-T", "RGB": "test-RGB"}[ds if ds == "m3fd" else src]
        m = stored(trained, ds, enc, fold)
        assert r[2] == "ours[scale=n]" and r[4] == "1"  # labelled with the model options of its runs
        assert (int(r[5]), int(r[6])) == (m["support"]["images"], m["support"]["instances"])
        assert (r[7], r[8]) == (pct(m["metrics"]["mAP50"]), pct(m["metrics"]["mAP50_95"]))
        safit = m["metrics"].get("safit")
        assert (r[9], r[10]) == ((pct(safit["mAP50"]), pct(safit["mAP50_95"])) if safit else ("-", "-"))
    # the two annotation sources of RGBT-Tiny: same images, different instances
    assert got["rgbt-tiny", "RGB", "proxy8"][5] == got["rgbt-tiny", "T", "proxy8"][5]
    assert got["rgbt-tiny", "RGB", "proxy8"][6] != got["rgbt-tiny", "T", "proxy8"][6]
    assert "NOT SAMPLE-MATCHED" not in res.output


def test_json_and_markdown_formats(trained, tmp_path):
    out = tmp_path / "table.json"
    res = invoke(
        ["compare", "--datasets", "rgbt-tiny", "--store", str(trained["store"]), "--format", "json", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["mismatches"] == [] and {r["source"] for r in data["rows"]} == {"T", "RGB"}
    row = next(r for r in data["rows"] if r["source"] == "T" and r["encoding"] == "ir8")
    m = stored(trained, "rgbt-tiny", "ir8", "test-T")
    assert row["map50_95"] == m["metrics"]["mAP50_95"] and row["safit50"] == m["metrics"]["safit"]["mAP50"]
    md = invoke(["compare", "--datasets", "rgbt-tiny", "--store", str(trained["store"]), "--format", "md"]).output
    assert md.startswith("| dataset | GT | detector |") and md.count("\n| rgbt-tiny |") == 3


def test_safit_is_rescored_from_stored_predictions_when_asked(trained):
    from harness.evaluation import evaluate

    table = build_table(trained["store"], ["m3fd"], safit=True)
    (row,) = table.rows
    run = Store(trained["store"]).run(RunKey("m3fd", "ours", "ir8", "val", 0))
    direct = evaluate(read_json(run.gt_path), read_json(run.predictions_path), matching="safit")["metrics"]["safit"]
    assert (row.safit50, row.safit50_95) == (direct["mAP50"], direct["mAP50_95"])
    assert build_table(trained["store"], ["m3fd"]).rows[0].safit50 is None  # not re-scored unless asked


def test_rows_on_different_supports_are_refused_or_labelled(trained, tmp_path):
    store = tmp_path / "store"
    shutil.copytree(trained["store"], store)
    # a real run of another encoding on every second test frame: a different support for the same dataset and source
    res = invoke(
        [
            "run",
            "--detector",
            "ours",
            "--dataset",
            "rgbt-tiny",
            "--encoding",
            "ir8",
            "--set",
            f"dataset.root={trained['rgbt_root']}",
            "--set",
            "dataset.gt=visible",
            "--set",
            "dataset.test_stride=2",
            *TINY_RUN,
            "--store",
            str(store),
        ],
        cache=trained["cache"],
    )
    assert res.exit_code == 0, res.output
    refused = invoke(["compare", "--datasets", "rgbt-tiny", "--store", str(store)])
    assert refused.exit_code == 2
    assert "refusing to compare detectors scored on different samples" in refused.output
    assert "[GT RGB] dataset 'rgbt-tiny' fold 'test-RGB'" in refused.output
    assert "image count: 2 (ours/ir8) vs 3 (ours/proxy8)" in refused.output and "--allow-mismatched" in refused.output
    labelled = invoke(["compare", "--datasets", "rgbt-tiny", "--store", str(store), "--allow-mismatched"])
    assert labelled.exit_code == 0
    assert "NOT SAMPLE-MATCHED" in labelled.output
    rows = {tuple(line.replace(" [scale=n]", "").split()[:5]) for line in labelled.output.splitlines()}
    # with two entries and no majority both RGB rows are suspect; the thermal rows stay unmarked
    assert ("rgbt-tiny", "RGB", "ours", "!", "ir8") in rows and ("rgbt-tiny", "RGB", "ours", "!", "proxy8") in rows
    assert ("rgbt-tiny", "T", "ours", "ir8", "1") in rows


def test_clear_errors_for_missing_store_or_dataset(trained, tmp_path):
    res = invoke(["compare", "--datasets", "rgbt-tiny", "--store", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "no results store here" in res.output
    res = invoke(["compare", "--datasets", "m3t,rgbt-tiny", "--store", str(trained["store"])])
    assert (
        res.exit_code == 2 and "no finished runs for dataset(s) m3t" in res.output and "m3fd, rgbt-tiny" in res.output
    )


def test_text_table_aligns_and_shows_mean_and_sd():
    from harness.compare import CompareRow, CompareTable

    rows = [
        CompareRow("m3t", "-", "ours", "c2", ["P1", "P2"], [0], 120, 900, 0.5, 0.1, 0.25, None),
        CompareRow("rgbt-tiny", "T", "a-longer-name", "proxy8", ["test-T"], [0], 7, 12, None, None, 0.0, None),
    ]
    lines = CompareTable(rows, []).to_text().splitlines()
    header, first, second = lines[0], lines[2], lines[4]
    assert first.startswith("m3t        -   ours") and second.startswith("rgbt-tiny  T   a-longer-name")
    end = header.index("images") + len("images")  # numbers are right-aligned under their header
    assert first[:end].endswith(" 120") and second[:end].endswith(" 7")
    end = header.index("mAP50:95") + len("mAP50:95")
    assert first[:end].endswith("50.0 ± 10.0      25.0") and second[:end].endswith("-       0.0")  # undefined AP: '-'
