"""Per-sensor calibration and undistortion (OpenCV's pinhole + Brown-Conrady model, no learned weights).

Camera model: a point ``(X, Y, Z)`` in the camera frame projects to ``x' = X/Z, y' = Y/Z``, is distorted with
``r^2 = x'^2 + y'^2``::

    x'' = x' (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x' y' + p2 (r^2 + 2 x'^2)
    y'' = y' (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y'^2) + 2 p2 x' y'

and lands at pixel ``u = fx x'' + cx, v = fy y'' + cy``. ``CameraModel`` stores ``K``, ``dist = (k1, k2, p1, p2,
k3)`` and the image size, in a readable YAML file. ``undistort_image`` removes the distortion and crops the
invalid (black) border, and the same correction goes to the RGB image, the thermal preview and the temperature
map (``undistort_points`` moves boxes and landmarks along).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from harness.errors import DataError

log = logging.getLogger(__name__)


@dataclass
class CameraModel:
    """Intrinsics ``K`` (3x3), distortion ``dist`` (k1, k2, p1, p2, k3) and ``image_size`` (width, height)."""

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    name: str = ""
    rms: float | None = None  # reprojection RMS of the calibration, pixels
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        d = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        if given.size > 5:
            raise DataError(f"camera {self.name or '?'}: expected at most 5 distortion coefficients, got {given.size}")
        d[: given.size] = given
        self.dist = d
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @classmethod
    def ideal(cls, focal_px: float, image_size: tuple[int, int], name: str = "") -> "CameraModel":
        """A distortion-free camera with square pixels and the principal point at the image centre."""
        w, h = image_size
        K = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1]], dtype=np.float64)
        return cls(K, np.zeros(5), (w, h), name=name)

    def scaled(self, image_size: tuple[int, int]) -> "CameraModel":
        """The same camera at another resolution (e.g. a calibration done at full size, used on a downscale)."""
        sx, sy = image_size[0] / self.image_size[0], image_size[1] / self.image_size[1]
        S = np.diag([sx, sy, 1.0])
        K = S @ self.K
        # pixel centres: u' + 0.5 = s (u + 0.5)
        K[0, 2] += 0.5 * sx - 0.5
        K[1, 2] += 0.5 * sy - 0.5
        return CameraModel(K, self.dist.copy(), image_size, name=self.name, rms=self.rms, extra=dict(self.extra))

    def to_dict(self) -> dict[str, Any]:
        k1, k2, p1, p2, k3 = (float(v) for v in self.dist)
        out: dict[str, Any] = {
            "name": self.name,
            "image_size": {"width": self.image_size[0], "height": self.image_size[1]},
            "intrinsics": {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "skew": float(self.K[0, 1])},
            "distortion": {"k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3},
        }
        if self.rms is not None:
            out["rms_px"] = float(self.rms)
        if self.extra:
            out["extra"] = dict(self.extra)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "<dict>") -> "CameraModel":
        try:
            size = data["image_size"]
            intr = data["intrinsics"]
            dist = data.get("distortion", {}) or {}
            K = np.array(
                [[intr["fx"], intr.get("skew", 0.0), intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]],
                dtype=np.float64,
            )
            d = [float(dist.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
            return cls(
                K,
                np.array(d),
                (int(size["width"]), int(size["height"])),
                name=str(data.get("name", "")),
                rms=data.get("rms_px"),
                extra=dict(data.get("extra", {}) or {}),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(
                f"{source}: not a camera model ({type(exc).__name__}: {exc}); expected keys image_size "
                "{width, height}, intrinsics {fx, fy, cx, cy}, distortion {k1, k2, p1, p2, k3}"
            ) from None

    def save(self, path: str | Path) -> Path:
        """Write a readable YAML file (``intrinsics``, ``distortion``, ``image_size``; pixels, OpenCV model)."""
        from harness.config import dump_yaml
        from harness.io import atomic_write_text

        head = (
            "# camera model: pinhole + Brown-Conrady distortion (OpenCV convention), pixels;\n"
            "# K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]], distortion (k1, k2, p1, p2, k3)\n"
        )
        return atomic_write_text(path, head + dump_yaml(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path) -> "CameraModel":
        from harness.config import read_yaml
        from harness.errors import ConfigError

        try:
            data = read_yaml(path)
        except ConfigError as exc:
            raise DataError(str(exc)) from None
        return cls.from_dict(data, str(path))


# ---------------------------------------------------------------------------------------------- calibration
def stretch_to_uint8(
    img: np.ndarray, low: float = 1.0, high: float = 99.0, clahe: bool = True, invert: bool = False
) -> np.ndarray:
    """Robust percentile stretch of any single-channel image to uint8, optional CLAHE and inversion.

    What thermal frames need before corner detection (the board's contrast is a few kelvin).
    """
    import cv2

    a = np.asarray(img)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.dtype == np.uint8 else a.mean(axis=2)
    a = a.astype(np.float32)
    lo, hi = np.percentile(a, [low, high])
    out = np.clip((a - lo) / max(float(hi - lo), 1e-6) * 255, 0, 255).astype(np.uint8)
    if clahe:
        out = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(out)
    return 255 - out if invert else out


def find_checkerboard(img: np.ndarray, pattern: tuple[int, int], thermal: bool = False) -> np.ndarray | None:
    """Inner-corner positions (N x 2 float32, row-major) of a ``pattern = (cols, rows)`` checkerboard, or None.

    Thermal frames (any dtype) are stretched with ``stretch_to_uint8`` (plain, then with CLAHE for low contrast)
    and tried both ways round (a warm board on a cold background and the inverse). Uses ``findChessboardCornersSB``
    (robust on low-resolution frames) and falls back to ``findChessboardCorners`` + ``cornerSubPix``.
    """
    import cv2

    if thermal or img.dtype != np.uint8:
        candidates = [
            stretch_to_uint8(img, clahe=False),
            stretch_to_uint8(img),
            stretch_to_uint8(img, clahe=False, invert=True),
            stretch_to_uint8(img, invert=True),
        ]
    else:
        candidates = [cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img]
    for gray in candidates:
        ok, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if ok:
            return corners.reshape(-1, 2).astype(np.float32)
        ok, corners = cv2.findChessboardCorners(
            gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        )
        if ok:
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
            corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), crit)
            return corners.reshape(-1, 2).astype(np.float32)
    return None


def load_view(path: str | Path, thermal: bool = False) -> np.ndarray:
    """A calibration view from a file: RGB uint8 for colour cameras; for thermal, the temperature map when the
    file is radiometric (R-JPEG, decoded temperature file), else the 8-bit frame."""
    from harness.sensing.registration import read_image_rgb, read_thermal_any

    return read_thermal_any(path) if thermal else read_image_rgb(path)


def board_points(pattern: tuple[int, int], square_size: float) -> np.ndarray:
    """3-D inner-corner coordinates of the board (Z = 0), row-major like the detector's output."""
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float32)
    return np.hstack([grid * square_size, np.zeros((grid.shape[0], 1), np.float32)])


