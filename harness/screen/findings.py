"""What is reported per detection: its boxes in the original images, its temperatures and its contrast.

* **Boxes.** The model sees the aligned frame (the thermal frame after undistortion and the common-support crop);
  its box there (``box_aligned``, continuous ``xyxy``) is the box the run's predictions store. ``box_thermal`` is
  the same box in the thermal image as shot: shifted by the crop origin and, when the run undistorted the thermal
  camera, its corners taken back through the lens model. ``box_rgb`` is its footprint in the wide image as shot:
  the corners through the inverse homography, the wide lens model and the decode scale, then their bounding box.
  Both are clipped to their image.
* **Temperatures** (C) inside the box: minimum, mean, maximum and 95th percentile (linear interpolation) over the
  pixels whose centres lie inside it (at least the pixel under its centre), on the temperature map the model's
  fourth channel came from: without thermal undistortion that is the decoded map itself, sliced.
* **Contrast** ``delta_t`` = mean inside the box minus the median of a ring around it: the pixels within
  ``max(2, ceil(shorter side / 4))`` pixels of the box, outside it, inside the map. ``t_ring`` is that median.

Missing temperatures (NaN) are left out of every statistic; a box or ring without a measured pixel has ``None``.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from harness.screen.frontend import Frame, scale_change
from harness.screen.position import FIELDS

#: the ring's width: at least this many pixels, else a quarter of the box's shorter side
RING_MIN_PX = 2
RING_FRACTION = 0.25
TEMPERATURE_KEYS = ("t_min", "t_mean", "t_max", "t_p95", "t_ring", "delta_t")


def pixel_span(lo: float, hi: float, size: int) -> tuple[int, int]:
    """Pixel indices ``[a, b)`` whose centres ``i + 0.5`` lie in ``[lo, hi)``; the pixel under the middle when
    none does; clipped to ``[0, size)``."""
    a, b = int(math.ceil(lo - 0.5)), int(math.ceil(hi - 0.5))
    if b <= a:
        a = int(math.floor((lo + hi) / 2))
        b = a + 1
    return max(0, min(a, size - 1)), max(1, min(b, size))


def box_temperatures(temp: np.ndarray, box: Sequence[float]) -> dict[str, float | None]:
    """``t_min``, ``t_mean``, ``t_max``, ``t_p95``, ``t_ring`` and ``delta_t`` of ``box`` (``xyxy``) on ``temp``."""
    h, w = temp.shape
    x0, x1 = pixel_span(float(box[0]), float(box[2]), w)
    y0, y1 = pixel_span(float(box[1]), float(box[3]), h)
    inside = temp[y0:y1, x0:x1]
    vals = inside[np.isfinite(inside)].astype(np.float64)
    out: dict[str, float | None] = dict.fromkeys(TEMPERATURE_KEYS)
    if vals.size:
        out.update(
            t_min=float(vals.min()),
            t_mean=float(vals.mean()),
            t_max=float(vals.max()),
            t_p95=float(np.percentile(vals, 95)),
        )
    r = max(RING_MIN_PX, int(math.ceil(RING_FRACTION * min(x1 - x0, y1 - y0))))
    ra, rb, rc, rd = max(0, y0 - r), min(h, y1 + r), max(0, x0 - r), min(w, x1 + r)
    ring = np.ones((rb - ra, rd - rc), bool)
    ring[y0 - ra : y1 - ra, x0 - rc : x1 - rc] = False
    around = temp[ra:rb, rc:rd][ring]
    around = around[np.isfinite(around)].astype(np.float64)
    if around.size:
        out["t_ring"] = float(np.median(around))
        if out["t_mean"] is not None:
            out["delta_t"] = float(out["t_mean"]) - out["t_ring"]  # type: ignore[operator]
    return out


def _corners(box: Sequence[float]) -> np.ndarray:
    """The four corners of an ``xyxy`` box in pixel-centre coordinates (edge - 0.5)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) - 0.5


def _envelope(points: np.ndarray, size: tuple[int, int]) -> list[float]:
    pts = points + 0.5
    w, h = size
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return [
        float(np.clip(lo[0], 0, w)),
        float(np.clip(lo[1], 0, h)),
        float(np.clip(hi[0], 0, w)),
        float(np.clip(hi[1], 0, h)),
    ]


def _camera_pair(cameras: dict[str, Any], sensor: str) -> tuple[Any, Any] | None:
    from harness.sensing.calibration import CameraModel

    rec = cameras.get(sensor)
    if not rec:
        return None
    return CameraModel.from_dict(rec["undistorted"]), CameraModel.from_dict(rec["camera"])


def box_in_thermal(frame: Frame, box: Sequence[float]) -> list[float]:
    """An aligned-frame box in the thermal image as shot."""
    from harness.sensing.calibration import distort_points

    pts = _corners(box) + np.asarray(frame.origin, np.float64)
    cams = _camera_pair(frame.cameras, "thermal")
    if cams is not None:
        pts = distort_points(pts, *cams)
    return _envelope(pts, frame.thermal_size)


def box_in_rgb(frame: Frame, box: Sequence[float]) -> list[float]:
    """An aligned-frame box's footprint in the wide image as shot."""
    from harness.sensing.calibration import distort_points
    from harness.sensing.registration import apply_homography

    pts = apply_homography(np.linalg.inv(frame.H), _corners(box))
    cams = _camera_pair(frame.cameras, "rgb")
    if cams is not None:
        pts = distort_points(pts, *cams)
    pts = apply_homography(scale_change(frame.reduction), pts)
    return _envelope(pts, frame.rgb_size)


def registration_note(quality: Mapping[str, Any]) -> str:
    """Why a frame was screened with the prior, and (a group's) how far off the prior is expected to be."""
    why = str(quality.get("reason", ""))
    if quality.get("expected_error_px") is not None:
        why += f"; expected registration error about {quality['expected_error_px']:g} px"
    return why


def frame_findings(
    frame: Frame, detections: list[dict[str, Any]], categories: Sequence[str], threshold: float
) -> list[dict[str, Any]]:
    """One record per detection scoring at least ``threshold``, best first (``detections``: COCO results of the
    frame, as the run's predictions store them)."""
    out = []
    for det in sorted(detections, key=lambda d: -d["score"]):
        if det["score"] < threshold:
            continue
        x, y, w, h = det["bbox"]
        aligned = [x, y, round(x + w, 2), round(y + h, 2)]
        label = int(det["category_id"]) - 1
        rec: dict[str, Any] = {
            "frame": frame.capture.name,
            "class": categories[label],
            "class_id": label,
            "score": det["score"],
            "bbox": list(det["bbox"]),
            "box_aligned": aligned,
            "box_thermal": box_in_thermal(frame, aligned),
            "box_rgb": box_in_rgb(frame, aligned),
        }
        rec.update(box_temperatures(frame.thermal, aligned))
        rec.update({k: getattr(frame.position, k) for k in FIELDS})
        rec["gps_source"] = frame.position.gps_source
        rec["temperature_route"] = "approximate" if frame.approximate_bound_c is not None else frame.thermal_decoder
        rec["t_bound_c"] = frame.approximate_bound_c
        rec["route"] = frame.route
        rec["expected_error_px"] = frame.registration.get("expected_error_px")
        out.append(rec)
    return out
