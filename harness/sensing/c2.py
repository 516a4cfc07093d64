"""C2: the signed local radiometric contrast channel, exactly as the seed defines it.

::

    B(x)   = (G_sigma * T)(x)                 Gaussian background, sigma = 11 px, T in C (float)
    dT(x)  = T(x) - B(x)
    p_clip = max(percentile_99(|dT|), 0.05 C)
    C2(x)  = clip(dT(x) / (2 p_clip) + 0.5, 0, 1)      neutral = 0.5; stored as round(255 * C2) uint8

Implementation notes (all exact, not approximations):

* The Gaussian has radius ``int(4 sigma + 0.5)`` taps each side (89 taps at sigma 11) and reflect-101 borders
  (``cv2.BORDER_REFLECT_101``, the same as ``scipy.ndimage.gaussian_filter(mode="mirror", truncate=4.0)``);
  it runs as an FFT convolution of the reflect-padded, mean-centred image (float32 throughout; the padding is
  wider than the kernel, so the periodic wrap never reaches the output). On one thread this is faster than
  OpenCV's separable float32 filter (about 1.7 ms against 3.2 ms for a 640x512 frame) and closer to a float64
  reference (the uint8 C2 of the real frames differs from it on 2-11 pixels, against 7-74 for the separable
  filter); a recursive Gaussian would only approximate the kernel. The transforms run in a per-thread workspace
  allocated once per frame size
  (no fresh multi-megabyte buffers, hence no page faults, per frame); the reflected rows' forward transforms are
  copies of the rows they reflect, and the inverse transform's last pass runs only over the rows that are kept.
  Each line is transformed with the same arithmetic as in ``scipy.fft.rfft2`` / ``irfft2``, so the uint8 C2 is
  byte for byte what the plain SciPy calls give (``tests/c2_reference.py`` keeps that code).
* ``percentile_99`` is NumPy's default (linear interpolation between order statistics). ``fast_percentile``
  finds the two order statistics among a small candidate set above a threshold taken from a strided subsample
  and falls back to a full selection when the candidates might not contain them, so the order statistics are
  exactly NumPy's at a fraction of the cost (their interpolation is done in float64).
* ``round`` is round-half-to-even (NumPy's ``rint``, Python's ``round``); a flat image maps to 127.5 -> 128.
* A map whose values are so large that the transforms could overflow float32 (a deviation from the mean above
  2**64) is scaled by a power of two first, and the floor with it: power-of-two scaling is exact in floating
  point, so C2 is what an overflow-free computation gives, never NaN.

Missing temperatures (NaN or +-inf: masked or dead pixels) are left out, never read as zero. With the validity
mask ``M`` (1 where ``T`` is finite), the background is the normalised convolution over valid pixels (the way
astropy's ``convolve`` interpolates NaN)::

    B(x)   = (G_sigma * (T M))(x) / (G_sigma * M)(x)
    p_clip = max(percentile_99(|dT| over valid pixels), 0.05 C)
    C2(x)  = 0.5 where T(x) is missing (neutral: no contrast), else as above

Both planes share the transforms (one call per pass). ``G_sigma * M`` depends only on the mask, so the last
few masks' are kept per thread: frames with the same missing pixels (a sensor's dead pixels, a fixed no-data
border) pay for one plane, about 1.3x the clean path; a mask never seen costs the second plane, about 2x. A map
whose every pixel is finite takes the unmasked code path (the test costs one mean, which the background needs
anyway). A map with no valid pixel, or with more than
``MAX_INVALID_FRACTION`` of its pixels missing, is a ``DataError`` naming the map. ``check_map`` refuses what is
not a real-valued 2-D map (empty, 1-D, 3-D, complex, boolean, or integers beyond float32's exact range) with one
message saying what was expected.
"""

from __future__ import annotations

import math
import threading
from functools import lru_cache
from typing import Any

import numpy as np

from harness.errors import DataError