@dataclass
class CalibrationResult:
    camera: CameraModel
    rms: float
    used: list[str]
    rejected: list[str]
    per_view_error: list[float]


def calibrate_checkerboard(
    images: Sequence[np.ndarray] | Iterable[tuple[str, np.ndarray]],
    pattern: tuple[int, int],
    square_size: float = 1.0,
    thermal: bool = False,
    name: str = "",
    fix_k3: bool = True,
    min_views: int = 3,
) -> CalibrationResult:
    """Calibrate one camera from checkerboard views with ``cv2.calibrateCamera``.

    ``images``: arrays, or ``(name, array)`` pairs so rejected views can be named. ``pattern`` = inner corners
    ``(cols, rows)``; ``square_size`` in any unit (only extrinsics depend on it). Views where the board is not
    found are skipped and listed; fewer than ``min_views`` usable views is a ``DataError``. ``k3`` is held at 0
    unless ``fix_k3=False`` (it is poorly constrained for narrow lenses).
    """
    import cv2

    obj = board_points(pattern, square_size)
    obj_pts, img_pts, used, rejected = [], [], [], []
    size: tuple[int, int] | None = None
    for k, item in enumerate(images):
        label, img = item if isinstance(item, tuple) else (f"view {k}", item)
        img = np.asarray(img)
        this = (img.shape[1], img.shape[0])
        if size is None:
            size = this
        elif this != size:
            raise DataError(
                f"{label}: image size {this[0]}x{this[1]} differs from the first view's {size[0]}x{size[1]}"
            )
        corners = find_checkerboard(img, pattern, thermal=thermal)
        if corners is None:
            rejected.append(label)
            continue
        obj_pts.append(obj)
        img_pts.append(corners.reshape(-1, 1, 2))
        used.append(label)
    if size is None or len(used) < min_views:
        raise DataError(
            f"checkerboard {pattern[0]}x{pattern[1]} found in {len(used)} view(s), "
            f"need at least {min_views}"
            + (f"; not found in: {', '.join(rejected[:10])}" if rejected else "")
            + ". Check the pattern size (inner corners, cols x rows) and the board's contrast."
        )
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj_pts, img_pts, size, None, None, flags=flags)
    errors = []
    for o, i, rv, tv in zip(obj_pts, img_pts, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
        errors.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=1)))))
    cam = CameraModel(
        K,
        dist.ravel()[:5],
        size,
        name=name,
        rms=float(rms),
        extra={"pattern": list(pattern), "square_size": square_size, "views": len(used)},
    )
    log.info("calibrated %s from %d views: rms %.3f px", name or "camera", len(used), rms)
    return CalibrationResult(cam, float(rms), used, rejected, errors)


