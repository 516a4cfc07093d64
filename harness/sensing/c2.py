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

Missing temperatures (NaN or +-inf: masked or dead pixels) are left out, never read as zero. With the validity
mask ``M`` (1 where ``T`` is finite), the background is the normalised convolution over valid pixels (the way
astropy's ``convolve`` interpolates NaN)::

    B(x)   = (G_sigma * (T M))(x) / (G_sigma * M)(x)
    p_clip = max(percentile_99(|dT| over valid pixels), 0.05 C)
    C2(x)  = 0.5 where T(x) is missing (neutral: no contrast), else as above

A map whose every pixel is finite takes the unmasked code path unchanged (the test costs one mean, which the
FFT background computes anyway), so its output is bit for bit what it was. A map with no valid pixel, or with
more than ``MAX_INVALID_FRACTION`` of its pixels missing, is a ``DataError`` naming the map. ``check_map``
refuses what is not a real-valued 2-D map (empty, 1-D, 3-D, complex, boolean, or integers beyond float32's
exact range) with one message saying what was expected.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from harness.errors import DataError

SIGMA = 11.0
PERCENTILE = 99.0
FLOOR = 0.05  # C
#: A map with more than this fraction of missing (non-finite) pixels is refused: its contrast would rest on too
#: few measurements to compare with the others.
MAX_INVALID_FRACTION = 0.5
#: Integers at or below this magnitude are exact in float32.
_FLOAT32_EXACT_INT = 2 ** 24


def _named(name: str | None) -> str:
    return f"{name}: " if name else ""


def check_map(temperature_c: object, name: str | None = None) -> np.ndarray:
    """``temperature_c`` as a float32 HxW array, or a ``DataError`` saying what was expected.

    Accepted: a non-empty 2-D array of real numbers (float, or integers exact in float32). Refused: empty,
    1-D, 3-D, complex, boolean or object arrays, integers beyond +-2**24 and floats beyond float32's range.
    Non-finite values are allowed here (they are missing pixels; see ``valid_mask``). An empty map must be refused
    before it reaches OpenCV: ``copyMakeBorder`` with a reflect-101 border never returns on a zero-length axis
    (its reflection loop cannot land inside an empty range), which made ``c2_uint8`` hang.
    """
    what = f"{_named(name)}expected a non-empty 2-D (HxW) temperature map in C of real numbers"
    try:
        a = np.asarray(temperature_c)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{what}; cannot read it as an array ({exc})") from None
    if a.dtype.kind not in "fiu":
        kinds = {"c": "complex", "b": "boolean", "O": "object", "U": "text", "S": "bytes"}
        kind = kinds.get(a.dtype.kind, a.dtype.name)
        raise DataError(f"{what}, got {kind} values (dtype {a.dtype.name})")
    if a.ndim != 2:
        raise DataError(f"{what}, got {a.ndim}-D shape {tuple(a.shape)}")
    if a.size == 0:
        raise DataError(f"{what}, got the empty shape {tuple(a.shape)}")
    if a.dtype.kind in "iu" and a.dtype.itemsize > 2:
        lo, hi = int(a.min()), int(a.max())
        if max(-lo, hi) > _FLOAT32_EXACT_INT:
            raise DataError(f"{what}, got integers {lo}..{hi}, beyond float32's exact range (+-2**24); "
                            "convert the counts to C first")
    elif a.dtype.kind == "f" and a.dtype.itemsize > 4:
        finite = a[np.isfinite(a)] if not np.isfinite(a.sum()) else a
        big = float(np.abs(finite).max()) if finite.size else 0.0
        if big > float(np.finfo(np.float32).max):
            raise DataError(f"{what}, got a value of magnitude {big:.3g}, beyond float32's range")
    return np.ascontiguousarray(a, dtype=np.float32)


def _finite_sum(a: np.ndarray) -> bool:
    """Whether ``a`` has no NaN or inf, from one float64 sum (which a finite float32 array cannot overflow)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return bool(np.isfinite(a.sum(dtype=np.float64)))


def valid_mask(t: np.ndarray, name: str | None = None,
               max_invalid_fraction: float = MAX_INVALID_FRACTION) -> np.ndarray:
    """``isfinite(t)``, after checking that at least one pixel, and at least ``1 - max_invalid_fraction`` of
    them, is valid (else a ``DataError`` naming the map and the count)."""
    mask = np.isfinite(t)
    n, bad = mask.size, int(mask.size - np.count_nonzero(mask))
    if bad == n:
        raise DataError(f"{_named(name)}no valid temperature: all {n} pixels are NaN or infinite")
    if bad > max_invalid_fraction * n:
        raise DataError(f"{_named(name)}{bad} of {n} pixels ({100.0 * bad / n:.1f} %) are NaN or infinite, more than "
                        f"the {100.0 * max_invalid_fraction:g} % a temperature map may miss")
    return mask


def invalid_count(temperature_c: np.ndarray) -> int:
    """How many pixels of a temperature map are missing (NaN or infinite)."""
    t = np.asarray(temperature_c)
    if t.dtype.kind != "f" or _finite_sum(t):
        return 0
    return int(t.size - np.count_nonzero(np.isfinite(t)))


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
    with np.errstate(invalid="ignore", over="ignore"):  # NaN when a pixel is missing (the caller checks)
        m = np.float32(src.mean(dtype=np.float64))
        centred = src - m
    return cv2.copyMakeBorder(centred, r, r, r, r, cv2.BORDER_REFLECT_101), m


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
    OpenCV's separable ``GaussianBlur`` (float32 accumulation, error about 2e-5 C). A map with missing pixels
    gets the normalised convolution over its valid pixels whichever the method.
    """
    src = check_map(t)
    if sigma <= 0:
        return src.copy()
    r = kernel_radius(sigma)
    if not _finite_sum(src):  # some pixel is missing: normalised convolution
        return _masked_background(src, valid_mask(src), sigma)
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


def _masked_background(src: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``B = G * (T M) / G * M`` (float32; meaningful where ``G * M > 0``, which holds at every valid pixel).

    ``T`` is centred on the valid mean first (as in the unmasked path); both blurs share one FFT of the two stacked
    reflect-padded planes."""
    import cv2
    import scipy.fft

    r = kernel_radius(sigma)
    h, w = src.shape
    m = np.float32(src[mask].mean(dtype=np.float64))
    planes = (np.where(mask, src - m, np.float32(0)), mask.astype(np.float32))
    hp, wp = (scipy.fft.next_fast_len(n + 2 * r, real=True) for n in (h, w))
    padded = np.zeros((2, hp, wp), np.float32)  # the FFT size at once: no further copy to pad it
    for k, plane in enumerate(planes):
        padded[k, :h + 2 * r, :w + 2 * r] = cv2.copyMakeBorder(plane, r, r, r, r, cv2.BORDER_REFLECT_101)
    spec = scipy.fft.rfft2(padded, workers=1)
    spec *= _kernel_spectrum(hp, wp, float(sigma))
    num, den = scipy.fft.irfft2(spec, s=(hp, wp), workers=1)[:, r:r + h, r:r + w]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = num / np.maximum(den, np.float32(1e-12))
    out += m
    return out.astype(np.float32, copy=False)


def _deviation(src: np.ndarray, sigma: float, name: str | None) -> tuple[np.ndarray, np.ndarray | None]:
    """``(dT, mask)`` of a checked float32 map: ``mask`` is ``None`` when every pixel is finite (the unmasked
    path), else the validity mask, and ``dT`` is NaN at the missing pixels."""
    if sigma <= 0:
        mask = None if _finite_sum(src) else valid_mask(src, name)
        out = np.zeros_like(src)
        if mask is not None:
            out[~mask] = np.nan
        return out, mask
    r = kernel_radius(sigma)
    h, w = src.shape
    xp, m = _centred_padded(src, r)
    if not np.isfinite(m):  # some pixel is missing (the mean of a finite float32 map cannot overflow in float64)
        mask = valid_mask(src, name)
        dt = src - _masked_background(src, mask, sigma)
        dt[~mask] = np.nan
        return dt, mask
    # (T - m) - G * (T - m) = T - G * T: the mean cancels (the kernel sums to 1)
    return np.subtract(xp[r:r + h, r:r + w], _blur_padded(xp, r, h, w, sigma)), None


def local_deviation(t: np.ndarray, sigma: float = SIGMA, name: str | None = None) -> np.ndarray:
    """``dT = T - B``: the temperature minus its Gaussian background (float32); NaN where ``T`` is missing."""
    return _deviation(check_map(t, name), sigma, name)[0]


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
    """``p_clip = max(percentile_99(|dT|), floor)``, the percentile over the finite values of ``dT``."""
    a = np.abs(dt)
    if not _finite_sum(a):
        a = a[np.isfinite(a)]
        if a.size == 0:
            raise DataError("no valid temperature deviation to take the clip percentile of")
    return max(fast_percentile(a, percentile), float(floor))


def _scaled(dt: np.ndarray, p: float) -> np.ndarray:
    out = np.asarray(dt, dtype=np.float32) * np.float32(1.0 / (2.0 * p))
    out += np.float32(0.5)
    return np.clip(out, 0.0, 1.0, out=out)


def c2_from_deviation(dt: np.ndarray, percentile: float = PERCENTILE, floor: float = FLOOR) -> np.ndarray:
    """``C2 = clip(dT / (2 p_clip) + 0.5, 0, 1)`` (float32) from a precomputed deviation ``dT``; pixels where
    ``dT`` is not finite (missing temperature) get the neutral 0.5."""
    out = _scaled(dt, clip_scale(dt, percentile, floor))
    if not _finite_sum(out):
        out[~np.isfinite(out)] = np.float32(0.5)
    return out


def c2(temperature_c: np.ndarray, sigma: float = SIGMA, percentile: float = PERCENTILE,
       floor: float = FLOOR, name: str | None = None) -> np.ndarray:
    """C2 of a temperature map in C: float32 HxW in 0..1, neutral 0.5 (see the module docstring); ``name`` (a
    file or sample) is named in errors."""
    dt, mask = _deviation(check_map(temperature_c, name), sigma, name)
    if mask is None:
        return _scaled(dt, max(fast_percentile(np.abs(dt), percentile), float(floor)))
    out = _scaled(dt, max(fast_percentile(np.abs(dt[mask]), percentile), float(floor)))
    out[~mask] = np.float32(0.5)
    return out


def to_uint8(c: np.ndarray) -> np.ndarray:
    """``round(255 * C2)`` as uint8 (round half to even)."""
    out = np.asarray(c, dtype=np.float32) * np.float32(255.0)
    np.rint(out, out=out)
    return out.astype(np.uint8)


def c2_uint8(temperature_c: np.ndarray, sigma: float = SIGMA, percentile: float = PERCENTILE,
             floor: float = FLOOR, name: str | None = None) -> np.ndarray:
    """``round(255 * C2)`` as uint8 HxW: what the prepared cache stores and detectors read (missing pixels 128)."""
    return to_uint8(c2(temperature_c, sigma, percentile, floor, name))


def contrast_amplitude(c: np.ndarray, box: tuple[float, float, float, float] | np.ndarray,
                       valid: np.ndarray | None = None) -> float:
    """Mean ``|C2 - 0.5|`` over the pixels a box ``(x1, y1, x2, y2)`` covers (NaN when it covers none).

    A pixel ``(i, j)`` is covered when its centre ``(j + 0.5, i + 0.5)`` lies inside the box. With ``valid`` (the
    map's validity mask) only covered pixels with a measured temperature count (NaN when none has one).
    """
    x1, y1, x2, y2 = (float(v) for v in box)
    h, w = c.shape
    j0, j1 = max(int(np.ceil(x1 - 0.5)), 0), min(int(np.ceil(x2 - 0.5)), w)
    i0, i1 = max(int(np.ceil(y1 - 0.5)), 0), min(int(np.ceil(y2 - 0.5)), h)
    if j1 <= j0 or i1 <= i0:
        return float("nan")
    a = np.abs(c[i0:i1, j0:j1].astype(np.float64) - 0.5)
    if valid is not None:
        a = a[valid[i0:i1, j0:j1]]
        if a.size == 0:
            return float("nan")
    return float(a.mean())