SIGMA = 11.0
PERCENTILE = 99.0
FLOOR = 0.05  # C
#: A map with more than this fraction of missing (non-finite) pixels is refused: its contrast would rest on too
#: few measurements to compare with the others.
MAX_INVALID_FRACTION = 0.5
#: Integers at or below this magnitude are exact in float32.
_FLOAT32_EXACT_INT = 2**24


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
            raise DataError(
                f"{what}, got integers {lo}..{hi}, beyond float32's exact range (+-2**24); "
                "convert the counts to C first"
            )
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


def valid_mask(
    t: np.ndarray, name: str | None = None, max_invalid_fraction: float = MAX_INVALID_FRACTION
) -> np.ndarray:
    """``isfinite(t)``, after checking that at least one pixel, and at least ``1 - max_invalid_fraction`` of
    them, is valid (else a ``DataError`` naming the map and the count)."""
    mask = np.isfinite(t)
    n, bad = mask.size, int(mask.size - np.count_nonzero(mask))
    if bad == n:
        raise DataError(f"{_named(name)}no valid temperature: all {n} pixels are NaN or infinite")
    if bad > max_invalid_fraction * n:
        raise DataError(
            f"{_named(name)}{bad} of {n} pixels ({100.0 * bad / n:.1f} %) are NaN or infinite, more than "
            f"the {100.0 * max_invalid_fraction:g} % a temperature map may miss"
        )
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
    kr[: 2 * r + 1] = g
    kc[: 2 * r + 1] = g
    kr, kc = np.roll(kr, -r), np.roll(kc, -r)  # centre tap at index 0
    return (np.fft.fft(kc)[:, None] * np.fft.rfft(kr)[None, :]).astype(np.complex64)


# ------------------------------------------------------------------------------------------- FFT workspace
#: Largest deviation from the mean that is convolved unscaled: the unnormalised transforms of a map of N pixels
#: stay below N**2 times it, far from float32's 2**128 for any frame that fits in memory.
_SAFE_SPAN = 2.0**64
#: Masks whose normaliser ``G * M`` each thread keeps (per frame size): frames of a flight share their missing
#: pixels (dead pixels, a no-data border), and a few cameras may be interleaved.
KEPT_MASKS = 4


@lru_cache(maxsize=1)
def _pocketfft() -> Any | None:
    """SciPy's pocketfft binding, which takes output buffers and single axes, or ``None`` where it is missing or
    does not give exactly what ``scipy.fft.rfft2`` / ``irfft2`` give (then the public functions are used)."""
    try:
        import scipy.fft
        from scipy.fft._pocketfft import pypocketfft as pp

        rng = np.random.default_rng(0)
        pad = rng.normal(size=(2, 30, 27)).astype(np.float32)
        ref = scipy.fft.irfft2(scipy.fft.rfft2(pad, workers=1), s=(30, 27), workers=1)[:, 5:25]
        spec = np.empty((2, 30, 14), np.complex64)
        back = np.empty((2, 20, 27), np.float32)
        pp.r2c(pad, axes=(2,), forward=True, inorm=0, out=spec, nthreads=1)
        pp.c2c(spec, axes=(1,), forward=True, inorm=0, out=spec, nthreads=1)
        pp.c2c(spec, axes=(1,), forward=False, inorm=0, out=spec, nthreads=1)
        pp.c2r(spec[:, 5:25], axes=(2,), lastsize=27, forward=False, inorm=0, out=back, nthreads=1)
        back *= np.float32(1 / np.longdouble(30 * 27))
        same = np.array_equal(back, ref)
        return pp if same else None
    except Exception:  # noqa: BLE001 (any failure means: use the public functions)
        return None