# ---------------------------------------------------------------------------------------------- undistortion
def undistorted_camera(cam: CameraModel, alpha: float = 0.0) -> tuple[CameraModel, tuple[int, int, int, int]]:
    """The new camera and the valid ROI ``(x, y, w, h)`` after undistortion (``alpha=0``: no invalid pixels)."""
    import cv2

    new_K, roi = cv2.getOptimalNewCameraMatrix(cam.K, cam.dist, cam.image_size, alpha, cam.image_size)
    x, y, w, h = (int(v) for v in roi)
    if w <= 0 or h <= 0:
        x, y, w, h = 0, 0, cam.image_size[0], cam.image_size[1]
    K = new_K.copy()
    K[0, 2] -= x
    K[1, 2] -= y
    return CameraModel(K, np.zeros(5), (w, h), name=cam.name, extra={"undistorted_from": cam.to_dict()}), (x, y, w, h)


#: undistortion maps kept per (K, distortion, size, alpha): a flight or a dataset reuses one calibration, and building
#: the maps costs about as much as the remap itself. Bounded in bytes; the latest entry always stays.
MAPS_CACHE_BYTES = 256 * 2**20
_MAPS: OrderedDict[tuple, tuple[np.ndarray, tuple[int, int, int, int], np.ndarray, np.ndarray]] = OrderedDict()
_MAPS_LOCK = threading.Lock()


def _undistort_maps(
    cam: CameraModel, alpha: float
) -> tuple[np.ndarray, tuple[int, int, int, int], np.ndarray, np.ndarray]:
    """(new K, roi, map x, map y) of ``undistort_image``: float32 maps of the cropped output, cached (read-only)."""
    import cv2

    key = (cam.K.tobytes(), cam.dist.tobytes(), tuple(cam.image_size), float(alpha))
    with _MAPS_LOCK:
        hit = _MAPS.get(key)
        if hit is not None:
            _MAPS.move_to_end(key)
            return hit
    new_cam, (x, y, rw, rh) = undistorted_camera(cam, alpha)
    full_K = new_cam.K.copy()
    full_K[0, 2] += x
    full_K[1, 2] += y
    mx, my = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, full_K, cam.image_size, cv2.CV_32FC1)
    mx, my = np.ascontiguousarray(mx[y : y + rh, x : x + rw]), np.ascontiguousarray(my[y : y + rh, x : x + rw])
    mx.flags.writeable = False
    my.flags.writeable = False
    new_K = new_cam.K.copy()
    new_K.flags.writeable = False
    entry = (new_K, (x, y, rw, rh), mx, my)
    with _MAPS_LOCK:
        _MAPS[key] = entry
        while len(_MAPS) > 1 and sum(e[2].nbytes + e[3].nbytes for e in _MAPS.values()) > MAPS_CACHE_BYTES:
            _MAPS.popitem(last=False)
    return entry


