"""Homography maths: points through ``H``, similarity parameters, focal-length priors, plane-induced homographies.

A homography ``H`` maps an RGB pixel ``(x, y)`` to the thermal pixel ``(u, v)``::

    [u', v', w']^T = H [x, y, 1]^T,   (u, v) = (u' / w', v' / w')

in OpenCV's pixel-centre convention (pixel ``(i, j)`` has its centre at ``x = j, y = i``). Every part of the
project that moves points through a homography (registration, its error measures, the dataset adapters, the
synthetic generator) calls ``apply_homography`` here.
"""

from __future__ import annotations

import math

import numpy as np

from harness.errors import DataError

#: diagonal of a 35 mm frame (36 x 24 mm), for 35-mm-equivalent focal lengths
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def project_points(H: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """N x 2 points through ``H``: the dehomogenised points (float64 N x 2) and each one's homogeneous ``w``
    (``w <= 0``: the point lies behind the plane at infinity)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    hom = np.hstack([pts, np.ones((len(pts), 1))]) @ np.asarray(H, dtype=np.float64).reshape(3, 3).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return hom[:, :2] / hom[:, 2:3], hom[:, 2]


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(u, v) = (H [x, y, 1]^T)`` dehomogenised, for N x 2 points (float64 N x 2)."""
    return project_points(H, points)[0]


def image_center(size: tuple[int, int]) -> tuple[float, float]:
    """Centre of a ``(width, height)`` image in pixel coordinates (pixel centres at integers)."""
    return ((size[0] - 1) / 2.0, (size[1] - 1) / 2.0)


def reprojection_errors(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``|| H(src_i) - dst_i ||`` in destination pixels."""
    return np.linalg.norm(apply_homography(H, src) - np.asarray(dst, dtype=np.float64).reshape(-1, 2), axis=1)


def corner_error(H_est: np.ndarray, H_true: np.ndarray, thermal_size: tuple[int, int]) -> np.ndarray:
    """Distances (thermal px) between where the two homographies put the thermal frame's four corners.

    Each corner of the thermal frame is taken to RGB with ``H_true^-1`` and brought back with ``H_est``.
    """
    w, h = thermal_size
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
    rgb = apply_homography(np.linalg.inv(H_true), corners)
    return np.linalg.norm(apply_homography(H_est, rgb) - corners, axis=1)


def normalize(H: np.ndarray) -> np.ndarray:
    """``H / H[2, 2]`` (float64)."""
    H = np.asarray(H, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
        raise DataError(f"not a usable homography: {H.tolist()}")
    return H / H[2, 2]


def homography_from_similarity(
    tx: float,
    ty: float,
    theta_deg: float,
    scale: float,
    rgb_center: tuple[float, float] = (0.0, 0.0),
    thermal_center: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """``u = s R(theta) (x - c_rgb) + c_thermal + t`` as a 3x3 homography.

    ``theta_deg`` is counter-clockwise on screen (image y points down, so ``R = [[cos, sin], [-sin, cos]]``
    in pixel coordinates); ``scale`` is thermal pixels per RGB pixel; ``(tx, ty)`` thermal pixels. With the
    default zero centres, rotation and scale are about the origin.
    """
    if scale <= 0:
        raise DataError(f"similarity scale must be positive, got {scale}")
    th = math.radians(theta_deg)
    c, s_ = math.cos(th), math.sin(th)
    A = scale * np.array([[c, s_], [-s_, c]])
    crgb = np.asarray(rgb_center, dtype=np.float64)
    cth = np.asarray(thermal_center, dtype=np.float64)
    H = np.eye(3)
    H[:2, :2] = A
    H[:2, 2] = cth + np.array([tx, ty]) - A @ crgb
    return H


def similarity_from_homography(
    H: np.ndarray, rgb_center: tuple[float, float] = (0.0, 0.0), thermal_center: tuple[float, float] = (0.0, 0.0)
) -> dict[str, float]:
    """The closest similarity ``(tx, ty, theta_deg, scale)`` to ``H`` (from its linear part at the centre)."""
    H = normalize(H)
    A = H[:2, :2]
    scale = math.sqrt(abs(np.linalg.det(A)))
    theta = math.degrees(math.atan2(A[0, 1] - A[1, 0], A[0, 0] + A[1, 1]))
    moved = apply_homography(H, np.array([rgb_center]))[0]
    t = moved - np.asarray(thermal_center)
    return {"tx": float(t[0]), "ty": float(t[1]), "theta_deg": float(theta), "scale": float(scale)}


def focal_length_px(
    focal_mm: float | None = None,
    pixel_pitch_mm: float | None = None,
    focal_35mm: float | None = None,
    image_size: tuple[int, int] | None = None,
    frame_diagonal_mm: float = FULL_FRAME_DIAGONAL_MM,
) -> float:
    """Focal length in pixels: ``f_mm / pitch_mm``, or ``f_35 * diagonal_px / frame_diagonal_mm`` from the 35-mm
    equivalent (the 36 x 24 mm frame's diagonal, 43.27 mm)."""
    if focal_mm and pixel_pitch_mm:
        return float(focal_mm) / float(pixel_pitch_mm)
    if focal_35mm and image_size:
        return float(focal_35mm) * math.hypot(*image_size) / frame_diagonal_mm
    raise DataError("focal length in pixels needs (focal_mm and pixel_pitch_mm) or (focal_35mm and image_size)")


def homography_from_focal_lengths(
    f_rgb_px: float,
    f_thermal_px: float,
    rgb_size: tuple[int, int],
    thermal_size: tuple[int, int],
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """The optics prior: centres aligned (plus ``offset``), scale ``f_thermal / f_rgb``, no rotation."""
    return homography_from_similarity(
        offset[0], offset[1], 0.0, f_thermal_px / f_rgb_px, image_center(rgb_size), image_center(thermal_size)
    )


def focal_prior(
    rgb_size: tuple[int, int],
    thermal_size: tuple[int, int],
    focal_35mm: tuple[float, float],
    f_rgb_px: float | None = None,
) -> np.ndarray:
    """The optics prior from the two cameras' 35-mm-equivalent focal lengths ``(rgb, thermal)``; ``f_rgb_px``
    replaces the RGB one where a calibration gives the focal length in pixels."""
    f_rgb = f_rgb_px if f_rgb_px is not None else focal_length_px(focal_35mm=focal_35mm[0], image_size=rgb_size)
    return homography_from_focal_lengths(
        f_rgb, focal_length_px(focal_35mm=focal_35mm[1], image_size=thermal_size), rgb_size, thermal_size
    )


def change_camera(H: np.ndarray, k_from: np.ndarray, k_to: np.ndarray) -> np.ndarray:
    """``H`` on pixels of the pinhole camera ``k_from`` -> the same mapping on pixels of ``k_to`` (same rays): a
    pixel ``p`` of ``k_to`` is the ray ``k_to^-1 p``, i.e. the pixel ``k_from k_to^-1 p`` of ``k_from``."""
    h = H @ k_from @ np.linalg.inv(k_to)
    return h / h[2, 2]


def plane_homography(
    k_rgb: np.ndarray, k_thermal: np.ndarray, rot: np.ndarray, t: np.ndarray, normal: np.ndarray, distance: float
) -> np.ndarray:
    """Homography of the plane ``n^T X = d`` (RGB-camera frame) from RGB to thermal pixels.

    ``X_T = R X + t`` and ``n^T X / d = 1`` on the plane give ``X_T = (R + t n^T / d) X``, hence
    ``H = K_T (R + t n^T / d) K_W^-1``, normalised so that ``H[2, 2] = 1``.
    """
    hmat = k_thermal @ (rot + np.outer(t, normal) / distance) @ np.linalg.inv(k_rgb)
    return hmat / hmat[2, 2]