class _Workspace:
    """Buffers for convolving ``h x w`` planes by the Gaussian of ``sigma``: the reflect-padded planes (zero beyond
    the padding), their spectra, the inverse transforms of the kept rows, a scratch plane, and the last
    ``KEPT_MASKS`` masks' ``max(G * M, 1e-12)``. One per thread and frame size, reused from frame to frame."""

    def __init__(self, h: int, w: int, sigma: float, planes: int):
        import scipy.fft

        self.h, self.w, self.sigma, self.r = h, w, sigma, kernel_radius(sigma)
        self.hp, self.wp = (scipy.fft.next_fast_len(n + 2 * self.r, real=True) for n in (h, w))
        self.spectrum = _kernel_spectrum(self.hp, self.wp, float(sigma))
        # irfft2's normalisation, as pocketfft computes it (1 / N in long double, then float32)
        self.fct = np.float32(1 / np.longdouble(self.hp * self.wp))
        self.pad = np.zeros((planes, self.hp, self.wp), np.float32)
        self.spec = np.empty((planes, self.hp, self.wp // 2 + 1), np.complex64)
        self.back = np.empty((planes, h, self.wp), np.float32)
        self.plane = np.empty((h, w), np.float32)
        #: the last masks' ``(missing count, mask, max(G * M, 1e-12))``, most recent first
        self.normalisers: list[tuple[int, np.ndarray, np.ndarray]] = []

    @property
    def planes(self) -> int:
        return self.pad.shape[0]

    def fill(self, k: int, plane: np.ndarray) -> None:
        """Plane ``k`` := ``plane`` with ``r`` reflect-101 pixels on every side."""
        import cv2

        r = self.r
        dst = self.pad[k, : self.h + 2 * r, : self.w + 2 * r]
        out = cv2.copyMakeBorder(plane, r, r, r, r, cv2.BORDER_REFLECT_101, dst=dst)
        if not np.shares_memory(out, dst):  # OpenCV allocated its own result
            dst[...] = out

    def blur(self, k: int) -> np.ndarray:
        """``G * plane`` for the first ``k`` planes: float32 ``(k, h, w)``, a view into the workspace that the next
        call overwrites. The same arithmetic as ``irfft2(rfft2(pad) * spectrum)`` (one line at a time either way)."""
        pad, spec, r, h, w = self.pad[:k], self.spec[:k], self.r, self.h, self.w
        pp = _pocketfft()
        if pp is None:
            import scipy.fft

            s = scipy.fft.rfft2(pad, workers=1)
            s *= self.spectrum
            return scipy.fft.irfft2(s, s=(self.hp, self.wp), workers=1)[:, r : r + h, r : r + w]
        back = self.back[:k]
        if h > r:  # the reflected rows' transforms are the transforms of the rows they copy
            pp.r2c(pad[:, r : r + h], axes=(2,), forward=True, inorm=0, out=spec[:, r : r + h], nthreads=1)
            if self.hp > h + 2 * r:  # zero rows below the padding
                pp.r2c(pad[:, h + 2 * r :], axes=(2,), forward=True, inorm=0, out=spec[:, h + 2 * r :], nthreads=1)
            spec[:, :r] = spec[:, 2 * r : r : -1]  # row r - i is row r + i
            spec[:, h + r : h + 2 * r] = spec[:, h + r - 2 : h - 2 : -1]  # row h + r - 1 + i is row h + r - 1 - i
        else:
            pp.r2c(pad, axes=(2,), forward=True, inorm=0, out=spec, nthreads=1)
        pp.c2c(spec, axes=(1,), forward=True, inorm=0, out=spec, nthreads=1)
        spec *= self.spectrum
        pp.c2c(spec, axes=(1,), forward=False, inorm=0, out=spec, nthreads=1)
        pp.c2r(spec[:, r : r + h], axes=(2,), lastsize=self.wp, forward=False, inorm=0, out=back, nthreads=1)
        out = back[:, :, r : r + w]
        out *= self.fct
        return out


_threads = threading.local()


def _workspace(h: int, w: int, sigma: float, planes: int) -> _Workspace:
    """This thread's workspace for the frame size (the last two sizes are kept), with at least ``planes`` planes."""
    kept: list[_Workspace] = getattr(_threads, "workspaces", None) or []
    ws = next((x for x in kept if (x.h, x.w, x.sigma) == (h, w, sigma)), None)
    if ws is None or ws.planes < planes:
        ws = _Workspace(h, w, sigma, max(planes, ws.planes if ws is not None else 1))
    _threads.workspaces = [ws] + [x for x in kept if (x.h, x.w, x.sigma) != (h, w, sigma)][:1]
    return ws


def _span_scale(lo: float, hi: float, m: float) -> float:
    """1, or the power of two that brings the largest deviation from the mean ``m`` down to ``_SAFE_SPAN``."""
    span = max(hi - m, m - lo)
    if span <= _SAFE_SPAN:
        return 1.0
    return 2.0 ** (round(math.log2(_SAFE_SPAN)) - math.ceil(math.log2(span)))


# --------------------------------------------------------------------------------------------- background
def _clean_background(src: np.ndarray, m: np.float32, ws: _Workspace) -> tuple[np.ndarray, np.ndarray]:
    """``(T - m, G * (T - m))`` of a map without missing pixels; the first is the workspace's scratch plane, the
    second a workspace view (both valid until the next call)."""
    centred = np.subtract(src, m, out=ws.plane)
    ws.fill(0, centred)
    return centred, ws.blur(1)[0]


def _masked_background(src: np.ndarray, mask: np.ndarray, m: np.float32, ws: _Workspace) -> np.ndarray:
    """``B = G * (T M) / G * M`` (float32; meaningful where ``G * M > 0``, which holds at every valid pixel), ``T``
    centred on the valid mean ``m`` first (as in the unmasked path). ``G * M`` of a mask seen among the last
    ``KEPT_MASKS`` is reused; otherwise both planes go through the same transforms."""
    missing = int(mask.size - np.count_nonzero(mask))
    plane = np.subtract(src, m, out=ws.plane)
    np.copyto(plane, np.float32(0), where=~mask)
    ws.fill(0, plane)
    kept = next((x for x in ws.normalisers if x[0] == missing and np.array_equal(x[1], mask)), None)
    if kept is not None:
        num, den = ws.blur(1)[0], kept[2]
        ws.normalisers.remove(kept)
    else:
        np.copyto(ws.plane, mask)
        ws.fill(1, ws.plane)
        num, den = ws.blur(2)
        den = np.maximum(den, np.float32(1e-12))
        kept = (missing, mask.copy(), den)
    ws.normalisers = [kept] + ws.normalisers[: KEPT_MASKS - 1]
    out = num / den
    out += m
    return out


def _prepared(
    src: np.ndarray, sigma: float, name: str | None
) -> tuple[np.ndarray, np.ndarray | None, float, np.float32, _Workspace]:
    """``(T', mask, s, mean, workspace)``: ``T' = s T`` with ``s`` a power of two (1 unless the map is huge),
    ``mask`` ``None`` when every pixel is finite, ``mean`` that of the valid pixels of ``T'`` (float32)."""
    h, w = src.shape
    with np.errstate(invalid="ignore", over="ignore"):
        m = np.float32(src.mean(dtype=np.float64))  # NaN when a pixel is missing (a finite map cannot overflow)
    mask = None
    if np.isfinite(m):
        lo, hi = float(src.min()), float(src.max())
        valid = src
    else:
        mask = valid_mask(src, name)
        valid = src[mask]
        m = np.float32(valid.mean(dtype=np.float64))
        lo, hi = float(valid.min()), float(valid.max())
    s = _span_scale(lo, hi, float(m))
    if s != 1.0:
        src = src * np.float32(s)  # exact: a power of two
        m = np.float32((src if mask is None else src[mask]).mean(dtype=np.float64))
    return src, mask, s, m, _workspace(h, w, float(sigma), 1 if mask is None else 2)


def _deviation(src: np.ndarray, sigma: float, name: str | None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """``(dT', mask, s)`` of a checked float32 map, with ``dT' = s dT`` (``s`` a power of two, 1 unless the map is
    huge): ``mask`` is ``None`` when every pixel is finite (the unmasked path), else the validity mask, and ``dT'``
    is 0 at the missing pixels. ``dT'`` is a new array the caller owns."""
    if sigma <= 0:
        mask = None if _finite_sum(src) else valid_mask(src, name)
        return np.zeros_like(src), mask, 1.0
    t, mask, s, m, ws = _prepared(src, sigma, name)
    if mask is None:
        # (T - m) - G * (T - m) = T - G * T: the mean cancels (the kernel sums to 1)
        return np.subtract(*_clean_background(t, m, ws)), None, s
    dt = np.subtract(t, _masked_background(t, mask, m, ws))
    np.copyto(dt, np.float32(0), where=~mask)
    return dt, mask, s


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
    if method not in ("fft", "direct"):
        raise ValueError(f"unknown method {method!r}; use 'fft' or 'direct'")
    if method == "direct" and _finite_sum(src):
        import cv2

        k = 2 * kernel_radius(sigma) + 1
        return cv2.GaussianBlur(
            src, (k, k), sigmaX=float(sigma), sigmaY=float(sigma), borderType=cv2.BORDER_REFLECT_101
        )
    t2, mask, s, m, ws = _prepared(src, sigma, None)
    out = _masked_background(t2, mask, m, ws) if mask is not None else np.add(_clean_background(t2, m, ws)[1], m)
    if s != 1.0:
        out *= np.float32(1.0 / s)
    return out


def local_deviation(t: np.ndarray, sigma: float = SIGMA, name: str | None = None) -> np.ndarray:
    """``dT = T - B``: the temperature minus its Gaussian background (float32); NaN where ``T`` is missing."""
    dt, mask, s = _deviation(check_map(t, name), sigma, name)
    if s != 1.0:
        dt *= np.float32(1.0 / s)
    if mask is not None:
        dt[~mask] = np.nan
    return dt


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


def c2(
    temperature_c: np.ndarray,
    sigma: float = SIGMA,
    percentile: float = PERCENTILE,
    floor: float = FLOOR,
    name: str | None = None,
) -> np.ndarray:
    """C2 of a temperature map in C: float32 HxW in 0..1, neutral 0.5 (see the module docstring); ``name`` (a
    file or sample) is named in errors. Computed in the deviation's own array (missing pixels have ``dT' = 0``,
    hence 0.5), which is returned: a new array the caller owns."""
    dt, mask, s = _deviation(check_map(temperature_c, name), sigma, name)
    a = np.abs(dt) if mask is None else np.abs(dt[mask])
    p = max(fast_percentile(a, percentile), float(floor) * s)  # both in the units of dT' = s dT
    del a
    dt *= np.float32(1.0 / (2.0 * p))
    dt += np.float32(0.5)
    return np.clip(dt, 0.0, 1.0, out=dt)


def _to_uint8_in_place(c: np.ndarray) -> np.ndarray:
    """``round(255 * c)`` as uint8, scaling the float32 array ``c`` itself on the way."""
    c *= np.float32(255.0)
    np.rint(c, out=c)
    return c.astype(np.uint8)


def to_uint8(c: np.ndarray) -> np.ndarray:
    """``round(255 * C2)`` as uint8 (round half to even)."""
    return _to_uint8_in_place(np.array(c, dtype=np.float32))


def c2_uint8(
    temperature_c: np.ndarray,
    sigma: float = SIGMA,
    percentile: float = PERCENTILE,
    floor: float = FLOOR,
    name: str | None = None,
) -> np.ndarray:
    """``round(255 * C2)`` as uint8 HxW: what the prepared cache stores and detectors read (missing pixels 128)."""
    return _to_uint8_in_place(c2(temperature_c, sigma, percentile, floor, name))


def contrast_amplitude(
    c: np.ndarray, box: tuple[float, float, float, float] | np.ndarray, valid: np.ndarray | None = None
) -> float:
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
