"""RGB -> thermal registration: one homography per inspection group.

A homography ``H`` maps an RGB pixel ``(x, y)`` to the thermal pixel ``(u, v)``::

    [u', v', w']^T = H [x, y, 1]^T,   (u, v) = (u' / w', v' / w')

It is obtained in one of three ways:

* **landmarks**: at least 4 pairs of clicked points, by least squares (``cv2.findHomography``, DLT +
  Levenberg-Marquardt on the reprojection error) or RANSAC against outliers;
* **similarity parameters** (the seed's interactive adjustment): translation ``(tx, ty)``, rotation ``theta`` and
  scale ``s`` about the image centres, ``u = s R(theta) (x - c_rgb) + c_thermal + t``;
* **automatically** (``estimate_homography_auto``), without learned weights: enhanced correlation coefficient
  (ECC, Evangelidis & Psarakis 2008) maximisation on gradient-magnitude images, coarse to fine, initialised from
  the two cameras' focal lengths or a given H, with a quality check that rejects poorly aligned pairs.

Groups come from capture time (``group_by_capture_time``) or are given. ``save_homographies`` writes a YAML
file a person can read and edit.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import DataError

log = logging.getLogger(__name__)

#: diagonal of a 35 mm frame (36 x 24 mm), for 35-mm-equivalent focal lengths
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


# ---------------------------------------------------------------------------------------------- basics
def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(u, v) = (H [x, y, 1]^T)`` dehomogenised, for N x 2 points (float64 N x 2)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    hom = np.hstack([pts, np.ones((len(pts), 1))]) @ np.asarray(H, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return hom[:, :2] / hom[:, 2:3]


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


# ---------------------------------------------------------------------------------------------- landmarks
def homography_from_landmarks(src: np.ndarray, dst: np.ndarray, method: str = "lsq",
                              ransac_threshold: float = 2.0, return_inliers: bool = False
                              ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Homography taking ``src`` (RGB, N x 2) onto ``dst`` (thermal, N x 2), N >= 4.

    ``method="lsq"``: every pair, least squares (normalised DLT refined by Levenberg-Marquardt on the
    reprojection error). ``"ransac"``: RANSAC with ``ransac_threshold`` pixels, then least squares on the
    inliers. With ``return_inliers`` also returns the boolean inlier mask.
    """
    import cv2

    s = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    if len(s) != len(d):
        raise DataError(f"{len(s)} RGB landmarks but {len(d)} thermal landmarks")
    if len(s) < 4:
        raise DataError(f"a homography needs at least 4 landmark pairs, got {len(s)}")
    for name, pts in (("RGB", s), ("thermal", d)):
        centred = pts - pts.mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        if sv[1] <= 1e-9 * max(sv[0], 1.0):
            raise DataError(f"the {name} landmarks are collinear or duplicated; a homography needs 4 points in general "
                            "position (no three on a line)")
    if method == "lsq":
        H, mask = cv2.findHomography(s, d, 0)
    elif method == "ransac":
        H, mask = cv2.findHomography(s, d, cv2.RANSAC, float(ransac_threshold), maxIters=5000, confidence=0.999)
        if H is not None:
            inl = mask.ravel().astype(bool)
            if inl.sum() >= 4:
                H, _ = cv2.findHomography(s[inl], d[inl], 0)
    else:
        raise DataError(f"unknown landmark method {method!r}; use 'lsq' or 'ransac'")
    if H is None or not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12 or abs(H[2, 2]) < 1e-12:
        raise DataError(f"no homography fits the {len(s)} landmark pairs (are they collinear or duplicated?)")
    H = normalize(H)
    if not return_inliers:
        return H
    if method == "ransac":
        inliers = reprojection_errors(H, s, d) <= ransac_threshold
    else:
        inliers = np.ones(len(s), dtype=bool)
    return H, inliers


