"""Boxes between the frames of one capture: the original RGB image, the original thermal image, and the
prepared frame every detector of the harness sees (thermal pixels after undistortion and the common-support crop).

What each prepared sample records in its ``meta`` is all that is needed (``harness.sensing.warp.AlignedPair``):

* ``H_rgb_to_frame``: RGB pixels (after RGB undistortion, when the dataset has a camera model) -> prepared frame;
* ``crop_origin``: the crop's top-left corner in the (undistorted) thermal frame;
* ``cameras``: per sensor, the calibrated camera and the undistorted camera the homography starts from.

**Into the prepared frame** (``to_prepared``) a box goes exactly the way the ground truth went: undistortion (the
bounding box of the four moved corners), the homography for RGB (corners, pixel-centre convention), the crop shift,
clipping to the frame. The bounding box of moved corners is not invertible by moving corners back (through a
rotation or a lens it grows each way), so **out of the prepared frame** (``from_prepared``) a box is the exact
preimage of that same map: the box ``X`` of the original frame whose forward map is the prepared box, found by
Newton's method from the corner-moved estimate (a few iterations reach the float64 round-off). Both directions
therefore use one transform, and a box exported and scored again comes back to the bit: coordinates arriving from
the ``thermal`` or ``rgb`` frame are rounded to float32, the precision detectors produce (and values within 1e-6 px
of zero to zero), which removes the float64 round-off of the two maps. A box too thin for the homography's shear
(say 1 px wide and 60 px tall under a 2 degree rotation) has no preimage; it is exported as the corner-moved
estimate and counted (``Preimage.inexact``). In the ``prepared`` frame nothing moves and nothing is rounded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from harness.errors import DataError

FRAMES = ("prepared", "thermal", "rgb")
#: Newton's method for the preimage: at most this many steps, stopped once the residual no longer shrinks.
NEWTON_STEPS = 12
#: The residual (px) below which a preimage is exact; the float64 round-off of the maps is about 1e-13 px.
EXACT_TOL = 1e-9
#: Coordinates moved in from the thermal or RGB frame this close to zero (px) are zero.
ZERO_TOL = 1e-6


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

    return (
        CameraModel.from_dict(cams["camera"], f"{sensor} camera"),
        CameraModel.from_dict(cams["undistorted"], f"{sensor} undistorted camera"),
    )


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
        inside = ~((b[:, 2] <= 0) | (b[:, 0] >= w) | (b[:, 3] <= 0) | (b[:, 1] >= h))
        b, keep = _finish(b, size, 0.0)
        return b[inside[keep]], keep & inside
    if size is not None:
        b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0, size[0])
        b[:, [1, 3]] = np.clip(b[:, [1, 3]], 0, size[1])
    keep = np.isfinite(b).all(axis=1) & ((b[:, 2] - b[:, 0]) >= min_size) & ((b[:, 3] - b[:, 1]) >= min_size)
    return b[keep], keep


def _check(frame: str, meta: Mapping[str, Any], where: str) -> None:
    if frame not in FRAMES:
        raise DataError(f"unknown frame {frame!r}; use one of {', '.join(FRAMES)}")
    if frame == "rgb" and "H_rgb_to_frame" not in meta:
        raise DataError(
            f"{where}: the prepared sample records no RGB-to-frame homography (the dataset has no "
            f"registration stage); use --frame prepared or thermal"
        )


def _forward(b: np.ndarray, frame: str, meta: Mapping[str, Any]) -> np.ndarray:
    """Boxes of ``frame`` -> the prepared frame, before clipping (the map the ground truth went through)."""
    b = np.array(b, dtype=np.float64).reshape(-1, 4)
    if frame == "thermal":
        origin, _ = _crop(meta)
        b = _undistort(b, _camera(meta, "thermal"))
        b[:, [0, 2]] -= origin[0]
        b[:, [1, 3]] -= origin[1]
    elif frame == "rgb":
        b = _homography(np.asarray(meta["H_rgb_to_frame"]), _undistort(b, _camera(meta, "rgb")))
    return b


def _estimate(b: np.ndarray, frame: str, meta: Mapping[str, Any]) -> np.ndarray:
    """The corner-moved estimate of the preimage: prepared boxes -> ``frame`` by the inverse maps."""
    b = np.array(b, dtype=np.float64).reshape(-1, 4)
    if frame == "thermal":
        origin, _ = _crop(meta)
        b[:, [0, 2]] += origin[0]
        b[:, [1, 3]] += origin[1]
        b = _distort(b, _camera(meta, "thermal"))
    elif frame == "rgb":
        b = _distort(
            _homography(np.linalg.inv(np.asarray(meta["H_rgb_to_frame"], np.float64)), b), _camera(meta, "rgb")
        )
    return b


def _snap(b: np.ndarray) -> np.ndarray:
    """Coordinates to float32 precision (as float64), values within ``ZERO_TOL`` of zero to zero."""
    out = b.astype(np.float32).astype(np.float64)
    out[np.abs(b) < ZERO_TOL] = 0.0
    return out


def to_prepared(
    boxes: np.ndarray,
    frame: str,
    meta: Mapping[str, Any],
    size: tuple[int, int] | None = None,
    min_size: float | None = 1.0,
    where: str = "sample",
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N x 4 xyxy) of ``frame`` -> the prepared frame: ``(kept boxes float64, keep mask)``.

    ``size`` (w, h) of the prepared frame clips the result (``meta['crop_size']`` when not given). A box thinner
    than ``min_size`` after clipping is dropped (``None``: only boxes wholly outside the frame; always so for the
    ``prepared`` frame). Boxes from the ``thermal`` or ``rgb`` frame are rounded to float32 (module docstring)."""
    _check(frame, meta, where)
    _, crop = _crop(meta)
    frame_wh = (float(size[0]), float(size[1])) if size is not None else crop
    b = _forward(boxes, frame, meta)
    if frame != "prepared":
        b = _snap(b)
    return _finish(b, frame_wh, min_size if frame != "prepared" else None)


