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
    "temperature_route",
    "t_bound_c",
    *FIELDS,
    "gps_source",
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
    "t_bound_c": 3,
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


def score_digits(scores: Sequence[float], most: int = 5) -> int:
    """Decimals that print every score with at least two significant digits and tell different scores apart
    (2 to ``most``): 0.87 and 0.62 take 2, 0.042 takes 3, 0.0042 takes 4, 0.5012 beside 0.5034 takes 3."""
    values = [float(v) for v in scores if v is not None and math.isfinite(float(v))]
    positive = [v for v in values if v > 0]
    digits = 2
    if positive:
        digits = max(digits, 1 - math.floor(math.log10(min(positive))))
    distinct = len({round(v, most) for v in values})
    while digits < most and len({round(v, digits) for v in values}) < distinct:
        digits += 1
    return int(min(digits, most))


def _label(f: dict[str, Any], digits: int = 2) -> str:
    dt = f.get("delta_t")
    return f"{f['class']} {f['score']:.{digits}f}" + (f" dT {dt:+.1f}C" if dt is not None else "")


def overlay_legend(findings: Sequence[dict[str, Any]]) -> list[str]:
    """The overlay's legend: one line per finding, numbered as its tag on the pictures (best first), after a line
    saying when the temperatures are approximate."""
    digits = score_digits([f["score"] for f in findings])
    bounds = [f.get("t_bound_c") for f in findings if f.get("temperature_route") == "approximate"]
    head = [f"approximate temperatures (within +-{max(bounds):g} C)"] if bounds else []
    return head + [f"{k}  {_label(f, digits)}" for k, f in enumerate(findings, 1)]


Rect = tuple[int, int, int, int]  # x, y, w, h


def _free(r: Rect, placed: Sequence[Rect], size: tuple[int, int]) -> bool:
    x, y, w, h = r
    if x < 0 or y < 0 or x + w > size[0] or y + h > size[1]:
        return False
    return all(x + w <= a or a + c <= x or y + h <= b or b + d <= y for a, b, c, d in placed)


