"""The stored C2 stays byte for byte what it was: the workspace FFT against a frozen copy of the previous code
(``tests/c2_reference.py``) on synthetic and real frames, clean and with missing pixels, the cached
``G * M`` of a recurring mask, the public-SciPy fallback, threads; and huge finite temperatures give a finite,
exact C2 instead of NaN."""

from __future__ import annotations

import threading
import warnings

import numpy as np
import pytest

import c2_reference as ref
from conftest import SHARED
from harness.sensing import c2 as c2mod

REAL = [SHARED / "data" / "dji-m3t-rjpeg" / f"m3t_{k}.jpg" for k in "abc"]
SDK_TEMPERATURES = SHARED / "data" / "dji-rjpeg-cameras" / "m3td_hirp_a_reference.npz"


def scene(h: int = 128, w: int = 160, seed: int = 0, noise: float = 0.15) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    t = 26 + 0.01 * xx + 3 * np.exp(-((xx - w / 2) ** 2 + (yy - h / 3) ** 2) / 300) + rng.normal(0, noise, (h, w))
    return t.astype(np.float32)


def variants(t: np.ndarray, seed: int = 1) -> dict[str, np.ndarray]:
    """The map, and the map with 1 % NaN, 1 % +-inf, a missing block and one missing pixel."""
    rng = np.random.default_rng(seed)
    out = {"clean": t}
    holes = t.copy()
    holes[rng.random(t.shape) < 0.01] = np.nan
    out["1% NaN"] = holes
    infs = t.copy()
    infs[rng.random(t.shape) < 0.005] = np.inf
    infs[rng.random(t.shape) < 0.005] = -np.inf
    out["1% inf"] = infs
    block = t.copy()
    block[: t.shape[0] // 3, : t.shape[1] // 4] = np.nan
    out["block"] = block
    one = t.copy()
    one[t.shape[0] // 2, t.shape[1] // 3] = np.nan
    out["one pixel"] = one
    return out


def assert_same_as_reference(t: np.ndarray, sigma: float = 11.0) -> None:
    assert np.array_equal(c2mod.c2_uint8(t, sigma=sigma), ref.c2_uint8(t, sigma=sigma))
    assert np.array_equal(c2mod.c2(t, sigma=sigma), ref.c2(t, sigma=sigma))
    dev = ref.deviation(t, sigma)[0]
    dev[~np.isfinite(t)] = np.nan
    assert np.array_equal(c2mod.local_deviation(t, sigma=sigma), dev, equal_nan=True)
    assert np.array_equal(c2mod.gaussian_background(t, sigma), ref.gaussian_background(t, sigma))


@pytest.mark.parametrize("shape, seed", [((128, 160), 0), ((97, 131), 1), ((60, 75), 3), ((40, 30), 2)])
def test_synthetic_frames_byte_for_byte_clean_and_masked(shape, seed):
    for name, t in variants(scene(*shape, seed=seed)).items():
        for sigma in (11.0, 3.0):
            assert_same_as_reference(t, sigma), (name, sigma)


@pytest.mark.skipif(not all(p.exists() for p in REAL), reason="shared R-JPEG samples not present")
def test_real_dji_frames_byte_for_byte_clean_and_masked():
    from harness.sensing.radiometry import read_thermal

    frames = [read_thermal(p)[0] for p in REAL]
    if SDK_TEMPERATURES.exists():
        frames.append(np.load(SDK_TEMPERATURES)["temp_c"].astype(np.float32))
    for t in frames:
        assert t.shape == (512, 640)
        for name, v in variants(np.ascontiguousarray(t, np.float32)).items():
            assert np.array_equal(c2mod.c2_uint8(v), ref.c2_uint8(v)), name


def test_recurring_and_changing_masks_use_the_right_normaliser():
    """``G * M`` is kept for the last few masks: a second frame with the same mask, frames with other masks (more
    than are kept), the first mask again and another frame size in between all give the reference bytes."""
    a, b = scene(seed=3), scene(seed=4)
    rng = np.random.default_rng(7)
    m1, m2 = rng.random(a.shape) < 0.01, rng.random(a.shape) < 0.01
    small = scene(60, 70, seed=5)
    small[3, 4] = np.nan
    more = [rng.random(a.shape) < 0.01 for _ in range(c2mod.KEPT_MASKS + 2)]  # more masks than are kept
    for t, m in (
        (a, m1),
        (b, m1),
        (b, m2),
        (small, None),
        (a, m1),
        (a, None),
        (b, m2),
        *((a, x) for x in more),
        *((b, x) for x in more),
        (a, m1),
    ):
        x = t.copy()
        if m is not None:
            x[m] = np.nan
        assert np.array_equal(c2mod.c2_uint8(x), ref.c2_uint8(x))


def test_the_public_scipy_route_gives_the_same_bytes(monkeypatch):
    """Where SciPy's pocketfft binding is missing or differs, the public ``rfft2`` / ``irfft2`` are used."""
    monkeypatch.setattr(c2mod, "_pocketfft", lambda: None)
    monkeypatch.setattr(c2mod, "_threads", threading.local())
    for t in variants(scene(seed=6)).values():
        assert np.array_equal(c2mod.c2_uint8(t), ref.c2_uint8(t))


def test_threads_do_not_share_buffers():
    frames = [v for s in range(4) for v in variants(scene(seed=10 + s)).values()]
    expected = [ref.c2_uint8(t) for t in frames]
    results: dict[int, list[bool]] = {}

    def work(k: int) -> None:
        results[k] = [np.array_equal(c2mod.c2_uint8(t), e) for _ in range(3) for t, e in zip(frames, expected)]

    threads = [threading.Thread(target=work, args=(k,)) for k in range(3)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert all(all(v) for v in results.values()) and len(results) == 3


def _float64_reference(t: np.ndarray) -> np.ndarray:
    import scipy.ndimage as ndi

    t64 = t.astype(np.float64)
    dt = t64 - ndi.gaussian_filter(t64, 11.0, mode="mirror", truncate=4.0)
    p = max(float(np.percentile(np.abs(dt), 99)), 0.05)
    return np.rint(np.clip(dt / (2 * p) + 0.5, 0, 1) * 255).astype(np.uint8)


def test_huge_finite_temperatures_give_a_finite_exact_c2_without_warnings():
    """A map scaled by 2**122 overflowed the transforms (NaN everywhere, cast to 0 with a RuntimeWarning); scaling
    by a power of two is exact, so its C2 is now byte for byte that of the unscaled map. A single pixel near
    float32's maximum lands within one grey level of a float64 computation."""
    t = scene(seed=8)
    huge = t * np.float32(2.0**122)
    spike = t.copy()
    spike[40, 50] = np.float32(3e38)
    holed = huge.copy()
    holed[5, 5] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.array_equal(c2mod.c2_uint8(huge), c2mod.c2_uint8(t))
        assert np.array_equal(c2mod.c2_uint8(holed), c2mod.c2_uint8(np.where(np.isnan(holed), np.nan, t)))
        got = c2mod.c2_uint8(spike)
        assert np.isfinite(c2mod.local_deviation(huge)).all()
        assert np.isfinite(c2mod.gaussian_background(spike)).all()
    assert np.abs(got.astype(int) - _float64_reference(spike).astype(int)).max() <= 1
    assert got[40, 50] == 255
