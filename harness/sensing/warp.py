"""Warp RGB into the thermal frame, find the common support, carry boxes along.

The temperature map is never resampled here: RGB is warped onto the thermal pixel grid with the group's
homography ``H`` (RGB -> thermal), and both are then cropped to the bounding extent of their common support
(valid warped RGB and valid thermal). Boxes move with the same ``H``: the four corners of each box are mapped,
their bounding box taken, shifted by the crop origin and clipped; boxes that end up degenerate are dropped and
counted.

Coordinates: ``H`` acts on pixel-centre coordinates (pixel ``(i, j)`` has its centre at ``x = j, y = i``), the
convention of OpenCV's warps. Boxes are continuous ``xyxy`` with the image spanning ``[0, W] x [0, H]``, so a box
edge ``x`` is the centre coordinate ``x - 0.5``; ``transform_boxes`` converts on the way in and out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.api import AlignedSample
from harness.errors import DataError
from harness.sensing.registration.homography import project_points

_INTERP = {"linear": 1, "nearest": 0, "cubic": 2, "area": 3}


def _linear_scale(H: np.ndarray, at: tuple[float, float]) -> float:
    """Thermal pixels per source pixel at thermal point ``at`` (sqrt of the local Jacobian determinant of H^-1)."""
    Hi = np.linalg.inv(H)
    u, v = at
    den = Hi[2, 0] * u + Hi[2, 1] * v + Hi[2, 2]
    x = (Hi[0, 0] * u + Hi[0, 1] * v + Hi[0, 2]) / den
    y = (Hi[1, 0] * u + Hi[1, 1] * v + Hi[1, 2]) / den
    J = (
        np.array(
            [[Hi[0, 0] - x * Hi[2, 0], Hi[0, 1] - x * Hi[2, 1]], [Hi[1, 0] - y * Hi[2, 0], Hi[1, 1] - y * Hi[2, 1]]]
        )
        / den
    )
    det = abs(np.linalg.det(J))
    return 1.0 / math.sqrt(det) if det > 0 else 1.0


def warp_to_thermal(
    rgb: np.ndarray,
    H: np.ndarray,
    thermal_shape: tuple[int, int],
    interpolation: str = "linear",
    antialias: bool = True,
    fill: str = "zero",
) -> tuple[np.ndarray, np.ndarray]:
    """Warp ``rgb`` (HxW or HxWx3, any dtype) into the thermal frame of shape ``(h, w)``.

    Each thermal pixel ``u`` samples the RGB image at ``H^-1 u``. Returns ``(warped, valid_mask)``: pixels whose
    source point lies outside the RGB image are 0 and ``False`` in the mask. With ``antialias`` the RGB image is
    first reduced by a Gaussian pyramid while the warp shrinks it by 2x or more, and blurred by
    ``0.5 sqrt(f^2 - 1)`` px for the remaining factor ``f`` (so a 4000 px frame mapped to 640 px does not alias).
    ``fill="replicate"`` extends the nearest RGB border pixel instead of 0 outside the mask (no artificial edge
    at the border of the support; what intensity-based registration wants).
    """
    import cv2

    H = np.asarray(H, dtype=np.float64).reshape(3, 3)
    h, w = int(thermal_shape[0]), int(thermal_shape[1])
    src = np.asarray(rgb)
    if antialias:
        factor = 1.0 / _linear_scale(H, ((w - 1) / 2, (h - 1) / 2))  # source pixels per thermal pixel
        while factor >= 2.0 and min(src.shape[:2]) >= 4:
            src = cv2.pyrDown(src)
            H = H @ np.diag([2.0, 2.0, 1.0])  # rgb(p) with p = 2 p' in the halved image
            factor /= 2.0
        if factor > 1.25:
            sigma = 0.5 * math.sqrt(factor**2 - 1.0)
            src = cv2.GaussianBlur(src, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
    sh, sw = src.shape[:2]
    mx, my, den = _source_coords(H, (h, w))
    valid = _inside(mx, my, den, (sh, sw))
    if fill == "replicate":
        ok = np.isfinite(mx) & np.isfinite(my) & (den > 0)
        mx = np.where(ok, np.clip(mx, 0, sw - 1), 0).astype(np.float32)
        my = np.where(ok, np.clip(my, 0, sh - 1), 0).astype(np.float32)
        return cv2.remap(src, mx, my, _INTERP[interpolation], borderMode=cv2.BORDER_REPLICATE), valid
    if fill != "zero":
        raise ValueError(f"fill must be 'zero' or 'replicate', got {fill!r}")
    mx = np.where(valid, mx, -1).astype(np.float32)
    my = np.where(valid, my, -1).astype(np.float32)
    warped = cv2.remap(src, mx, my, _INTERP[interpolation], borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    warped[~valid] = 0
    return warped, valid


def _source_coords(H: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source (RGB) coordinates ``H^-1 u`` of every thermal pixel ``u`` and the homogeneous denominators."""
    h, w = shape
    Hi = np.linalg.inv(np.asarray(H, dtype=np.float64))
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    den = Hi[2, 0] * uu + Hi[2, 1] * vv + Hi[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        mx = (Hi[0, 0] * uu + Hi[0, 1] * vv + Hi[0, 2]) / den
        my = (Hi[1, 0] * uu + Hi[1, 1] * vv + Hi[1, 2]) / den
    return mx, my, den


def _inside(mx: np.ndarray, my: np.ndarray, den: np.ndarray, src_shape: tuple[int, int]) -> np.ndarray:
    sh, sw = src_shape
    return (den > 0) & (mx >= 0) & (mx <= sw - 1) & (my >= 0) & (my <= sh - 1)


def support_mask(H: np.ndarray, rgb_size: tuple[int, int], thermal_shape: tuple[int, int]) -> np.ndarray:
    """Thermal pixels that receive an RGB pixel under ``H`` (``rgb_size = (w, h)``, ``thermal_shape = (h, w)``)."""
    mx, my, den = _source_coords(H, thermal_shape)
    return _inside(mx, my, den, (int(rgb_size[1]), int(rgb_size[0])))


def common_support_box(valid_mask: np.ndarray) -> tuple[int, int, int, int]:
    """Bounding extent ``(x0, y0, x1, y1)`` of the mask's ``True`` pixels (``x1``, ``y1`` exclusive)."""
    m = np.asarray(valid_mask, dtype=bool)
    rows = np.nonzero(m.any(axis=1))[0]
    cols = np.nonzero(m.any(axis=0))[0]
    if len(rows) == 0:
        raise DataError("the RGB and thermal images have no common support: check the homography")
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def transform_boxes(
    boxes: np.ndarray,
    H: np.ndarray | None,
    origin: tuple[float, float] = (0.0, 0.0),
    size: tuple[int, int] | None = None,
    min_size: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Map boxes (N x 4 xyxy) through ``H``, shift by ``-origin``, clip to ``size = (w, h)``, drop degenerate ones.

    For each box the four corners go through ``H`` (centre-coordinate convention, see the module docstring),
    the bounding box of the results is shifted by the crop ``origin = (x0, y0)`` and clipped to ``[0, w] x [0,
    h]``. A box is dropped when its clipped width or height is below ``min_size`` pixels or a corner maps to
    infinity (behind the plane at infinity). ``H=None`` means the boxes are already in the thermal frame.
    Returns ``(kept boxes float32 K x 4, keep bool N)``.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if len(b) == 0:
        return np.zeros((0, 4), np.float32), np.zeros(0, dtype=bool)
    finite: np.ndarray
    if H is None:
        out = b.copy()
        finite = np.ones(len(b), dtype=bool)
    else:
        corners = np.stack([b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1).reshape(-1, 2) - 0.5
        moved, depth = project_points(H, corners)
        finite = np.asarray((depth > 1e-12).reshape(-1, 4).all(axis=1))
        pts = moved.reshape(-1, 4, 2) + 0.5
        out = np.concatenate([pts.min(axis=1), pts.max(axis=1)], axis=1)
        out[~finite] = 0.0
    out[:, [0, 2]] -= origin[0]
    out[:, [1, 3]] -= origin[1]
    if size is not None:
        w, h = size
        out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0, w)
        out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0, h)
    keep = (
        finite
        & np.isfinite(out).all(axis=1)
        & ((out[:, 2] - out[:, 0]) >= min_size)
        & ((out[:, 3] - out[:, 1]) >= min_size)
    )
    return out[keep].astype(np.float32), keep


@dataclass
class AlignedPair:
    """The pieces of an ``AlignedSample`` in the cropped thermal frame, and what the alignment did."""

    rgb: np.ndarray
    thermal: np.ndarray | None
    ir8: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    origin: tuple[int, int]  # crop origin (x0, y0) in the uncropped thermal frame
    size: tuple[int, int]  # (w, h) after the crop
    valid: np.ndarray  # common-support mask inside the crop
    kept: np.ndarray  # bool over the input boxes
    H: np.ndarray  # RGB -> cropped thermal frame
    #: the undistortion applied before ``H``, per sensor: {"rgb"|"thermal": {"camera": ..., "undistorted": ...}}
    cameras: dict[str, Any] = field(default_factory=dict)

    @property
    def dropped(self) -> int:
        return int((~self.kept).sum())

    @property
    def support_fraction(self) -> float:
        return float(self.valid.mean()) if self.valid.size else 0.0

    def meta(self) -> dict[str, Any]:
        out = {
            "crop_origin": list(self.origin),
            "crop_size": list(self.size),
            "H_rgb_to_frame": self.H.tolist(),
            "support_fraction": round(self.support_fraction, 6),
            "boxes_dropped": self.dropped,
        }
        if self.cameras:
            out["cameras"] = self.cameras
        return out

    def to_sample(self, image_id: int, group: str, meta: dict[str, Any] | None = None) -> AlignedSample:
        """An ``AlignedSample`` with the alignment's provenance merged into ``meta``."""
        return AlignedSample(
            image_id=int(image_id),
            rgb=self.rgb,
            thermal=self.thermal,
            ir8=self.ir8,
            boxes=self.boxes,
            labels=self.labels,
            group=group,
            meta={**self.meta(), **dict(meta or {})},
        )


def align_pair(
    rgb: np.ndarray,
    thermal: np.ndarray | None,
    ir8: np.ndarray,
    boxes: np.ndarray,
    labels: np.ndarray,
    H: np.ndarray,
    boxes_frame: str = "thermal",
    thermal_valid: np.ndarray | None = None,
    crop: bool = True,
    min_box_size: float = 1.0,
    interpolation: str = "linear",
    antialias: bool = True,
) -> AlignedPair:
    """Register one capture: RGB warped into the thermal frame, both cropped to the common support, boxes moved.

    ``rgb`` uint8 HxWx3 (RGB order, its own resolution); ``thermal`` float32 temperature map in C (or None for
    8-bit datasets) and ``ir8`` uint8 preview, both in the thermal frame; ``boxes`` xyxy in ``boxes_frame``
    (``"thermal"``: annotated on the thermal image, ``"rgb"``: on the RGB image, moved through ``H``);
    ``thermal_valid``: optional mask of usable thermal pixels (e.g. after undistortion). Common support =
    valid warped RGB and valid thermal; with ``crop`` everything is cut to its bounding extent, otherwise the
    full thermal frame is kept. The temperature map is only sliced, never resampled.
    """
    ir8 = np.asarray(ir8)
    h, w = ir8.shape[:2]
    if thermal is not None and thermal.shape[:2] != (h, w):
        raise DataError(f"thermal map {thermal.shape} and preview {ir8.shape} differ in size")
    H = np.asarray(H, dtype=np.float64)
    warped, valid = warp_to_thermal(rgb, H, (h, w), interpolation=interpolation, antialias=antialias)
    if warped.ndim == 2:
        warped = np.repeat(warped[:, :, None], 3, axis=2)
    if thermal_valid is not None:
        valid &= np.asarray(thermal_valid, dtype=bool)
    x0, y0, x1, y1 = common_support_box(valid) if crop else (0, 0, w, h)
    size = (x1 - x0, y1 - y0)
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    if boxes_frame == "rgb":
        out_boxes, keep = transform_boxes(boxes, H, (x0, y0), size, min_box_size)
    elif boxes_frame == "thermal":
        out_boxes, keep = transform_boxes(boxes, None, (x0, y0), size, min_box_size)
    else:
        raise DataError(f"boxes_frame must be 'thermal' or 'rgb', got {boxes_frame!r}")
    if len(labels) != len(keep):
        raise DataError(f"{len(labels)} labels for {len(keep)} boxes")
    T = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
    return AlignedPair(
        rgb=np.ascontiguousarray(warped[y0:y1, x0:x1]),
        thermal=None if thermal is None else np.ascontiguousarray(thermal[y0:y1, x0:x1], dtype=np.float32),
        ir8=np.ascontiguousarray(ir8[y0:y1, x0:x1]),
        boxes=out_boxes,
        labels=labels[keep],
        origin=(x0, y0),
        size=size,
        valid=valid[y0:y1, x0:x1],
        kept=keep,
        H=T @ H,
    )
