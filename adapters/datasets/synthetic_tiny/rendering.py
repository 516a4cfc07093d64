"""Pixels of an RGBT-Tiny-like sequence: sky, sea and ground backgrounds in both modalities, targets with an
extended thermal signature, and the two sensors (thermal: optics, vignetting, column and temporal noise, per-frame
AGC to 8 bit; visible: exposure, vignetting, noise)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from adapters.datasets.synthetic_tiny.model import Sequence, Track

#: The warm halo's sigma is at least this many pixels, however small the target.
HALO_MIN_PX = 2.5
#: Thermal sensor noise (NETD-like, per frame) and column fixed-pattern noise, degrees C.
NETD_C = 0.08
COLUMN_C = 0.05


def _field(rng: np.random.Generator, shape: tuple[int, int], sigma: float | tuple[float, float]) -> np.ndarray:
    """Smooth zero-mean unit-std noise: white noise blurred by a Gaussian (``(sx, sy)`` for anisotropic)."""
    import cv2

    sx, sy = (sigma, sigma) if isinstance(sigma, (int, float)) else sigma
    white = rng.standard_normal(shape).astype(np.float32)
    f = cv2.GaussianBlur(white, (0, 0), sigmaX=float(sx), sigmaY=float(sy), borderType=cv2.BORDER_REFLECT)
    return (f - f.mean()) / max(float(f.std()), 1e-6)


@dataclass
class Backdrop:
    """A sequence's background on a canvas larger than the frame (the camera pans over it)."""

    thermal: np.ndarray  # float32 HxW, degrees C
    rgb: np.ndarray  # float32 HxWx3, reflectance 0..1
    origin: tuple[float, float]  # canvas position of the frame's top-left at frame 0


def make_backdrop(seq: Sequence, size: tuple[int, int], frames: int, rng: np.random.Generator) -> Backdrop:
    import cv2

    w, h = size
    travel = (abs(seq.pan[0]) * frames, abs(seq.pan[1]) * frames)
    pad = 8
    cw, ch = int(w + travel[0] + 2 * pad), int(h + travel[1] + 2 * pad)
    ox = pad + (travel[0] if seq.pan[0] < 0 else 0)
    oy = pad + (travel[1] if seq.pan[1] < 0 else 0)
    res = min(w / 640, h / 512)
    yy = np.linspace(0, 1, ch, dtype=np.float32)[:, None] * np.ones((1, cw), np.float32)
    night = seq.spec.light == "night"
    scene = seq.spec.scene
    if scene == "sky":
        base = float(rng.uniform(-20, -5))
        clouds = np.clip(_field(rng, (ch, cw), 40 * res) * 0.8 + float(rng.uniform(-0.6, 0.4)), 0, None)
        thermal = base + float(rng.uniform(3, 8)) * yy + float(rng.uniform(2, 5)) * clouds
        top, bottom = np.array([0.25, 0.45, 0.80]), np.array([0.65, 0.78, 0.92])
        rgb = top + (bottom - top) * yy[..., None]
        rgb = rgb + np.clip(clouds, 0, 1.2)[..., None] * (np.array([0.92, 0.92, 0.95]) - rgb) * 0.8
    elif scene == "sea":
        base = float(rng.uniform(12, 20))
        waves = _field(rng, (ch, cw), (6 * res, 1.5 * res))
        swell = _field(rng, (ch, cw), 60 * res)
        thermal = base + 0.45 * waves + 0.6 * swell - 0.8 * yy
        colour = np.array([0.10, 0.28, 0.35]) + rng.uniform(-0.04, 0.04, 3)
        rgb = colour + 0.05 * waves[..., None] + 0.03 * swell[..., None]
        glint = np.clip(_field(rng, (ch, cw), 0.8 * res) - 2.6, 0, None)  # sun glints: bright specks
        rgb = rgb + 1.5 * glint[..., None]
    else:  # ground: fields, rooftops and roads with sharp edges, fine texture
        base = float(rng.uniform(15, 30)) if not night else float(rng.uniform(5, 15))
        labels = np.digitize(_field(rng, (ch, cw), 25 * res), [-0.8, -0.2, 0.4, 1.0])
        temps = rng.uniform(-5, 8, 5) * (0.5 if night else 1.0)
        earth = np.array([[0.25, 0.38, 0.18], [0.42, 0.36, 0.26], [0.52, 0.52, 0.50], [0.55, 0.30, 0.24]])
        palette = earth[rng.integers(0, len(earth), 5)] * rng.uniform(0.8, 1.2, (5, 1))
        thermal = base + temps[labels]
        rgb = palette[labels]
        for _ in range(int(rng.integers(2, 4))):  # roads: straight bands, warm asphalt
            angle = float(rng.uniform(0, math.pi))
            dist = np.cos(angle) * np.arange(cw)[None, :] + np.sin(angle) * np.arange(ch)[:, None]
            dist = np.abs(dist - float(rng.uniform(0, max(cw, ch))))
            road = (dist < float(rng.uniform(6, 14)) * res).astype(np.float32)
            thermal = thermal * (1 - road) + road * (base + float(rng.uniform(2, 6)))
            rgb = rgb * (1 - road[..., None]) + road[..., None] * np.array([0.35, 0.35, 0.36])
        texture = _field(rng, (ch, cw), 1.0)
        thermal = thermal + 0.5 * texture
        rgb = rgb * (1 + 0.08 * texture[..., None])
        thermal = cv2.GaussianBlur(thermal.astype(np.float32), (0, 0), 0.8)
    rgb = np.clip(rgb, 0, 1).astype(np.float32)
    if night:
        rgb = rgb * float(rng.uniform(0.05, 0.10))
        if scene == "ground":  # street lights
            lights = np.clip(_field(rng, (ch, cw), 1.5 * res) - 3.0, 0, None)
            rgb = rgb + 0.8 * lights[..., None] * np.array([1.0, 0.8, 0.5], np.float32)
    return Backdrop(np.ascontiguousarray(thermal, dtype=np.float32), rgb.astype(np.float32), (ox, oy))