def undistort_image(
    img: np.ndarray, cam: CameraModel, alpha: float = 0.0, interpolation: str = "linear"
) -> tuple[np.ndarray, CameraModel, tuple[int, int, int, int]]:
    """Undistort ``img`` (RGB, preview or float temperature map) and crop to the valid region.

    Returns ``(image, new_cam, roi)``: the cropped undistorted image, the distortion-free camera that describes
    it (principal point shifted by the crop) and ``roi = (x, y, w, h)`` in the uncropped undistorted frame.
    ``alpha=0`` keeps only valid pixels (no black border); ``alpha=1`` keeps every source pixel. Temperature maps
    keep their dtype (float32, bilinear). A distortion-free camera returns the image unchanged. The maps are built
    once per camera model, size and ``alpha`` and reused (``MAPS_CACHE_BYTES``).
    """
    import cv2

    h, w = img.shape[:2]
    if (w, h) != cam.image_size:
        raise DataError(
            f"camera {cam.name or '?'} was calibrated at {cam.image_size[0]}x{cam.image_size[1]}, "
            f"image is {w}x{h}; use CameraModel.scaled() for a resized image"
        )
    if not np.any(cam.dist):
        return img, CameraModel(cam.K.copy(), np.zeros(5), cam.image_size, name=cam.name), (0, 0, w, h)
    new_K, (x, y, rw, rh), mx, my = _undistort_maps(cam, alpha)
    new_cam = CameraModel(new_K.copy(), np.zeros(5), (rw, rh), name=cam.name, extra={"undistorted_from": cam.to_dict()})
    interp = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}[interpolation]
    out = cv2.remap(img, mx, my, interp, borderMode=cv2.BORDER_REPLICATE)
    return out, new_cam, (x, y, rw, rh)


def undistort_points(points: np.ndarray, cam: CameraModel, new_cam: CameraModel) -> np.ndarray:
    """Move pixel coordinates (N x 2) from the distorted image to the undistorted, cropped one of ``new_cam``."""
    import cv2

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    return cv2.undistortPoints(pts, cam.K, cam.dist, P=new_cam.K).reshape(-1, 2)


def distort_points(points: np.ndarray, new_cam: CameraModel, cam: CameraModel) -> np.ndarray:
    """The inverse of ``undistort_points``: pixel coordinates (N x 2) of the undistorted image of ``new_cam`` back
    to the image as shot by ``cam`` (its lens distortion applied again)."""
    import cv2

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    rays = np.linalg.solve(new_cam.K, np.vstack([pts.T, np.ones(len(pts))])).T
    rays = rays / rays[:, 2:3]
    moved, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return moved.reshape(-1, 2)


def undistort_boxes(boxes: np.ndarray, cam: CameraModel, new_cam: CameraModel) -> np.ndarray:
    """Boxes (N x 4 xyxy) through ``undistort_points``: the bounding box of each box's four moved corners."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if len(b) == 0:
        return np.zeros((0, 4), np.float32)
    corners = np.stack([b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1).reshape(-1, 2)
    moved = undistort_points(corners, cam, new_cam).reshape(-1, 4, 2)
    return np.concatenate([moved.min(axis=1), moved.max(axis=1)], axis=1).astype(np.float32)
