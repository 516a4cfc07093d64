"""Automatic registration pooled over an inspection group: one homography from the evidence of all its frames.

An inspection group is one rig at one distance from one facade, so every frame of it shares the RGB -> thermal
homography; a single frame often holds too little common structure for ECC to be trusted (cross-modal correlations
of 0.2-0.5, a periodic facade that lets ECC lock onto a neighbouring window). Pooling turns many weak frames into one
strong estimate:

1. every frame (at most ``max_frames``, spread evenly over the group) gives a **candidate**: ECC from the factory
   prior on its structure images (``structure_pair``, ``refine_warp``), without a check of its own;
2. each candidate is scored by its **pooled correlation**: the mean, over all frames, of ECC's criterion with the
   frame's RGB warped by the candidate; the best candidate wins;
3. the candidates that **agree** with the winner (median distance over a grid of the thermal frame at most
   ``agree_px``) are averaged: a least-squares homography through all their grid correspondences;
4. **the group's check**: enough frames agree (at least ``min_agreement`` of the frames used, and two) or the pooled
   correlation reaches ``min_correlation`` (the single-frame check, now over every frame: all a group of one frame
   can offer), the pooled correlation at the result beats the prior's, and no thermal corner moved more than
   ``max_corner_shift`` from the prior.

A group that fails keeps the prior (``ok=False`` with the reason); ``PRIOR_ERROR_FRACTION`` is what the prior is then
expected to be off by.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field
from typing import Any, Iterator, Sequence

import numpy as np

from harness.sensing.registration.auto import (
    _warp_inverse,
    ecc_correlation,
    refine_warp,
    structure_pair,
)
from harness.sensing.registration.files import HomographyEntry
from harness.sensing.registration.homography import apply_homography, corner_error, normalize

#: The factory prior's median error against the true homographies, as a fraction of the thermal frame's diagonal:
#: 4.5-5.8 px on the 320x256 thermal frames of the eight m3t-synth (small) groups (``benchmarks/bench_pooled.py``),
#: 1.2-1.4 % of the diagonal. A group screened with the prior is expected to be off by about this much.
PRIOR_ERROR_FRACTION = 0.014
#: Grid points per axis over the thermal frame, for distances between homographies.
GRID = 9


def prior_error_px(thermal_size: tuple[int, int]) -> float:
    """What the factory prior is expected to be off by in a thermal frame of ``(w, h)`` pixels (median, px)."""
    return round(PRIOR_ERROR_FRACTION * math.hypot(*thermal_size), 1)


@dataclass
class PooledRegistration:
    """An inspection group's automatic registration: ``H`` (RGB -> thermal, the prior when ``ok`` is False)."""

    H: np.ndarray
    ok: bool
    frames: int  # frames that gave evidence
    agreeing: int  # of those, frames whose own estimate agrees with the pooled one
    correlation: float  # pooled correlation (mean over the frames) at H
    prior_correlation: float  # the same at the prior
    corner_shift_px: float  # largest move of a thermal-frame corner from the prior
    spread_px: float  # median distance of the agreeing frames' estimates from the pooled one (thermal px)
    reason: str = ""
    expected_error_px: float | None = None  # with ok False: what the prior is expected to be off by
    per_frame: list[dict[str, Any]] = field(default_factory=list)

    def quality(self) -> dict[str, Any]:
        """The fields recorded wherever a pooled registration is (frame records, homographies files)."""
        out: dict[str, Any] = {
            "pooled": True,
            "frames": self.frames,
            "agreeing": self.agreeing,
            "correlation": _r(self.correlation, 4),
            "prior_correlation": _r(self.prior_correlation, 4),
            "corner_shift_px": _r(self.corner_shift_px, 2),
            "spread_px": _r(self.spread_px, 2),
        }
        if not self.ok:
            out["reason"] = self.reason
            out["expected_error_px"] = self.expected_error_px
        return out

    def entry(
        self, rgb_size: tuple[int, int] | None = None, thermal_size: tuple[int, int] | None = None
    ) -> HomographyEntry:
        return HomographyEntry(
            self.H, "auto" if self.ok else "focal", None, rgb_size, thermal_size, quality=self.quality()
        )


def _r(v: float, n: int) -> float | None:
    return round(float(v), n) if np.isfinite(v) else None


def _grid(w: int, h: int) -> np.ndarray:
    xs, ys = np.meshgrid(np.linspace(0, w - 1, GRID), np.linspace(0, h - 1, GRID))
    return np.c_[xs.ravel(), ys.ravel()]


def _distance(Wa: np.ndarray, Wb: np.ndarray, pts: np.ndarray) -> float:
    """Median distance between two warps over ``pts`` (px)."""
    return float(np.median(np.linalg.norm(apply_homography(Wa, pts) - apply_homography(Wb, pts), axis=1)))


@contextlib.contextmanager
def reproducible_opencv() -> Iterator[None]:
    """OpenCV without Intel IPP in this thread, for the ``with`` block.

    Some of IPP's kernels (``cv2.magnitude`` among those ECC's structure images use) take a path that depends on
    where a buffer lies in memory, so the same registration of the same images could land a few hundredths of a
    pixel (a candidate's ECC converging elsewhere) apart from one call to the next; without IPP it gives the same
    digits every time, so a screen and ``harness score-route`` register a group identically. OpenCV keeps the
    setting per thread."""
    import cv2

    before = cv2.ipp.useIPP()
    cv2.ipp.setUseIPP(False)
    try:
        yield
    finally:
        cv2.ipp.setUseIPP(before)


