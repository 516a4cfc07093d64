"""One capture: the painted scene through the thermal camera (physics, optics, sensor) and the wide camera (rig,
distortion, exposure), and the landmark pairs an annotator clicks on it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from adapters.datasets.synthetic.geometry import Canvas, Rig, Session
from adapters.datasets.synthetic.painting import (
    PAINTERS,
    Layers,
    SceneObject,
    fbm,
    luminance,
    paint_downpipe,
    paint_wall,
    paint_window,
    place_objects,
    smooth,
    window_grid,
)
from adapters.datasets.synthetic.profiles import Look
from harness.sensing.registration.homography import apply_homography

_R2: dict[tuple[int, int], np.ndarray] = {}


def _radius2(shape: tuple[int, int]) -> np.ndarray:
    """Squared distance from the image centre, 0 at the centre and 1 in the corners (cached per size)."""
    if shape not in _R2:
        h, w = shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        _R2[shape] = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return _R2[shape]


@dataclass
class Frame:
    """One rendered capture: what the cameras record and what the ground truth says."""

    rgb: np.ndarray  # uint8 HxWx3 (R, G, B), distorted wide-camera frame
    temperature: np.ndarray  # float32, measured by the thermal camera (drift, vignetting, noise)
    true_temperature: np.ndarray  # float32, the scene at the sensor grid (no sensor effects)
    objects: list[SceneObject]
    drift_c: float
    vignette_c: float


def render_frame(
    rig: Rig,
    session: Session,
    canvas: Canvas,
    maps: tuple[np.ndarray, np.ndarray] | None,
    look: Look,
    rng: np.random.Generator,
    drift_c: float,
) -> Frame:
    """One capture. ``maps=None`` renders the thermal side only (the RGB is then an empty array): the same scene,
    the same random draws for everything the thermal camera sees."""
    import cv2

    ppm = rig.k_thermal[0, 0] / session.distance_m
    layers = Layers(
        canvas,
        np.zeros((canvas.height, canvas.width, 3), np.float32),
        np.zeros((canvas.height, canvas.width), np.float32),
        np.full((canvas.height, canvas.width), np.nan, np.float32),
        ppm,
    )
    paint_wall(layers, look, rng)
    windows = window_grid(layers, look, rng)
    if rng.random() < 0.3:
        paint_downpipe(layers, canvas.snap(rng.uniform(-canvas.mx, canvas.thermal_size[0] + canvas.mx)), 0.1 * ppm, rng)
    for w in windows:
        paint_window(layers, w, look, rng)
    objects = place_objects(layers, look, windows, rng)
    kept: list[SceneObject] = []
    for obj in objects:
        extent = PAINTERS[obj.category](layers, obj, look, rng)
        if extent is None and obj.category not in ("ac_unit", "vent"):
            continue
        if extent is not None:
            obj.box = extent
        kept.append(obj)
    objects = windows + kept

    # --- thermal: wall physics from absorptivity, overlays, glass, over the footprint; block-average to the sensor
    ys, xs = canvas.thermal_slice()
    sigma = max(0.5, 0.08 * ppm * canvas.k)  # lateral conduction, 8 cm
    pad = int(3 * sigma) + 2
    region = (
        slice(max(ys.start - pad, 0), min(ys.stop + pad, canvas.height)),
        slice(max(xs.start - pad, 0), min(xs.stop + pad, canvas.width)),
    )
    absorb = smooth(1 - 0.7 * luminance(layers.albedo[region]), sigma)
    a_wall = 1 - 0.7 * float(luminance(np.array(look.wall_rgb)))
    rows = canvas.v(np.arange(region[0].start, region[0].stop))[:, None].astype(np.float32)
    temp = (
        look.ambient_c
        + look.sun_load_c * (1 + 0.4 * (absorb - a_wall) / a_wall)
        - 0.08 * (rows / ppm)
        + 0.25 * fbm(absorb.shape, 1.2 * ppm * canvas.k, rng, octaves=2)
        + layers.dtemp[region]
    )
    if look.slab_bridge_c > 0 and windows:  # floor slabs between storeys
        slab_v = np.array(sorted({round(w.attrs["storey_top"], 3) for w in windows}), np.float32)
        d = np.min(np.abs(rows - slab_v[None, :]), axis=1, keepdims=True)
        temp += look.slab_bridge_c * np.exp(-0.5 * (d / (0.12 * ppm)) ** 2)
    glass = layers.glass[region]
    temp = np.where(np.isnan(glass), temp, glass).astype(np.float32)
    tw, th = canvas.thermal_size
    inner = (
        slice(ys.start - region[0].start, ys.stop - region[0].start),
        slice(xs.start - region[1].start, xs.stop - region[1].start),
    )
    true_t = cv2.resize(temp[inner], (tw, th), interpolation=cv2.INTER_AREA)
    meas = cv2.GaussianBlur(true_t, (0, 0), 0.55)
    vig = look.vignette_c * rng.uniform(0.8, 1.2)
    meas = (
        meas
        + drift_c
        + vig * _radius2((th, tw))
        + rng.normal(0, 0.03, size=(1, tw)).astype(np.float32)
        + 0.05 * rng.standard_normal((th, tw), dtype=np.float32)
    )

    if maps is None:
        return Frame(
            np.zeros((0, 0, 3), np.uint8),
            meas.astype(np.float32),
            true_t.astype(np.float32),
            objects,
            float(drift_c),
            float(vig),
        )
    # --- RGB: sample the canvas through the rig geometry and lens distortion, then the camera
    img = cv2.remap(layers.albedo, maps[0], maps[1], interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    rh, rw = img.shape[:2]
    gain = np.float32(rng.uniform(0.88, 1.1)) * (1 - 0.22 * _radius2((rh, rw)))
    balance = np.array([rng.uniform(0.95, 1.05), 1.0, rng.uniform(0.93, 1.06)], np.float32)
    img *= gain[..., None]
    img *= balance
    img += 0.012 * rng.standard_normal(img.shape, dtype=np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 0.5)
    img *= 255.0
    rgb = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return Frame(rgb, meas.astype(np.float32), true_t.astype(np.float32), objects, float(drift_c), float(vig))


def pick_landmarks(
    frame: Frame, session: Session, rig: Rig, rng: np.random.Generator, limit: int, clicks: str = "human"
) -> list[dict[str, Any]]:
    """Corners of windows, AC units and vents (sharp in both images) inside the thermal frame, spread out by
    farthest-point selection as a careful annotator would, clicked in both images with a little noise."""
    tw, th = rig.thermal_size
    pts = []
    for o in frame.objects:
        if o.category not in ("window", "ac_unit", "vent") or o.attrs.get("round"):
            continue
        for x, y in ((o.box[0], o.box[1]), (o.box[2], o.box[1]), (o.box[0], o.box[3]), (o.box[2], o.box[3])):
            if 4 <= x <= tw - 4 and 4 <= y <= th - 4:
                pts.append((x - 0.5, y - 0.5))
    while len(pts) < 4:  # a plain wall: distinctive texture points instead
        pts.append((rng.uniform(8, tw - 8), rng.uniform(8, th - 8)))
    cand = np.array(pts, np.float64)
    chosen = [int(np.argmin(cand[:, 0] + cand[:, 1]))]
    dist = np.linalg.norm(cand - cand[chosen[0]], axis=1)
    while len(chosen) < min(limit, len(cand)):
        nxt = int(np.argmax(dist))
        if dist[nxt] <= 0:
            break
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(cand - cand[nxt], axis=1))
    thermal = cand[chosen]
    rgb = apply_homography(np.linalg.inv(session.homography), thermal)  # undistorted wide image (camera K)
    return [
        {"rgb": [round(float(a), 2), round(float(b), 2)], "thermal": [round(float(c), 2), round(float(d), 2)]}
        for (a, b), (c, d) in zip(*click_landmarks(rgb, thermal, rig, rng, clicks))
    ]


#: Landmark clicking, a human-factors model (see docs/datasets.md): in the thermal image a corner is a soft
#: transition about this many pixels wide (optics spot ~2 px at F1.0 and 12 um pitch, the pixel itself, the warm
#: frame's halo, the palette's rendering), and the click lands anywhere across it.
THERMAL_CORNER_PX = 8.0
#: Hand jitter of a click on the zoomed image, px (1 sigma per axis); clicks snap to whole pixels.
CLICK_JITTER_PX = 1.0
#: A corner in the wide camera's native 4000x3000 frame is sharp: 1.5 native px (1 sigma per axis).
RGB_CLICK_NATIVE_PX = 1.5
#: Share of clicks that take the neighbouring edge of the frame (glass corner for outer corner): 2-5 px off.
MISPICK_RATE = 0.1


def click_landmarks(
    rgb: np.ndarray, thermal: np.ndarray, rig: Rig, rng: np.random.Generator, clicks: str = "human"
) -> tuple[np.ndarray, np.ndarray]:
    """Where a person clicks true corresponding points (Nx2 each): RGB nearly exact, thermal a few px off.

    ``clicks="precise"``: sub-pixel clicks (0.8 RGB px, 0.35 thermal px), for the test profile.
    """
    if clicks == "precise":
        return rgb + rng.normal(0, 0.8, rgb.shape), thermal + rng.normal(0, 0.35, thermal.shape)
    if clicks != "human":
        raise ValueError(f"unknown click model {clicks!r}")
    n = len(thermal)
    t_err = rng.uniform(-THERMAL_CORNER_PX / 2, THERMAL_CORNER_PX / 2, (n, 2)) + rng.normal(0, CLICK_JITTER_PX, (n, 2))
    mis = rng.random(n) < MISPICK_RATE
    t_err[mis] += rng.uniform(2.0, 5.0, (int(mis.sum()), 1)) * rng.choice([-1.0, 1.0], (int(mis.sum()), 2))
    thermal_click = np.round(thermal + t_err)
    rgb_click = rgb + rng.normal(0, RGB_CLICK_NATIVE_PX * rig.rgb_size[0] / 4000, rgb.shape)
    return rgb_click, thermal_click
