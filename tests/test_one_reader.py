"""The results store has one reader (``harness.report.reader``): ``harness report``, ``compare``,
``compare-detectors`` and the tables ``harness run`` prints read entries, folds, seeds, complexity and labels through
it, and show a result's labels (approximate temperatures, accepted risks) the same way beside the same numbers."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from harness.report.reader import (
    ACCEPTED,
    APPROXIMATE,
    INPUT_RISK,
    ResultLabel,
    StoreView,
    label_notes,
    marks,
    merge_labels,
    read_run,
    run_labels,
)
from harness.store import RunKey, Store
from report_fixtures import QUALITY, make_detections, make_gt, write_run

ROOT = Path(__file__).resolve().parents[1]
READER = "harness/report/reader.py"
#: The modules that build what the four commands print (the runner writes the store; it reads back through
#: ``read_run``, which the scan of ``read_metrics`` below covers).
COMMANDS = [
    "harness/report/compare.py",
    "harness/report/run_tables.py",
    "harness/commands/compare.py",
    "harness/commands/report.py",
    "harness/commands/run.py",
    *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "harness" / "report").glob("*.py")),
]
#: What the reader holds, each defined once in ``harness/``.
CONCEPTS = {
    "FoldResult",
    "Entry",
    "StoreView",
    "StoredRun",
    "ResultLabel",
    "average_seeds",
    "natural_key",
    "normalise_category",
    "annotation_source",
    "mean_sd",
    "label_notes",
}


def _tree(rel: str) -> ast.AST:
    return ast.parse((ROOT / rel).read_text(encoding="utf-8"))


def _call_name(node: ast.Call) -> str | None:
    return getattr(node.func, "attr", None) or getattr(node.func, "id", None)


def test_every_command_reads_the_store_through_the_one_reader():
    """``metrics.json`` is read in one place; the commands' modules open no store and list no runs themselves, and
    mean ± SD, seed averaging and category-name matching are not written a second time."""
    readers, listers, defined, again = [], [], {}, []
    for path in sorted((ROOT / "harness").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        tree = _tree(rel)
        for node in tree.body:  # module-level definitions (the prepared cache's own ``Entry`` is another concept)
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name in CONCEPTS and "cache" not in rel:
                defined.setdefault(node.name, []).append(rel)
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr in ("read_metrics", "metrics_path") and rel != READER:
                if rel != "harness/store.py" and not (node.attr == "metrics_path" and _only_written(rel)):
                    readers.append(f"{rel}:{node.lineno} {node.attr}")
            if isinstance(node, ast.Call) and rel in COMMANDS and rel != READER:
                name = _call_name(node)
                if name == "Store" or (name == "runs" and (node.args or node.keywords)):
                    listers.append(f"{rel}:{node.lineno} {name}")
                if name in ("stdev", "fmean"):
                    again.append(f"{rel}:{node.lineno} {name}")
            if isinstance(node, ast.Constant) and node.value == r"[\s_\-]+" and rel != READER:
                again.append(f"{rel}:{node.lineno} category-name pattern")
    # the sample-matched guard accepts store runs as well as metrics dicts (its API): the one allowed exception
    assert [r.split(":")[0] for r in readers] == ["harness/evaluation/guard.py"], readers
    assert _analysis_readers() == []
    assert listers == []
    assert again == []
    assert {n: where for n, where in defined.items() if len(where) != 1} == {}
    assert {n: where[0] for n, where in defined.items() if n != "mean_sd"} == {
        n: READER for n in CONCEPTS - {"mean_sd", "annotation_source"}
    }
    for rel in (
        "harness/report/compare.py",
        "harness/runner.py",
        "harness/report/run_tables.py",
        "harness/report/tables.py",
        "harness/report/build.py",
        "harness/report/stats.py",
    ):
        imported = {n.module for n in ast.walk(_tree(rel)) if isinstance(n, ast.ImportFrom)}
        assert "harness.report.reader" in imported, rel


def _analysis_readers() -> list[str]:
    """``analysis.json`` is read by ``harness.evaluation.analysis.analysis_of`` (the store defines the file, the
    runner deletes a stale one) and reaches the commands through ``StoredRun.analysis`` alone."""
    allowed = {"harness/store.py", "harness/evaluation/analysis.py", "harness/runner.py"}
    found = []
    for path in sorted((ROOT / "harness").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        for node in ast.walk(_tree(rel)):
            name = node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else None
            if name in ("read_analysis", "analysis_path") and rel not in allowed:
                found.append(f"{rel}:{node.lineno} {name}")
            if name == "analysis_of" and rel in COMMANDS and rel != READER:
                found.append(f"{rel}:{node.lineno} {name}")
    return found


def _only_written(rel: str) -> bool:
    """The runner names ``metrics.json`` to delete a stale one and to hand it to trackers, never to read it."""
    return rel == "harness/runner.py"


# ------------------------------------------------------------------------------------------------ the label concept
OLD_METRICS = {  # a metrics.json as runs and `harness score` have written them (three separate fields)
    "labels": ["detector 'x': 9 of the 10 boxes were degenerate; stored anyway because eval.allow_degenerate is set"],
    "input_risks": ["no-labels: fold 'B' held-out part (B): 8 image(s) and not one box"],
    "temperatures": {
        "label": "approximate temperatures",
        "samples": 8,
        "bound_c": 0.2,
        "approximations": ["emissivity-remap-skipped"],
    },
}


def test_the_three_stored_fields_read_as_one_label_concept():
    labels = run_labels(OLD_METRICS, "B/seed0")
    assert [(lab.kind, lab.mark, lab.runs) for lab in labels] == [
        (ACCEPTED, "†", ("B/seed0",)),
        (INPUT_RISK, "†", ("B/seed0",)),
        (APPROXIMATE, "~", ("B/seed0",)),
    ]
    assert labels[1].text == OLD_METRICS["input_risks"][0] and labels[2].bound_c == 0.2
    assert run_labels({"metrics": {}}) == [] and marks([]) == ""
    assert marks(labels) == "~†" and marks(reversed(labels)) == "~†"  # one order whatever the order read


def test_labels_of_several_runs_merge_and_their_notes_name_the_runs_they_concern():
    worse = {"label": "approximate temperatures", "bound_c": 0.5, "approximations": ["builtin-table"]}
    merged = merge_labels(
        [
            *run_labels(OLD_METRICS, "A/seed0"),
            *run_labels({"temperatures": worse}, "A/seed1"),
            *run_labels({"labels": OLD_METRICS["labels"]}, "B/seed0"),
        ]
    )
    assert [(lab.kind, lab.runs) for lab in merged] == [
        (ACCEPTED, ("A/seed0", "B/seed0")),
        (INPUT_RISK, ("A/seed0",)),
        (APPROXIMATE, ("A/seed0", "A/seed1")),
    ]
    assert merged[2].bound_c == 0.5 and merged[2].record["approximations"] == [
        "emissivity-remap-skipped",
        "builtin-table",
    ]
    notes = label_notes([("det/c2", merged, ["A/seed0", "A/seed1", "B/seed0"])])
    assert notes[0] == (
        "~ measured on approximate temperatures (det/c2: within 0.5 C of DJI's SDK at worst; "
        "builtin-table, emissivity-remap-skipped; docs/sensing.md)"
    )
    assert notes[1] == f"† accepted risk (det/c2, runs A/seed0, B/seed0): {OLD_METRICS['labels'][0]}"
    assert notes[2] == f"† accepted input risk (det/c2, run A/seed0): {OLD_METRICS['input_risks'][0]}"
    # a label of every run of the row names the row only; a table of one row names nothing
    whole = label_notes([(None, [ResultLabel(INPUT_RISK, "risk", ("A/seed0",))], ["A/seed0"])])
    assert whole == ["† accepted input risk: risk"]


# ------------------------------------------------------------------------------------------------ one store, all tables
@pytest.fixture
def labelled_store(tmp_path):
    """Dataset ``synth``: ``alpha`` (two seeds per fold; seed 1 of P1 accepted a risk, seed 1 of P2 is on approximate
    temperatures) and ``beta`` (one seed, no label), on folds P1 and P2; ``alpha/ir8`` on P2 for the ablation."""
    store = Store(tmp_path / "store")
    rng = np.random.default_rng(3)
    gts = {f: make_gt(5, rng, first_id=1 + 5 * i) for i, f in enumerate(("P1", "P2"))}
    extra = {
        ("alpha", "P1", 1): {"labels": OLD_METRICS["labels"]},
        ("alpha", "P2", 1): {"temperatures": OLD_METRICS["temperatures"]},
    }
    for det, enc, quality, seeds, folds in (
        ("alpha", "c2", "strong", (0, 1), ("P1", "P2")),
        ("beta", "c2", "weak", (0,), ("P1", "P2")),
        ("alpha", "ir8", "weak", (0,), ("P2",)),
    ):
        for f in folds:
            for seed in seeds:
                key = RunKey("synth", det, enc, f, seed)
                write_run(
                    store,
                    key,
                    gts[f],
                    make_detections(gts[f], np.random.default_rng([seed, len(det)]), **QUALITY[quality]),
                )
                if (det, f, seed) in extra:
                    run = store.run(key)
                    run.write_metrics({**run.read_metrics(), **extra[(det, f, seed)]})
    return store


ACCEPTED_NOTE = f"† accepted risk (alpha/c2, run P1/seed1): {OLD_METRICS['labels'][0]}"
APPROX_NOTE = "~ measured on approximate temperatures (alpha/c2: within 0.2 C of DJI's SDK at worst"


def test_every_table_shows_the_labels_of_a_seed_beside_the_numbers_it_concerns(labelled_store, cli_runner):
    """Labels of one seed of a fold reach every table: the fold's and the mean's numbers carry the marks, the other
    fold's and the other detector's do not, and each table says what the marks mean. (The report used to average
    seeds without their labels, and ``compare`` knew only the first seed's temperatures and no accepted risk.)"""
    from harness.report.tables import ablation_tables, category_table, cross_dataset_table, project_table

    view = StoreView(labelled_store)
    table = project_table(view, "synth")
    rows = {r["detector"]: r for r in table.rows}
    cell = {k: table.cell(rows["alpha"], c) for c in table.columns for k in [c.key]}
    assert cell["P1:mAP50"].endswith(" †") and cell["P2:mAP50"].endswith(" ~") and cell["mAP50"].endswith(" ~†")
    assert not any(table.cell(rows["beta"], c).endswith(("~", "†", "~†")) for c in table.columns)
    for t in (table, category_table(view, "synth"), cross_dataset_table(view, ["synth"])):
        assert ACCEPTED_NOTE in t.notes and any(n.startswith(APPROX_NOTE) for n in t.notes), t.name
        assert "~†" in t.to_text() and "~†" in t.to_markdown()
    (ablation,), _ = ablation_tables(view, "synth")  # fold P2 only: the temperatures, not P1's accepted risk
    assert any(n.startswith(APPROX_NOTE) for n in ablation.notes) and ACCEPTED_NOTE not in ablation.notes
    res = cli_runner(["compare", "--datasets", "synth", "--store", str(labelled_store.root), "--allow-mismatched"])
    assert res.exit_code == 0, res.output
    alpha = next(
        line for line in res.stdout.splitlines() if line.startswith("synth") and " alpha " in line and " c2 " in line
    )
    assert alpha.count(" ~†") == 2 and ACCEPTED_NOTE.split(":")[0] in res.stdout
    res = cli_runner(
        [
            "compare",
            "--datasets",
            "synth",
            "--store",
            str(labelled_store.root),
            "--allow-mismatched",
            "--format",
            "json",
        ]
    )
    rows_json = {(r["detector"], r["encoding"]): r for r in json.loads(res.stdout)["rows"]}
    assert [lab["kind"] for lab in rows_json[("alpha", "c2")]["labels"]] == [ACCEPTED, APPROXIMATE]
    assert "labels" not in rows_json[("beta", "c2")]  # rows without labels are written as before

    def compare_detectors(a: str, b: str, *extra: str):
        args = ["--dataset", "synth", "--store", str(labelled_store.root), "--resamples", "0", *extra]
        return cli_runner(["compare-detectors", a, b, *args])

    res = compare_detectors("alpha/c2", "beta")
    assert res.exit_code == 0, res.output
    p1 = next(line for line in res.stdout.splitlines() if line.startswith("P1"))
    assert "†" in p1 and "~" not in p1 and ACCEPTED_NOTE.split(":")[0] in res.stdout
    res = compare_detectors("alpha/c2", "beta", "--format", "json")
    paired = json.loads(res.stdout)
    assert [lab["kind"] for lab in paired["labels"]["a"]] == [ACCEPTED, APPROXIMATE] and paired["labels"]["b"] == []
    assert paired["fold_marks"] == {"a": ["†", "~"], "b": ["", ""]}
    res = compare_detectors("beta", "alpha/ir8", "--format", "json")
    assert "label_notes" not in json.loads(res.stdout)  # a pair without labels is written as before


def test_the_run_tables_read_the_labels_of_each_run(labelled_store):
    from harness.report.run_tables import category_table, fold_table
    from harness.runner import RunOutcome, RunSummary

    summary = RunSummary("alpha", "synth", "c2", "smoke", labelled_store.root, {}, ["window", "crack"])
    for f in ("P1", "P2"):
        for seed in (0, 1):
            summary.results.append(
                RunOutcome(read_run(labelled_store.run(RunKey("synth", "alpha", "c2", f, seed))), "skipped", 10, 5)
            )
    printed = fold_table(summary)
    lines = {tuple(line.split()[:2]): line for line in printed.splitlines() if line.startswith(("P1", "P2"))}
    assert "†" in lines[("P1", "1")] and "~" in lines[("P2", "1")]
    assert not any(m in lines[("P1", "0")] + lines[("P2", "0")] for m in ("~", "†"))
    assert next(line for line in printed.splitlines() if line.startswith("mean ± SD")).count("~†") == 3
    assert "† accepted risk (run P1/seed1): detector 'x'" in printed
    assert "~ measured on approximate temperatures (within 0.2 C" in printed
    cats = category_table(summary)
    assert "† accepted risk (run P1/seed1)" in cats and "~†" in cats


def test_seeds_are_averaged_once_for_every_command(labelled_store):
    """The report's fold value, compare's per-fold value and the bootstrap's stored mean are the reader's seed
    average; the means over folds agree between report and compare."""
    from harness.compare import build_table
    from harness.report.tables import project_table

    view = StoreView(labelled_store)
    alpha = view.entry("synth", "alpha/c2")
    stored = [
        read_run(labelled_store.run(RunKey("synth", "alpha", "c2", "P1", s))).metrics["metrics"]["mAP50"]
        for s in (0, 1)
    ]
    assert alpha.folds["P1"].metrics["metrics"]["mAP50"] == pytest.approx(sum(stored) / 2)
    row = next(r for r in project_table(view, "synth").rows if r["detector"] == "alpha")
    compared = next(
        r
        for r in build_table(view, ["synth"], allow_mismatched=True).rows
        if (r.detector, r.encoding) == ("alpha", "c2")
    )
    assert row["P1:mAP50"] == compared.per_fold[0]["map50"] == alpha.folds["P1"].metrics["metrics"]["mAP50"]
    assert row["mAP50"].mean == compared.map50 and row["mAP50"].sd == compared.map50_sd
    assert compared.seeds == [0, 1] and compared.per_fold[0]["seeds"] == [0, 1]


@pytest.mark.parametrize("sensing_stage", [False, True])
def test_the_report_knows_a_datasets_sensing_stage_from_the_store(labelled_store, sensing_stage):
    """``synth`` is registered by no plugin: what its runs recorded (``<dataset>/_dataset.json``) decides whether the
    report keeps the absent registration and displacement sections (the report used to ask the plugin host)."""
    from harness.io import atomic_write_json
    from harness.report.build import dataset_sections

    atomic_write_json(
        labelled_store.dataset_path("synth"),
        {"dataset": "synth", "thermal": "radiometric", "sensing_stage": sensing_stage},
    )
    sections, _ = dataset_sections(StoreView(labelled_store), "synth", 0, 0, ["window"])
    keys = {s.key for s in sections}
    assert ({"registration", "displacement", "screening-route"} <= keys) is sensing_stage
