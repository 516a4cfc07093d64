"""The generator's cameras and scene geometry: the rig, inspection groups (sessions), the supersampled canvas, and
the projections between the canvas, the thermal frame and the distorted RGB frame.

Homographies go through ``harness.sensing.registration`` (``plane_homography``, ``apply_homography``,
``focal_length_px``): the generator and the registration that reads its output share one geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from typing import Sequence

import numpy as np

from adapters.datasets.m3t import M3T_FOCAL_35MM
from adapters.datasets.synthetic.profiles import Look, Profile
from harness.sensing.registration.homography import apply_homography, focal_length_px, plane_homography

#: The 35-mm frame diagonal, rounded, that the generator's cameras have always been built with (the exact value,
#: ``harness.sensing.registration.FULL_FRAME_DIAGONAL_MM``, would change every generated set).
GENERATOR_FRAME_DIAGONAL_MM = 43.27


def camera_matrix(size: tuple[int, int], equiv_focal_mm: float, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Pinhole K for a 35-mm-equivalent focal length: ``f = f_equiv * diagonal_px / 43.27`` (OpenCV centres)."""
    w, h = size
    f = focal_length_px(focal_35mm=equiv_focal_mm, image_size=size, frame_diagonal_mm=GENERATOR_FRAME_DIAGONAL_MM)
    return np.array([[f, 0.0, (w - 1) / 2 + offset[0]], [0.0, f, (h - 1) / 2 + offset[1]], [0.0, 0.0, 1.0]])


