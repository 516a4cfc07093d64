"""Training curves in the report: per-epoch loss and held-out mAP from log.jsonl, mean and band over folds, and the
figure on the HTML page in headless Chromium."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from engine_helpers import fast_overrides
from harness.report.curves import METRICS, entry_curves, read_log
from report_fixtures import chromium_screenshot, needs_chromium

RUN = fast_overrides(epochs=3, warmup_epochs=0)


def _rec(epoch, box, cls, m50=None, m5095=None):
    return {
        "epoch": epoch,
        "loss": {"box": box, "cls": cls},
        "metrics": None if m50 is None else {"mAP50": m50, "mAP50_95": m5095},
    }


def test_curves_average_the_runs_that_reached_each_epoch_and_leave_gaps_out(tmp_path):
    a = [_rec(1, 2.0, 1.0, 0.1, 0.05), _rec(2, 1.0, 0.5, 0.3, float("nan")), _rec(3, 0.5, 0.25, 0.4, 0.2)]
    b = [_rec(1, 4.0, 3.0, 0.3, 0.15), _rec(2, 3.0, 2.5)]  # stopped early; epoch 2 not validated
    ec = entry_curves("det/enc", [a, b, []])
    assert ec.runs == 2
    epochs, mean, lo, hi = ec.losses["box"].series()
    assert epochs == [1, 2, 3] and mean == [3.0, 2.0, 0.5] and lo == [2.0, 1.0, 0.5] and hi == [4.0, 3.0, 0.5]
    epochs, mean, lo, hi = ec.metrics["mAP50"].series()
    assert epochs == [1, 2, 3] and mean == pytest.approx([0.2, 0.3, 0.4]) and (lo[0], hi[0]) == (0.1, 0.3)
    epochs, mean, _, _ = ec.metrics["mAP50_95"].series()  # NaN and missing are gaps, never zeros
    assert epochs == [1, 3] and mean == pytest.approx([0.1, 0.2])
    log = tmp_path / "log.jsonl"
    log.write_text(json.dumps(a[0]) + "\nnot json\n\n" + json.dumps(a[1]) + "\n")
    assert [r["epoch"] for r in read_log(log)] == [1, 2]


@pytest.fixture(scope="module")
def curves_report(tmp_path_factory):
    """Two real detectors (the example TinyDet, single and dual stream), both folds of the engine tests' shapes
    dataset, 3 epochs each, and the report of that store."""
    from engine_helpers import ShapesPlugin, tinydet_module
    from harness.report import build_report
    from harness.runner import RunRequest, run
    from harness.testing import temporary_plugin

    root = tmp_path_factory.mktemp("curves")
    mp = pytest.MonkeyPatch()
    mp.setenv("HARNESS_CACHE", str(root / "cache"))
    tinydet_module()
    import harness_tinydet.plugin as tinydet_plugin
    import torch

    threads = torch.get_num_threads()
    try:
        with (
            temporary_plugin(ShapesPlugin(), name="shapes-curves"),
            temporary_plugin(tinydet_plugin, name="tiny-curves"),
        ):
            for det in ("tinydet", "tinydet-dual"):
                run(
                    RunRequest(
                        detector=det,
                        dataset="shapes",
                        encoding="test-ir8",
                        store=root / "store",
                        overrides=RUN,
                        progress=False,
                    )
                )
            report = build_report(root / "store", out=root / "report", resamples=0)
    finally:
        torch.set_num_threads(threads)
        mp.undo()
    return report, root / "report"


@pytest.mark.slow
def test_report_has_a_curves_figure_per_dataset_from_the_logs(curves_report):
    report, out = curves_report
    sec = next(s for s in report.sections if s.key == "curves")
    assert sec.dataset == "shapes" and sec.absent is None
    (fig,) = sec.figures
    assert fig.name == "training_curves_shapes" and "held-out mAP" in fig.svg
    for label in ("tinydet/test-ir8", "tinydet-dual/test-ir8"):
        assert f"{label}: training loss (mean of 2 runs)" in fig.svg
    assert (out / "figures" / "training_curves_shapes.png").stat().st_size > 5_000
    html = (out / "report.html").read_text()
    section = html.split('<section id="shapes-curves">', 1)[1].split("</section>", 1)[0]
    assert "<svg" in section and "training_curves_shapes.png" in section
    assert "figures/training_curves_shapes.png" in (out / "report.md").read_text()


@pytest.mark.slow
@needs_chromium
def test_chromium_screenshot_shows_the_curves(curves_report, tmp_path):
    import cv2

    _, out = curves_report
    shot = tmp_path / "page.png"  # a tall window: the error analysis and the galleries come before the curves
    proc, _ = chromium_screenshot(out / "report.html", shot, tmp_path / "profile", "1400,12000")
    assert proc.returncode == 0, proc.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[1] == 1400
    pixels = img.reshape(-1, 3).astype(int)

    def share(hex_color: str, tol: int = 10) -> float:
        rgb = [int(hex_color[i : i + 2], 16) for i in (1, 3, 5)]
        return float(np.mean(np.all(np.abs(pixels - np.array(rgb[::-1])) <= tol, axis=1)))

    # the two mAP colours exist only in the curves figure (the store has no profile, so no accuracy figure)
    for _, _, color in METRICS:
        assert share(color) > 2e-5, f"no {color} pixels: the curves are not on the page"
    assert share("#1f77b4") > 2e-5  # the first loss component
