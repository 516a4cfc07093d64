"""The reference benchmark and reference results, end to end on tiny real runs.

The example plugin's TinyDet stands in for the reference detectors: ``harness benchmark run`` trains its cells in two
lanes (``harness run`` processes), a second call finds nothing left to do, ``harness benchmark export`` writes a
compact reference store, a user's store of another detector is reported beside it (paired, since both were trained
at the same budget on the same samples), a store trained on another synthetic seed is refused, and one reference
cell trained again from the references' own configuration gives identical metrics and predictions.
"""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import pytest

from engine_helpers import set_args
from report_fixtures import TINY_RUN, TINYDET_SRC, cli, tinydet_on_path

for _module in ("harness.evaluation", "harness.runner", "harness.cache"):
    pytest.importorskip(_module)

FAST = [*TINY_RUN, "dataset.profile=tiny"]
FOLDS = "P1,P4+P5"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A tiny benchmark (TinyDet, 2 folds x 2 seeds, 1 epoch at 64 px) run in lanes, and its export."""
    root = tmp_path_factory.mktemp("bench")
    shim = root / "plugins"
    shim.mkdir()
    # the lanes' `harness run` processes find the plugin the way an unpackaged plugin is found
    (shim / "tinydet_shim.py").write_text("from harness_tinydet.plugin import *  # noqa: F401,F403\n")
    from harness.testing import reset_plugins

    store = root / "store"
    sets = set_args(FAST)
    with tinydet_on_path(
        root,
        HARNESS_DATA=str(root / "data"),
        HARNESS_PLUGINS_DIR=str(shim),
        PYTHONPATH=os.pathsep.join([str(TINYDET_SRC), os.environ.get("PYTHONPATH", "")]),
    ):
        reset_plugins()  # this process loads the plugin from HARNESS_PLUGINS_DIR too, as the lanes do
        try:
            cells = [
                "benchmark",
                "run",
                "--store",
                str(store),
                "--detectors",
                "tinydet",
                "--folds",
                FOLDS,
                "--seeds",
                "0,1",
            ]
            first = cli([*cells, "--no-ablation", "--lanes", "2", *sets])
            again = cli([*cells, "--no-ablation", "--dry-run", *sets])
            yield {"root": root, "store": store, "first": first, "again": again, "sets": sets}
        finally:
            reset_plugins()


def _export(bench, out: Path):
    from harness.benchmark import BenchmarkSpec, finished_cells
    from harness.references import export_references

    spec = BenchmarkSpec(store=bench["store"], detectors=("tinydet",), folds=FOLDS, seeds=(0, 1), ablation=False)
    found, missing = finished_cells(spec)
    assert not missing and len(found) == 4
    return export_references(bench["store"], out, found)


def _user_run(bench, folds: str, store: Path, *extra: str) -> None:
    """A user's run of the other TinyDet (dual-stream) at the tiny benchmark's profile and settings, seed 0."""
    cli(
        [
            "run",
            "--detector",
            "tinydet-dual",
            "--dataset",
            "m3t-synth",
            "--folds",
            folds,
            "--seeds",
            "0",
            "--store",
            str(store),
            "--profile",
            "benchmark",
            *bench["sets"],
            *extra,
        ]
    )


def test_lanes_train_every_cell_and_a_second_call_has_nothing_left(bench):
    assert bench["first"].count("trained") == 4, bench["first"]
    assert "benchmark: 4 cells" in bench["first"]
    assert "0 cell(s) to run, 4 finished" in bench["again"]
    logs = sorted((bench["store"] / "_benchmark" / "logs").glob("*.log"))
    assert len(logs) == 4
    timing = json.loads((bench["store"] / "_benchmark" / "timing.json").read_text())
    assert timing["calls"][0]["cells"] == 4 and timing["calls"][0]["lanes"] == 2 and timing["cpu_s"] > 0


def test_every_run_records_its_samples_by_content(bench):
    from harness.store import Store

    runs = list(Store(bench["store"]).runs(dataset="m3t-synth"))
    by_fold: dict[str, set[str]] = {}
    for r in runs:
        s = json.loads(r.metrics_path.read_text())["samples"]
        assert s["encoding"] == r.key.encoding and len(s["held_out"]) == 32 and s["aligned"]["held_out"]
        by_fold.setdefault(r.key.fold, set()).add(s["held_out"])
    assert all(len(v) == 1 for v in by_fold.values())  # seeds of a fold: the same samples
    assert by_fold["P1"] != by_fold["P4+P5"]


def test_export_is_compact_and_reads_back(bench, tmp_path):
    from harness.references import load_references

    manifest = _export(bench, tmp_path / "refs")
    assert manifest["bytes"] < 10 * 2**20 and len(manifest["cells"]) == 4
    assert set(manifest["samples"]) == {"P1/c2", "P4+P5/c2"}
    assert manifest["generator"]["seed"] == 0 and manifest["training"]["imgsz"] == 64
    run = tmp_path / "refs" / "m3t-synth" / "tinydet" / "c2" / "P1" / "seed0"
    assert not (run / "checkpoints").exists() and not (run / "predictions.json").exists()
    assert not (run / "log.jsonl").exists() and (run / "log.jsonl.gz").is_file()  # the training log, compressed
    original = json.loads(
        (bench["store"] / "m3t-synth" / "tinydet" / "c2" / "P1" / "seed0" / "predictions.json").read_text()
    )
    from harness.io import read_json, unpack_detections

    assert unpack_detections((run / "predictions.npz").read_bytes()) == original  # packed, value for value
    assert json.loads(gzip.decompress((run / "gt.json.gz").read_bytes())) == read_json(run / "gt.json.gz")
    refs = load_references(tmp_path / "refs")
    runs = refs.runs()
    assert {r.key.detector for r in runs} == {"ref:tinydet"} and len(runs) == 4
    assert runs[0].predictions() and runs[0].ground_truth()["images"]
    from harness.report.curves import read_log
    from harness.store import Run, RunKey

    logged = Run(tmp_path / "refs", RunKey("m3t-synth", "tinydet", "c2", "P1", 0))
    assert logged.log_path.name == "log.jsonl.gz"
    epochs = [r["epoch"] for r in read_log(logged.log_path)]
    assert epochs and epochs == [r["epoch"] for r in logged.read_log()]


def test_export_refuses_what_would_take_the_shipped_folders_together_over_their_limit(bench, tmp_path, monkeypatch):
    import harness.references as R
    from harness.errors import StoreError

    beside = tmp_path / "refs" / R.SHIPPED_FOLDERS[1]  # another suite's references, already in the folder
    beside.mkdir(parents=True)
    (beside / "blob").write_bytes(b"x" * 200_000)
    size = _export(bench, tmp_path / "refs" / R.SHIPPED)["bytes"]  # fits beside it
    monkeypatch.setattr(R, "MAX_TOTAL_BYTES", size + 150_000)
    with pytest.raises(StoreError, match=r"together") as err:
        _export(bench, tmp_path / "refs" / R.SHIPPED)
    assert R.SHIPPED_FOLDERS[1] in str(err.value) and "0.20 MB" in str(err.value)
    assert (tmp_path / "refs" / R.SHIPPED).is_dir()  # the folder exported before is kept
    assert not (tmp_path / "refs" / f"{R.SHIPPED}.tmp").exists()


def test_the_shipped_reference_folders_fit_together():
    from harness.references import MAX_TOTAL_BYTES, SHIPPED_FOLDERS, shipped_root

    sizes = {
        n: sum(p.stat().st_size for p in (shipped_root() / n).rglob("*") if p.is_file())
        for n in SHIPPED_FOLDERS
        if (shipped_root() / n).is_dir()
    }
    assert sizes and sum(sizes.values()) <= MAX_TOTAL_BYTES, sizes


def test_a_users_detector_is_compared_with_the_references_without_training_them(bench, tmp_path):
    from harness.references import load_references
    from harness.report import build_report

    _export(bench, tmp_path / "refs")
    user = tmp_path / "user"
    _user_run(bench, FOLDS, user)
    report = build_report(
        user, ["m3t-synth"], resamples=20, references=load_references(tmp_path / "refs"), gallery=False
    )
    text = report.to_text()
    assert "ref:tinydet" in text and "Reference results (4 runs" in text
    paired = next(s for s in report.sections if s.key == "paired")
    assert paired.tables, paired.notes
    assert "ref:tinydet" in paired.tables[0].to_text() and "tinydet-dual" in paired.tables[0].to_text()
    out = cli(
        [
            "compare-detectors",
            "ref:tinydet",
            "tinydet-dual",
            "--dataset",
            "m3t-synth",
            "--store",
            str(user),
            "--reference-results",
            str(tmp_path / "refs"),
            "--resamples",
            "20",
            "--no-progress",
        ]
    )
    assert "ref:tinydet" in out


def test_references_on_other_samples_are_refused_naming_the_seed(bench, tmp_path):
    _export(bench, tmp_path / "refs")
    other = tmp_path / "other"
    _user_run(bench, "P1", other, "--set", "dataset.seed=1")
    out = cli(
        [
            "report",
            "--store",
            str(other),
            "--reference-results",
            str(tmp_path / "refs"),
            "--out",
            str(tmp_path / "r"),
            "--resamples",
            "0",
            "--no-progress",
        ],
        code=2,
    )
    assert "other samples" in out and "seed 1 vs 0" in out


def test_another_training_budget_is_shown_beside_not_paired(bench, tmp_path):
    from harness.references import load_references
    from harness.report import build_report

    _export(bench, tmp_path / "refs")
    user = tmp_path / "budget"
    _user_run(bench, "P1", user, "--set", "protocol.imgsz=96")
    report = build_report(
        user, ["m3t-synth"], resamples=0, references=load_references(tmp_path / "refs"), gallery=False
    )
    folds = next(s for s in report.sections if s.key == "folds")
    assert "ref:tinydet" in folds.tables[0].to_text()
    assert any("not paired" in n for n in folds.notes)
    paired = next(s for s in report.sections if s.key == "paired")
    assert all("ref:" not in t.to_text() for t in paired.tables)


def test_one_reference_cell_trained_again_is_identical(bench, tmp_path):
    from harness.benchmark import rerun_cell
    from harness.references import load_references

    _export(bench, tmp_path / "refs")
    refs = load_references(tmp_path / "refs")
    result = rerun_cell(refs, "tinydet", "c2", "P1", 1, tmp_path / "rerun")
    assert result["identical"], result
    assert result["mAP50"][0] == result["mAP50"][1]


def test_a_rerun_that_differs_is_reported(bench, tmp_path):
    from harness.benchmark import rerun_cell
    from harness.references import load_references

    _export(bench, tmp_path / "refs")
    metrics = tmp_path / "refs" / "m3t-synth" / "tinydet" / "c2" / "P1" / "seed0" / "metrics.json"
    m = json.loads(metrics.read_text())
    m["metrics"]["mAP50"] = 0.123456  # as if the references had been made by other code
    metrics.write_text(json.dumps(m))
    result = rerun_cell(load_references(tmp_path / "refs"), "tinydet", "c2", "P1", 0, tmp_path / "rerun")
    assert not result["identical"] and any("mAP50 0.1235 vs " in d for d in result["differences"])


def test_progress_eta_uses_measured_epochs_and_relative_costs():
    from harness.benchmark import RELATIVE_COST
    from harness.progress import BenchmarkProgress
    from harness.sweep import SweepJob

    t = [0.0]
    jobs = [SweepJob("ours", "m3t-synth", "c2", f"P{i}", 0, "s") for i in (1, 2)]
    jobs.append(SweepJob("cmadet", "m3t-synth", "ir8", "P1", 0, "s"))
    lines: list[str] = []

    class Sink:
        def write(self, text: str) -> None:
            lines.append(text)

        def flush(self) -> None:
            pass

    p = BenchmarkProgress(
        jobs,
        epochs=10,
        lanes=2,
        stream=Sink(),
        now=lambda: t[0],  # type: ignore[arg-type]
        relative_cost=RELATIVE_COST,
    )
    assert p.eta() is None  # nothing timed yet
    p.started(jobs[0])
    t[0] = 20.0
    p.epoch(jobs[0], 2)  # ours: 10 s per epoch
    # ours P1: 8 epochs left, ours P2: 10, cmadet: 10 x 2.3 x 10 s; over 2 lanes
    assert p.eta() == pytest.approx((80 + 100 + 230) / 2)
    p.finished(jobs[0], ok=True)
    assert "benchmark 1/3 cells (0 running)" in "".join(lines)


def test_unknown_reference_folder_is_a_clear_error(tmp_path):
    out = cli(["report", "--store", str(tmp_path), "--reference-results", str(tmp_path / "nowhere")], code=2)
    assert "no reference results here" in out


def test_claims_are_tested_on_the_data_with_intervals(bench, tmp_path):
    """The claims section on a store laid out as the benchmark's (TinyDet's runs copied under the reference names):
    every claim gets a verdict and intervals computed from the stored predictions."""
    import shutil

    from harness.report.claims import CONTRADICTED, INCONCLUSIVE, SUPPORTED, evaluate_claims
    from harness.report.reader import StoreView

    src = bench["store"] / "m3t-synth" / "tinydet" / "c2"
    store = tmp_path / "store"
    for det, enc in (("ours", "c2"), ("eme", "ir8"), ("icafusion", "ir8"), ("cmadet", "ir8")):
        shutil.copytree(src, store / "m3t-synth" / det / enc)
    for enc in ("none", "ir8", "linear16"):
        shutil.copytree(src / "P4+P5", store / "m3t-synth" / "ours" / enc / "P4+P5")
    from harness.report.stats import BootstrapScorer

    view = StoreView(store)
    cats = list(view.entries("m3t-synth")[0].folds["P1"].metrics["per_category"])
    claims, notes = evaluate_claims(view, "m3t-synth", BootstrapScorer(20, categories=cats))
    assert [c.number for c in claims] == [1, 2, 3, 4, 5, 6]
    assert all(c.verdict in (SUPPORTED, CONTRADICTED, INCONCLUSIVE) for c in claims)  # every entry is there
    # identical runs under every name: no difference can exclude 0, so the comparisons cannot be supported
    assert claims[1].verdict == INCONCLUSIVE and "c2 - ir8: 0.000 [0.000, 0.000]" in claims[1].evidence[0]
    assert claims[5].verdict != SUPPORTED
    assert any("[" in e for c in claims for e in c.evidence) and "this store's runs" in notes[0]


def test_verdicts_combine_parts():
    from harness.report.claims import CONTRADICTED, INCONCLUSIVE, SUPPORTED, Interval, combine

    assert combine([SUPPORTED, SUPPORTED]) == SUPPORTED
    assert combine([SUPPORTED, INCONCLUSIVE]) == INCONCLUSIVE
    assert combine([INCONCLUSIVE, CONTRADICTED]) == CONTRADICTED
    assert Interval(0.1, 0.02, 0.2).above(0.0) and not Interval(0.1, -0.01, 0.2).above(0.0)
    assert Interval(-0.1, -0.2, -0.01).below(0.0) and Interval(0.1, 0.05, 0.2).text() == "0.100 [0.050, 0.200]"


def test_a_detector_run_on_one_fold_is_paired_with_the_references_on_that_fold(bench, tmp_path):
    from harness.references import load_references
    from harness.report import build_report

    _export(bench, tmp_path / "refs")
    user = tmp_path / "onefold"
    _user_run(bench, "P1", user)
    report = build_report(
        user, ["m3t-synth"], resamples=10, references=load_references(tmp_path / "refs"), gallery=False
    )
    paired = next(s for s in report.sections if s.key == "paired")
    rows = [line for t in paired.tables for line in t.to_text().splitlines() if "tinydet-dual" in line]
    assert rows and "ref:tinydet" in rows[0], paired.tables[0].to_text() if paired.tables else paired.notes
    # A - B is the store's detector minus the reference, as `harness compare-detectors tinydet-dual ref:...` reads
    assert rows[0].index("tinydet-dual") < rows[0].index("ref:tinydet")


def test_exporting_an_unfinished_benchmark_is_refused(bench, tmp_path):
    out = cli(["benchmark", "export", "--store", str(bench["store"]), "--out", str(tmp_path / "refs")], code=2)
    assert "is not finished" in out and "ours: no runs" in out and not (tmp_path / "refs").exists()
    out = cli(["benchmark", "export", "--store", str(tmp_path / "nowhere")], code=2)
    assert "no results store here" in out
