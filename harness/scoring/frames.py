"""Boxes between the frames of one capture: the original RGB image, the original thermal image, and the
prepared frame every detector of the harness sees (thermal pixels after undistortion and the common-support crop).

What each prepared sample records in its ``meta`` is all that is needed (``harness.sensing.warp.AlignedPair``):

* ``H_rgb_to_frame``: RGB pixels (after RGB undistortion, when the dataset has a camera model) -> prepared frame;
* ``crop_origin``: the crop's top-left corner in the (undistorted) thermal frame;
* ``cameras``: per sensor, the calibrated camera and the undistorted camera the homography starts from.

Into the prepared frame a box goes exactly the way the ground truth went: undistortion (the bounding box of the four
moved corners), the homography for RGB (corners, pixel-centre convention), the crop shift, clipping to the frame; a
box that ends up thinner than ``min_size`` is dropped. Out of the prepared frame the same steps run backwards.
Coordinates are kept in float64 and rounded to 1e-4 px, so a round trip returns the boxes it started from; through
a lens model (a dataset with camera calibrations) a box's edges bend, so the bounding box of its moved corners grows
by a fraction of a pixel each way, as the ground truth's did.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from harness.errors import DataError

FRAMES = ("prepared", "thermal", "rgb")
DECIMALS = 4


def _corners(b: np.ndarray) -> np.ndarray:
    return np.stack([b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1).reshape(-1, 2)


def _bbox(points: np.ndarray) -> np.ndarray:
    p = points.reshape(-1, 4, 2)
    return np.concatenate([p.min(axis=1), p.max(axis=1)], axis=1)


def _homography(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Boxes through ``H`` the way the sensing pipeline moves them (corners, OpenCV pixel-centre convention)."""
    from harness.sensing.registration.homography import project_points

    moved, depth = project_points(H, _corners(b) - 0.5)
    out = moved + 0.5
    out[np.repeat((depth <= 1e-12).reshape(-1, 4).any(axis=1), 4)] = np.nan
    return _bbox(out)


def _camera(meta: Mapping[str, Any], sensor: str) -> tuple[Any, Any] | None:
    cams = (meta.get("cameras") or {}).get(sensor)
    if not cams:
        return None
    from harness.sensing.calibration import CameraModel

    return (CameraModel.from_dict(cams["camera"], f"{sensor} camera"),
            CameraModel.from_dict(cams["undistorted"], f"{sensor} undistorted camera"))


def _undistort(b: np.ndarray, cams: tuple[Any, Any] | None) -> np.ndarray:
    if cams is None or len(b) == 0:
        return b
    from harness.sensing.calibration import undistort_points

    return _bbox(undistort_points(_corners(b), cams[0], cams[1]))


def _distort(b: np.ndarray, cams: tuple[Any, Any] | None) -> np.ndarray:
    """Undistorted (``cams[1]``) pixels -> the calibrated camera's distorted pixels (``cams[0]``)."""
    if cams is None or len(b) == 0:
        return b
    import cv2

    cam, new = cams
    pts = _corners(b)
    rays = np.hstack([pts, np.ones((len(pts), 1))]) @ np.linalg.inv(new.K).T
    img, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return _bbox(img.reshape(-1, 2))


def _crop(meta: Mapping[str, Any]) -> tuple[np.ndarray, tuple[float, float] | None]:
    origin = np.asarray(meta.get("crop_origin") or (0, 0), np.float64)
    size = meta.get("crop_size")
    return origin, (float(size[0]), float(size[1])) if size else None


def _finish(b: np.ndarray, size: tuple[float, float] | None, min_size: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Clip to the frame and drop what is thinner than ``min_size``; ``None``: drop only boxes wholly outside."""
    if min_size is None:
        w, h = size if size is not None else (np.inf, np.inf)
        inside = (b[:, 2] >= 0) & (b[:, 0] <= w) & (b[:, 3] >= 0) & (b[:, 1] <= h) & \
            ~((b[:, 2] <= 0) | (b[:, 0] >= w) | (b[:, 3] <= 0) | (b[:, 1] >= h))
        b, keep = _finish(b, size, 0.0)
        return b[inside[keep]], keep & inside
    if size is not None:
        b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0, size[0])
        b[:, [1, 3]] = np.clip(b[:, [1, 3]], 0, size[1])
    keep = np.isfinite(b).all(axis=1) & ((b[:, 2] - b[:, 0]) >= min_size) & ((b[:, 3] - b[:, 1]) >= min_size)
    return np.round(b[keep], DECIMALS), keep


def _check(frame: str, meta: Mapping[str, Any], where: str) -> None:
    if frame not in FRAMES:
        raise DataError(f"unknown frame {frame!r}; use one of {', '.join(FRAMES)}")
    if frame == "rgb" and "H_rgb_to_frame" not in meta:
        raise DataError(f"{where}: the prepared sample records no RGB-to-frame homography (the dataset has no "
                        f"registration stage); use --frame prepared or thermal")


def to_prepared(boxes: np.ndarray, frame: str, meta: Mapping[str, Any], size: tuple[int, int] | None = None,
                min_size: float = 1.0, where: str = "sample") -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N x 4 xyxy) of ``frame`` -> the prepared frame: ``(kept boxes float64, keep mask)``.

    ``size`` (w, h) of the prepared frame clips the result (``meta['crop_size']`` when not given)."""
    _check(frame, meta, where)
    b = np.asarray(boxes, np.float64).reshape(-1, 4).copy()
    origin, crop = _crop(meta)
    size = (float(size[0]), float(size[1])) if size is not None else crop
    if frame == "thermal":
        b = _undistort(b, _camera(meta, "thermal"))
        b[:, [0, 2]] -= origin[0]
        b[:, [1, 3]] -= origin[1]
    elif frame == "rgb":
        b = _homography(np.asarray(meta["H_rgb_to_frame"]), _undistort(b, _camera(meta, "rgb")))
    return _finish(b, size, min_size if frame != "prepared" else None)


def from_prepared(boxes: np.ndarray, frame: str, meta: Mapping[str, Any], where: str = "sample") -> np.ndarray:
    """Boxes (N x 4 xyxy) of the prepared frame -> ``frame`` (every box kept, rounded to 1e-4 px)."""
    _check(frame, meta, where)
    b = np.asarray(boxes, np.float64).reshape(-1, 4).copy()
    if frame == "thermal":
        origin, _ = _crop(meta)
        b[:, [0, 2]] += origin[0]
        b[:, [1, 3]] += origin[1]
        b = _distort(b, _camera(meta, "thermal"))
    elif frame == "rgb":
        b = _distort(_homography(np.linalg.inv(np.asarray(meta["H_rgb_to_frame"], np.float64)), b),
                     _camera(meta, "rgb"))
    return np.round(b, DECIMALS)


def image_name(meta: Mapping[str, Any], frame: str, image_id: int) -> str:
    """The file name that identifies a sample's image in ``frame`` (RGB file for rgb, thermal file for thermal)."""
    if frame == "thermal" and meta.get("thermal_file"):
        return str(meta["thermal_file"])
    return str(meta.get("file_name") or image_id)
