"""Automatic registration without learned weights: enhanced correlation coefficient (ECC, Evangelidis & Psarakis
2008) maximisation on gradient-magnitude images, coarse to fine, initialised from the two cameras' focal lengths
or a given H, with a quality check that rejects poorly aligned pairs."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import DataError
from harness.sensing.registration.files import HomographyEntry
from harness.sensing.registration.homography import (
    corner_error,
    focal_prior,
    homography_from_similarity,
    image_center,
    normalize,
)


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

    def quality(self) -> dict[str, Any]:
        """The quality fields written wherever an automatic registration is recorded."""
        return {
            "correlation": round(self.correlation, 4),
            "initial_correlation": round(self.initial_correlation, 4),
            "corner_shift_px": round(self.corner_shift_px, 2),
        }

    def entry(
        self, rgb_size: tuple[int, int] | None = None, thermal_size: tuple[int, int] | None = None
    ) -> HomographyEntry:
        return HomographyEntry(self.H, "auto", None, rgb_size, thermal_size, quality=self.quality())


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


def _ecc(
    template: np.ndarray,
    image: np.ndarray,
    warp: np.ndarray,
    motion: str,
    iterations: int,
    eps: float,
    mask: np.ndarray | None,
) -> tuple[float, np.ndarray]:
    """One ``cv2.findTransformECC`` run; ``warp`` and the result are 3x3 (thermal pixel -> image pixel)."""
    import cv2

    mt = {
        "translation": cv2.MOTION_TRANSLATION,
        "euclidean": cv2.MOTION_EUCLIDEAN,
        "affine": cv2.MOTION_AFFINE,
        "homography": cv2.MOTION_HOMOGRAPHY,
    }[motion]
    w = warp.astype(np.float32)
    w = w if motion == "homography" else w[:2].copy()
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, eps)
    rho, found = cv2.findTransformECC(template, image, w, mt, crit, mask, 1)  # type: ignore[arg-type]  # None: no mask
    out = np.eye(3)
    out[: found.shape[0]] = found
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


def _coarse_search(
    template: np.ndarray, image: np.ndarray, mask: np.ndarray, scales: np.ndarray, thetas: np.ndarray
) -> tuple[float, np.ndarray]:
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


def estimate_homography_auto(
    rgb: np.ndarray,
    thermal: np.ndarray,
    init: np.ndarray | None = None,
    levels: int | None = None,
    motion: str = "homography",
    iterations: int = 100,
    search_scale: float = 0.06,
    search_rotation_deg: float = 4.0,
    min_correlation: float = 0.5,
    max_corner_shift: float | None = None,
    structure_sigma: float = 1.0,
) -> AutoRegistration:
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
    th = np.asarray(thermal)
    if th.ndim != 2:
        import cv2

        th = cv2.cvtColor(th, cv2.COLOR_RGB2GRAY)
    h, w = th.shape
    rgb_arr = np.asarray(rgb)
    if init is None:
        init = homography_from_similarity(
            0, 0, 0, w / rgb_arr.shape[1], image_center((rgb_arr.shape[1], rgb_arr.shape[0])), image_center((w, h))
        )
    H0 = normalize(init)
    if max_corner_shift is None:
        max_corner_shift = 0.1 * math.hypot(w, h)
    pair = structure_pair(rgb_arr, th, H0, structure_sigma)
    if pair is None:
        return AutoRegistration(
            H0,
            False,
            float("nan"),
            float("nan"),
            0.0,
            reason="the initial homography puts less than 10% of the thermal frame on RGB pixels",
        )
    tmpl, img, mask = pair
    init_rho = ecc_correlation(tmpl, img, mask)
    W, converged, report = refine_warp(tmpl, img, mask, levels, motion, iterations, search_scale, search_rotation_deg)
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
    return AutoRegistration(
        H if ok else H0, ok, float(final_rho), float(init_rho), shift, reason="; ".join(reasons), levels=report
    )


def structure_pair(
    rgb: np.ndarray, thermal: np.ndarray, H0: np.ndarray, structure_sigma: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(thermal structure, structure of the RGB warped into the thermal frame by ``H0``, mask) on the thermal pixel
    grid, what ECC compares; the mask is where the pre-warped RGB is real (eroded: the replicated border carries no
    structure). None when ``H0`` puts less than 10 % of the thermal frame on RGB pixels."""
    import cv2

    from harness.sensing.warp import warp_to_thermal

    th = np.asarray(thermal)
    if th.ndim != 2:
        th = cv2.cvtColor(th, cv2.COLOR_RGB2GRAY)
    h, w = th.shape
    warped, valid = warp_to_thermal(np.asarray(rgb), H0, (h, w), fill="replicate")
    tmpl = structure_image(th, structure_sigma)
    img = structure_image(warped, structure_sigma)
    mask = cv2.erode(valid.astype(np.uint8), np.ones((9, 9), np.uint8))
    if mask.sum() < 0.1 * h * w:
        return None
    return tmpl, img, mask


