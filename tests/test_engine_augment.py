"""Augmentation: geometry moves every channel and the boxes identically; HSV jitter never touches channel 4."""

from __future__ import annotations

import numpy as np
import pytest

from harness.engine import augment as A


def _scene(h: int = 96, w: int = 128, rects=((20, 30, 60, 70),), channels: int = 4, value: int = 250):
    """Black image with bright filled rectangles, identical on every channel."""
    img = np.zeros((h, w, channels), np.uint8)
    for x1, y1, x2, y2 in rects:
        img[y1:y2, x1:x2] = value
    return img, np.asarray(rects, np.float32)


def _bright_bbox(img: np.ndarray, channel: int = 0, thr: int = 200) -> list[int]:
    ys, xs = np.nonzero(img[:, :, channel] > thr)
    return [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]


# ------------------------------------------------------------------ HSV
def test_hsv_changes_rgb_and_never_channel_4():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (40, 50, 4), dtype=np.uint8)
    before = img.copy()
    changed = 0
    for seed in range(20):
        out = A.augment_hsv(img, np.random.default_rng(seed), 0.5, 0.9, 0.9)
        assert out.shape == img.shape and out.dtype == np.uint8
        np.testing.assert_array_equal(out[:, :, 3], before[:, :, 3])  # byte-identical fourth channel
        changed += int((out[:, :, :3] != before[:, :, :3]).any())
    np.testing.assert_array_equal(img, before)  # the input is not modified in place
    assert changed == 20  # and the jitter really does act on RGB


def test_hsv_gains_zero_is_identity():
    img = np.random.default_rng(1).integers(0, 256, (8, 8, 4), dtype=np.uint8)
    assert A.augment_hsv(img, np.random.default_rng(0), 0, 0, 0) is img


# ------------------------------------------------------------------ geometry
@pytest.mark.parametrize(
    "kw",
    [
        dict(degrees=0, translate=0.2, scale=0.5),
        dict(degrees=30, translate=0.1, scale=0.3),
        dict(degrees=10, translate=0.1, scale=0.2, shear=10),
    ],
)
def test_random_affine_moves_all_channels_and_boxes_identically(kw):
    img, boxes = _scene()
    labels = np.array([2])
    for seed in range(5):
        out, b, lab = A.random_affine(img, boxes, labels, np.random.default_rng(seed), **kw)
        for c in range(1, 4):
            np.testing.assert_array_equal(out[:, :, c], out[:, :, 0])
        if len(b) == 0:  # the object left the frame; nothing to compare
            continue
        assert lab.tolist() == [2]
        # the warped box is the bounding box of the warped rectangle's pixels (within interpolation blur)
        np.testing.assert_allclose(_bright_bbox(out), b[0], atol=2.0)


def test_random_affine_with_perspective_keeps_channels_together():
    img, boxes = _scene()
    out, b, _ = A.random_affine(img, boxes, np.array([0]), np.random.default_rng(3), degrees=5, perspective=0.0005)
    for c in range(1, 4):
        np.testing.assert_array_equal(out[:, :, c], out[:, :, 0])
    if len(b):
        np.testing.assert_allclose(_bright_bbox(out), b[0], atol=3.0)


def test_mosaic_then_affine_keeps_boxes_on_their_objects():
    s = 64
    images, boxes, labels = [], [], []
    for k in range(4):
        img, b = _scene(48, 64, rects=((10 + 4 * k, 8, 30 + 4 * k, 28),))
        images.append(img)
        boxes.append(b)
        labels.append(np.array([k]))
    for seed in range(6):
        rng = np.random.default_rng(seed)
        canvas, b, lab = A.mosaic4(images, boxes, labels, s, rng)
        assert canvas.shape == (2 * s, 2 * s, 4)
        out, b2, lab2 = A.random_affine(canvas, b, lab, rng, translate=0.1, scale=0.3, border=-s // 2)
        assert out.shape == (s, s, 4)
        for c in range(1, 4):
            np.testing.assert_array_equal(out[:, :, c], out[:, :, 0])
        for box in b2:  # every surviving box covers bright pixels and its inside is mostly bright
            x1, y1, x2, y2 = np.round(box).astype(int)
            patch = out[y1:y2, x1:x2, 0]
            assert patch.size and (patch > 200).mean() > 0.6


def test_flips_map_boxes_exactly():
    img, boxes = _scene(rects=((20, 30, 60, 70),))
    out, b = A.flip_lr(img, boxes)
    assert b.tolist() == [[128 - 60, 30, 128 - 20, 70]]
    assert _bright_bbox(out) == b[0].tolist()
    out, b = A.flip_ud(img, boxes)
    assert b.tolist() == [[20, 96 - 70, 60, 96 - 30]]
    assert _bright_bbox(out) == b[0].tolist()


def test_letterbox_records_how_to_undo_it():
    img = np.zeros((60, 100, 4), np.uint8)
    out, lb = A.letterbox(img, 64)
    assert out.shape == (64, 64, 4)
    assert lb.ratio == pytest.approx(0.64) and lb.pad == (0.0, 13.0) and lb.shape == (60, 100)
    boxes = np.array([[10, 20, 50, 40], [0, 0, 100, 60]], np.float32)
    moved = A.scale_boxes(boxes, lb.ratio, lb.pad)
    np.testing.assert_allclose(moved[0], [6.4, 25.8, 32.0, 38.6], atol=1e-5)
    np.testing.assert_allclose(lb.to_original(moved), boxes, atol=1e-4)
    # padding is the grey fill on every channel, the image area is untouched
    assert (out[:13] == A.PAD_VALUE).all() and (out[13:51] == 0).all() and (out[51:] == A.PAD_VALUE).all()


def test_box_candidates_drops_slivers_and_vanished_boxes():
    before = np.array([[0, 0, 20, 20], [0, 0, 20, 20], [0, 0, 20, 20]], np.float32)
    after = np.array([[0, 0, 18, 19], [0, 0, 1.5, 20], [0, 0, 5, 5]], np.float32)
    assert A.box_candidates(before, after).tolist() == [True, False, False]
