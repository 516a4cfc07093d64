"""C2: the signed local radiometric contrast channel, exactly as the seed defines it.

::

    B(x)   = (G_sigma * T)(x)                 Gaussian background, sigma = 11 px, T in C (float)
    dT(x)  = T(x) - B(x)
    p_clip = max(percentile_99(|dT|), 0.05 C)
    C2(x)  = clip(dT(x) / (2 p_clip) + 0.5, 0, 1)      neutral = 0.5; stored as round(255 * C2) uint8

Implementation notes (all exact, not approximations):

* The Gaussian has radius ``int(4 sigma + 0.5)`` taps each side (89 taps at sigma 11) and reflect-101 borders
  (``cv2.BORDER_REFLECT_101``, the same as ``scipy.ndimage.gaussian_filter(mode="mirror", truncate=4.0)``);
  it runs as an FFT convolution of the reflect-padded, mean-centred image (see ``gaussian_background``).
* ``percentile_99`` is NumPy's default (linear interpolation between order statistics). ``fast_percentile``
  finds the two order statistics among a small candidate set above a threshold taken from a strided subsample
  and falls back to a full selection when the candidates might not contain them, so the value is identical
  to ``np.percentile`` at a fraction of the cost.
* ``round`` is round-half-to-even (NumPy's ``rint``, Python's ``round``); a flat image maps to 127.5 -> 128.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

SIGMA = 11.0
PERCENTILE = 99.0
FLOOR = 0.05  # C


def kernel_radius(sigma: float, truncate: float = 4.0) -> int:
    """Taps each side of the centre: ``int(truncate * sigma + 0.5)`` (scipy's rule; 44 at sigma 11)."""
    return int(truncate * float(sigma) + 0.5)


@lru_cache(maxsize=8)
def _kernel_spectrum(height: int, width: int, sigma: float) -> np.ndarray:
    """Spectrum of the separable Gaussian (radius ``kernel_radius``) on a ``height x width`` periodic grid."""
    r = kernel_radius(sigma)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    kr = np.zeros(width)
    kc = np.zeros(height)
    kr[:2 * r + 1] = g
    kc[:2 * r + 1] = g
    kr, kc = np.roll(kr, -r), np.roll(kc, -r)  # centre tap at index 0
    return (np.fft.fft(kc)[:, None] * np.fft.rfft(kr)[None, :]).astype(np.complex64)


def _centred_padded(t: np.ndarray, r: int) -> tuple[np.ndarray, np.float32]:
    """``T - mean(T)`` with ``r`` reflect-101 pixels added on every side (float32), and the mean."""
    import cv2

    src = np.asarray(t, dtype=np.float32)
    m = np.float32(src.mean(dtype=np.float64))
    return cv2.copyMakeBorder(src - m, r, r, r, r, cv2.BORDER_REFLECT_101), m


def _blur_padded(xp: np.ndarray, r: int, h: int, w: int, sigma: float) -> np.ndarray:
    import scipy.fft

    # FFT sizes with small prime factors; the zeros beyond the reflect padding are never reached by the kernel
    hp, wp = (scipy.fft.next_fast_len(n, real=True) for n in xp.shape)
    spec = scipy.fft.rfft2(xp, s=(hp, wp), workers=1)
    spec *= _kernel_spectrum(hp, wp, float(sigma))
    return scipy.fft.irfft2(spec, s=(hp, wp), workers=1)[r:r + h, r:r + w]


def gaussian_background(t: np.ndarray, sigma: float = SIGMA, method: str = "fft") -> np.ndarray:
    """``B = G_sigma * T`` with reflect-101 borders, float32 (same size as ``t``).

    ``method="fft"`` (default): the image, less its mean, is padded by the kernel radius with reflect-101
    pixels and convolved by FFT; the padding is wide enough that the periodic wrap never reaches the output, so
    this is the same linear convolution as the direct one (float32 error about 1e-6 C). ``method="direct"``:
    OpenCV's separable ``GaussianBlur`` (float32 accumulation, error about 2e-5 C).
    """
    src = np.ascontiguousarray(t, dtype=np.float32)
    if sigma <= 0:
        return src.copy()
    r = kernel_radius(sigma)
    if method == "direct":
        import cv2

        k = 2 * r + 1
        return cv2.GaussianBlur(src, (k, k), sigmaX=float(sigma), sigmaY=float(sigma),
                                borderType=cv2.BORDER_REFLECT_101)
    if method != "fft":
        raise ValueError(f"unknown method {method!r}; use 'fft' or 'direct'")
    h, w = src.shape
    xp, m = _centred_padded(src, r)
    out = _blur_padded(xp, r, h, w, sigma)
    out += m
    return out


def local_deviation(t: np.ndarray, sigma: float = SIGMA) -> np.ndarray:
    """``dT = T - B``: the temperature minus its Gaussian background (float32)."""
    src = np.ascontiguousarray(t, dtype=np.float32)
    if sigma <= 0:
        return np.zeros_like(src)
    r = kernel_radius(sigma)
    h, w = src.shape
    xp, _ = _centred_padded(src, r)
    # (T - m) - G * (T - m) = T - G * T: the mean cancels (the kernel sums to 1)
    return np.subtract(xp[r:r + h, r:r + w], _blur_padded(xp, r, h, w, sigma))


def fast_percentile(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear method) for a large array, computed from a candidate subset.

    The answer interpolates the order statistics of ranks ``floor(r)`` and ``floor(r) + 1`` with
    ``r = q / 100 * (n - 1)``. A threshold from a strided subsample selects the values above it; when at least
    ``n - floor(r)`` values pass, both order statistics are among them and are found by partitioning only those.
    """
    a = np.asarray(values).ravel()
    n = a.size
    if n == 0:
        raise ValueError("percentile of an empty array")
    r = q / 100.0 * (n - 1)
    lo = int(np.floor(r))
    frac = r - lo
    need = n - lo  # values at or above the lo-th order statistic
    if n < 20000 or need > n // 8:
        return float(np.percentile(a, q))
    step = max(1, n // 4096)
    sample = a[::step]
    # a threshold that about 2x the needed count exceeds, so the candidates almost surely contain both ranks
    k = max(0, sample.size - 1 - int(2 * need / n * sample.size) - 2)
    thr = np.partition(sample, k)[k]
    cand = a[a >= thr]
    if cand.size < need + 1 or not np.isfinite(thr):
        return float(np.percentile(a, q))
    # ranks within the candidates (sorted ascending): the lo-th overall is the (lo - (n - m))-th candidate
    m = cand.size
    j = lo - (n - m)
    if j < 0:
        return float(np.percentile(a, q))
    hi_j = min(j + 1, m - 1)
    part = np.partition(cand, (j, hi_j))
    v0, v1 = float(part[j]), float(part[hi_j])
    return v0 + (v1 - v0) * frac if frac else v0


def clip_scale(dt: np.ndarray, percentile: float = PERCENTILE, floor: float = FLOOR) -> float:
    """``p_clip = max(percentile_99(|dT|), floor)``."""
    return max(fast_percentile(np.abs(dt), percentile), float(floor))


def c2_from_deviation(dt: np.ndarray, percentile: float = PERCENTILE, floor: float = FLOOR) -> np.ndarray:
    """``C2 = clip(dT / (2 p_clip) + 0.5, 0, 1)`` (float32) from a precomputed deviation ``dT``."""
    p = clip_scale(dt, percentile, floor)
    out = np.asarray(dt, dtype=np.float32) * np.float32(1.0 / (2.0 * p))
    out += np.float32(0.5)
    return np.clip(out, 0.0, 1.0, out=out)


def c2(temperature_c: np.ndarray, sigma: float = SIGMA, percentile: float = PERCENTILE,
       floor: float = FLOOR) -> np.ndarray:
    """C2 of a temperature map in C: float32 HxW in 0..1, neutral 0.5 (see the module docstring)."""
    return c2_from_deviation(local_deviation(temperature_c, sigma), percentile, floor)


def to_uint8(c: np.ndarray) -> np.ndarray:
    """``round(255 * C2)`` as uint8 (round half to even)."""
    out = np.asarray(c, dtype=np.float32) * np.float32(255.0)
    np.rint(out, out=out)
    return out.astype(np.uint8)


def c2_uint8(temperature_c: np.ndarray, sigma: float = SIGMA, percentile: float = PERCENTILE,
             floor: float = FLOOR) -> np.ndarray:
    """``round(255 * C2)`` as uint8 HxW: what the prepared cache stores and detectors read."""
    return to_uint8(c2(temperature_c, sigma, percentile, floor))


def contrast_amplitude(c: np.ndarray, box: tuple[float, float, float, float] | np.ndarray) -> float:
    """Mean ``|C2 - 0.5|`` over the pixels a box ``(x1, y1, x2, y2)`` covers (NaN when it covers none).

    A pixel ``(i, j)`` is covered when its centre ``(j + 0.5, i + 0.5)`` lies inside the box.
    """
    x1, y1, x2, y2 = (float(v) for v in box)
    h, w = c.shape
    j0, j1 = max(int(np.ceil(x1 - 0.5)), 0), min(int(np.ceil(x2 - 0.5)), w)
    i0, i1 = max(int(np.ceil(y1 - 0.5)), 0), min(int(np.ceil(y2 - 0.5)), h)
    if j1 <= j0 or i1 <= i0:
        return float("nan")
    return float(np.abs(c[i0:i1, j0:j1].astype(np.float64) - 0.5).mean())
