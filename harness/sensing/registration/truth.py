"""Registration error beside the truth: where a dataset knows its true homographies (a synthetic set does).

Two numbers explain a registration-error table when the truth is known:

* the landmarks' error under the *true* homographies: how far the clicked points are from the true
  correspondence (the clicking error alone, no fit involved);
* the *fitted* homographies (the ones evaluated, or one least-squares fit per group from the landmarks) against
  the true ones, over a grid of the thermal frame: how far the registration that the pipeline uses actually is
  from the truth, which no landmark-based measure can see.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from harness.errors import DataError
from harness.sensing.registration.homography import apply_homography
from harness.sensing.registration.landmarks import Landmarks, fit_groups, registration_error
from harness.textable import text_table

#: Grid points per axis over the thermal frame for the fitted-vs-true comparison.
GRID = 9


def _stats(values: np.ndarray) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return {"n": 0, "mean": float("nan"), "median": float("nan"), "p95": float("nan")}
    return {
        "n": int(len(v)),
        "mean": float(v.mean()),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
    }


def frame_grid(thermal_size: tuple[int, int], n: int = GRID) -> np.ndarray:
    """``n x n`` points spread over the thermal frame (pixel centres, OpenCV convention), as an Nx2 array."""
    w, h = thermal_size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    return np.c_[xs.ravel(), ys.ravel()]


def against_truth(
    landmarks: Landmarks,
    true_h: Mapping[str, np.ndarray],
    fitted_h: Mapping[str, np.ndarray] | None,
    thermal_size: tuple[int, int] | None,
    method: str = "lsq",
) -> dict[str, Any]:
    """The landmarks' error under ``true_h`` and, per group, the distance between ``fitted_h`` (default: a fit of
    each group's landmarks) and ``true_h`` over a grid of the thermal frame. Thermal pixels throughout.

    ``thermal_size`` is the frame the grid covers; without it the landmarks' own thermal extent is used.
    """
    missing = sorted(set(landmarks.groups()) - set(true_h))
    if missing:
        raise DataError(
            f"the true homographies have no group {', '.join(map(repr, missing))} "
            f"(have: {', '.join(sorted(true_h)) or 'none'})"
        )
    on_true = registration_error(landmarks, dict(true_h))
    fitted = dict(fitted_h) if fitted_h is not None else {g: f.H for g, f in fit_groups(landmarks, method).items()}
    per_group: dict[str, dict[str, float]] = {}
    dists = []
    for group in landmarks.groups():
        if group not in fitted:
            continue
        if thermal_size is not None:
            pts = frame_grid(thermal_size)
        else:
            t = landmarks.by_group(group).thermal
            lo, hi = t.min(axis=0), t.max(axis=0)
            xs, ys = np.meshgrid(np.linspace(lo[0], hi[0], GRID), np.linspace(lo[1], hi[1], GRID))
            pts = np.c_[xs.ravel(), ys.ravel()]
        rgb = apply_homography(np.linalg.inv(true_h[group]), pts)
        d = np.linalg.norm(apply_homography(fitted[group], rgb) - pts, axis=1)
        per_group[group] = _stats(d)
        dists.append(d)
    grid = _stats(np.concatenate(dists)) if dists else _stats(np.array([]))
    return {
        "landmarks_on_true": {k: on_true[k] for k in ("n", "mean", "median", "p95")},
        "fitted_vs_true": grid,
        "fitted_vs_true_per_group": per_group,
        "fitted": "given homographies" if fitted_h is not None else f"{method} fit per group",
        "grid": f"{GRID}x{GRID} points over the thermal frame"
        if thermal_size is not None
        else f"{GRID}x{GRID} points over the landmarks' extent",
    }


def format_against_truth(result: Mapping[str, Any], measured: Mapping[str, Any]) -> str:
    """The measured error beside the error against the truth: one aligned table, thermal px."""
    on_true, grid = result["landmarks_on_true"], result["fitted_vs_true"]
    rows = [
        [
            "landmarks, as measured",
            str(measured["n"]),
            f"{measured['mean']:.2f}",
            f"{measured['median']:.2f}",
            f"{measured['p95']:.2f}",
        ],
        [
            "landmarks, true homography",
            str(on_true["n"]),
            f"{on_true['mean']:.2f}",
            f"{on_true['median']:.2f}",
            f"{on_true['p95']:.2f}",
        ],
        [
            "fitted vs true homography",
            str(grid["n"]),
            f"{grid['mean']:.2f}",
            f"{grid['median']:.2f}",
            f"{grid['p95']:.2f}",
        ],
    ]
    note = f"against the truth (fitted: {result['fitted']}; fitted vs true on {result['grid']})"
    return note + "\n" + text_table(["error (thermal px)", "n", "mean", "median", "P95"], rows, align="lrrrr")