def refine_warp(
    tmpl: np.ndarray,
    img: np.ndarray,
    mask: np.ndarray,
    levels: int | None = None,
    motion: str = "homography",
    iterations: int = 100,
    search_scale: float = 0.06,
    search_rotation_deg: float = 4.0,
) -> tuple[np.ndarray, int, list[dict[str, Any]]]:
    """ECC coarse to fine from the identity (``estimate_homography_auto``'s steps 2 and 3): the warp ``W`` (thermal
    pixel -> pre-warped pixel), how many levels converged, and a report per level."""
    import cv2

    h, w = tmpl.shape
    if levels is None:
        levels = 1
        while min(h, w) / 2**levels >= 64 and w / 2**levels >= 80:
            levels += 1
    pyr_t, pyr_i, pyr_m = [tmpl], [img], [mask]
    for _ in range(1, levels):
        pyr_t.append(cv2.pyrDown(pyr_t[-1]))
        pyr_i.append(cv2.pyrDown(pyr_i[-1]))
        pyr_m.append(
            (
                cv2.resize(pyr_m[-1], (pyr_t[-1].shape[1], pyr_t[-1].shape[0]), interpolation=cv2.INTER_NEAREST) > 0
            ).astype(np.uint8)
        )
    top = len(pyr_t) - 1
    report: list[dict[str, Any]] = []
    n_scales = max(1, int(round(2 * search_scale / 0.01)) + 1)
    n_thetas = max(1, int(round(2 * search_rotation_deg / 1.0)) + 1)
    rho, Wc = _coarse_search(
        pyr_t[top],
        pyr_i[top],
        pyr_m[top],
        np.linspace(1 - search_scale, 1 + search_scale, n_scales),
        np.linspace(-search_rotation_deg, search_rotation_deg, n_thetas),
    )
    S = np.diag([0.5**top, 0.5**top, 1.0])
    W = np.linalg.inv(S) @ Wc @ S
    report.append({"level": top, "step": "search", "correlation": rho})
    converged = 0
    for lvl in range(top, -1, -1):
        S = np.diag([0.5**lvl, 0.5**lvl, 1.0])
        mot = motion if lvl == 0 else ("affine" if motion == "homography" else motion)
        try:
            rho, W_l = _ecc(pyr_t[lvl], pyr_i[lvl], S @ W @ np.linalg.inv(S), mot, iterations, 1e-6, pyr_m[lvl])
        except cv2.error:
            report.append({"level": lvl, "step": mot, "converged": False})
            continue
        W = np.linalg.inv(S) @ W_l @ S
        converged += 1
        report.append({"level": lvl, "step": mot, "correlation": rho, "converged": True})
    return W, converged, report


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
    """A thermal file for registration: temperature (R-JPEG or decoded file) when radiometric, else 8-bit grey.

    Registration needs the scene's structure, not its temperatures: a file whose temperatures are not decoded by the
    default route (an 8-bit thermal JPEG, or an R-JPEG the default refuses) is registered on its 8-bit picture, and
    a log line says so and why."""
    import logging

    import cv2

    from harness.sensing.radiometry import read_thermal

    path = Path(path)
    try:
        return read_thermal(path)[0]
    except DataError as exc:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise
        logging.getLogger(__name__).info(
            "%s: registered on its 8-bit picture (temperatures not decoded: %s)",
            path.name,
            str(exc).splitlines()[0][:160],
        )
        return img


def optics_prior(
    rgb_path: str | Path, thermal_path: str | Path, rgb_size: tuple[int, int], thermal_size: tuple[int, int]
) -> np.ndarray | None:
    """Focal-length prior from the two files' EXIF 35-mm-equivalent focal lengths (None when either lacks it)."""
    from harness.sensing import jpeg

    f35 = []
    for path in (rgb_path, thermal_path):
        try:
            exif = jpeg.read_exif(path) if Path(path).suffix.lower() in (".jpg", ".jpeg") else {}
        except DataError:
            exif = {}
        if not exif.get("FocalLengthIn35mmFilm"):
            return None
        f35.append(float(exif["FocalLengthIn35mmFilm"]))
    return focal_prior(rgb_size, thermal_size, (f35[0], f35[1]))


def register_files(
    rgb_path: str | Path, thermal_path: str | Path, init: HomographyEntry | np.ndarray | None = None, **kwargs: Any
) -> tuple[AutoRegistration, tuple[int, int], tuple[int, int]]:
    """``estimate_homography_auto`` on two files; the start is ``init``, else the EXIF optics prior, else the
    default. Returns the result and the two image sizes ``(w, h)``."""
    rgb = read_image_rgb(rgb_path)
    th = read_thermal_any(thermal_path)
    rgb_size, th_size = (rgb.shape[1], rgb.shape[0]), (th.shape[1], th.shape[0])
    H0 = init.H if isinstance(init, HomographyEntry) else init
    if H0 is None:
        H0 = optics_prior(rgb_path, thermal_path, rgb_size, th_size)
    return estimate_homography_auto(rgb, th, init=H0, **kwargs), rgb_size, th_size