def rotation_matrix(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """R = Rz(roll) Ry(yaw) Rx(pitch), angles in degrees (camera axes: x right, y down, z forward)."""
    a, b, c = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def distort_points(pts: np.ndarray, k: np.ndarray, dist: Sequence[float]) -> np.ndarray:
    """Ideal (undistorted) pixels -> distorted pixels, radial model ``x_d = x (1 + k1 r^2 + k2 r^4)``."""
    k1, k2 = float(dist[0]), float(dist[1])
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    x = (pts[:, 0] - k[0, 2]) / k[0, 0]
    y = (pts[:, 1] - k[1, 2]) / k[1, 1]
    r2 = x * x + y * y
    s = 1 + k1 * r2 + k2 * r2 * r2
    return np.c_[x * s * k[0, 0] + k[0, 2], y * s * k[1, 1] + k[1, 2]]


def undistort_points_dense(pts: np.ndarray, k: np.ndarray, dist: Sequence[float], iterations: int = 30) -> np.ndarray:
    """Distorted pixels -> ideal pixels by fixed-point iteration of the radial model (used to render, not to align)."""
    k1, k2 = float(dist[0]), float(dist[1])
    pts = np.asarray(pts, dtype=np.float64)
    shape = pts.shape
    pts = pts.reshape(-1, 2)
    xd = (pts[:, 0] - k[0, 2]) / k[0, 0]
    yd = (pts[:, 1] - k[1, 2]) / k[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        s = 1 + k1 * r2 + k2 * r2 * r2
        x, y = xd / s, yd / s
    return np.c_[x * k[0, 0] + k[0, 2], y * k[1, 1] + k[1, 2]].reshape(shape)


@dataclass(frozen=True)
class Rig:
    """The M3T's two cameras as the generator models them."""

    k_rgb: np.ndarray
    dist_rgb: tuple[float, float, float, float, float]
    k_thermal: np.ndarray
    rgb_size: tuple[int, int]
    thermal_size: tuple[int, int]
    rotation: np.ndarray
    baseline_m: np.ndarray

    @staticmethod
    def for_profile(profile: Profile) -> "Rig":
        w, h = profile.rgb_size
        k_rgb = camera_matrix(profile.rgb_size, M3T_FOCAL_35MM[0], offset=(0.004 * w, -0.003 * h))
        k_th = camera_matrix(profile.thermal_size, M3T_FOCAL_35MM[1])
        return Rig(
            k_rgb,
            (-0.105, 0.045, 0.0, 0.0, 0.0),
            k_th,
            profile.rgb_size,
            profile.thermal_size,
            rotation_matrix(0.35, -0.25, 0.15),
            np.array([0.021, 0.034, 0.0]),
        )


@dataclass(frozen=True)
class Session:
    """One inspection group (a flight over one facade): its distance, facade normal and true homography."""

    name: str
    project: str
    start: datetime
    distance_m: float
    homography: np.ndarray  # undistorted RGB px -> thermal px (OpenCV centres)
    rotation: np.ndarray
    normal: np.ndarray


def make_session(rig: Rig, project: str, index: int, start: datetime, look: Look, rng: np.random.Generator) -> Session:
    distance = float(rng.uniform(*look.distance_m))
    jitter = rotation_matrix(*rng.normal(0.0, 0.06, size=3))  # gimbal / mount settling between flights
    rot = jitter @ rig.rotation
    tilt = np.deg2rad(rng.uniform(-6, 6, size=2))
    normal = np.array([math.sin(tilt[0]), math.sin(tilt[1]), 1.0])
    normal /= np.linalg.norm(normal)
    hmat = plane_homography(rig.k_rgb, rig.k_thermal, rot, rig.baseline_m, normal, distance)
    name = f"{project}-{index + 1:02d}"  # what grouping by capture time calls it
    return Session(name, project, start, distance, hmat, rot, normal)


@dataclass(frozen=True)
class Canvas:
    """The supersampled scene raster. ``k`` canvas pixels per thermal pixel; margins in whole thermal pixels.

    Edge coordinates ``u`` (thermal frame ``[0, W]``): canvas column ``j`` covers ``[j / k - mx, (j + 1) / k - mx]``.
    Thermal pixel-centre coordinates are ``x = u - 0.5``.
    """

    k: int
    mx: int
    my: int
    thermal_size: tuple[int, int]

    @property
    def width(self) -> int:
        return (self.thermal_size[0] + 2 * self.mx) * self.k

    @property
    def height(self) -> int:
        return (self.thermal_size[1] + 2 * self.my) * self.k

    def u(self, j: np.ndarray | float) -> np.ndarray:
        """Edge coordinate of canvas column centres."""
        return (np.asarray(j, dtype=np.float64) + 0.5) / self.k - self.mx

    def v(self, i: np.ndarray | float) -> np.ndarray:
        return (np.asarray(i, dtype=np.float64) + 0.5) / self.k - self.my

    def col(self, u: float) -> int:
        """Canvas column whose left edge is at edge coordinate ``u`` (``u`` on the canvas grid)."""
        return int(round((u + self.mx) * self.k))

    def row(self, v: float) -> int:
        return int(round((v + self.my) * self.k))

    def snap(self, value: float) -> float:
        return round(value * self.k) / self.k

    def thermal_slice(self) -> tuple[slice, slice]:
        w, h = self.thermal_size
        return slice(self.my * self.k, (self.my + h) * self.k), slice(self.mx * self.k, (self.mx + w) * self.k)

    def extent_box(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Edge-coordinate box of canvas pixels (index arrays)."""
        return np.array(
            [
                cols.min() / self.k - self.mx,
                rows.min() / self.k - self.my,
                (cols.max() + 1) / self.k - self.mx,
                (rows.max() + 1) / self.k - self.my,
            ]
        )


def canvas_for_session(rig: Rig, session: Session, k: int = 2) -> Canvas:
    """A canvas large enough for every RGB pixel of the session to fall inside it."""
    w, h = rig.rgb_size
    n = 64
    edge = np.concatenate(
        [
            np.c_[np.linspace(0, w - 1, n), np.zeros(n)],
            np.c_[np.linspace(0, w - 1, n), np.full(n, h - 1)],
            np.c_[np.zeros(n), np.linspace(0, h - 1, n)],
            np.c_[np.full(n, w - 1), np.linspace(0, h - 1, n)],
        ]
    )
    pts = apply_homography(session.homography, undistort_points_dense(edge, rig.k_rgb, rig.dist_rgb)) + 0.5
    tw, th = rig.thermal_size
    mx = int(math.ceil(max(-pts[:, 0].min(), pts[:, 0].max() - tw, 0))) + 3
    my = int(math.ceil(max(-pts[:, 1].min(), pts[:, 1].max() - th, 0))) + 3
    return Canvas(k, mx, my, rig.thermal_size)


def rgb_render_maps(rig: Rig, session: Session, canvas: Canvas, undist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every distorted RGB pixel, its canvas position (``cv2.remap`` maps)."""
    w, h = rig.rgb_size
    pts = apply_homography(session.homography, undist.reshape(-1, 2))
    cx = (pts[:, 0] + 0.5 + canvas.mx) * canvas.k - 0.5
    cy = (pts[:, 1] + 0.5 + canvas.my) * canvas.k - 0.5
    return cx.reshape(h, w).astype(np.float32), cy.reshape(h, w).astype(np.float32)


def project_box_to_rgb(box: np.ndarray, hinv: np.ndarray, rig: Rig, samples: int = 16) -> np.ndarray:
    """Envelope, in the distorted RGB frame (edge coordinates), of a thermal-frame box's outline."""
    x0, y0, x1, y1 = (float(b) for b in box)
    t = np.linspace(0.0, 1.0, samples)
    outline = (
        np.concatenate(
            [
                np.c_[x0 + (x1 - x0) * t, np.full(samples, y0)],
                np.c_[x0 + (x1 - x0) * t, np.full(samples, y1)],
                np.c_[np.full(samples, x0), y0 + (y1 - y0) * t],
                np.c_[np.full(samples, x1), y0 + (y1 - y0) * t],
            ]
        )
        - 0.5
    )
    rgb = distort_points(apply_homography(hinv, outline), rig.k_rgb, rig.dist_rgb) + 0.5
    return np.array([rgb[:, 0].min(), rgb[:, 1].min(), rgb[:, 0].max(), rgb[:, 1].max()])
