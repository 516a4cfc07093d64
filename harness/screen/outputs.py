"""What a screen writes into its output folder.

==========================  ============================================================================
``findings.csv``            one row per finding (columns: ``CSV_COLUMNS``), frames in name order, best first
``findings.geojson``        the same findings as GeoJSON points at the capture's GPS position (``[lon, lat,
                            absolute altitude]``; ``null`` geometry without GPS), every column a property
``overlays/<frame>.jpg``    per frame with findings: the aligned RGB and the thermal colour map side by side,
                            each finding's box, class, score and contrast on both
``crops/<frame>_<k>.jpg``   each finding's neighbourhood in both images (the gallery's thumbnails)
``index.html``              the gallery (``harness.screen.gallery``)
``manifest.json``           model, run, configuration, fingerprints of inputs and weights, settings, counts,
                            failures, registration routes, timings, harness version
``frames/<frame>.json``     one record per screened frame (what a re-run reads to skip it)
==========================  ============================================================================
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from harness.io import atomic_write_bytes, atomic_write_text, dumps_json
from harness.screen.findings import TEMPERATURE_KEYS
from harness.screen.position import FIELDS

BOX_KEYS = ("box_thermal", "box_rgb", "box_aligned")
CSV_COLUMNS = (
    "frame",
    "class",
    "score",
    "thermal_x0",
    "thermal_y0",
    "thermal_x1",
    "thermal_y1",
    "rgb_x0",
    "rgb_y0",
    "rgb_x1",
    "rgb_y1",
    "aligned_x0",
    "aligned_y0",
    "aligned_x1",
    "aligned_y1",
    *TEMPERATURE_KEYS,
    *FIELDS,
    "route",
    "expected_error_px",
    "rgb_file",
    "thermal_file",
    "overlay",
)
#: decimals per column in the CSV
_DIGITS = {
    "score": 5,
    "lat": 8,
    "lon": 8,
    "alt_abs": 3,
    "alt_rel": 3,
    "gimbal_yaw": 2,
    "gimbal_pitch": 2,
    "gimbal_roll": 2,
    "flight_yaw": 2,
    **dict.fromkeys(TEMPERATURE_KEYS, 3),
}
#: BGR colours per class index (OpenCV drawing), cycled
PALETTE = (
    (80, 200, 255),
    (255, 160, 60),
    (90, 230, 120),
    (60, 60, 255),
    (255, 90, 220),
    (250, 250, 90),
    (40, 160, 250),
    (200, 120, 255),
    (140, 255, 200),
    (120, 180, 120),
)


def safe_name(frame: str) -> str:
    """A frame name (capture, possibly with sub-folders) as one file name."""
    return frame.replace("/", "__").replace("\\", "__")


def _fmt(key: str, value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, float):
        return f"{value:.{_DIGITS.get(key, 2)}f}"
    return str(value)


def csv_row(f: dict[str, Any]) -> list[str]:
    flat = dict(f)
    for key in BOX_KEYS:
        prefix = key.split("_", 1)[1]
        for name, v in zip(("x0", "y0", "x1", "y1"), f[key]):
            flat[f"{prefix}_{name}"] = float(v)
    return [_fmt(c, flat.get(c)) for c in CSV_COLUMNS]


def write_csv(path: Path, findings: Iterable[dict[str, Any]]) -> Path:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for f in findings:
        w.writerow(csv_row(f))
    return atomic_write_text(path, buf.getvalue())


def write_geojson(path: Path, findings: Iterable[dict[str, Any]]) -> Path:
    features = []
    for f in findings:
        geometry = None
        if f.get("lat") is not None and f.get("lon") is not None:
            coords = [f["lon"], f["lat"]] + ([f["alt_abs"]] if f.get("alt_abs") is not None else [])
            geometry = {"type": "Point", "coordinates": coords}
        features.append({"type": "Feature", "geometry": geometry, "properties": dict(f)})
    return atomic_write_text(path, dumps_json({"type": "FeatureCollection", "features": features}, indent=1))


def write_json(path: Path, obj: Any) -> Path:
    return atomic_write_text(path, dumps_json(obj))


# ------------------------------------------------------------------------------------------------ pictures
def thermal_colours(temp: np.ndarray) -> np.ndarray:
    """A temperature map as a BGR colour image (inferno, stretched over its 1st..99th percentile; missing grey)."""
    import cv2

    finite = np.isfinite(temp)
    if finite.any():
        lo, hi = np.percentile(temp[finite], [1, 99])
    else:
        lo, hi = 0.0, 1.0
    scaled = np.clip((np.where(finite, temp, lo) - lo) / max(float(hi - lo), 1e-3) * 255, 0, 255).astype(np.uint8)
    out = cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)
    out[~finite] = (128, 128, 128)
    return out


def _label(f: dict[str, Any]) -> str:
    dt = f.get("delta_t")
    return f"{f['class']} {f['score']:.2f}" + (f" dT {dt:+.1f}C" if dt is not None else "")


def overlay(rgb: np.ndarray, temp: np.ndarray, findings: Sequence[dict[str, Any]], min_height: int = 360) -> np.ndarray:
    """The aligned RGB and the thermal colour map side by side (BGR), boxes and labels on both; frames lower than
    ``min_height`` pixels are enlarged by a whole factor first."""
    import cv2

    k = max(1, math.ceil(min_height / rgb.shape[0]))
    left = np.ascontiguousarray(rgb[:, :, ::-1])
    right = thermal_colours(temp)
    if k > 1:
        left = cv2.resize(left, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
        right = cv2.resize(right, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
    scale = 0.4 + 0.1 * k if rgb.shape[0] * k < 700 else 0.6
    for panel in (left, right):
        for f in reversed(findings):  # the best drawn last, on top
            colour = PALETTE[int(f["class_id"]) % len(PALETTE)]
            x0, y0, x1, y1 = (int(round(v * k)) for v in f["box_aligned"])
            cv2.rectangle(panel, (x0, y0), (max(x1 - 1, x0), max(y1 - 1, y0)), colour, max(1, k // 2 + 1))
            text = _label(f)
            (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
            ty = y0 - 3 if y0 - th - base - 3 >= 0 else min(y1 + th + 3, panel.shape[0] - base)
            cv2.rectangle(panel, (x0, ty - th - 2), (x0 + tw + 2, ty + base - 1), (0, 0, 0), -1)
            cv2.putText(panel, text, (x0 + 1, ty - 1), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    gap = np.full((left.shape[0], 6, 3), 255, np.uint8)
    return np.hstack([left, gap, right])


def crop(rgb: np.ndarray, temp: np.ndarray, box: Sequence[float], height: int = 112) -> np.ndarray:
    """A finding's neighbourhood (its box plus half its size around it) in RGB and thermal colours, side by side
    at ``height`` pixels (BGR)."""
    import cv2

    h, w = rgb.shape[:2]
    x0, y0, x1, y1 = (float(v) for v in box)
    mx, my = max(4.0, 0.5 * (x1 - x0)), max(4.0, 0.5 * (y1 - y0))
    a, b = int(max(0, math.floor(x0 - mx))), int(min(w, math.ceil(x1 + mx)))
    c, d = int(max(0, math.floor(y0 - my))), int(min(h, math.ceil(y1 + my)))
    colours = thermal_colours(temp)
    parts = []
    for img in (np.ascontiguousarray(rgb[:, :, ::-1]), colours):
        part = np.ascontiguousarray(img[c:d, a:b])
        cv2.rectangle(
            part,
            (int(round(x0)) - a, int(round(y0)) - c),
            (int(round(x1)) - a - 1, int(round(y1)) - c - 1),
            (255, 255, 255),
            1,
        )
        f = height / max(part.shape[0], 1)
        parts.append(
            cv2.resize(
                part,
                (max(1, int(round(part.shape[1] * f))), height),
                interpolation=cv2.INTER_NEAREST if f >= 1 else cv2.INTER_AREA,
            )
        )
    return np.hstack([parts[0], np.full((height, 3, 3), 255, np.uint8), parts[1]])


def write_jpeg(path: Path, bgr: np.ndarray, quality: int = 90) -> Path:
    import cv2

    ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover
        raise OSError(f"{path}: could not encode the picture")
    return atomic_write_bytes(path, data.tobytes())
