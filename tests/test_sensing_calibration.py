"""Camera models, checkerboard calibration on rendered views with known intrinsics, undistortion."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from harness.errors import DataError
from harness.sensing.calibration import (
    CameraModel,
    calibrate_checkerboard,
    undistort_boxes,
    undistort_image,
    undistort_points,
)

SIZE = (320, 240)
K_TRUE = np.array([[300.0, 0, 161.0], [0, 302.0, 118.0], [0, 0, 1]])
DIST_TRUE = np.array([-0.18, 0.05, 0.0, 0.0, 0.0])
PATTERN = (7, 5)  # inner corners
SQUARE = 1.0


def _rodrigues(v):
    import cv2

    return cv2.Rodrigues(np.asarray(v, dtype=np.float64))[0]


@lru_cache(maxsize=1)
def _rays(ss: int = 2) -> tuple[np.ndarray, ...]:
    """Ideal normalised rays of every supersample of every pixel of the distorted camera (computed once)."""
    import cv2

    w, h = SIZE
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    out = []
    for dy in offs:
        for dx in offs:
            pts = np.stack([uu + dx, vv + dy], axis=-1).reshape(-1, 1, 2)
            out.append(cv2.undistortPoints(pts, K_TRUE, DIST_TRUE).reshape(-1, 2))  # distorted pixel -> ideal ray
    return tuple(out)


def _render_board(rvec, tvec, warm=False) -> np.ndarray:
    """A distorted view of a checkerboard of (PATTERN + 1) squares, 2 x 2 supersampled."""
    w, h = SIZE
    R = _rodrigues(rvec)
    Hinv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, float)]))  # ray -> board (a, b)
    acc = np.zeros(w * h)
    rays = _rays()
    for norm in rays:
        den = Hinv[2, 0] * norm[:, 0] + Hinv[2, 1] * norm[:, 1] + Hinv[2, 2]
        a = (Hinv[0, 0] * norm[:, 0] + Hinv[0, 1] * norm[:, 1] + Hinv[0, 2]) / den
        b = (Hinv[1, 0] * norm[:, 0] + Hinv[1, 1] * norm[:, 1] + Hinv[1, 2]) / den
        inside = (a >= -1) & (a < PATTERN[0]) & (b >= -1) & (b < PATTERN[1])
        white = (np.floor(a + 1) + np.floor(b + 1)) % 2 == 0
        acc += np.where(inside, white.astype(float), 0.55)
    img = (acc / len(rays)).reshape(h, w)
    if warm:  # a thermal view: temperatures, not grey levels
        return (24.0 + 3.0 * img).astype(np.float32)
    return (img * 255).astype(np.uint8)


def _views(n=8, warm=False):
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        rvec = rng.uniform(-0.45, 0.45, 3)
        # board centre (3, 2) on the optical axis, shifted a little, 8.5-10.5 units away
        centre = _rodrigues(rvec) @ np.array([3.0, 2.0, 0.0])
        tvec = -centre + np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.4, 0.4), rng.uniform(8.5, 10.5)])
        out.append(_render_board(rvec, tvec, warm=warm))
    return out


def test_camera_model_yaml_round_trip_and_errors(tmp_path):
    cam = CameraModel(K_TRUE, DIST_TRUE[:4], SIZE, name="rgb", rms=0.21)
    path = cam.save(tmp_path / "cam.yaml")
    text = path.read_text()
    assert "fx: 300.0" in text and "k1: -0.18" in text and "width: 320" in text
    back = CameraModel.load(path)
    np.testing.assert_allclose(back.K, K_TRUE)
    np.testing.assert_allclose(back.dist, DIST_TRUE)
    assert back.image_size == SIZE and back.name == "rgb" and back.rms == pytest.approx(0.21)
    (tmp_path / "bad.yaml").write_text("intrinsics: {fx: 1}\n")
    with pytest.raises(DataError, match="bad.yaml: not a camera model"):
        CameraModel.load(tmp_path / "bad.yaml")
    half = cam.scaled((160, 120))
    assert half.fx == pytest.approx(150.0) and half.cx == pytest.approx((161.0 + 0.5) / 2 - 0.5)


@pytest.mark.parametrize("warm", [False, True])
def test_checkerboard_calibration_recovers_known_intrinsics(warm):
    views = _views(10, warm=warm)
    views.append(np.zeros((SIZE[1], SIZE[0]), np.float32 if warm else np.uint8))  # a view without a board
    res = calibrate_checkerboard(
        [(f"v{i}", v) for i, v in enumerate(views)], PATTERN, SQUARE, thermal=warm, name="thermal" if warm else "rgb"
    )
    cam = res.camera
    assert res.rejected == ["v10"] and len(res.used) == 10
    assert res.rms < 0.3
    assert cam.fx == pytest.approx(300.0, rel=0.01) and cam.fy == pytest.approx(302.0, rel=0.01)
    assert cam.cx == pytest.approx(161.0, abs=3) and cam.cy == pytest.approx(118.0, abs=3)
    assert cam.dist[0] == pytest.approx(-0.18, abs=0.03)


def test_calibration_without_enough_boards_is_a_clear_error():
    blank = [np.zeros((SIZE[1], SIZE[0]), np.uint8)] * 3
    with pytest.raises(DataError, match=r"found in 0 view\(s\), need at least 3"):
        calibrate_checkerboard(blank, PATTERN)


def test_undistortion_removes_the_border_and_moves_points_consistently():
    import cv2

    cam = CameraModel(K_TRUE, DIST_TRUE, SIZE)
    white = np.full((SIZE[1], SIZE[0]), 200, np.uint8)
    out, new_cam, roi = undistort_image(white, cam)
    assert out.shape == (roi[3], roi[2]) and (out == 200).all()  # alpha = 0: no invalid pixel left
    temp = np.full((SIZE[1], SIZE[0]), 31.5, np.float32)
    t_out, _, _ = undistort_image(temp, cam)
    assert t_out.dtype == np.float32 and np.allclose(t_out, 31.5)
    # a 3-D point seen by the distorted camera lands where the ideal new camera projects it
    X = np.array([[0.3, -0.2, 2.0]])
    distorted, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    ideal, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), new_cam.K, np.zeros(5))
    np.testing.assert_allclose(
        undistort_points(distorted.reshape(-1, 2), cam, new_cam), ideal.reshape(-1, 2), atol=1e-3
    )
    box = undistort_boxes(np.array([[100, 80, 140, 120]]), cam, new_cam)
    assert box.shape == (1, 4) and box[0, 2] > box[0, 0]
    with pytest.raises(DataError, match="calibrated at 320x240"):
        undistort_image(np.zeros((10, 10), np.uint8), cam)
    same, _, roi = undistort_image(white, CameraModel(K_TRUE, np.zeros(5), SIZE))
    assert same is white and roi == (0, 0, 320, 240)


def test_undistortion_maps_are_built_once_per_camera_and_change_nothing(monkeypatch):
    """The maps are cached per camera model, size and alpha: the output is bit for bit the uncached computation's,
    and another calibration (or alpha) gets its own maps."""
    import cv2

    from harness.sensing import calibration
    from harness.sensing.calibration import undistorted_camera

    real = cv2.initUndistortRectifyMap

    def reference(img, cam, alpha, interp):
        new_cam, (x, y, w, h) = undistorted_camera(cam, alpha)
        K = new_cam.K.copy()
        K[0, 2] += x
        K[1, 2] += y
        mx, my = real(cam.K, cam.dist, None, K, cam.image_size, cv2.CV_32FC1)
        return cv2.remap(
            img, mx[y : y + h, x : x + w], my[y : y + h, x : x + w], interp, borderMode=cv2.BORDER_REPLICATE
        )

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (SIZE[1], SIZE[0], 3), dtype=np.uint8)
    temp = rng.normal(25.0, 4.0, (SIZE[1], SIZE[0])).astype(np.float32)
    cams = [CameraModel(K_TRUE, DIST_TRUE, SIZE), CameraModel(K_TRUE, DIST_TRUE * 0.5, SIZE)]
    getattr(calibration, "_MAPS", {}).clear()
    built = []
    monkeypatch.setattr(cv2, "initUndistortRectifyMap", lambda *a: built.append(1) or real(*a))
    for _ in range(3):
        for cam in cams:
            for alpha in (0.0, 1.0):
                out, new_cam, _ = undistort_image(rgb, cam, alpha)
                assert np.array_equal(out, reference(rgb, cam, alpha, cv2.INTER_LINEAR))
                assert new_cam.to_dict() == undistorted_camera(cam, alpha)[0].to_dict()
                t_out = undistort_image(temp, cam, alpha, "cubic")[0]
                assert np.array_equal(t_out, reference(temp, cam, alpha, cv2.INTER_CUBIC))
    monkeypatch.setattr(cv2, "initUndistortRectifyMap", real)
    assert len(built) == 4  # two cameras x two alphas, whatever the number of images