# ---------------------------------------------------------------------------------------------- similarity
def homography_from_similarity(tx: float, ty: float, theta_deg: float, scale: float,
                               rgb_center: tuple[float, float] = (0.0, 0.0),
                               thermal_center: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
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


def similarity_from_homography(H: np.ndarray, rgb_center: tuple[float, float] = (0.0, 0.0),
                               thermal_center: tuple[float, float] = (0.0, 0.0)) -> dict[str, float]:
    """The closest similarity ``(tx, ty, theta_deg, scale)`` to ``H`` (from its linear part at the centre)."""
    H = normalize(H)
    A = H[:2, :2]
    scale = math.sqrt(abs(np.linalg.det(A)))
    theta = math.degrees(math.atan2(A[0, 1] - A[1, 0], A[0, 0] + A[1, 1]))
    moved = apply_homography(H, np.array([rgb_center]))[0]
    t = moved - np.asarray(thermal_center)
    return {"tx": float(t[0]), "ty": float(t[1]), "theta_deg": float(theta), "scale": float(scale)}


def focal_length_px(focal_mm: float | None = None, pixel_pitch_mm: float | None = None,
                    focal_35mm: float | None = None, image_size: tuple[int, int] | None = None) -> float:
    """Focal length in pixels: ``f_mm / pitch_mm``, or ``f_35 * diagonal_px / 43.27`` from the 35-mm equivalent."""
    if focal_mm and pixel_pitch_mm:
        return float(focal_mm) / float(pixel_pitch_mm)
    if focal_35mm and image_size:
        return float(focal_35mm) * math.hypot(*image_size) / FULL_FRAME_DIAGONAL_MM
    raise DataError("focal length in pixels needs (focal_mm and pixel_pitch_mm) or (focal_35mm and image_size)")


def homography_from_focal_lengths(f_rgb_px: float, f_thermal_px: float, rgb_size: tuple[int, int],
                                  thermal_size: tuple[int, int], offset: tuple[float, float] = (0.0, 0.0)
                                  ) -> np.ndarray:
    """The optics prior: centres aligned (plus ``offset``), scale ``f_thermal / f_rgb``, no rotation."""
    return homography_from_similarity(offset[0], offset[1], 0.0, f_thermal_px / f_rgb_px,
                                      image_center(rgb_size), image_center(thermal_size))


# ---------------------------------------------------------------------------------------------- automatic
@dataclass
class AutoRegistration:
    """Result of ``estimate_homography_auto``: ``H`` (RGB -> thermal) and its quality check."""

    H: np.ndarray
    ok: bool
    correlation: float  # ECC correlation of the structure images at the finest level after alignment
    initial_correlation: float  # the same before refinement (at the initial H)
    corner_shift_px: float  # largest move of a thermal-frame corner relative to the initial H
    reason: str = ""
    levels: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"H": self.H.tolist(), "ok": self.ok, "correlation": self.correlation,
                "initial_correlation": self.initial_correlation, "corner_shift_px": self.corner_shift_px,
                "reason": self.reason}


def structure_image(img: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    """Modality-independent structure: the saturated gradient magnitude ``g / (g + P90(g))`` (float32 0..1).

    ``g`` is the Sobel gradient magnitude of the image smoothed by ``sigma``. Works for RGB (converted to grey),
    8-bit previews and temperature maps alike: edges of the same objects coincide across modalities even where
    intensities do not, and the saturation keeps a strong edge in one modality from outweighing the others
    (edge strength depends on colour contrast in RGB and on temperature contrast in thermal). Missing temperatures
    (NaN or inf) carry no structure: they and the pixels whose filter window reaches them get 0.
    """
    import cv2

    a = np.asarray(img)
    valid = None
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        valid = np.isfinite(a if a.ndim == 2 else a.sum(axis=2))
        if not valid.any():
            return np.zeros(valid.shape, np.float32)
        fill = np.median(a[valid])
        a = np.where(valid if a.ndim == 2 else valid[:, :, None], a, fill).astype(np.float32)
    if a.ndim == 3:
        a = cv2.cvtColor(a if a.dtype == np.uint8 else a.astype(np.float32), cv2.COLOR_RGB2GRAY)
    a = a.astype(np.float32)
    if sigma > 0:
        a = cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT_101)
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT_101)
    mag = cv2.magnitude(gx, gy)
    if valid is not None:  # the Gaussian (4 sigma) and Sobel (1 px) windows must see measured pixels only
        k = 2 * (int(np.ceil(4 * sigma)) + 1) + 1 if sigma > 0 else 3
        mag[cv2.erode(valid.astype(np.uint8), np.ones((k, k), np.uint8)) == 0] = 0
    c = float(np.percentile(mag, 90))
    return mag / (mag + c) if c > 0 else mag


def _ecc(template: np.ndarray, image: np.ndarray, warp: np.ndarray, motion: str, iterations: int, eps: float,
         mask: np.ndarray | None) -> tuple[float, np.ndarray]:
    """One ``cv2.findTransformECC`` run; ``warp`` and the result are 3x3 (thermal pixel -> image pixel)."""
    import cv2

    mt = {"translation": cv2.MOTION_TRANSLATION, "euclidean": cv2.MOTION_EUCLIDEAN, "affine": cv2.MOTION_AFFINE,
          "homography": cv2.MOTION_HOMOGRAPHY}[motion]
    w = warp.astype(np.float32)
    w = w if motion == "homography" else w[:2].copy()
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, eps)
    rho, w = cv2.findTransformECC(template, image, w, mt, crit, mask, 1)
    out = np.eye(3)
    out[:w.shape[0]] = w
    return float(rho), out


