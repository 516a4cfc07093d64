"""A report from a results store filled by real small runs, and the HTML page in headless Chromium.

The store is filled once per session by the commands a user runs (in-process): ``harness run`` of the example
plugin's two detectors (single- and dual-stream TinyDet) on every project-grouped fold of the tiny synthetic M3T
(1 epoch at 64 px), ``harness ablate`` over three encodings, ``harness profile`` of both detectors, the two
sensing analyses, and the same two detectors on a second dataset (the engine tests' ``shapes``) for the
cross-dataset table. Nothing in it is written by hand.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

for _module in ("harness.evaluation", "harness.runner", "harness.cache", "harness.profiling"):
    pytest.importorskip(_module)

from engine_helpers import set_args  # noqa: E402
from report_fixtures import TINY_RUN, chromium_screenshot, cli, needs_chromium, tinydet_on_path  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

FAST = [*TINY_RUN, "dataset.profile=tiny"]
DATASET = "m3t-synth"


def _fill(root: Path, store: Path) -> None:
    """The runs, ablation, profiles and sensing analyses of ``real_store``, as a user runs them."""
    import harness_tinydet.plugin as tinydet

    from engine_helpers import ShapesPlugin
    from harness.testing import temporary_plugin

    sets = set_args(FAST)
    with (
        temporary_plugin(tinydet, name="tinydet-report-test"),
        temporary_plugin(ShapesPlugin(), name="shapes-report-test"),
    ):
        cli(["run", "--detector", "tinydet", "--dataset", DATASET, "--folds", "all", "--store", str(store), *sets])
        cli(
            [
                "run",
                "--detector",
                "tinydet-dual",
                "--dataset",
                DATASET,
                "--folds",
                "all",
                "--store",
                str(store),
                *sets,
            ]
        )
        cli(
            [
                "ablate",
                "--detector",
                "tinydet",
                "--dataset",
                DATASET,
                "--encodings",
                "c2,ir8,none",
                "--folds",
                "P4+P5",
                "--store",
                str(store),
                *sets,
            ]
        )
        cli(["score-route", str(store / DATASET / "tinydet" / "c2" / "P4+P5" / "seed0")])
        for det in ("tinydet", "tinydet-dual"):
            cli(
                [
                    "run",
                    "--detector",
                    det,
                    "--dataset",
                    "shapes",
                    "--encoding",
                    "test-ir8",
                    "--folds",
                    "all",
                    "--store",
                    str(store),
                    *sets[:-2],
                ]
            )
            cli(
                [
                    "profile",
                    "--detector",
                    det,
                    "--imgsz",
                    "64",
                    "--no-latency",
                    "--no-onnx",
                    "--no-fvcore",
                    "--store",
                    str(store),
                ]
            )
    landmarks = next((root / "data").glob("*/registration/landmarks.json"))
    cli(
        [
            "sensing",
            "registration-error",
            "--landmarks",
            str(landmarks),
            "--dataset",
            DATASET,
            "--store",
            str(store),
        ]
    )
    cli(
        [
            "sensing",
            "displacement",
            "--dataset",
            DATASET,
            "--set",
            "dataset.profile=tiny",
            "--shifts",
            "2,5,10",
            "--store",
            str(store),
        ]
    )


@pytest.fixture(scope="session")
def real_store(tmp_path_factory):
    """Tiny real runs, profiles and sensing analyses in one results store (about 15 s on 2 cores)."""
    import torch

    root = tmp_path_factory.mktemp("real")
    store = root / "store"
    threads = torch.get_num_threads()
    with tinydet_on_path(root, HARNESS_DATA=str(root / "data")):
        try:
            _fill(root, store)
        finally:
            torch.set_num_threads(threads)
    return store


@pytest.fixture(scope="session")
def real_report(real_store, tmp_path_factory):
    from harness.report import build_report

    out = tmp_path_factory.mktemp("report") / "m3t-synth"
    # the galleries draw from the prepared cache the runs used (the fixture's HARNESS_CACHE)
    return build_report(real_store, out=out, resamples=20, seed=0, cache_root=real_store.parent / "cache"), out


@pytest.mark.slow
def test_report_of_real_runs_has_every_section(real_store, real_report):
    from harness.store import Store

    report, out = real_report
    assert report.datasets == [DATASET, "shapes"]
    absent = {f"{s.dataset}/{s.key}": s.absent for s in report.sections if s.absent}
    # the seed's dataset has every section; the second dataset says what would fill its ablation, and has no sensing
    # sections: its runs recorded that it has no sensing stage (its plugin is not even loaded now)
    assert sorted(absent) == ["shapes/ablation"] and "harness ablate" in absent["shapes/ablation"]
    assert not any(
        s.key in ("registration", "displacement", "screening-route") for s in report.sections if s.dataset == "shapes"
    )
    (route,) = [s for s in report.sections if s.key == "screening-route" and s.dataset == DATASET]
    assert [r["run"] for r in route.tables[0].rows] == ["tinydet/c2/P4+P5/seed0"]
    store = Store(real_store)
    titles = [t.title for t in report.tables]
    assert titles[:4] == [
        f"{DATASET}: project-grouped folds (held-out mAP, %)",
        f"{DATASET}: training budget (plateau slope in points/epoch)",
        f"{DATASET}: per category (AP over the folds that contain the category, %)",
        f"{DATASET}: encoding ablation of tinydet (held-out fold P4+P5, %)",
    ]
    # project table: the numbers are the stored ones, the costs those each run measured on its model
    folds = report.tables[0]
    assert [r["detector"] for r in folds.rows] == ["tinydet", "tinydet-dual", "support"]
    assert folds.warning is None
    runs = {(r.key.detector, r.key.encoding, r.key.fold): r.read_metrics() for r in store.runs(DATASET)}
    assert {k[2] for k in runs} == {"P1", "P2", "P3", "P4+P5"}
    for row, enc in zip(folds.rows[:2], ("c2", "ir8")):
        for f in ("P1", "P2", "P3", "P4+P5"):
            assert row[f"{f}:mAP50_95"] == runs[(row["detector"], enc, f)]["metrics"]["mAP50_95"]
        measured = runs[(row["detector"], enc, "P1")]["complexity"]  # measured in the run, not the profile
        assert row["gflops"] == measured["gflops"]["640"]["paper"] > 0
        assert row["params"] == pytest.approx(measured["params_fused"] / 1e6)
    assert folds.rows[0]["images"] == sum(
        runs[("tinydet", "c2", f)]["support"]["images"] for f in ("P1", "P2", "P3", "P4+P5")
    )
    # the ablation: one row per encoding, with the seed's two thermal-only defects
    ablation = report.tables[3]  # after the folds, training budget and per-category tables
    assert [r["encoding"] for r in ablation.rows] == ["c2", "ir8", "none"]
    assert [c.label for c in ablation.columns][-2:] == ["AP50 delamination", "AP50 water_seepage"]
    # paired comparisons with bootstrap intervals that bracket their observed difference
    paired = next(t for t in report.tables if t.name == f"{DATASET}-paired")
    assert len(paired.rows) == 3
    for c in report.comparisons:
        for b in c.bootstrap.values():
            assert b.valid == 20 and b.ci_low <= b.ci_high
    # sensing tables straight from the analyses' JSON
    reg = json.loads(store.sensing_path(DATASET, "registration_error").read_text())
    reg_table = next(t for t in report.tables if "registration" in t.name)
    assert reg_table.rows[-1]["scene"] == "all" and reg_table.rows[-1]["n"] == reg["n"] > 0
    disp_table = next(t for t in report.tables if "displacement" in t.name)
    assert [c.label for c in disp_table.columns][-3:] == ["R(2 px) %", "R(5 px) %", "R(10 px) %"]
    # the figure and every file
    fig = next(f for s in report.sections for f in s.figures if f.name == "accuracy_vs_gflops")
    assert {(p.dataset, p.label) for p in fig.points} == {
        (d, det) for d in (DATASET, "shapes") for det in ("tinydet", "tinydet-dual")
    }
    assert "64x64" in fig.caption and "cpu" in fig.caption and "'paper' convention" in fig.caption
    for name in (
        "report.md",
        "report.html",
        "tidy.csv",
        "figures/accuracy_vs_gflops.png",
        "figures/accuracy_vs_gflops.svg",
    ):
        assert (out / name).stat().st_size > 500, name
    cross = next(t for t in report.tables if t.name == "cross-dataset")
    assert [(r["dataset"], r["detector"]) for r in cross.rows] == [
        (DATASET, "tinydet"),
        (DATASET, "tinydet-dual"),
        ("shapes", "tinydet"),
        ("shapes", "tinydet-dual"),
    ]
    assert cross.warning is None and cross.rows[0]["images"] == folds.rows[0]["images"]
    assert cross.rows[0]["mAP50_95"].mean == folds.rows[0]["mAP50_95"].mean
    tidy = (out / "tidy.csv").read_text().splitlines()
    assert len(tidy) > 100 and all(line.count(",") >= 14 for line in tidy[:50])
    # the evidence of every run's stored analysis: error types, confusion matrices, PR curves, AP per size bin, and
    # one gallery per detector drawn from the prepared samples the runs were trained on
    for ds in (DATASET, "shapes"):
        keys = {s.key: s for s in report.sections if s.dataset == ds}
        assert all(keys[k].figures for k in ("errors", "confusion", "pr")), ds
        assert any(t.name.startswith(f"{ds}-size-ap") for t in keys["sizes"].tables)
        galleries = keys["gallery"].galleries
        assert [g.name for g in galleries] == ["tinydet", "tinydet-dual"] and all(g.thumbs for g in galleries), ds
        for g in galleries:
            assert all(t.path.is_file() and t.data[:3] == b"\xff\xd8\xff" for t in g.thumbs)  # JPEG files
    shapes = next(s for s in report.sections if s.dataset == "shapes" and s.key == "gallery")
    assert any("encoding 'test-ir8' is not installed here" in n for g in shapes.galleries for n in g.notes)
    (m3t,) = [s for s in report.sections if s.dataset == DATASET and s.key == "gallery"]
    assert not any(n for g in m3t.galleries for n in g.notes)
    # each detector's pictures show its own encoding's channel (single-stream c2, dual-stream ir8)
    assert [{t.fourth for t in g.thumbs} for g in m3t.galleries] == [{"c2"}, {"ir8"}]


@pytest.mark.slow
def test_report_command_prints_every_table_of_the_real_store(real_store, tmp_path):
    out = cli(
        [
            "report",
            "--store",
            str(real_store),
            "--out",
            str(tmp_path / "r"),
            "--resamples",
            "0",
            "--file-types",
            "csv",
            "--print",
        ]
    )
    for title in (
        "project-grouped folds",
        "per category",
        "encoding ablation of tinydet",
        "paired comparisons",
        "registration error",
        "C2 amplitude kept under thermal displacement",
    ):
        assert title in out, title
    block = out.split("project-grouped folds (held-out mAP, %)")[1].splitlines()
    rule = block[3]
    ends = [m.end() for m in re.finditer(r"-+", rule)]
    for line in block[4:6]:  # numbers end under the end of their rule
        assert all(line[e - 1] != " " for e in ends[2:-1]), line


# ------------------------------------------------------------------------------------------------ Chromium
@pytest.mark.slow
@needs_chromium
def test_html_report_opens_in_chromium_without_console_errors(real_report, tmp_path):
    import cv2

    _, out = real_report
    # the detector of console messages works: a page with an error is caught
    bad = tmp_path / "bad.html"
    bad.write_text("<!DOCTYPE html><html><body><script>console.error('probe'); nope();</script></body></html>")
    proc, console = chromium_screenshot(bad, tmp_path / "bad.png", tmp_path / "profile-bad", "400,300")
    assert proc.returncode == 0 and any("probe" in ln for ln in console) and any("nope" in ln for ln in console)

    shot = tmp_path / "report.png"
    proc, console = chromium_screenshot(out / "report.html", shot, tmp_path / "profile", "1400,20000")
    assert proc.returncode == 0 and console == [], console
    keep = os.environ.get("HARNESS_REPORT_SCREENSHOT")
    if keep:
        shutil.copyfile(shot, keep)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[1] == 1400 and img.shape[0] >= 3000
    assert shot.stat().st_size > 50_000
    bgr = img.reshape(-1, 3).astype(int)

    def share(rgb: tuple[int, int, int], tol: int = 12) -> float:
        return float(np.mean(np.all(np.abs(bgr - np.array(rgb[::-1])) <= tol, axis=1)))

    assert share((31, 119, 180)) > 1e-5 and share((255, 127, 14)) > 1e-5  # the plot's two detector markers (tab10)
    assert share((238, 242, 246), 2) > 1e-3  # table header cells
    dark = np.mean(img.max(axis=2) < 100)
    assert dark > 0.005  # text
    content = (img.min(axis=2) < 200).any(axis=1)
    last = int(np.flatnonzero(content)[-1])
    assert 2000 < last < img.shape[0] - 100 and content[:last].mean() > 0.4  # a long page, mostly filled, all shown

    # the evidence of the first dataset, in the page's order: confusion matrices, PR curves, one gallery per detector
    from harness.report.pictures import GT_COLOUR

    def rows_with(rgb: tuple[int, int, int], tol: int, part: np.ndarray = img) -> np.ndarray:
        return np.flatnonzero(np.all(np.abs(part.astype(int) - np.array(rgb[::-1])) <= tol, axis=2).any(axis=1))

    def bands(rows: np.ndarray, gap: int = 60) -> list[tuple[int, int]]:
        """Runs of rows, split where ``gap`` rows hold none."""
        if not len(rows):
            return []
        cut = np.flatnonzero(np.diff(rows) > gap)
        return list(
            zip([int(rows[0]), *(int(rows[c + 1]) for c in cut)], [*(int(rows[c]) for c in cut), int(rows[-1])])
        )

    navy = rows_with((8, 48, 107), 10)  # the confusion matrices' darkest cells (Blues) and their colour bar
    legends = bands(rows_with(GT_COLOUR, 30), 100)  # the ground-truth key under each row of gallery pictures
    assert len(navy) > 50 and len(legends) >= 4, (len(navy), legends)  # two galleries of two rows or more
    saturated = np.mean(img.max(axis=2).astype(int) - img.min(axis=2) > 60, axis=1)
    matrices_end = int(navy[navy < legends[0][0]][-1])
    matrices_end += int(np.flatnonzero(saturated[matrices_end:] < 0.05)[0])  # below the last row of cells
    tall = np.convolve((saturated[matrices_end:] > 0.2).astype(int), np.ones(20, int), "valid") == 20
    pictures_top = matrices_end + int(np.flatnonzero(tall)[0])  # 20 rows of colour in a row: a picture, not a line
    assert pictures_top < legends[0][0] < pictures_top + 400  # the first row of pictures, then its key
    between = img[matrices_end:pictures_top]  # after the confusion matrices, before the pictures: the PR panels
    for colour in ((31, 119, 180), (255, 127, 14)):  # both detectors' curves and legend keys (tab10)
        assert len(rows_with(colour, 12, between)) >= 3, colour
    pictures = img[pictures_top : legends[-1][1]]
    orange = np.all(np.abs(pictures.astype(int) - np.array((60, 140, 245))) <= 60, axis=2)  # inferno's mid tones
    assert orange.mean() > 0.01  # the thermal panels' colour map
    html = (out / "report.html").read_text()
    for ds in (DATASET, "shapes"):
        section = html.split(f'<section id="{ds}-gallery">', 1)[1].split("</section>", 1)[0]
        heads = re.findall(r"<h3[^>]*>Galleries: ([^<]+)</h3>", section)
        assert heads == ["tinydet", "tinydet-dual"], heads
        assert section.count('<figure class="thumb"><img src="data:image/jpeg;base64,') >= 4


@pytest.mark.slow
@pytest.mark.parametrize("reference", ["tinydet", "tinydet-dual"])
def test_paired_comparisons_hold_the_reference_detector_against_each_other(real_store, reference):
    """Whichever is more accurate, the reference detector is side A of the detectors' pair."""
    from harness.report.build import dataset_sections
    from harness.report.reader import StoreView

    _, comps = dataset_sections(StoreView(real_store), DATASET, 0, 0, ["delamination"], reference=reference)
    across = [c for c in comps if c.a.split("/")[0] != c.b.split("/")[0]]
    assert across and all(c.a.split("/")[0] == reference for c in across)
