"""Box operations: NMS equals the textbook greedy algorithm; IoU variants against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from harness.boxes import batched_nms, bbox_iou, box_iou, nms, xywh_to_xyxy, xyxy_to_xywh


def greedy_reference(boxes, scores, thr):
    order = np.argsort(-scores, kind="stable")
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        rest = order[1:]
        ious = box_iou(torch.tensor(boxes[i : i + 1]), torch.tensor(boxes[rest])).numpy()[0]
        order = rest[ious <= thr]
    return keep


@pytest.mark.parametrize("n, thr", [(50, 0.5), (700, 0.45), (1200, 0.7)])
def test_nms_matches_greedy_reference(n, thr):
    rng = np.random.default_rng(n)
    centres = rng.uniform(0, 600, (max(n // 10, 1), 2))
    c = centres[rng.integers(0, len(centres), n)] + rng.normal(0, 6, (n, 2))
    wh = rng.uniform(10, 60, (n, 2))
    boxes = np.concatenate([c - wh / 2, c + wh / 2], 1).astype(np.float32)
    scores = rng.permutation(n).astype(np.float32) / n  # distinct scores: no tie ambiguity
    kept = nms(torch.tensor(boxes), torch.tensor(scores), thr, block=64).tolist()
    assert kept == greedy_reference(boxes, scores, thr)
    assert nms(torch.tensor(boxes), torch.tensor(scores), thr, max_keep=5).tolist() == kept[:5]


def test_batched_nms_never_suppresses_across_classes():
    boxes = torch.tensor([[0, 0, 10, 10], [0, 0, 10, 10], [1, 1, 10, 10]], dtype=torch.float32)
    scores = torch.tensor([0.9, 0.8, 0.7])
    classes = torch.tensor([0, 1, 0])
    assert batched_nms(boxes, scores, classes, 0.5).tolist() == [0, 1]
    assert nms(torch.zeros(0, 4), torch.zeros(0), 0.5).numel() == 0


def test_iou_variants_hand_computed():
    a = torch.tensor([[0.0, 0.0, 2.0, 2.0]])
    b = torch.tensor([[1.0, 1.0, 3.0, 3.0]])
    iou = 1 / 7
    assert bbox_iou(a, b).item() == pytest.approx(iou, abs=1e-6)
    assert box_iou(a, b).item() == pytest.approx(iou, abs=1e-6)
    assert bbox_iou(a, b, "giou").item() == pytest.approx(iou - (9 - 7) / 9, abs=1e-6)
    # centres (1,1) and (2,2): rho^2 = 2; enclosing diagonal^2 = 18; same aspect ratio so v = 0
    assert bbox_iou(a, b, "diou").item() == pytest.approx(iou - 2 / 18, abs=1e-6)
    assert bbox_iou(a, b, "ciou").item() == pytest.approx(iou - 2 / 18, abs=1e-6)
    c = torch.tensor([[0.0, 0.0, 4.0, 2.0]])  # same centre-x shifted, different aspect ratio
    v = 4 / math.pi**2 * (math.atan(4 / 2) - math.atan(2 / 2)) ** 2
    i = 4 / 8
    alpha = v / (1 - i + v)
    rho2 = 1.0  # centres (1,1) and (2,1)
    c2 = 16 + 4
    assert bbox_iou(a, c, "ciou").item() == pytest.approx(i - rho2 / c2 - alpha * v, abs=1e-5)


def test_box_format_round_trip():
    b = np.array([[1.0, 2.0, 4.0, 6.0]])
    assert xyxy_to_xywh(b).tolist() == [[1.0, 2.0, 3.0, 4.0]]
    assert xywh_to_xyxy(xyxy_to_xywh(b)).tolist() == b.tolist()
    t = torch.tensor(b)
    assert torch.equal(xywh_to_xyxy(xyxy_to_xywh(t)), t)