def ecc_correlation(template: np.ndarray, image: np.ndarray, mask: np.ndarray | None = None) -> float:
    """ECC's criterion at the identity warp: correlation of the zero-mean, unit-norm images (over ``mask``)."""
    import cv2

    m = None if mask is None else mask.astype(np.uint8)
    return float(cv2.computeECC(template.astype(np.float32), image.astype(np.float32), m))


def _similarity_about(scale: float, theta_deg: float, center: tuple[float, float]) -> np.ndarray:
    return homography_from_similarity(0.0, 0.0, theta_deg, scale, center, center)


def _warp_inverse(img: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``out(x) = img(W x)`` (the convention of ECC's warp), linear, zero outside."""
    import cv2

    h, w = img.shape[:2]
    return cv2.warpPerspective(img, W, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def _coarse_search(template: np.ndarray, image: np.ndarray, mask: np.ndarray, scales: np.ndarray,
                   thetas: np.ndarray) -> tuple[float, np.ndarray]:
    """Best warp over a grid of scales and rotations (about the centre), each with the translation that phase
    correlation finds, scored by ECC's criterion."""
    import cv2

    h, w = template.shape
    center = ((w - 1) / 2.0, (h - 1) / 2.0)
    window = cv2.createHanningWindow((w, h), cv2.CV_64F)
    t64 = template.astype(np.float64)
    best_rho, best_W = -2.0, np.eye(3)
    for s in scales:
        for th in thetas:
            W = _similarity_about(float(s), float(th), center)
            (dx, dy), _ = cv2.phaseCorrelate(t64, _warp_inverse(image, W).astype(np.float64), window)
            W = W @ np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
            rho = ecc_correlation(template, _warp_inverse(image, W), mask)
            if rho > best_rho:
                best_rho, best_W = rho, W
    return best_rho, best_W


def estimate_homography_auto(rgb: np.ndarray, thermal: np.ndarray, init: np.ndarray | None = None,
                             levels: int | None = None, motion: str = "homography", iterations: int = 100,
                             search_scale: float = 0.06, search_rotation_deg: float = 4.0,
                             min_correlation: float = 0.5, max_corner_shift: float | None = None,
                             structure_sigma: float = 1.0) -> AutoRegistration:
    """RGB -> thermal homography by ECC on structure images, coarse to fine, with a quality check.

    ``rgb``: uint8 HxWx3 (any size); ``thermal``: temperature map (float) or 8-bit preview, in the thermal frame.
    ``init``: the starting H (default: centres aligned, the scale that fits the RGB width into the thermal
    width; pass ``homography_from_focal_lengths(...)`` for the optics prior).

    1. RGB is warped into the thermal frame with ``init`` (anti-aliased), so both share the thermal pixel grid,
       and both become ``structure_image``s; ECC looks for the residual warp ``W`` (thermal pixel -> pre-warped
       pixel) with ``H = W^-1 H_init``.
    2. On the coarsest pyramid level (about 80-160 px wide) a grid search over scale (``1 +- search_scale``) and
       rotation (``+- search_rotation_deg``), each with the translation from phase correlation, picks the start.
    3. ECC refines level by level: affine on the coarse levels, ``motion`` on the finest; a level where ECC
       does not converge keeps the previous estimate.

    Quality check (``ok``): the ECC correlation of the structure images at full resolution is at least
    ``min_correlation``, and no thermal corner moved more than ``max_corner_shift`` pixels from ``init``
    (default: 10 % of the thermal diagonal). A failed pair comes back with ``ok=False``, a ``reason`` and
    ``H = init``.
    """
    import cv2

    from harness.sensing.warp import warp_to_thermal

    th = np.asarray(thermal)
    if th.ndim != 2:
        th = cv2.cvtColor(th, cv2.COLOR_RGB2GRAY)
    h, w = th.shape
    rgb_arr = np.asarray(rgb)
    if init is None:
        init = homography_from_similarity(0, 0, 0, w / rgb_arr.shape[1],
                                          image_center((rgb_arr.shape[1], rgb_arr.shape[0])), image_center((w, h)))
    H0 = normalize(init)
    if max_corner_shift is None:
        max_corner_shift = 0.1 * math.hypot(w, h)
    warped, valid = warp_to_thermal(rgb_arr, H0, (h, w), fill="replicate")
    tmpl = structure_image(th, structure_sigma)
    img = structure_image(warped, structure_sigma)
    # only where the pre-warped RGB is real (eroded: the replicated border carries no structure)
    mask = cv2.erode(valid.astype(np.uint8), np.ones((9, 9), np.uint8))
    if mask.sum() < 0.1 * h * w:
        return AutoRegistration(H0, False, float("nan"), float("nan"), 0.0,
                                reason="the initial homography puts less than 10% of the thermal frame on RGB pixels")
    init_rho = ecc_correlation(tmpl, img, mask)
    if levels is None:
        levels = 1
        while min(h, w) / 2 ** levels >= 64 and w / 2 ** levels >= 80:
            levels += 1
    pyr_t, pyr_i, pyr_m = [tmpl], [img], [mask]
    for _ in range(1, levels):
        pyr_t.append(cv2.pyrDown(pyr_t[-1]))
        pyr_i.append(cv2.pyrDown(pyr_i[-1]))
        pyr_m.append((cv2.resize(pyr_m[-1], (pyr_t[-1].shape[1], pyr_t[-1].shape[0]),
                                 interpolation=cv2.INTER_NEAREST) > 0).astype(np.uint8))
    top = len(pyr_t) - 1
    report: list[dict[str, Any]] = []
    n_scales = max(1, int(round(2 * search_scale / 0.01)) + 1)
    n_thetas = max(1, int(round(2 * search_rotation_deg / 1.0)) + 1)
    rho, Wc = _coarse_search(pyr_t[top], pyr_i[top], pyr_m[top],
                             np.linspace(1 - search_scale, 1 + search_scale, n_scales),
                             np.linspace(-search_rotation_deg, search_rotation_deg, n_thetas))
    S = np.diag([0.5 ** top, 0.5 ** top, 1.0])
    W = np.linalg.inv(S) @ Wc @ S
    report.append({"level": top, "step": "search", "correlation": rho})
    converged = 0
    for lvl in range(top, -1, -1):
        S = np.diag([0.5 ** lvl, 0.5 ** lvl, 1.0])
        mot = motion if lvl == 0 else ("affine" if motion == "homography" else motion)
        try:
            rho, W_l = _ecc(pyr_t[lvl], pyr_i[lvl], S @ W @ np.linalg.inv(S), mot, iterations, 1e-6, pyr_m[lvl])
        except cv2.error:
            report.append({"level": lvl, "step": mot, "converged": False})
            continue
        W = np.linalg.inv(S) @ W_l @ S
        converged += 1
        report.append({"level": lvl, "step": mot, "correlation": rho, "converged": True})
    final_rho = ecc_correlation(tmpl, _warp_inverse(img, W), mask)
    H = normalize(np.linalg.inv(W) @ H0)
    shift = float(corner_error(H, H0, (w, h)).max())
    reasons = []
    if not converged:
        reasons.append("ECC did not converge at any level")
    if not np.isfinite(final_rho) or final_rho < min_correlation:
        reasons.append(f"structure correlation {final_rho:.3f} below {min_correlation}")
    if shift > max_corner_shift:
        reasons.append(f"a corner moved {shift:.1f} px from the initial homography (limit {max_corner_shift:.1f})")
    ok = not reasons
    return AutoRegistration(H if ok else H0, ok, float(final_rho), float(init_rho), shift, reason="; ".join(reasons),
                            levels=report)


def read_image_rgb(path: str | Path) -> np.ndarray:
    """An RGB image file as uint8 HxWx3 (R, G, B); unreadable files are a ``DataError`` naming them."""
    import cv2

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: file not found")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: not a readable image")
    return img[:, :, ::-1].copy()


def read_thermal_any(path: str | Path) -> np.ndarray:
    """A thermal file for registration: temperature (R-JPEG or decoded file) when radiometric, else 8-bit grey."""
    import cv2

    from harness.sensing.radiometry import read_thermal

    path = Path(path)
    try:
        return read_thermal(path)[0]
    except DataError:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise
        return img


def optics_prior(rgb_path: str | Path, thermal_path: str | Path, rgb_size: tuple[int, int],
                 thermal_size: tuple[int, int]) -> np.ndarray | None:
    """Focal-length prior from the two files' EXIF 35-mm-equivalent focal lengths (None when either lacks it)."""
    from harness.sensing import jpeg

    f = []
    for path, size in ((rgb_path, rgb_size), (thermal_path, thermal_size)):
        try:
            exif = jpeg.read_exif(path) if Path(path).suffix.lower() in (".jpg", ".jpeg") else {}
        except DataError:
            exif = {}
        f35 = exif.get("FocalLengthIn35mmFilm")
        if not f35:
            return None
        f.append(focal_length_px(focal_35mm=float(f35), image_size=size))
    return homography_from_focal_lengths(f[0], f[1], rgb_size, thermal_size)


def register_files(rgb_path: str | Path, thermal_path: str | Path, init: "HomographyEntry | np.ndarray | None" = None,
                   **kwargs: Any) -> tuple[AutoRegistration, tuple[int, int], tuple[int, int]]:
    """``estimate_homography_auto`` on two files; the start is ``init``, else the EXIF optics prior, else the
    default. Returns the result and the two image sizes ``(w, h)``."""
    rgb = read_image_rgb(rgb_path)
    th = read_thermal_any(thermal_path)
    rgb_size, th_size = (rgb.shape[1], rgb.shape[0]), (th.shape[1], th.shape[0])
    H0 = init.H if isinstance(init, HomographyEntry) else init
    if H0 is None:
        H0 = optics_prior(rgb_path, thermal_path, rgb_size, th_size)
    return estimate_homography_auto(rgb, th, init=H0, **kwargs), rgb_size, th_size


def support_boxes(entries: Mapping[str, "HomographyEntry"]) -> dict[str, tuple[int, int, int, int]]:
    """Common-support box of every entry that records both image sizes (thermal frame, x1/y1 exclusive)."""
    from harness.sensing.warp import common_support_box, support_mask

    out = {}
    for group, e in entries.items():
        if e.rgb_size and e.thermal_size:
            mask = support_mask(e.H, e.rgb_size, (e.thermal_size[1], e.thermal_size[0]))
            if mask.any():
                out[group] = common_support_box(mask)
    return out


# ---------------------------------------------------------------------------------------------- groups
def capture_time(path: str | Path) -> datetime | None:
    """EXIF ``DateTimeOriginal`` (+ sub-seconds) of a JPEG, or None when it has none."""
    from harness.sensing import jpeg

    exif = jpeg.read_exif(path)
    return jpeg.parse_exif_datetime(exif.get("DateTimeOriginal") or exif.get("DateTime"),
                                    exif.get("SubSecTimeOriginal"))


def group_by_capture_time(times: Mapping[str, datetime | str | None], gap_s: float = 300.0,
                          prefix: str = "G") -> dict[str, str]:
    """Split captures into inspection groups wherever consecutive capture times are more than ``gap_s`` apart.

    ``times``: ``{capture key: datetime or EXIF 'YYYY:MM:DD HH:MM:SS'}``. Returns ``{key: group}`` with groups
    named ``<prefix>01``, ``<prefix>02``, ... in time order. A capture without a time is a ``DataError`` naming it
    (give its group explicitly instead).
    """
    from harness.sensing.jpeg import parse_exif_datetime

    parsed: list[tuple[datetime, str]] = []
    missing = []
    for key, value in times.items():
        dt = parse_exif_datetime(value) if value is not None else None
        if dt is None:
            missing.append(str(key))
        else:
            parsed.append((dt, str(key)))
    if missing:
        raise DataError(f"no capture time for {len(missing)} capture(s) ({', '.join(missing[:5])}"
                        f"{', ...' if len(missing) > 5 else ''}); give their groups explicitly")
    parsed.sort()
    out: dict[str, str] = {}
    group = 0
    prev: datetime | None = None
    for dt, key in parsed:
        if prev is None or (dt - prev).total_seconds() > gap_s:
            group += 1
        out[key] = f"{prefix}{group:02d}"
        prev = dt
    return out


# ---------------------------------------------------------------------------------------------- files
@dataclass
class HomographyEntry:
    """One group's registration as stored in the homographies file."""

    H: np.ndarray
    method: str = "manual"  # landmarks | similarity | auto | focal | manual
    similarity: dict[str, float] | None = None
    rgb_size: tuple[int, int] | None = None
    thermal_size: tuple[int, int] | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"method": self.method}
        if self.method == "similarity" and self.similarity is not None:
            out["similarity"] = {k: float(v) for k, v in self.similarity.items()}
        else:
            out["H"] = [[float(f"{v:.10g}") for v in row] for row in normalize(self.H)]
        if self.rgb_size:
            out["rgb_size"] = [int(v) for v in self.rgb_size]
        if self.thermal_size:
            out["thermal_size"] = [int(v) for v in self.thermal_size]
        if self.quality:
            out["quality"] = self.quality
        if self.note:
            out["note"] = self.note
        return out


def entry_from_similarity(params: Mapping[str, float], rgb_size: tuple[int, int] | None,
                          thermal_size: tuple[int, int] | None, note: str = "") -> HomographyEntry:
    """An entry defined by similarity parameters about the image centres (origin when a size is unknown)."""
    missing = {"tx", "ty", "theta_deg", "scale"} - set(params)
    if missing:
        raise DataError(f"similarity parameters lack {sorted(missing)}; give tx, ty, theta_deg, scale")
    H = homography_from_similarity(float(params["tx"]), float(params["ty"]), float(params["theta_deg"]),
                                   float(params["scale"]),
                                   image_center(rgb_size) if rgb_size else (0.0, 0.0),
                                   image_center(thermal_size) if thermal_size else (0.0, 0.0))
    return HomographyEntry(H, "similarity", {k: float(params[k]) for k in ("tx", "ty", "theta_deg", "scale")},
                           rgb_size, thermal_size, note=note)


HOMOGRAPHY_FILE_HEADER = """\
# RGB -> thermal homographies, one per inspection group: thermal pixel ~ H @ [x_rgb, y_rgb, 1].
# Edit freely. An entry is either
#   H: 3x3 matrix (row-major), or
#   similarity: {tx, ty, theta_deg, scale}   # u = scale * R(theta) (x - c_rgb) + c_thermal + (tx, ty)
# where c_rgb / c_thermal are the image centres ((w-1)/2, (h-1)/2) from rgb_size / thermal_size [w, h].
# When both are present, H wins.
"""


def save_homographies(path: str | Path, homographies: Mapping[str, np.ndarray | HomographyEntry],
                      meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``{group: H or HomographyEntry}`` as a commented, human-editable YAML file."""
    from harness.config import dump_yaml
    from harness.io import atomic_write_text

    groups = {}
    for group, value in homographies.items():
        entry = value if isinstance(value, HomographyEntry) else HomographyEntry(np.asarray(value))
        groups[str(group)] = entry.to_dict()
    body: dict[str, Any] = {"schema": 1, "groups": groups}
    if meta:
        body["meta"] = dict(meta)
    return atomic_write_text(path, HOMOGRAPHY_FILE_HEADER + dump_yaml(body))


def load_homography_entries(path: str | Path) -> dict[str, HomographyEntry]:
    """Every group's entry of a homographies file (``H`` computed from ``similarity`` where needed)."""
    from harness.config import read_yaml
    from harness.errors import ConfigError

    path = Path(path)
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise DataError(str(exc)) from None
    groups = data.get("groups")
    if not isinstance(groups, dict) or not groups:
        raise DataError(f"{path}: expected a 'groups' mapping {{group: {{H: ... or similarity: ...}}}}")
    out: dict[str, HomographyEntry] = {}
    for group, raw in groups.items():
        where = f"{path}: group {group!r}"
        if not isinstance(raw, dict):
            raise DataError(f"{where}: expected a mapping with 'H' or 'similarity'")
        rgb_size = tuple(raw["rgb_size"]) if raw.get("rgb_size") else None
        thermal_size = tuple(raw["thermal_size"]) if raw.get("thermal_size") else None
        if "H" in raw:
            try:
                H = np.asarray(raw["H"], dtype=np.float64)
            except (TypeError, ValueError):
                raise DataError(f"{where}: H is not a 3x3 matrix of numbers") from None
            if H.shape != (3, 3):
                raise DataError(f"{where}: H has shape {H.shape}, expected 3x3")
            try:
                H = normalize(H)
            except DataError as exc:
                raise DataError(f"{where}: {exc}") from None
            entry = HomographyEntry(H, str(raw.get("method", "manual")), raw.get("similarity"), rgb_size,  # type: ignore[arg-type]
                                    thermal_size, dict(raw.get("quality", {}) or {}), str(raw.get("note", "")))
        elif "similarity" in raw:
            try:
                entry = entry_from_similarity(raw["similarity"], rgb_size, thermal_size,  # type: ignore[arg-type]
                                              note=str(raw.get("note", "")))
            except (DataError, TypeError, ValueError) as exc:
                raise DataError(f"{where}: {exc}") from None
        else:
            raise DataError(f"{where}: needs 'H' or 'similarity'")
        out[str(group)] = entry
    return out


def load_homographies(path: str | Path) -> dict[str, np.ndarray]:
    """``{group: H}`` from a homographies file written by ``save_homographies`` (or by hand)."""
    return {g: e.H for g, e in load_homography_entries(path).items()}


# ---------------------------------------------------------------------------------------------- landmarks
@dataclass
class Landmarks:
    """Pairs of corresponding points: ``rgb`` and ``thermal`` (N x 2 pixels), with scene and group per pair."""

    rgb: np.ndarray
    thermal: np.ndarray
    scene: list[str]
    group: list[str]

    def __post_init__(self) -> None:
        self.rgb = np.asarray(self.rgb, dtype=np.float64).reshape(-1, 2)
        self.thermal = np.asarray(self.thermal, dtype=np.float64).reshape(-1, 2)
        n = len(self.rgb)
        if len(self.thermal) != n or len(self.scene) != n or len(self.group) != n:
            raise DataError("landmarks: rgb, thermal, scene and group must have the same length")

    def __len__(self) -> int:
        return len(self.rgb)

    def select(self, mask: np.ndarray) -> "Landmarks":
        idx = np.nonzero(np.asarray(mask))[0]
        return Landmarks(self.rgb[idx], self.thermal[idx], [self.scene[i] for i in idx], [self.group[i] for i in idx])

    def groups(self) -> list[str]:
        return sorted(set(self.group))

    def by_group(self, group: str) -> "Landmarks":
        return self.select(np.array([g == group for g in self.group], dtype=bool))


LANDMARK_COLUMNS = ("scene", "group", "rgb_x", "rgb_y", "thermal_x", "thermal_y")


def read_landmarks(path: str | Path) -> Landmarks:
    """Read a landmarks file: CSV with header ``scene,group,rgb_x,rgb_y,thermal_x,thermal_y`` (``group``
    optional, defaults to ``scene``) or JSON ``{"landmarks": [{"scene", "group", "rgb": [x, y],
    "thermal": [x, y]}, ...]}`` (a bare list works too). Coordinates are pixels of the original images."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: landmarks file not found")
    rows: list[tuple[str, str, float, float, float, float]] = []
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise DataError(f"{path}: invalid JSON at line {exc.lineno}: {exc.msg}") from None
        items = data.get("landmarks") if isinstance(data, dict) else data
        if not isinstance(items, list):
            raise DataError(f"{path}: expected {{'landmarks': [...]}} or a list of landmark records")
        for k, it in enumerate(items):
            try:
                scene = str(it["scene"])
                group = str(it.get("group") or scene)
                rx, ry = (float(v) for v in it["rgb"])
                tx, ty = (float(v) for v in it["thermal"])
            except (KeyError, TypeError, ValueError) as exc:
                raise DataError(f"{path}: landmark {k}: expected scene, rgb [x, y], thermal [x, y] ({exc})") from None
            rows.append((scene, group, rx, ry, tx, ty))
    else:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            fields = set(reader.fieldnames or [])
            need = {"scene", "rgb_x", "rgb_y", "thermal_x", "thermal_y"}
            if not need <= fields:
                raise DataError(f"{path}: CSV header lacks {sorted(need - fields)}; expected columns "
                                f"{', '.join(LANDMARK_COLUMNS)} (group optional)")
            for line, rec in enumerate(reader, start=2):
                try:
                    scene = rec["scene"].strip()
                    group = (rec.get("group") or "").strip() or scene
                    vals = [float(rec[c]) for c in ("rgb_x", "rgb_y", "thermal_x", "thermal_y")]
                except (TypeError, ValueError, AttributeError):
                    raise DataError(f"{path}: line {line}: non-numeric or missing coordinate") from None
                rows.append((scene, group, *vals))  # type: ignore[arg-type]
    if not rows:
        raise DataError(f"{path}: no landmarks")
    arr = np.array([r[2:] for r in rows], dtype=np.float64)
    if not np.isfinite(arr).all():
        raise DataError(f"{path}: non-finite landmark coordinates")
    return Landmarks(arr[:, :2], arr[:, 2:], [r[0] for r in rows], [r[1] for r in rows])


def write_landmarks(path: str | Path, landmarks: Landmarks) -> Path:
    """Write landmarks as CSV (``.csv``) or JSON (``.json``) in the format ``read_landmarks`` reads."""
    from harness.io import atomic_write_json, atomic_write_text

    path = Path(path)
    if path.suffix.lower() == ".json":
        items = [{"scene": s, "group": g, "rgb": r.tolist(), "thermal": t.tolist()}
                 for s, g, r, t in zip(landmarks.scene, landmarks.group, landmarks.rgb, landmarks.thermal)]
        return atomic_write_json(path, {"landmarks": items})
    lines = [",".join(LANDMARK_COLUMNS)]
    for s, g, r, t in zip(landmarks.scene, landmarks.group, landmarks.rgb, landmarks.thermal):
        lines.append(f"{s},{g},{r[0]:.6g},{r[1]:.6g},{t[0]:.6g},{t[1]:.6g}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def _percentile(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


def registration_error(landmarks: Landmarks | tuple[np.ndarray, np.ndarray], H: np.ndarray | Mapping[str, np.ndarray],
                       support: tuple[float, float, float, float] | Mapping[str, tuple[float, float, float, float]] | None = None
                       ) -> dict[str, Any]:
    """Reprojection error ``|| H(rgb_i) - thermal_i ||`` in thermal pixels (the aligned frame: the common-support
    crop only shifts coordinates, so distances are the same).

    ``H``: one matrix for every landmark, or ``{group: H}``. ``support``: ``(x0, y0, x1, y1)`` in the thermal
    frame (or one per group); landmarks whose thermal point falls outside are left out and counted.
    Returns ``n``, ``mean``, ``median``, ``p95``, ``max``, ``rmse``, ``outside_support``, ``per_scene``
    (``{scene: {n, mean, median}}``), ``per_group`` and the individual ``errors``.
    """
    lm = landmarks if isinstance(landmarks, Landmarks) else Landmarks(
        landmarks[0], landmarks[1], ["all"] * len(np.asarray(landmarks[0]).reshape(-1, 2)),
        ["all"] * len(np.asarray(landmarks[0]).reshape(-1, 2)))
    errors = np.full(len(lm), np.nan)
    keep = np.ones(len(lm), dtype=bool)
    for group in lm.groups():
        idx = np.array([g == group for g in lm.group])
        if isinstance(H, Mapping):
            if group not in H:
                raise DataError(f"no homography for group {group!r} (have: {', '.join(sorted(H)) or 'none'})")
            Hg = H[group]
        else:
            Hg = H
        errors[idx] = reprojection_errors(Hg, lm.rgb[idx], lm.thermal[idx])
        box = support.get(group) if isinstance(support, Mapping) else support
        if box is not None:
            x0, y0, x1, y1 = box
            t = lm.thermal[idx]
            inside = (t[:, 0] >= x0) & (t[:, 0] < x1) & (t[:, 1] >= y0) & (t[:, 1] < y1)
            keep[np.nonzero(idx)[0][~inside]] = False
    e = errors[keep]
    kept = lm.select(keep)

    def summary(values: np.ndarray) -> dict[str, float]:
        return {"n": int(len(values)), "mean": float(values.mean()) if len(values) else float("nan"),
                "median": _percentile(values, 50)}

    per_scene = {s: summary(e[np.array([x == s for x in kept.scene])]) for s in sorted(set(kept.scene))}
    per_group = {g: summary(e[np.array([x == g for x in kept.group])]) for g in sorted(set(kept.group))}
    return {
        "n": int(len(e)),
        "mean": float(e.mean()) if len(e) else float("nan"),
        "median": _percentile(e, 50),
        "p95": _percentile(e, 95),
        "max": float(e.max()) if len(e) else float("nan"),
        "rmse": float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan"),
        "outside_support": int((~keep).sum()),
        "per_scene": per_scene,
        "per_group": per_group,
        "errors": [float(v) for v in e],
        "units": "thermal pixels",
    }


def fit_group_homographies(landmarks: Landmarks, method: str = "lsq", ransac_threshold: float = 2.0
                           ) -> dict[str, np.ndarray]:
    """One homography per group from that group's landmarks."""
    out = {}
    for group in landmarks.groups():
        sub = landmarks.by_group(group)
        try:
            out[group] = homography_from_landmarks(sub.rgb, sub.thermal, method, ransac_threshold)  # type: ignore[assignment]
        except DataError as exc:
            raise DataError(f"group {group!r}: {exc}") from None
    return out


def leave_one_out_errors(landmarks: Landmarks, method: str = "lsq", ransac_threshold: float = 2.0) -> np.ndarray:
    """Each landmark's error under the homography fitted to the other landmarks of its group (NaN when the
    rest are fewer than 4): an honest estimate of registration error when no independent checkpoints exist."""
    errors = np.full(len(landmarks), np.nan)
    for group in landmarks.groups():
        idx = np.nonzero(np.array([g == group for g in landmarks.group]))[0]
        if len(idx) < 5:
            continue
        for k in idx:
            rest = idx[idx != k]
            H = homography_from_landmarks(landmarks.rgb[rest], landmarks.thermal[rest], method, ransac_threshold)
            errors[k] = reprojection_errors(H, landmarks.rgb[[k]], landmarks.thermal[[k]])[0]  # type: ignore[arg-type]
    return errors