def moved(boxes: np.ndarray, frame: str, meta: Mapping[str, Any], where: str = "sample") -> np.ndarray:
    """Boxes (N x 4 xyxy) of ``frame`` -> the prepared frame, neither clipped nor dropped (what ``to_prepared`` clips):
    how much of each lies inside the frame is the box guard's question (``harness.scoring.plausibility``)."""
    _check(frame, meta, where)
    b = _forward(boxes, frame, meta)
    return _snap(b) if frame != "prepared" else b


@dataclass
class Preimage:
    """Boxes of an original frame whose forward map (``to_prepared``) is the given prepared boxes."""

    boxes: np.ndarray  # N x 4 xyxy, float64
    exact: np.ndarray  # bool N: the forward map returns the prepared box to within EXACT_TOL

    @property
    def inexact(self) -> int:
        return int((~self.exact).sum())


def preimage(boxes: np.ndarray, frame: str, meta: Mapping[str, Any], where: str = "sample") -> Preimage:
    """Boxes (N x 4 xyxy) of the prepared frame -> ``frame``, each the exact preimage under the forward map where
    one exists (module docstring), else the corner-moved estimate."""
    _check(frame, meta, where)
    target = np.array(boxes, dtype=np.float64).reshape(-1, 4)
    if frame == "prepared" or len(target) == 0:
        return Preimage(target, np.ones(len(target), dtype=bool))
    x = _estimate(target, frame, meta)
    best, best_r = x.copy(), np.full(len(x), np.inf)
    for _ in range(NEWTON_STEPS):
        fx = _forward(x, frame, meta)
        err = np.abs(fx - target).max(axis=1)
        err[~np.isfinite(err)] = np.inf
        better = err < best_r
        best[better], best_r[better] = x[better], err[better]
        active = best_r > EXACT_TOL * 1e-3
        if not active.any():
            break
        jac = np.empty((len(x), 4, 4))
        for k in range(4):
            step = np.zeros(4)
            step[k] = 1e-4 * max(1.0, float(np.abs(x[:, k]).max(initial=0.0)) * 1e-3)
            jac[:, :, k] = (_forward(x + step, frame, meta) - fx) / step[k]
        with np.errstate(all="ignore"):
            delta = np.einsum("nij,nj->ni", np.linalg.pinv(jac), fx - target)
        delta[~np.isfinite(delta)] = 0.0
        x = np.where(active[:, None], x - delta, x)
        for lo, hi in ((0, 2), (1, 3)):  # no inverted box: a box too thin for the map stays a (thin) box
            mid = (x[:, lo] + x[:, hi]) / 2
            flip = x[:, hi] < x[:, lo]
            x[flip, lo] = x[flip, hi] = mid[flip]
    exact = best_r <= EXACT_TOL
    out = best
    return Preimage(out, exact)


def from_prepared(boxes: np.ndarray, frame: str, meta: Mapping[str, Any], where: str = "sample") -> np.ndarray:
    """Boxes (N x 4 xyxy) of the prepared frame -> ``frame`` (``preimage(...).boxes``: every box kept, unrounded)."""
    return preimage(boxes, frame, meta, where).boxes


def image_name(meta: Mapping[str, Any], frame: str, image_id: int) -> str:
    """The file name that identifies a sample's image in ``frame`` (RGB file for rgb, thermal file for thermal)."""
    if frame == "thermal" and meta.get("thermal_file"):
        return str(meta["thermal_file"])
    return str(meta.get("file_name") or image_id)