def evenly(n: int, k: int) -> list[int]:
    """``min(n, k)`` indices spread evenly over ``range(n)`` (all of them when ``n <= k``)."""
    if n <= k:
        return list(range(n))
    return sorted({int(round(i * (n - 1) / (k - 1))) for i in range(k)})


def register_pooled(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]],
    init: np.ndarray,
    **kwargs: Any,
) -> PooledRegistration:
    """One homography for an inspection group from its ``(rgb, thermal)`` pairs (see the module docstring), the same
    to the last digit on every call (``reproducible_opencv``); ``kwargs``: those of ``_register_pooled``."""
    with reproducible_opencv():
        return _register_pooled(pairs, init, **kwargs)


def _register_pooled(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]],
    init: np.ndarray,
    max_frames: int = 24,
    min_agreement: float = 0.25,
    agree_px: float | None = None,
    min_correlation: float = 0.5,
    max_corner_shift: float | None = None,
    structure_sigma: float = 1.0,
    iterations: int = 100,
) -> PooledRegistration:
    """``register_pooled``'s work.

    ``pairs``: the group's frames in a fixed order (the result depends on it only through the choice of frames when
    there are more than ``max_frames``); RGB in the frame ``init`` starts from, thermal as temperature or 8-bit.
    ``agree_px``: default 1 % of the thermal diagonal, at least 2 px.
    """
    H0 = normalize(np.asarray(init, np.float64))
    evidence = []
    size: tuple[int, int] | None = None
    for i in evenly(len(pairs), max_frames):
        rgb, thermal = pairs[i]
        got = structure_pair(rgb, thermal, H0, structure_sigma)
        if got is None:
            continue
        h, w = got[0].shape
        if size is not None and size != (w, h):
            from harness.errors import DataError

            raise DataError(f"an inspection group mixes thermal frames of {size[0]}x{size[1]} and {w}x{h} pixels")
        size = (w, h)
        evidence.append((i, *got))
    if size is None:
        return PooledRegistration(
            H0,
            False,
            0,
            0,
            float("nan"),
            float("nan"),
            0.0,
            float("nan"),
            reason="the prior puts less than 10% of any thermal frame on RGB pixels",
        )
    w, h = size
    if max_corner_shift is None:
        max_corner_shift = 0.1 * math.hypot(w, h)
    if agree_px is None:
        agree_px = max(2.0, 0.01 * math.hypot(w, h))
    pts = _grid(w, h)

    def pooled(W: np.ndarray) -> float:
        return float(np.mean([ecc_correlation(t, _warp_inverse(im, W), m) for _, t, im, m in evidence]))

    candidates = []
    for _, t, im, m in evidence:
        W, converged, _ = refine_warp(t, im, m, None, "homography", iterations, 0.0, 0.0)
        candidates.append(W if converged else None)
    scores = [pooled(W) if W is not None else -math.inf for W in candidates]
    prior_rho = pooled(np.eye(3))
    best = int(np.argmax(scores))
    per_frame: list[dict[str, Any]] = []
    W_best = candidates[best]
    if W_best is None:
        return PooledRegistration(
            H0,
            False,
            len(evidence),
            0,
            float("nan"),
            prior_rho,
            0.0,
            float("nan"),
            reason="ECC converged on no frame",
            expected_error_px=prior_error_px(size),
        )
    agree: list[np.ndarray] = []
    for (i, *_), cand, s in zip(evidence, candidates, scores):
        d = _distance(cand, W_best, pts) if cand is not None else math.inf
        per_frame.append({"frame": i, "pooled_correlation": _r(s, 4), "distance_px": _r(d, 2)})
        if cand is not None and d <= agree_px:
            agree.append(cand)
    W_pool: np.ndarray = W_best
    if len(agree) > 1:  # least squares through every agreeing frame's correspondences
        import cv2

        src = np.concatenate([pts] * len(agree)).astype(np.float64)
        dst = np.concatenate([apply_homography(W, pts) for W in agree]).astype(np.float64)
        W_avg, _ = cv2.findHomography(src, dst, 0)
        if W_avg is not None:
            W_avg = normalize(W_avg)
            if pooled(W_avg) >= scores[best]:
                W_pool = W_avg
    rho = pooled(W_pool)
    H = normalize(np.linalg.inv(W_pool) @ H0)
    shift = float(corner_error(H, H0, (w, h)).max())
    spread = float(np.median([_distance(W, W_pool, pts) for W in agree]))
    n = len(evidence)
    need = max(2, math.ceil(min_agreement * n))
    reasons = []
    if len(agree) < need and not (np.isfinite(rho) and rho >= min_correlation):
        reasons.append(
            (
                f"{len(agree)} of {n} frames agree within {agree_px:.1f} px (need {need}) and the "
                if n > 1
                else "one frame only, and its "
            )
            + f"structure correlation {rho:.3f} is below {min_correlation}"
        )
    if not rho > prior_rho:
        reasons.append(f"pooled correlation {rho:.3f} not above the prior's {prior_rho:.3f}")
    if shift > max_corner_shift:
        reasons.append(f"a corner moved {shift:.1f} px from the prior (limit {max_corner_shift:.1f})")
    ok = not reasons
    return PooledRegistration(
        H if ok else H0,
        ok,
        n,
        len(agree),
        rho,
        prior_rho,
        shift,
        spread,
        reason="; ".join(reasons),
        expected_error_px=None if ok else prior_error_px(size),
        per_frame=per_frame,
    )
