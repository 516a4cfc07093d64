"""Warp RGB into the thermal frame, common support, boxes through H + crop + clip, align_pair."""

from __future__ import annotations

import numpy as np
import pytest

from harness.contracts import validate_sample
from harness.errors import DataError
from harness.sensing.registration import homography_from_similarity
from harness.sensing.warp import align_pair, common_support_box, support_mask, transform_boxes, warp_to_thermal


def _translation(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def test_translation_warp_moves_pixels_and_marks_the_uncovered_border_invalid():
    rgb = np.random.default_rng(0).integers(0, 255, (20, 30, 3)).astype(np.uint8)
    warped, valid = warp_to_thermal(rgb, _translation(3, 2), (20, 30), antialias=False)
    np.testing.assert_array_equal(warped[2:, 3:], rgb[:-2, :-3])  # thermal (u, v) shows rgb (u - 3, v - 2)
    assert not valid[:2].any() and not valid[:, :3].any() and valid[2:, 3:].all()
    assert (warped[~valid] == 0).all()
    filled, _ = warp_to_thermal(rgb, _translation(3, 2), (20, 30), antialias=False, fill="replicate")
    np.testing.assert_array_equal(filled[0, 3:], rgb[0, :-3])  # nearest RGB row replicated, no black edge


def test_downscaling_warp_is_antialiased():
    stripes = np.zeros((400, 400, 3), np.uint8)
    stripes[:, ::2] = 255  # 1-px stripes, far above the thermal Nyquist frequency at 1/4 scale
    H = np.diag([0.25, 0.25, 1.0])
    smooth, valid = warp_to_thermal(stripes, H, (100, 100))
    aliased, _ = warp_to_thermal(stripes, H, (100, 100), antialias=False)
    inner = smooth[5:-5, 5:-5].astype(float)
    assert abs(inner.mean() - 127.5) < 3 and inner.std() < 3
    assert abs(aliased[5:-5, 5:-5].mean() - 127.5) > 100  # every sample hits a white stripe
    assert valid[:99, :99].all()


def test_common_support_box_is_the_bounding_extent():
    m = np.zeros((10, 12), bool)
    m[2:7, 3:9] = True
    m[8, 5] = True
    assert common_support_box(m) == (3, 2, 9, 9)
    with pytest.raises(DataError, match="no common support"):
        common_support_box(np.zeros((4, 4), bool))


def test_boxes_through_h_crop_and_clip_by_hand():
    H = np.array([[0.5, 0.0, 10.0], [0.0, 0.5, 20.0], [0.0, 0.0, 1.0]])
    boxes = np.array(
        [
            [100, 50, 200, 150],  # inside, partly clipped on the right and bottom
            [20, 30, 60, 70],  # inside
            [500, 500, 520, 510],  # lands outside the crop: dropped
            [100, 50, 101, 51],  # 0.5 x 0.5 px after scaling: degenerate, dropped
        ],
        dtype=np.float32,
    )
    out, keep = transform_boxes(boxes, H, origin=(5, 10), size=(100, 80))
    # edge x -> centre coordinate x - 0.5 -> 0.5 (x - 0.5) + 10 -> + 0.5 -> minus the origin
    x = lambda v: 0.5 * (v - 0.5) + 10 + 0.5 - 5  # noqa: E731
    y = lambda v: 0.5 * (v - 0.5) + 20 + 0.5 - 10  # noqa: E731
    np.testing.assert_array_equal(keep, [True, True, False, False])
    np.testing.assert_allclose(out, [[x(100), y(50), 100, 80], [x(20), y(30), x(60), y(70)]], atol=1e-5)
    assert out.dtype == np.float32


def test_rotated_boxes_become_the_bounding_box_of_their_corners():
    H = homography_from_similarity(0, 0, 90.0, 1.0, (0.0, 0.0), (50.0, 50.0))
    out, keep = transform_boxes(np.array([[10.5, 0.5, 20.5, 5.5]]), H, size=(100, 100))
    # centre coords (10, 0)-(20, 5) rotated by 90 deg on screen: (x, y) -> (y, -x) about the origin, + 50
    np.testing.assert_allclose(out, [[50.5, 30.5, 55.5, 40.5]], atol=1e-9)
    assert keep.all()
    none, keep = transform_boxes(np.zeros((0, 4)), H)
    assert none.shape == (0, 4) and keep.shape == (0,)


def test_boxes_in_the_thermal_frame_are_only_shifted_and_clipped():
    out, keep = transform_boxes(np.array([[2, 3, 10, 12], [0, 0, 1.5, 40]]), None, origin=(2, 2), size=(6, 20))
    np.testing.assert_allclose(out, [[0, 1, 6, 10]])
    np.testing.assert_array_equal(keep, [True, False])  # the second is 0 px wide after the crop


def test_align_pair_crops_without_resampling_temperature():
    rng = np.random.default_rng(1)
    th_h, th_w = 64, 80
    thermal = (20 + rng.normal(size=(th_h, th_w))).astype(np.float32)
    ir8 = rng.integers(0, 255, (th_h, th_w)).astype(np.uint8)
    rgb = rng.integers(0, 255, (120, 140, 3)).astype(np.uint8)
    H = np.array([[0.5, 0.0, 12.0], [0.0, 0.5, 8.0], [0.0, 0.0, 1.0]])  # RGB covers x 12..81.5, y 8..67.5
    boxes = np.array([[20, 10, 30, 20], [0, 0, 10, 5], [70, 40, 79, 60]], np.float32)
    pair = align_pair(rgb, thermal, ir8, boxes, np.array([0, 1, 2]), H, boxes_frame="thermal")
    x0, y0 = pair.origin
    assert (x0, y0) == (12, 8) and pair.size == (th_w - 12, th_h - 8)
    np.testing.assert_array_equal(pair.thermal, thermal[8:, 12:])  # a slice: the same bits
    np.testing.assert_array_equal(pair.ir8, ir8[8:, 12:])
    np.testing.assert_allclose(pair.boxes, [[8, 2, 18, 12], [58, 32, 67, 52]])
    np.testing.assert_array_equal(pair.labels, [0, 2])
    assert pair.dropped == 1 and pair.meta()["boxes_dropped"] == 1
    assert pair.support_fraction == pytest.approx(1.0)
    sample = validate_sample(pair.to_sample(7, "P1", {"file_name": "DJI_0001"}), num_classes=3)
    assert sample.meta["crop_origin"] == [12, 8] and sample.meta["file_name"] == "DJI_0001"
    np.testing.assert_allclose(pair.H @ np.array([0, 0, 1.0]), [0, 0, 1])  # RGB origin lands on the crop origin


def test_align_pair_moves_rgb_boxes_through_h_and_respects_thermal_validity():
    rgb = np.full((200, 200, 3), 90, np.uint8)
    thermal = np.full((50, 60), 25.0, np.float32)
    H = np.diag([0.25, 0.25, 1.0])  # RGB covers the top-left 50 x 50 thermal pixels
    valid = np.ones((50, 60), bool)
    valid[:, :4] = False  # e.g. the undistortion border
    pair = align_pair(
        rgb,
        thermal,
        np.zeros((50, 60), np.uint8),
        np.array([[40, 40, 80, 120]], np.float32),
        np.array([0]),
        H,
        boxes_frame="rgb",
        thermal_valid=valid,
    )
    assert pair.origin == (4, 0) and pair.size == (46, 50)
    x = lambda v: 0.25 * (v - 0.5) + 0.5 - 4  # noqa: E731
    yv = lambda v: 0.25 * (v - 0.5) + 0.5  # noqa: E731
    np.testing.assert_allclose(pair.boxes, [[x(40), yv(40), x(80), yv(120)]], atol=1e-5)
    assert (pair.rgb[pair.valid] == 90).all()
    assert support_mask(H, (200, 200), (50, 60))[:, 50:].sum() == 0
    with pytest.raises(DataError, match="boxes_frame"):
        align_pair(rgb, thermal, np.zeros((50, 60), np.uint8), np.zeros((0, 4)), np.zeros(0), H, boxes_frame="x")


def test_sensing_context_runs_a_capture_as_the_config_says(tmp_path):
    from harness.config import load_config
    from harness.sensing.calibration import CameraModel
    from harness.sensing.pipeline import SensingContext
    from harness.sensing.registration import save_homographies

    rgb = np.full((200, 200, 3), 90, np.uint8)
    thermal = np.full((50, 60), 25.0, np.float32)
    ir8 = np.zeros((50, 60), np.uint8)
    H = np.diag([0.25, 0.25, 1.0])
    save_homographies(tmp_path / "H.yaml", {"P1": H})
    CameraModel(np.array([[60.0, 0, 29.5], [0, 60.0, 24.5], [0, 0, 1]]), [-0.2, 0, 0, 0, 0], (60, 50)).save(
        tmp_path / "th.yaml"
    )
    cfg = load_config(
        overrides=[
            "sensing.registration.homographies=H.yaml",
            "sensing.registration.method=file",
            "sensing.warp.min_box_size=2.0",
        ]
    )
    ctx = SensingContext.from_config(cfg, base=tmp_path)
    pair = ctx.align_capture(rgb, thermal, ir8, np.array([[10, 10, 20, 20], [0, 0, 1.5, 1.5]]), np.array([0, 1]), "P1")
    assert pair.dropped == 1 and pair.origin == (0, 0)
    with pytest.raises(DataError, match="group 'P9' has no homography"):
        ctx.align_capture(rgb, thermal, ir8, np.zeros((0, 4)), np.zeros(0), "P9")
    cfg = load_config(overrides=["sensing.undistort.thermal_camera=th.yaml"])
    ctx = SensingContext.from_config(cfg, base=tmp_path)
    th_u, ir8_u, cam = ctx.undistort_thermal(thermal, ir8)
    assert th_u.shape == ir8_u.shape and th_u.shape[0] < 50 and np.allclose(th_u, 25.0)
    with pytest.raises(DataError, match="'focal' needs"):
        SensingContext.from_config(load_config(overrides=["sensing.registration.method=focal"])).homography(
            "P1", rgb, thermal
        )
