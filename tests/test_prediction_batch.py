"""Predictions against the prediction batch: ``detection_changes``, ``batch_changes`` and the plugin kit's check
(``harness.testing.assert_batch_independent``, the ``harness_batch_check`` fixture)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from harness.engine.predict import BATCH_BOX_TOL, BATCH_SCORE_TOL, batch_changes, detection_changes
from harness.testing import assert_batch_independent


def dets(boxes, scores, labels):
    return {"boxes": torch.tensor(boxes, dtype=torch.float32), "scores": torch.tensor(scores), "labels": labels}


def test_identical_predictions_change_nothing():
    a = [dets([[0, 0, 10, 10], [5, 5, 20, 20]], [0.9, 0.4], [0, 1]), dets(np.zeros((0, 4)), [], [])]
    ch = detection_changes(a, a)
    assert (ch.score, ch.box, ch.unmatched, ch.detections) == (0.0, 0.0, 0, 4)
    assert ch.within()


def test_the_largest_score_and_box_change_of_counterparts():
    a = [dets([[0, 0, 10, 10], [5, 5, 20, 20]], [0.9, 0.4], [0, 1])]
    b = [dets([[5, 5, 20.25, 20], [0, 0.5, 10, 10]], [0.375, 0.9], [1, 0])]  # other order, moved a little
    ch = detection_changes(a, b)
    assert ch.box == pytest.approx(0.5) and ch.score == pytest.approx(0.025, abs=1e-7) and ch.unmatched == 0
    assert not ch.within()


def test_equal_boxes_pair_by_the_nearest_score():
    a = [dets([[0, 0, 10, 10], [0, 0, 10, 10]], [0.9, 0.2], [0, 0])]  # two boxes clipped to the same place
    b = [dets([[0, 0, 10, 10], [0, 0, 10, 10]], [0.2, 0.9], [0, 0])]
    assert detection_changes(a, b).score == 0.0


def test_a_far_box_another_label_or_a_missing_detection_is_unmatched():
    a = [dets([[0, 0, 10, 10]], [0.9], [0]), dets([[0, 0, 10, 10]], [0.9], [0]), dets([[1, 1, 4, 4]], [0.5], [2])]
    b = [dets([[3, 0, 10, 10]], [0.9], [0]), dets([[0, 0, 10, 10]], [0.9], [1]), dets(np.zeros((0, 4)), [], [])]
    assert detection_changes(a, b).unmatched == 2 + 2 + 1
    with pytest.raises(ValueError, match="3 images against 1"):
        detection_changes(a, b[:1])


class PerImage(nn.Module):
    """A toy detector: one box per image, its score from the image alone; ``mix`` makes it depend on the batch."""

    def __init__(self, mix: bool = False):
        super().__init__()
        self.conv, self.mix = nn.Conv2d(4, 2, 3, padding=1), mix

    def forward(self, x):
        f = self.conv(x).mean((1, 2, 3))
        if self.mix:  # a batch-wide normalisation, as BatchNorm in train mode would do
            f = f - f.mean()
        box, label = torch.tensor([[4.0, 4.0, 20.0, 24.0]]), torch.zeros(1, dtype=torch.long)
        return [{"boxes": box, "scores": v.sigmoid()[None], "labels": label} for v in f]


def test_a_per_image_model_passes_and_a_batch_mixing_one_fails(harness_batch_check):
    torch.manual_seed(0)
    x = torch.rand(8, 4, 32, 32)
    harness_batch_check(PerImage(), x)
    changes = batch_changes(PerImage(mix=True), x, (1, 8))
    assert changes[1].score == 0.0 and changes[8].score > 10 * BATCH_SCORE_TOL
    with pytest.raises(AssertionError, match=r"predictions 2 images at a time differ from 1 .* mix the images"):
        assert_batch_independent(PerImage(mix=True), x)


@pytest.mark.slow
def test_ours_predicts_within_the_bound_whatever_the_batch():
    from harness.plugins import get_host

    spec = get_host().detector("ours")
    torch.manual_seed(0)
    model = spec.build(8, in_channels=4, scale="n")
    model.conf = 0.0  # every point a candidate: the scores of all of them are compared
    x = torch.rand(4, 4, 64, 64)
    changes = batch_changes(model, x, (1, 4))
    assert changes[4].detections > 2 * 4 * 50
    for ch in changes.values():
        assert ch.unmatched == 0 and ch.score <= BATCH_SCORE_TOL and ch.box <= BATCH_BOX_TOL
