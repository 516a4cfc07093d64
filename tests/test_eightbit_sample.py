"""The adapters of 8-bit releases (FLIR-aligned, LLVIP, M3FD, RGBT-Tiny) build their samples in one place:
``adapters.datasets._eightbit.pair_sample``."""

from __future__ import annotations

import numpy as np

from adapters.datasets._eightbit import pair_sample


def test_an_eightbit_pair_becomes_a_sample_with_its_boxes_clipped_and_counted():
    ir8 = np.zeros((20, 30), np.uint8)
    rgb = np.zeros((20, 30, 3), np.uint8)
    xyxy = np.array([[2, 2, 10, 10], [25, 5, 40, 15], [31, 0, 35, 5]], np.float64)  # inside, clipped, outside
    meta = {"file_name": "ir/1.jpg", "split": "train"}
    sample, stats = pair_sample(7, rgb, ir8, xyxy, np.array([0, 1, 2]), "train", meta)
    assert sample.image_id == 7 and sample.thermal is None and sample.group == "train" and sample.meta == meta
    assert sample.boxes.tolist() == [[2, 2, 10, 10], [25, 5, 30, 15]] and sample.labels.tolist() == [0, 1]
    assert (stats.kept, stats.clipped, stats.degenerate) == (2, 1, 1)
    assert sample.ir8 is ir8 and sample.rgb is rgb
