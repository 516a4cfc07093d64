"""Detections from decoded predictions: confidence filter, per-class NMS, multi-label candidates, max_det, clipping."""

from __future__ import annotations

import pytest
import torch

from adapters.detectors.yolo.postprocess import clip_boxes, postprocess

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def scene():
    boxes = torch.tensor(
        [
            [
                [10.0, 10.0, 50.0, 50.0],  # 0: class 0, 0.9
                [12.0, 11.0, 52.0, 49.0],  # 1: overlaps 0 (IoU ~0.86), class 0, 0.8 -> suppressed
                [11.0, 10.0, 51.0, 50.0],  # 2: overlaps 0, but class 1, 0.7 -> kept
                [100.0, 100.0, 140.0, 150.0],  # 3: far away, class 0, 0.6 -> kept
                [-5.0, 60.0, 30.0, 90.0],  # 4: crosses the left border, class 2, 0.5 -> kept, clipped
                [60.0, 60.0, 70.0, 70.0],
            ]
        ]
    )  # 5: below the confidence threshold
    scores = torch.zeros(1, 6, 3)
    scores[0, 0, 0], scores[0, 1, 0], scores[0, 2, 1], scores[0, 3, 0], scores[0, 4, 2], scores[0, 5, 1] = (
        0.9,
        0.8,
        0.7,
        0.6,
        0.5,
        0.0005,
    )
    return boxes, scores


def test_per_class_nms_keeps_other_classes_and_drops_low_scores():
    boxes, scores = scene()
    (out,) = postprocess(boxes, scores, conf=0.001, iou=0.7, max_det=300, image_hw=(128, 160))
    assert set(out) == {"boxes", "scores", "labels"}
    assert out["scores"].tolist() == torch.tensor([0.9, 0.7, 0.6, 0.5]).tolist()
    assert out["labels"].tolist() == [0, 1, 0, 2] and out["labels"].dtype == torch.int64
    assert out["boxes"].dtype == torch.float32 and out["boxes"].shape == (4, 4)
    assert out["boxes"][3].tolist() == [0.0, 60.0, 30.0, 90.0]  # clipped to the image
    assert out["boxes"][2].tolist() == [100.0, 100.0, 140.0, 128.0]  # height 128


def test_max_det_and_the_iou_threshold():
    boxes, scores = scene()
    (top2,) = postprocess(boxes, scores, max_det=2)
    assert top2["scores"].tolist() == torch.tensor([0.9, 0.7]).tolist()
    (loose,) = postprocess(boxes, scores, iou=0.95)  # IoU 0.86 < 0.95: box 1 survives
    assert len(loose["scores"]) == 5


def test_multi_label_makes_one_candidate_per_class_above_threshold():
    boxes = torch.tensor([[[0.0, 0.0, 10.0, 10.0]]])
    scores = torch.tensor([[[0.6, 0.3, 0.0001]]])
    (multi,) = postprocess(boxes, scores, conf=0.001, multi_label=True)
    (single,) = postprocess(boxes, scores, conf=0.001, multi_label=False)
    assert multi["labels"].tolist() == [0, 1] and single["labels"].tolist() == [0]


def test_no_candidates_gives_empty_tensors_of_the_right_shape():
    (out,) = postprocess(torch.zeros(1, 5, 4), torch.zeros(1, 5, 2), conf=0.25)
    assert out["boxes"].shape == (0, 4) and out["scores"].shape == (0,) and out["labels"].shape == (0,)


def test_settings_are_keywords_and_an_unknown_one_is_refused():
    boxes, scores = torch.zeros(1, 5, 4), torch.zeros(1, 5, 2)
    with pytest.raises(TypeError, match="positional argument"):  # conf, iou, ...: keywords, never read by position
        postprocess(boxes, scores, 0.25)
    with pytest.raises(TypeError, match="unknown setting.*confidence"):
        postprocess(boxes, scores, confidence=0.25)


def test_clip_boxes():
    b = torch.tensor([[-1.0, -2.0, 70.0, 30.0]])
    assert clip_boxes(b, (20, 64)).tolist() == [[0.0, 0.0, 64.0, 20.0]]
