"""A detector whose eval-mode boxes are degenerate (x, y, w, h instead of x1, y1, x2, y2, NaN, inverted): the boxes
are counted in metrics.json, and a run where most are dropped stops naming the detector."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from engine_helpers import DetectorsPlugin, ShapesPlugin, single_stream, tinydet_module
from harness.engine.augment import Letterbox
from harness.engine.predict import DegenerateBoxes, detections_to_coco
from harness.errors import PluginError
from harness.testing import temporary_plugin
from scale_helpers import TINY

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: What the faulty detector returns for every image (input pixels): five boxes written as x, y, w, h (inverted as
#: x1, y1, x2, y2), one NaN box, and one x, y, w, h box that happens to look valid (w > x, h > y).
XYWH = [[30.0, 20.0, 10.0, 8.0]] * 5 + [[float("nan"), 1.0, 2.0, 3.0], [2.0, 2.0, 20.0, 20.0]]


def _faulty_plugin():
    m = tinydet_module()

    class XywhDet(m.TinyDet):
        """TinyDet that trains normally but returns its boxes as x, y, w, h in eval mode."""

        def forward(self, inputs, targets=None):
            if self.training:
                return super().forward(inputs, targets)
            boxes = torch.tensor(XYWH)
            return [
                {
                    "boxes": boxes.clone(),
                    "scores": torch.linspace(0.9, 0.3, len(XYWH)),
                    "labels": torch.zeros(len(XYWH), dtype=torch.long),
                }
                for _ in range(len(inputs))
            ]

    return DetectorsPlugin(single_stream("xywh-det", "returns x, y, w, h boxes", XywhDet))


def test_degenerate_boxes_are_counted_by_kind():
    det = {
        "boxes": torch.tensor(XYWH + [[5.0, 5.0, 5.0, 9.0], [-30.0, -30.0, -10.0, -10.0]]),
        "scores": torch.full((9,), 0.5),
        "labels": torch.zeros(9, dtype=torch.long),
    }
    counts = DegenerateBoxes()
    lb = Letterbox(ratio=1.0, pad=(0.0, 0.0), shape=(64, 80))
    out = detections_to_coco(det, 1, lb, num_classes=1, name="d", degenerate=counts)
    assert [o["bbox"] for o in out] == [[2.0, 2.0, 18.0, 18.0]]
    d = counts.to_dict()
    assert (d["returned"], d["inverted"], d["non_finite"], d["zero_size"], d["outside_image"]) == (9, 5, 1, 1, 1)
    assert d["examples"]["inverted"] == [[30.0, 20.0, 10.0, 8.0]] * 3
    with pytest.raises(PluginError, match=r"detector 'd': 7 of the 9 boxes .* degenerate .*5 inverted.*x, y, w, h"):
        counts.check("d")


@pytest.mark.slow
def test_a_run_whose_detector_returns_xywh_boxes_stops_naming_it(tmp_path, monkeypatch):
    from harness.runner import RunRequest, run

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    request = dict(detector="xywh-det", dataset="shapes", folds="A", store=tmp_path / "store", progress=False)
    with (
        temporary_plugin(ShapesPlugin(), name="shapes-degenerate"),
        temporary_plugin(_faulty_plugin(), name="xywh-plugin"),
    ):
        with pytest.raises(PluginError) as err:
            run(RunRequest(**request, overrides=TINY))
        text = str(err.value)
        assert "detector 'xywh-det'" in text and "40 inverted" in text and "8 non finite" in text
        assert "eval.allow_degenerate" in text
        summary = run(RunRequest(**request, overrides=TINY + ["eval.allow_degenerate=true"]))
    [result] = summary.results
    assert result.state == "resumed"  # the trained model was kept: only the scoring was redone
    stored = json.loads((result.path / "metrics.json").read_text())
    d = stored["degenerate_detections"]
    assert (d["returned"], d["inverted"], d["non_finite"]) == (56, 40, 8)
    assert stored["metrics"]["detections"] == 8 == len(json.loads((result.path / "predictions.json").read_text()))
    assert any("xywh-det" in lab and "eval.allow_degenerate" in lab for lab in stored["labels"])
    assert np.isfinite(stored["metrics"]["mAP50"])