def place_labels(
    boxes: Sequence[Sequence[float]], sizes: Sequence[tuple[int, int]], size: tuple[int, int]
) -> list[tuple[Rect, bool]]:
    """Where each box's tag goes, no two overlapping: (rectangle, whether it needs a leader line to its box).

    In order, each tag takes the first free place at its box (above its top-left corner, inside it, below it, at
    its right), else the free place nearest the box found on a grid (with a leader line); ``size``: the panel's
    (width, height). A tag is put at its box even if overlapping only when the panel has no free place left."""
    placed: list[Rect] = []
    out: list[tuple[Rect, bool]] = []
    W, H = size
    for box, (w, h) in zip(boxes, sizes):
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        near = [(x0, y0 - h), (x0, y0), (x0, y1), (x1 - w, y0 - h), (x1, y0), (x1 - w, y1), (x0 - w, y0)]
        choice: tuple[Rect, bool] | None = None
        for x, y in near:
            r = (x, y, w, h)
            if _free(r, placed, size):
                choice = (r, False)
                break
        if choice is None:
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            step_x, step_y = max(2, w // 2), max(1, h // 2)
            grid = [(x, y) for y in range(0, max(1, H - h + 1), step_y) for x in range(0, max(1, W - w + 1), step_x)]
            grid.sort(key=lambda p: (p[0] + w / 2 - cx) ** 2 + (p[1] + h / 2 - cy) ** 2)
            for x, y in grid:
                r = (x, y, w, h)
                if _free(r, placed, size):
                    choice = (r, True)
                    break
        if choice is None:  # no room left anywhere: at the box
            choice = ((max(0, min(x0, W - w)), max(0, min(y0, H - h)), w, h), False)
        placed.append(choice[0])
        out.append(choice)
    return out


def overlay(rgb: np.ndarray, temp: np.ndarray, findings: Sequence[dict[str, Any]], min_height: int = 360) -> np.ndarray:
    """The aligned RGB and the thermal colour map side by side (BGR), each finding's box with a numbered tag on both
    (tags never overlap: one that finds no room at its box is put nearby with a leader line), and below them the
    legend: number, class, score (as many decimals as the scores need, ``score_digits``) and contrast, headed by a
    note when the temperatures are approximate. Frames lower than ``min_height`` pixels are enlarged by a whole
    factor first."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    k = max(1, math.ceil(min_height / rgb.shape[0]))
    left = np.ascontiguousarray(rgb[:, :, ::-1])
    right = thermal_colours(temp)
    if k > 1:
        left = cv2.resize(left, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
        right = cv2.resize(right, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
    scale = 0.4 + 0.1 * k if rgb.shape[0] * k < 700 else 0.6
    boxes = [[v * k for v in f["box_aligned"]] for f in findings]
    sizes = []
    for n in range(1, len(findings) + 1):
        (tw, th), base = cv2.getTextSize(str(n), font, scale, 1)
        sizes.append((tw + 4, th + base + 3))
    places = place_labels(boxes, sizes, (left.shape[1], left.shape[0]))
    for panel in (left, right):
        for n in range(len(findings), 0, -1):  # the best drawn last, on top
            f = findings[n - 1]
            colour = PALETTE[int(f["class_id"]) % len(PALETTE)]
            x0, y0, x1, y1 = (int(round(v)) for v in boxes[n - 1])
            cv2.rectangle(panel, (x0, y0), (max(x1 - 1, x0), max(y1 - 1, y0)), colour, max(1, k // 2 + 1))
        for n, ((x, y, w, h), leader) in enumerate(places, 1):
            f = findings[n - 1]
            colour = PALETTE[int(f["class_id"]) % len(PALETTE)]
            if leader:
                x0, y0, x1, y1 = boxes[n - 1]
                bx = int(round(min(max(x + w / 2, x0), x1)))
                by = int(round(min(max(y + h / 2, y0), y1)))
                cv2.line(panel, (x + w // 2, y + h // 2), (bx, by), colour, 1, cv2.LINE_AA)
            cv2.rectangle(panel, (x, y), (x + w - 1, y + h - 1), (0, 0, 0), -1)
            (_, th), base = cv2.getTextSize(str(n), font, scale, 1)
            cv2.putText(panel, str(n), (x + 2, y + h - base - 1), font, scale, colour, 1, cv2.LINE_AA)
    gap = np.full((left.shape[0], 6, 3), 255, np.uint8)
    pictures = np.hstack([left, gap, right])
    return np.vstack([pictures, _legend(overlay_legend(findings), findings, pictures.shape[1], scale)])


def _legend(lines: Sequence[str], findings: Sequence[dict[str, Any]], width: int, scale: float) -> np.ndarray:
    """The legend strip: ``lines`` in columns (a note line first, across the width), numbers in their class colour."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    head = list(lines[: len(lines) - len(findings)])
    entries = list(lines[len(lines) - len(findings) :])
    (_, th), base = cv2.getTextSize("Ag", font, scale, 1)
    line_h = th + base + 6
    col_w = max([cv2.getTextSize(t, font, scale, 1)[0][0] for t in entries] + [1]) + 24
    cols = max(1, (width - 8) // col_w)
    rows = math.ceil(len(entries) / cols) if entries else 0
    strip = np.full((12 + line_h * (len(head) + rows), width, 3), 255, np.uint8)
    y = 4 + th
    for text in head:
        cv2.putText(strip, text, (6, y), font, scale, (0, 0, 176), 1, cv2.LINE_AA)
        y += line_h
    for n, (text, f) in enumerate(zip(entries, findings)):
        col, row = divmod(n, rows) if rows else (0, 0)
        x, yy = 6 + col * col_w, y + row * line_h
        number, _, rest = text.partition("  ")
        colour = PALETTE[int(f["class_id"]) % len(PALETTE)]
        (nw, _), _ = cv2.getTextSize(number, font, scale, 1)
        cv2.rectangle(strip, (x - 2, yy - th - 2), (x + nw + 2, yy + base), (0, 0, 0), -1)
        cv2.putText(strip, number, (x, yy), font, scale, colour, 1, cv2.LINE_AA)
        cv2.putText(strip, rest, (x + nw + 8, yy), font, scale, (20, 20, 20), 1, cv2.LINE_AA)
    return strip


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