def _view(
    img: np.ndarray, origin: tuple[float, float], shift: tuple[float, float], size: tuple[int, int]
) -> np.ndarray:
    """The frame-sized window of a canvas whose top-left sits at ``origin + shift`` (sub-pixel, bilinear)."""
    import cv2

    x, y = origin[0] + shift[0], origin[1] + shift[1]
    m = np.array([[1, 0, -x], [0, 1, -y]], np.float64)
    return cv2.warpAffine(img, m, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _gauss_window(box: tuple[float, float, float, float], sx: float, sy: float, size: tuple[int, int]):
    """Pixel ranges around a box centre covering 3 sigma, and the centre."""
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    x0, x1 = max(int(cx - 3 * sx - 1), 0), min(int(cx + 3 * sx + 2), size[0])
    y0, y1 = max(int(cy - 3 * sy - 1), 0), min(int(cy + 3 * sy + 2), size[1])
    return x0, x1, y0, y1, cx, cy


def add_signature(thermal: np.ndarray, track: Track, box: tuple[float, float, float, float]) -> None:
    """The target's thermal signature: a soft core the size of the object plus a warm halo wider than the box
    (Gaussian, soft edges; engine heat, exhaust, warmed surroundings), added in place."""
    h, w = thermal.shape
    bw, bh = box[2] - box[0], box[3] - box[1]
    parts = (
        (max(track.core * bw, 0.6), max(track.core * bh, 0.6), 1.0),
        (max(track.halo * bw, HALO_MIN_PX), max(track.halo * bh, HALO_MIN_PX), track.halo_share),
    )
    for sx, sy, share in parts:
        x0, x1, y0, y1, cx, cy = _gauss_window(box, sx, sy, (w, h))
        if x1 <= x0 or y1 <= y0:
            continue
        gx = np.exp(-0.5 * ((np.arange(x0, x1) + 0.5 - cx) / sx) ** 2)
        gy = np.exp(-0.5 * ((np.arange(y0, y1) + 0.5 - cy) / sy) ** 2)
        thermal[y0:y1, x0:x1] += np.float32(track.warmth * share) * np.outer(gy, gx).astype(np.float32)


def add_outline(rgb: np.ndarray, track: Track, box: tuple[float, float, float, float], night: bool) -> None:
    """The object in the visible frame: an anti-aliased rounded body in its own colour with a darker lower half
    (shading); at night only its lights."""
    h, w = rgb.shape[:2]
    x0, x1 = max(int(box[0]) - 1, 0), min(int(box[2]) + 2, w)
    y0, y1 = max(int(box[1]) - 1, 0), min(int(box[3]) + 2, h)
    if x1 <= x0 or y1 <= y0:
        return
    xs, ys = np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    rx, ry = max((box[2] - box[0]) / 2, 0.5), max((box[3] - box[1]) / 2, 0.5)
    dx, dy = np.abs(xs[None, :] - cx) / rx, np.abs(ys[:, None] - cy) / ry
    rounded = track.category in ("pedestrian", "cyclist", "drone")
    d = np.sqrt(dx**2 + dy**2) if rounded else np.maximum(dx, dy)
    scale = min(rx, ry)
    alpha = np.clip((1 - d) * scale + 0.5, 0, 1).astype(np.float32)[..., None]
    if night:
        colour = np.array([1.0, 0.95, 0.75], np.float32)
        alpha = alpha * np.clip(1.5 - 2.5 * d, 0, 1).astype(np.float32)[..., None]
    else:
        shade = np.where(ys[:, None] > cy, 0.75, 1.0).astype(np.float32)[..., None]
        colour = np.array(track.colour, np.float32) * shade
    patch = rgb[y0:y1, x0:x1]
    rgb[y0:y1, x0:x1] = patch * (1 - alpha) + colour * alpha


def _vignette(size: tuple[int, int]) -> np.ndarray:
    w, h = size
    xx = (np.arange(w, dtype=np.float32) - w / 2) / (w / 2)
    yy = (np.arange(h, dtype=np.float32) - h / 2) / (h / 2)
    return (xx[None, :] ** 2 + yy[:, None] ** 2) / 2  # 0 at the centre, 1 in the corners


def agc8(frame: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The camera's automatic gain control: this frame's 0.5th..99.8th percentile stretched to 0..255, with a
    little gain and level wander, rounded to 8 bits (targets hotter than the range saturate)."""
    sub = frame[::4, ::4]
    lo, hi = (float(v) for v in np.percentile(sub, [0.5, 99.8]))
    span = max(hi - lo, 1.0) * float(rng.uniform(1.0, 1.08))
    lo -= float(rng.uniform(0.0, 0.04)) * span
    out = (frame - np.float32(lo)) * np.float32(255.0 / span)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def render_frame(
    seq: Sequence, backdrop: Backdrop, t: int, size: tuple[int, int], columns: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(visible RGB uint8 HxWx3, thermal uint8 HxW) of frame ``t``."""
    import cv2

    w, h = size
    shift = (seq.pan[0] * t, seq.pan[1] * t)
    thermal = _view(backdrop.thermal, backdrop.origin, shift, size)
    # the visible frame is the same scene warped into the thermal frame: it is off by the registration offset
    vshift = (shift[0] - seq.offset[0] - seq.jitter[t, 0], shift[1] - seq.offset[1] - seq.jitter[t, 1])
    rgb = _view(backdrop.rgb, backdrop.origin, vshift, size)
    night = seq.spec.light == "night"
    for tr in seq.tracks:
        if tr.thermal:
            add_signature(thermal, tr, tr.box(t))
        if tr.visible:  # an object hidden in the visible frame is simply not drawn there
            add_outline(rgb, tr, seq.visible_box(tr, t), night)
    thermal = cv2.GaussianBlur(thermal, (0, 0), 0.7)
    vig = _vignette(size)
    thermal = thermal - np.float32(0.6) * vig + columns[None, :]
    thermal = thermal + rng.normal(0, NETD_C, (h, w)).astype(np.float32)
    ir8 = agc8(thermal, rng)
    exposure = float(rng.uniform(0.92, 1.08))
    rgb = rgb * exposure * (1 - np.float32(0.2) * vig)[..., None]
    noise = (0.025 if night else 0.01) * rng.standard_normal((h, w, 3)).astype(np.float32)
    rgb8 = np.clip(np.rint((rgb + noise) * 255), 0, 255).astype(np.uint8)
    return rgb8, ir8
