"""``build_report`` and ``harness report`` on small synthetic stores: files, absent sections, labels, errors."""

from __future__ import annotations

import csv
import io
import re

import numpy as np
import pytest

pytest.importorskip("harness.evaluation")

from harness.errors import HarnessError  # noqa: E402
from harness.report import build_report  # noqa: E402
from harness.store import RunKey  # noqa: E402
from report_fixtures import make_detections, make_gt, synthetic_store, write_run  # noqa: E402

EXTERNAL = re.compile(r"""(?:src|href|url)\s*[=(]\s*["']?\s*(?:https?:|//|ftp:)""", re.I)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("store")
    store = synthetic_store(
        root,
        folds=("P1", "P2"),
        per_fold=4,
        detectors={"alpha": "strong", "beta": "weak"},
        encodings={"alpha": ["ir8"]},
        profiles={"alpha": (2_000_000, 6.0)},
    )
    out = tmp_path_factory.mktemp("out") / "rep"
    return store, out, build_report(store, out=out, resamples=8, seed=1)


def test_report_writes_every_format(built):
    store, out, report = built
    names = {p.relative_to(out).as_posix() for p in report.files}
    assert {
        "report.md",
        "report.html",
        "report.txt",
        "tidy.csv",
        "figures/accuracy_vs_gflops.png",
        "figures/accuracy_vs_gflops.svg",
        "csv/synth-folds.csv",
        "csv/synth-categories.csv",
        "csv/synth-ablation-alpha.csv",
        "csv/synth-paired.csv",
    } <= names
    assert all((out / n).stat().st_size > 0 for n in names)
    assert (out / "figures/accuracy_vs_gflops.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    tidy = list(csv.DictReader(io.StringIO((out / "tidy.csv").read_text())))
    assert {r["table"] for r in tidy} >= {"synth-folds", "synth-categories", "synth-ablation-alpha", "synth-paired"}
    fold_recs = [r for r in tidy if r["table"] == "synth-folds" and r["fold"] == "P1" and r["metric"] == "mAP50"]
    stored = store.run(RunKey("synth", "beta", "c2", "P1", 0)).read_metrics()
    beta = next(r for r in fold_recs if r["detector"] == "beta")
    assert float(beta["value"]) == pytest.approx(stored["metrics"]["mAP50"])
    assert (
        int(beta["images"]) == stored["support"]["images"] and int(beta["instances"]) == stored["support"]["instances"]
    )


def test_absent_sections_are_stated_with_the_command_that_fills_them(built):
    _, out, report = built
    absent = {s.key: s.absent for s in report.sections if s.absent}
    assert "harness sensing registration-error" in absent["registration"]
    assert "harness sensing displacement --dataset synth" in absent["displacement"]
    assert "harness score-route RUN_DIR" in absent["screening-route"]
    md = (out / "report.md").read_text()
    assert md.count("*Absent.*") == len(absent)
    for title in (
        "project-grouped folds",
        "per category",
        "encoding ablation of alpha",
        "paired comparisons",
        "Registration error",
        "C2 under thermal displacement",
        "Accuracy versus GFLOPs",
        "Cross-dataset comparison",
    ):
        assert title in md, title
    assert "beta/c2: Params and GFLOPs absent, run(s) without a complexity record" in md


def test_html_page_is_self_contained(built):
    _, out, report = built
    page = (out / "report.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "<style>" in page and "<svg" in page
    assert "<script" not in page.lower() and "<link" not in page.lower() and "<img" not in page.lower()
    assert not EXTERNAL.search(page)
    assert page.count("<table>") == len(report.tables) >= 4 and "Absent." in page
    assert '<th colspan="2" class="group">P1</th>' in page  # fold headers span their two metrics


def test_text_report_is_aligned(built):
    _, _, report = built
    text = report.to_text()
    block = text.split("synth: project-grouped folds")[1].split("\n\n")[0].splitlines()
    rule = block[3]
    assert set(rule) <= {"-", " "}
    spans = [m.span() for m in re.finditer(r"-+", rule)]
    for line in block[4:6]:
        assert all(line[b - 1] != " " for a, b in spans[2:-1])


def test_unmatched_rows_get_a_loud_label_everywhere(tmp_path):
    store = synthetic_store(tmp_path / "s", folds=("P1",), per_fold=4, detectors={"alpha": "strong"})
    rng = np.random.default_rng(3)
    gt = make_gt(3, rng, first_id=50)
    write_run(store, RunKey("synth", "odd", "c2", "P1", 0), gt, make_detections(gt, rng))
    report = build_report(store, out=tmp_path / "out", resamples=0)
    assert report.tables[0].warning.startswith("NOT sample-matched")
    page = (tmp_path / "out" / "report.html").read_text()
    assert page.count('class="loud"') >= 2  # the page banner and the table's own label
    assert "!!! NOT SAMPLE-MATCHED" in (tmp_path / "out" / "report.txt").read_text()
    paired = next(s for s in report.sections if s.key == "paired")
    assert paired.absent and "image count" in paired.absent


def test_report_command_prints_tables_and_refuses_bad_input(cli_runner, built, tmp_path, monkeypatch):
    store, _, _ = built
    res = cli_runner(
        [
            "report",
            "--store",
            str(store.root),
            "--out",
            str(tmp_path / "r"),
            "--file-types",
            "md",
            "--resamples",
            "0",
            "--print",
        ]
    )
    assert res.exit_code == 0, res.output
    assert "synth: project-grouped folds" in res.output and "Registration error: ABSENT" in res.output
    # --print with --out DIR prints and writes DIR too, naming the files
    assert (tmp_path / "r" / "report.md").exists() and not (tmp_path / "r" / "report.html").exists()
    assert f"-> {tmp_path / 'r' / 'report.md'}" in res.output
    assert "-> " not in res.stdout and "synth: project-grouped folds" in res.stdout  # the files are named on stderr
    (tmp_path / "w").mkdir()
    monkeypatch.chdir(tmp_path / "w")
    res = cli_runner(["report", "--store", str(store.root), "--resamples", "0", "--print"])
    assert res.exit_code == 0 and "synth: project-grouped folds" in res.output and "-> " not in res.output
    assert not (tmp_path / "w" / "reports").exists()  # --print alone prints instead of writing
    res = cli_runner(["report", "--store", str(store.root), "--out", str(tmp_path / "r2"), "--resamples", "0"])
    assert res.exit_code == 0 and "-> " in res.output and "report.html" in res.output
    res = cli_runner(["report", "--store", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "no results store here" in res.output
    res = cli_runner(["report", "--store", str(store.root), "--dataset", "m3t", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "nothing stored for dataset(s) m3t" in res.output and "synth" in res.output
    res = cli_runner(["report", "--store", str(store.root), "--file-types", "pdf", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "unknown file type(s) pdf" in res.output


def test_unreadable_files_are_skipped_and_named(tmp_path):
    store = synthetic_store(tmp_path / "s", folds=("P1", "P2"), per_fold=3, profiles={"alpha": (1e6, 1.0)})
    store.run(RunKey("synth", "beta", "c2", "P2", 0)).metrics_path.write_text("{ not json")
    store.sensing_path("synth", "displacement").parent.mkdir(parents=True, exist_ok=True)
    store.sensing_path("synth", "displacement").write_text("{}x")
    report = build_report(store, out=tmp_path / "out", resamples=0)
    assert any("synth/beta/c2/P2/seed0: skipped" in p and "invalid JSON" in p for p in report.problems)
    disp = next(s for s in report.sections if s.key == "displacement")
    assert disp.absent.startswith("unreadable:") and "displacement.json" in disp.absent
    folds = report.tables[0]
    assert [r["detector"] for r in folds.rows] == ["alpha", "support"]  # beta lost a fold: out of the table, named
    assert any("beta/c2 [P1]" in n for n in folds.notes)
    assert "UNREADABLE FILES IN THE STORE" in (tmp_path / "out" / "report.txt").read_text()
    assert "unreadable files in the store" in (tmp_path / "out" / "report.html").read_text()


def test_an_empty_store_is_a_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(HarnessError, match="holds no finished runs"):
        build_report(tmp_path / "empty")
