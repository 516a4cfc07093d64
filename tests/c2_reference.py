"""A frozen copy of the C2 arithmetic as it was before the workspace FFT, kept as the reference that the stored
uint8 C2 must equal byte for byte: the clean path (FFT background of the reflect-padded, mean-centred map) and the
masked path (normalised convolution over the finite pixels, both planes in one stacked FFT).

Only the arithmetic is kept: the input is a float32 HxW map that ``harness.sensing.c2.check_map`` accepts, with at
least one finite pixel, and values small enough that the FFT does not overflow. Do not edit: a change here would
hide a change of the stored C2. Used by ``tests/test_sensing_c2_parity.py`` and ``benchmarks/bench_c2.py``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


def kernel_radius(sigma: float, truncate: float = 4.0) -> int:
    return int(truncate * float(sigma) + 0.5)


@lru_cache(maxsize=8)
def _kernel_spectrum(height: int, width: int, sigma: float) -> np.ndarray:
    r = kernel_radius(sigma)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    kr = np.zeros(width)
    kc = np.zeros(height)
    kr[: 2 * r + 1] = g
    kc[: 2 * r + 1] = g
    kr, kc = np.roll(kr, -r), np.roll(kc, -r)
    return (np.fft.fft(kc)[:, None] * np.fft.rfft(kr)[None, :]).astype(np.complex64)


def _centred_padded(t: np.ndarray, r: int) -> tuple[np.ndarray, np.float32]:
    import cv2

    src = np.asarray(t, dtype=np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        m = np.float32(src.mean(dtype=np.float64))
        centred = src - m
    return cv2.copyMakeBorder(centred, r, r, r, r, cv2.BORDER_REFLECT_101), m


def _blur_padded(xp: np.ndarray, r: int, h: int, w: int, sigma: float) -> np.ndarray:
    import scipy.fft

    hp, wp = (scipy.fft.next_fast_len(n, real=True) for n in xp.shape)
    spec = scipy.fft.rfft2(xp, s=(hp, wp), workers=1)
    spec *= _kernel_spectrum(hp, wp, float(sigma))
    return scipy.fft.irfft2(spec, s=(hp, wp), workers=1)[r : r + h, r : r + w]


def _masked_background(src: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    import cv2
    import scipy.fft

    r = kernel_radius(sigma)
    h, w = src.shape
    m = np.float32(src[mask].mean(dtype=np.float64))
    planes = (np.where(mask, src - m, np.float32(0)), mask.astype(np.float32))
    hp, wp = (scipy.fft.next_fast_len(n + 2 * r, real=True) for n in (h, w))
    padded = np.zeros((2, hp, wp), np.float32)
    for k, plane in enumerate(planes):
        padded[k, : h + 2 * r, : w + 2 * r] = cv2.copyMakeBorder(plane, r, r, r, r, cv2.BORDER_REFLECT_101)
    spec = scipy.fft.rfft2(padded, workers=1)
    spec *= _kernel_spectrum(hp, wp, float(sigma))
    num, den = scipy.fft.irfft2(spec, s=(hp, wp), workers=1)[:, r : r + h, r : r + w]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = num / np.maximum(den, np.float32(1e-12))
    out += m
    return out.astype(np.float32, copy=False)


def gaussian_background(src: np.ndarray, sigma: float = 11.0) -> np.ndarray:
    """``B = G * T`` (the FFT method), float32."""
    r = kernel_radius(sigma)
    mask = np.isfinite(src)
    if not mask.all():
        return _masked_background(src, mask, sigma)
    h, w = src.shape
    xp, m = _centred_padded(src, r)
    out = _blur_padded(xp, r, h, w, sigma)
    out += m
    return out


def deviation(src: np.ndarray, sigma: float = 11.0) -> tuple[np.ndarray, np.ndarray | None]:
    """``(dT, mask)``: ``mask`` is ``None`` for a map without missing pixels; ``dT`` is NaN at missing pixels."""
    r = kernel_radius(sigma)
    h, w = src.shape
    xp, m = _centred_padded(src, r)
    if not np.isfinite(m):
        mask = np.isfinite(src)
        dt = src - _masked_background(src, mask, sigma)
        dt[~mask] = np.nan
        return dt, mask
    return np.subtract(xp[r : r + h, r : r + w], _blur_padded(xp, r, h, w, sigma)), None


def fast_percentile(values: np.ndarray, q: float) -> float:
    a = np.asarray(values).ravel()
    n = a.size
    r = q / 100.0 * (n - 1)
    lo = int(np.floor(r))
    frac = r - lo
    need = n - lo
    if n < 20000 or need > n // 8:
        return float(np.percentile(a, q))
    step = max(1, n // 4096)
    sample = a[::step]
    k = max(0, sample.size - 1 - int(2 * need / n * sample.size) - 2)
    thr = np.partition(sample, k)[k]
    cand = a[a >= thr]
    if cand.size < need + 1 or not np.isfinite(thr):
        return float(np.percentile(a, q))
    m = cand.size
    j = lo - (n - m)
    if j < 0:
        return float(np.percentile(a, q))
    hi_j = min(j + 1, m - 1)
    part = np.partition(cand, (j, hi_j))
    v0, v1 = float(part[j]), float(part[hi_j])
    return v0 + (v1 - v0) * frac if frac else v0


def _scaled(dt: np.ndarray, p: float) -> np.ndarray:
    out = np.asarray(dt, dtype=np.float32) * np.float32(1.0 / (2.0 * p))
    out += np.float32(0.5)
    return np.clip(out, 0.0, 1.0, out=out)


def c2(src: np.ndarray, sigma: float = 11.0, percentile: float = 99.0, floor: float = 0.05) -> np.ndarray:
    dt, mask = deviation(src, sigma)
    if mask is None:
        return _scaled(dt, max(fast_percentile(np.abs(dt), percentile), float(floor)))
    out = _scaled(dt, max(fast_percentile(np.abs(dt[mask]), percentile), float(floor)))
    out[~mask] = np.float32(0.5)
    return out


def to_uint8(c: np.ndarray) -> np.ndarray:
    out = np.asarray(c, dtype=np.float32) * np.float32(255.0)
    np.rint(out, out=out)
    return out.astype(np.uint8)


def c2_uint8(src: np.ndarray, sigma: float = 11.0, percentile: float = 99.0, floor: float = 0.05) -> np.ndarray:
    """``round(255 * C2)`` as uint8, exactly as before (missing pixels 128)."""
    return to_uint8(c2(np.ascontiguousarray(src, dtype=np.float32), sigma, percentile, floor))
