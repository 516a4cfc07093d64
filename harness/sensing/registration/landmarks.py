"""Landmark pairs and what is fitted to them: one homography per inspection group, as one record (``LandmarkFit``)
with one set of quality fields, and the registration error they measure.

``fit_landmarks`` is the only landmark fit: ``harness sensing register``, the dataset adapters (through
``harness.sensing.registration.dataset``) and the registration-error studies all call it.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import DataError
from harness.sensing.registration.files import HomographyEntry
from harness.sensing.registration.homography import normalize, reprojection_errors


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
                raise DataError(
                    f"{path}: CSV header lacks {sorted(need - fields)}; expected columns "
                    f"{', '.join(LANDMARK_COLUMNS)} (group optional)"
                )
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
        items = [
            {"scene": s, "group": g, "rgb": r.tolist(), "thermal": t.tolist()}
            for s, g, r, t in zip(landmarks.scene, landmarks.group, landmarks.rgb, landmarks.thermal)
        ]
        return atomic_write_json(path, {"landmarks": items})
    lines = [",".join(LANDMARK_COLUMNS)]
    for s, g, r, t in zip(landmarks.scene, landmarks.group, landmarks.rgb, landmarks.thermal):
        lines.append(f"{s},{g},{r[0]:.6g},{r[1]:.6g},{t[0]:.6g},{t[1]:.6g}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def homography_from_landmarks(
    src: np.ndarray, dst: np.ndarray, method: str = "lsq", ransac_threshold: float = 2.0
) -> np.ndarray:
    """Homography taking ``src`` (RGB, N x 2) onto ``dst`` (thermal, N x 2), N >= 4.

    ``method="lsq"``: every pair, least squares (normalised DLT refined by Levenberg-Marquardt on the
    reprojection error). ``"ransac"``: RANSAC with ``ransac_threshold`` pixels, then least squares on the
    inliers. ``fit_landmarks`` adds the inliers and the fit's error.
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
            raise DataError(
                f"the {name} landmarks are collinear or duplicated; a homography needs 4 points in general "
                "position (no three on a line)"
            )
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
    return normalize(H)


@dataclass(frozen=True)
class LandmarkFit:
    """A homography fitted to landmark pairs and how well it fits them: the record every caller keeps."""

    H: np.ndarray  # RGB -> thermal, H[2, 2] = 1
    method: str  # lsq | ransac
    inliers: np.ndarray  # bool per pair: within the RANSAC threshold of H (all of them for lsq)
    rms_px: float  # root-mean-square reprojection error over the inliers, thermal px

    @property
    def pairs(self) -> int:
        return len(self.inliers)

    def quality(self) -> dict[str, Any]:
        """The quality fields written wherever a landmark fit is recorded (homographies files, prepare notes)."""
        return {"pairs": self.pairs, "inliers": int(self.inliers.sum()), "rms_px": round(self.rms_px, 4)}

    def entry(
        self, rgb_size: tuple[int, int] | None = None, thermal_size: tuple[int, int] | None = None
    ) -> HomographyEntry:
        return HomographyEntry(self.H, "landmarks", None, rgb_size, thermal_size, quality=self.quality())


def fit_landmarks(src: np.ndarray, dst: np.ndarray, method: str = "lsq", ransac_threshold: float = 2.0) -> LandmarkFit:
    """``homography_from_landmarks`` with its inliers (RANSAC: the pairs within ``ransac_threshold`` px of the
    final H) and the RMS reprojection error over them."""
    H = homography_from_landmarks(src, dst, method, ransac_threshold)
    s = np.asarray(src, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(dst, dtype=np.float64).reshape(-1, 2)
    inliers = reprojection_errors(H, s, d) <= ransac_threshold if method == "ransac" else np.ones(len(s), bool)
    err = reprojection_errors(H, s[inliers], d[inliers])
    return LandmarkFit(H, method, inliers, float(np.sqrt(np.mean(err**2))))


def fit_groups(landmarks: Landmarks, method: str = "lsq", ransac_threshold: float = 2.0) -> dict[str, LandmarkFit]:
    """One fit per group from that group's landmarks; a group that fits no homography is a ``DataError`` naming it."""
    out = {}
    for group in landmarks.groups():
        sub = landmarks.by_group(group)
        try:
            out[group] = fit_landmarks(sub.rgb, sub.thermal, method, ransac_threshold)
        except DataError as exc:
            raise DataError(f"group {group!r}: {exc}") from None
    return out


def _percentile(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


Box = tuple[float, float, float, float]


def registration_error(
    landmarks: Landmarks | tuple[np.ndarray, np.ndarray],
    H: np.ndarray | Mapping[str, np.ndarray],
    support: Box | Mapping[str, Box] | None = None,
) -> dict[str, Any]:
    """Reprojection error ``|| H(rgb_i) - thermal_i ||`` in thermal pixels (the aligned frame: the common-support
    crop only shifts coordinates, so distances are the same).

    ``H``: one matrix for every landmark, or ``{group: H}``. ``support``: ``(x0, y0, x1, y1)`` in the thermal
    frame (or one per group); landmarks whose thermal point falls outside are left out and counted.
    Returns ``n``, ``mean``, ``median``, ``p95``, ``max``, ``rmse``, ``outside_support``, ``per_scene``
    (``{scene: {n, mean, median}}``), ``per_group`` and the individual ``errors``.
    """
    lm = (
        landmarks
        if isinstance(landmarks, Landmarks)
        else Landmarks(
            landmarks[0],
            landmarks[1],
            ["all"] * len(np.asarray(landmarks[0]).reshape(-1, 2)),
            ["all"] * len(np.asarray(landmarks[0]).reshape(-1, 2)),
        )
    )
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
        return {
            "n": int(len(values)),
            "mean": float(values.mean()) if len(values) else float("nan"),
            "median": _percentile(values, 50),
        }

    per_scene = {s: summary(e[np.array([x == s for x in kept.scene])]) for s in sorted(set(kept.scene))}
    per_group = {g: summary(e[np.array([x == g for x in kept.group])]) for g in sorted(set(kept.group))}
    return {
        "n": int(len(e)),
        "mean": float(e.mean()) if len(e) else float("nan"),
        "median": _percentile(e, 50),
        "p95": _percentile(e, 95),
        "max": float(e.max()) if len(e) else float("nan"),
        "rmse": float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
        "outside_support": int((~keep).sum()),
        "per_scene": per_scene,
        "per_group": per_group,
        "errors": [float(v) for v in e],
        "units": "thermal pixels",
    }


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
