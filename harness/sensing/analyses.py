"""Sensor-level analyses of the seed: registration error on landmarks, and the displacement study of C2.

Displacement study (how much of the local contrast a box keeps when thermal and boxes are misregistered)::

    for every box b of class c and shift d in {0, 2, 5, 10, 15} px:
        for each direction (right, left, down, up):
            T_d   = thermal shifted by d px in that direction, borders replicated
            C2_d  = C2(T_d)                                  (background and p_clip recomputed)
            a     = mean over the box's pixels of |C2_d - 0.5|
        A_b(d) = mean of a over the four directions
    A_c(d) = mean over the boxes of class c of A_b(d)        (every box weighs the same)
    R_c(d) = 100 * A_c(d) / A_c(0)  [%]

Missing temperatures (NaN or inf) are left out: C2 is computed over the valid pixels (``harness.sensing.c2``) and
a box's amplitude averages only its pixels with a measured temperature; the result counts them
(``invalid_pixels``), and a map ``c2`` refuses (none valid, or too many missing) is an error naming the sample.

Both analyses return plain dicts (written as JSON) and have a text formatter whose columns line up.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from harness.api import AlignedSample
from harness.errors import DataError
from harness.io import nan_to_none  # noqa: F401  (JSON-safe copies; its old home)
from harness.sensing import c2 as c2mod
from harness.textable import text_table

log = logging.getLogger(__name__)

SHIFTS = (2, 5, 10, 15)
#: (dx, dy) unit steps: right, left, down, up
DIRECTIONS: tuple[tuple[int, int], ...] = ((1, 0), (-1, 0), (0, 1), (0, -1))


# ---------------------------------------------------------------------------------------------- displacement
def shift_replicate(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``out(x, y) = img(x - dx, y - dy)`` with the border pixels replicated into the uncovered strip."""
    h, w = img.shape[:2]
    if abs(dx) >= w or abs(dy) >= h:
        raise ValueError(f"shift ({dx}, {dy}) is not smaller than the {w}x{h} image")
    xs = np.clip(np.arange(w) - dx, 0, w - 1)
    ys = np.clip(np.arange(h) - dy, 0, h - 1)
    return img[ys[:, None], xs[None, :]]


def box_amplitudes(
    thermal: np.ndarray,
    boxes: np.ndarray,
    shifts: Sequence[int] = SHIFTS,
    directions: Sequence[tuple[int, int]] = DIRECTIONS,
    sigma: float = c2mod.SIGMA,
    percentile: float = c2mod.PERCENTILE,
    floor: float = c2mod.FLOOR,
    name: str | None = None,
) -> np.ndarray:
    """``A_b(d)`` for every box (rows) and shift ``d`` in ``(0, *shifts)`` (columns): mean ``|C2 - 0.5|`` in the
    box, averaged over the directions; C2 is recomputed on each shifted temperature map. Pixels with a missing
    temperature are left out of the box means (a box with none valid gets NaN); ``name`` is named in errors."""
    thermal = c2mod.check_map(thermal, name)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    out = np.full((len(b), 1 + len(shifts)), np.nan)
    if len(b) == 0:
        return out
    clean = c2mod.invalid_count(thermal) == 0
    c0 = c2mod.c2(thermal, sigma, percentile, floor, name)
    valid0 = None if clean else np.isfinite(thermal)
    out[:, 0] = [c2mod.contrast_amplitude(c0, box, valid0) for box in b]
    for k, d in enumerate(shifts, start=1):
        acc = np.zeros(len(b))
        for ux, uy in directions:
            td = shift_replicate(thermal, ux * d, uy * d)
            cd = c2mod.c2(td, sigma, percentile, floor, name)
            acc += [c2mod.contrast_amplitude(cd, box, None if clean else np.isfinite(td)) for box in b]
        out[:, k] = acc / len(directions)
    return out


