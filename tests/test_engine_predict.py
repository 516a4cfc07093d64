"""Inference: detections come back in thermal-frame pixels as COCO results with category_id = label + 1."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from engine_helpers import ENCODINGS, write_dataset
from harness.engine.augment import Letterbox
from harness.engine.data import SampleSource
from harness.engine.predict import detections_to_coco, predict
from harness.errors import PluginError

IR8 = ENCODINGS[0]


class Oracle(nn.Module):
    """Finds the dark-blue 'window' rectangles of the shapes data by colour: boxes in input pixels, label 0."""

    conf, iou, max_det = 0.25, 0.7, 300

    def forward(self, x, targets=None):
        out = []
        for img in x:
            mask = ((img[2] - img[0]) > 0.15).numpy()  # blue well above red
            boxes = []
            if mask.any():
                from scipy import ndimage

                lab, n = ndimage.label(mask)
                for sl in ndimage.find_objects(lab):
                    boxes.append([sl[1].start, sl[0].start, sl[1].stop, sl[0].stop])
            b = torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4)
            out.append(
                {"boxes": b, "scores": torch.full((len(b),), 0.9), "labels": torch.zeros(len(b), dtype=torch.long)}
            )
        return out


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("shapes") / "ds", per_group=6, size=(96, 120))


def test_letterbox_is_undone_exactly():
    lb = Letterbox(ratio=0.5, pad=(0.0, 16.0), shape=(64, 200))
    det = {
        "boxes": torch.tensor([[10.0, 26.0, 30.0, 46.0], [90.0, 40.0, 120.0, 60.0]]),
        "scores": torch.tensor([0.9, 0.4]),
        "labels": torch.tensor([2, 0]),
    }
    out = detections_to_coco(det, 7, lb)
    # the score at the model's full float32 precision (not rounded to 5 decimals)
    assert out[0] == {
        "image_id": 7,
        "category_id": 3,
        "bbox": [20.0, 20.0, 40.0, 40.0],
        "score": float(np.float32(0.9)),
    }
    assert out[1]["bbox"] == [180.0, 48.0, 20.0, 16.0]  # clipped to the 200 x 64 frame
    assert out[1]["category_id"] == 1


def test_predict_returns_thermal_frame_boxes(prepared):
    """An oracle that finds windows in the letterboxed input: mapped back, its boxes are the ground truth."""
    src = SampleSource(prepared, None, IR8)
    dets = predict(Oracle(), src, 64, batch=4)
    assert {d["category_id"] for d in dets} == {1}
    checked = 0
    for k in range(len(src)):
        boxes, labels = src.targets(k)
        gt = boxes[labels == 0]
        mine = np.array([d["bbox"] for d in dets if d["image_id"] == src.image_id(k)]).reshape(-1, 4)
        assert len(mine) == len(gt)
        for g in gt:  # each GT window has a detection within the resampling error (1 input px = 1.9 frame px)
            xyxy = np.c_[mine[:, :2], mine[:, :2] + mine[:, 2:]]
            assert np.abs(xyxy - g).max(1).min() <= 2.5
            checked += 1
    assert checked > 3


def test_predict_validates_the_model_output(prepared):
    class Wrong(nn.Module):
        def forward(self, x):
            return {"boxes": torch.zeros(0, 4)}

    src = SampleSource(prepared, [0, 1], IR8)
    with pytest.raises(PluginError, match="one dict per image"):
        predict(Wrong(), src, 64, name="wrong")

    class BadLabel(nn.Module):
        def forward(self, x):
            return [
                {"boxes": torch.tensor([[1.0, 1, 5, 5]]), "scores": torch.tensor([0.5]), "labels": torch.tensor([7])}
                for _ in x
            ]

    with pytest.raises(PluginError, match="labels. must lie in 0..2, got 7"):
        predict(BadLabel(), src, 64, num_classes=3, name="bad")


def test_predict_sets_the_model_thresholds(prepared):
    m = Oracle()
    predict(m, SampleSource(prepared, [0], IR8), 64, conf=0.01, iou=0.5, max_det=10)
    assert (m.conf, m.iou, m.max_det) == (0.01, 0.5, 10)
