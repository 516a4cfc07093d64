"""Object-size summary: boxes per category and SAFit size bin, at ``harness prepare`` and in the report."""

from __future__ import annotations

import numpy as np
import pytest

from harness.summary import SIZE_BINS, SizeSummary, bin_label, size_bin


def test_bins_are_the_safit_area_ranges_with_the_lower_edge_included():
    assert [(lo, hi) for _, _, lo, hi in SIZE_BINS] == [(0, 64), (64, 256), (256, 1024), (1024, 9216), (9216, np.inf)]
    areas = [0.5, 63.99, 64, 255.9, 256, 1023, 1024, 9215.5, 9216, 1e7]
    assert size_bin(areas).tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert [bin_label(k) for k in range(5)] == ["ET <8", "T 8-16", "S 16-32", "M 32-96", "L >=96"]


def test_bins_have_the_edges_the_safit_evaluation_scores():
    safit = pytest.importorskip("harness.evaluation.safit")
    ranges = [v for k, v in safit.TINY_AREA_RANGES.items() if k != "all"]
    assert [lo for _, _, lo, _ in SIZE_BINS] == [lo for lo, _ in ranges]
    assert [hi for _, _, _, hi in SIZE_BINS[:-1]] == [hi for _, hi in ranges[:-1]]


def test_counts_per_category_and_bin_by_hand():
    s = SizeSummary(["car", "person"])
    s.add(np.array([[0, 0, 7, 9], [10, 10, 18, 18], [0, 0, 100, 100], [5, 5, 45, 30]]), np.array([0, 1, 1, 0]))
    s.add(np.zeros((0, 4)), np.zeros(0, np.int64))  # an image without boxes counts as an image
    # 7x9=63 -> ET; 8x8=64 -> T; 100x100 -> L; 40x25=1000 -> S
    assert s.counts.tolist() == [[1, 0, 1, 0, 0], [0, 1, 0, 0, 1]] and s.images == 2 and s.total == 4
    rows = s.rows()
    assert rows[-2] == ["all", 1, 1, 1, 0, 1, 4] and rows[-1][1:] == ["25.0", "25.0", "25.0", "0.0", "25.0", "100.0"]
    assert (
        s.headline().startswith("object sizes: 25.0 % of 4 boxes are under 8x8 px")
        and "50.0 % under 16x16" in s.headline()
    )
    assert all(len(line) <= 100 for line in s.to_text().splitlines())


def test_coco_and_prepared_views_agree(tmp_path):
    from adapters.datasets import m3fd
    from eightbit_fixtures import write_m3fd
    from harness.cache import prepare
    from harness.config import load_config

    write_m3fd(tmp_path / "m3fd")
    cfg = load_config(protocol="m3fd", overrides=[f"dataset.root={tmp_path / 'm3fd'}"])
    ds = prepare("m3fd", cfg, cache_root=tmp_path / "cache", progress=False)
    a, b = SizeSummary.of_prepared(ds), SizeSummary.of_coco(ds.coco())
    assert a.categories == b.categories == list(m3fd.CATEGORIES)
    assert a.counts.tolist() == b.counts.tolist() and a.images == b.images == 8 and a.total == 16
    # the fixture's boxes are 8 to 15 px a side: all tiny or small
    assert a.counts[:, [0, 3, 4]].sum() == 0


def test_prepare_prints_the_table_for_every_dataset(tmp_path, cli_runner):
    from eightbit_fixtures import write_rgbt_tiny

    write_rgbt_tiny(tmp_path / "rgbt", train_seqs=("DJI_0001_1",), test_seqs=("DJI_0101_1",), frames=2)
    res = cli_runner(
        ["prepare", "--dataset", "rgbt-tiny", "--root", str(tmp_path / "rgbt"), "--cache", str(tmp_path / "cache")]
    )
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("category"))
    header = "category ET <8 T 8-16 S 16-32 M 32-96 L >=96 total"
    assert lines[head].split() == header.split()
    rows = {line.split()[0]: line.split()[1:] for line in lines[head + 2 : head + 9]}
    assert list(rows) == ["ship", "car", "cyclist", "pedestrian", "bus", "drone", "plane"]
    alls = next(line for line in lines if line.startswith("all ")).split()
    assert int(alls[-1]) == 8 and sum(int(v) for v in alls[1:-1]) == 8  # 4 frames x 2 thermal boxes
    assert any(line.startswith("object sizes: ") for line in lines)


# ------------------------------------------------------------------ the report
def _areas(gt):
    return [a["bbox"][2] * a["bbox"][3] for a in gt["annotations"]]


def test_report_sums_disjoint_folds_and_splits_overlapping_ones(tmp_path):
    pytest.importorskip("harness.evaluation")
    from harness.report import build_report
    from harness.store import RunKey, Store
    from report_fixtures import make_detections, make_gt, write_run

    store = Store(tmp_path / "store")
    rng = np.random.default_rng(3)
    gts = {"P1": make_gt(3, rng, first_id=1), "P2": make_gt(3, rng, first_id=4)}
    for f, gt in gts.items():
        for det in ("alpha", "beta"):  # two detectors on the same fold: its ground truth counts once
            write_run(store, RunKey("synth", det, "c2", f, 0), gt, make_detections(gt, rng))
    # the same images as P1 under another annotation source
    write_run(store, RunKey("twin", "alpha", "c2", "test-T", 0), gts["P1"], make_detections(gts["P1"], rng))
    write_run(store, RunKey("twin", "alpha", "c2", "test-RGB", 0), gts["P1"], make_detections(gts["P1"], rng))
    report = build_report(store, out=tmp_path / "rep", resamples=4, seed=0)

    (sec,) = [s for s in report.sections if s.key == "sizes" and s.dataset == "synth"]
    (table,) = [t for t in sec.tables if "-sizes" in t.name]  # the counts; AP per size bin follows them
    want = np.bincount(size_bin(_areas(gts["P1"]) + _areas(gts["P2"])), minlength=5)
    got = next(r for r in table.rows if r["category"] == "all")
    assert [got[f"bin{k}"] for k in range(5)] == want.tolist() and got["total"] == want.sum() > 0
    assert "held-out folds P1, P2" in table.title
    twin = [s for s in report.sections if s.key == "sizes" and s.dataset == "twin"][0]
    assert sorted(t.name for t in twin.tables if "-sizes" in t.name) == ["twin-sizes-test-rgb", "twin-sizes-test-t"]
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "scored boxes per size bin" in md and "ET <8" in md