def displacement_study(
    samples: Iterable[AlignedSample],
    categories: Sequence[str],
    shifts: Sequence[int] = SHIFTS,
    sigma: float = c2mod.SIGMA,
    percentile: float = c2mod.PERCENTILE,
    floor: float = c2mod.FLOOR,
    max_images: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """The seed's displacement study over aligned samples (see the module docstring).

    Returns ``{"shifts": [0, *shifts], "classes": {name: {"boxes": n, "A": [A_c(d)...], "R": [R_c(d) %...]}},
    "mean_over_classes": {"A", "R"}, "images": n, "boxes": n, "params": {...}}``. Samples without thermal (8-bit
    datasets) are a ``DataError``: the study is about radiometric contrast.
    """
    shifts = [int(d) for d in shifts]
    if any(d <= 0 for d in shifts):
        raise DataError(f"displacements must be positive pixel counts, got {shifts}")
    per_class: dict[int, list[np.ndarray]] = {k: [] for k in range(len(categories))}
    images = 0
    invalid = 0
    for sample in samples:
        if max_images is not None and images >= max_images:
            break
        if sample.thermal is None:
            raise DataError(f"{sample.name}: no radiometric thermal; the displacement study needs temperatures")
        images += 1
        invalid += c2mod.invalid_count(sample.thermal)
        if len(sample.boxes):
            amps = box_amplitudes(
                sample.thermal, sample.boxes, shifts, sigma=sigma, percentile=percentile, floor=floor, name=sample.name
            )
            for lab, row in zip(np.asarray(sample.labels).tolist(), amps):
                if np.isfinite(row).all():
                    per_class.setdefault(int(lab), []).append(row)
        if progress is not None:
            progress(1)
    classes: dict[str, Any] = {}
    for k, name in enumerate(categories):
        rows = per_class.get(k, [])
        if not rows:
            classes[name] = {"boxes": 0, "A": None, "R": None}
            continue
        A = np.mean(np.stack(rows), axis=0)
        R = 100.0 * A / A[0] if A[0] > 0 else np.full_like(A, np.nan)
        classes[name] = {"boxes": len(rows), "A": [float(v) for v in A], "R": [float(v) for v in R]}
    present = [v for v in classes.values() if v["A"] is not None]
    mean = None
    if present:
        mean = {
            "A": [float(np.mean([v["A"][i] for v in present])) for i in range(len(shifts) + 1)],
            "R": [float(np.nanmean([v["R"][i] for v in present])) for i in range(len(shifts) + 1)],
        }
    return {
        "analysis": "displacement",
        "shifts": [0, *shifts],
        "classes": classes,
        "mean_over_classes": mean,
        "images": images,
        "boxes": int(sum(v["boxes"] for v in classes.values())),
        "invalid_pixels": invalid,
        "params": {
            "sigma": sigma,
            "percentile": percentile,
            "floor": floor,
            "directions": "right,left,down,up",
            "border": "replicate",
        },
        "definition": "R_c(d) = 100 * A_c(d) / A_c(0); A_c(d) = mean over class-c boxes of the direction-averaged "
        "mean |C2 - 0.5| in the box after shifting the thermal map d px",
    }


def format_displacement(result: Mapping[str, Any]) -> str:
    """``class | boxes | A(0) | R(2 px) ... R(15 px)`` with percentages; a mean-over-classes row at the end."""
    shifts = result["shifts"][1:]
    header = ["class", "boxes", "A(0)", *[f"R({d} px)" for d in shifts]]
    rows = []
    for name, v in result["classes"].items():
        if v["A"] is None:
            rows.append([name, "0", "-", *["-" for _ in shifts]])
        else:
            rows.append([name, str(v["boxes"]), f"{v['A'][0]:.4f}", *[f"{r:.1f}%" for r in v["R"][1:]]])
    mean = result.get("mean_over_classes")
    if mean:
        rows.append(
            ["mean (classes)", str(result["boxes"]), f"{mean['A'][0]:.4f}", *[f"{r:.1f}%" for r in mean["R"][1:]]]
        )
    title = (
        f"C2 retained under thermal displacement (R_c(d) = A_c(d) / A_c(0)), {result['images']} images, "
        f"{result['boxes']} boxes"
    )
    return title + "\n" + text_table(header, rows)


# ---------------------------------------------------------------------------------------------- registration error
def registration_error_study(
    landmarks: Any,
    homographies: Mapping[str, np.ndarray] | None = None,
    method: str = "lsq",
    support: Mapping[str, tuple[float, float, float, float]] | None = None,
) -> dict[str, Any]:
    """Registration error on a landmarks file's points.

    With ``homographies`` (``{group: H}``, e.g. the similarity-adjusted ones actually used) the landmarks are
    independent checkpoints. Without, each group's homography is fitted to its own landmarks and every point
    is scored leave-one-out (the point left out of the fit), which does not flatter the fit.
    """
    from harness.sensing import registration as reg

    lm = landmarks
    if homographies is not None:
        result = reg.registration_error(lm, homographies, support=support)
        result["mode"] = "given homographies"
        return result
    errors = reg.leave_one_out_errors(lm, method=method)
    keep = np.isfinite(errors)
    if not keep.any():
        raise DataError("leave-one-out needs at least 5 landmarks in a group; give --homographies instead")
    skipped = sorted({g for g, k in zip(lm.group, keep) if not k})
    sub = lm.select(keep)
    e = errors[keep]
    per_scene = {}
    for s in sorted(set(sub.scene)):
        v = e[np.array([x == s for x in sub.scene])]
        per_scene[s] = {"n": int(len(v)), "mean": float(v.mean()), "median": float(np.median(v))}
    per_group = {}
    for g in sorted(set(sub.group)):
        v = e[np.array([x == g for x in sub.group])]
        per_group[g] = {"n": int(len(v)), "mean": float(v.mean()), "median": float(np.median(v))}
    return {
        "n": int(len(e)),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p95": float(np.percentile(e, 95)),
        "max": float(e.max()),
        "rmse": float(np.sqrt(np.mean(e**2))),
        "outside_support": 0,
        "per_scene": per_scene,
        "per_group": per_group,
        "errors": [float(v) for v in e],
        "units": "thermal pixels",
        "mode": f"leave-one-out {method} fit per group",
        "groups_skipped": skipped,
    }


def format_registration_error(result: Mapping[str, Any]) -> str:
    """Overall mean / median / P95 (px) and the per-scene mean, aligned."""
    head = text_table(
        ["landmarks", "mean (px)", "median (px)", "P95 (px)", "max (px)"],
        [
            [
                str(result["n"]),
                f"{result['mean']:.2f}",
                f"{result['median']:.2f}",
                f"{result['p95']:.2f}",
                f"{result['max']:.2f}",
            ]
        ],
        align="rrrrr",
    )
    rows = [[scene, str(v["n"]), f"{v['mean']:.2f}", f"{v['median']:.2f}"] for scene, v in result["per_scene"].items()]
    per = text_table(["scene", "n", "mean (px)", "median (px)"], rows)
    note = f"registration error in thermal pixels ({result.get('mode', '')})"
    if result.get("outside_support"):
        note += f"; {result['outside_support']} landmark(s) outside the common support left out"
    return f"{note}\n{head}\n\nper scene\n{per}"
