"""C2 with missing temperatures (NaN, inf) and malformed maps: missing pixels are left out, never read as zero."""

from __future__ import annotations

import time

import numpy as np
import pytest

from harness.errors import DataError
from harness.sensing import c2 as c2mod
from harness.sensing.analyses import box_amplitudes


def scene(h: int = 160, w: int = 200, seed: int = 0, noise: float = 0.3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    t = 20 + 0.02 * xx + 4 * np.exp(-((xx - 80) ** 2 + (yy - 60) ** 2) / 300) + rng.normal(0, noise, (h, w))
    return t.astype(np.float32)


def masked_reference(t: np.ndarray, sigma: float = 11.0, percentile: float = 99.0, floor: float = 0.05) -> np.ndarray:
    """An independent C2 over valid pixels: SciPy's Gaussian filter of T*M and of M (mirror border = reflect-101),
    their ratio as background, NumPy's percentile over the valid |dT|, neutral 0.5 at missing pixels (float64)."""
    import scipy.ndimage as ndi

    m = np.isfinite(t)
    tz = np.where(m, t, 0).astype(np.float64)
    num = ndi.gaussian_filter(tz, sigma, mode="mirror", truncate=4.0)
    den = ndi.gaussian_filter(m.astype(np.float64), sigma, mode="mirror", truncate=4.0)
    dt = tz - num / den
    p = max(float(np.percentile(np.abs(dt[m]), percentile)), floor)
    c = np.clip(dt / (2 * p) + 0.5, 0, 1)
    c[~m] = 0.5
    return np.rint(c * 255).astype(np.uint8)


def test_one_percent_nan_matches_an_independent_masked_reference_within_one_grey_level():
    t = scene()
    rng = np.random.default_rng(1)
    holes = rng.random(t.shape) < 0.01
    t[holes] = np.nan
    ours = c2mod.c2_uint8(t)
    ref = masked_reference(t)
    valid = ~holes
    assert np.abs(ours[valid].astype(int) - ref[valid].astype(int)).max() <= 1
    assert (ours[holes] == 128).all()  # missing pixels are neutral, not zero
    # not a near-empty channel: contrast survives on the valid pixels
    assert np.abs(ours[valid].astype(int) - 128).mean() > 10


def test_one_nan_changes_c2_only_within_the_kernel_radius_of_that_pixel():
    t = scene(noise=0.005)  # P99(|dT|) stays under the floor, so p_clip is the same with or without the hole
    clean = c2mod.c2(t)
    y, x = 90, 120
    t1 = t.copy()
    t1[y, x] = np.nan
    holed = c2mod.c2(t1)
    r = c2mod.kernel_radius(c2mod.SIGMA)
    diff = np.abs(holed.astype(np.float64) - clean)
    near = np.zeros(t.shape, bool)
    near[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1] = True
    assert diff[~near].max() < 1e-4  # float32 FFT noise only
    assert diff[near].max() > 1e-2  # the hole shows around itself
    assert holed[y, x] == 0.5


def test_inf_is_treated_like_nan():
    t = scene()
    t_nan, t_inf = t.copy(), t.copy()
    t_nan[10:14, 30:33] = np.nan
    t_inf[10:14, 30:33] = np.inf
    t_inf[100, 150] = -np.inf
    t_nan[100, 150] = np.nan
    assert np.array_equal(c2mod.c2_uint8(t_inf), c2mod.c2_uint8(t_nan))


@pytest.mark.parametrize(
    "bad, expected",
    [
        (np.zeros((0, 0), np.float32), "empty shape (0, 0)"),
        (np.zeros((0, 640), np.float32), "empty shape (0, 640)"),
        (np.zeros(10, np.float32), "1-D shape (10,)"),
        (np.zeros((4, 5, 3), np.float32), "3-D shape (4, 5, 3)"),
        (np.zeros((4, 5), np.complex64), "complex"),
        (np.full((4, 5), 2**40, np.int64), "beyond float32's exact range"),
        (np.full((4, 5), 1e300), "beyond float32's range"),
        (np.zeros((4, 5), bool), "boolean"),
    ],
)
def test_malformed_maps_get_one_clear_error_quickly(bad, expected):
    t0 = time.perf_counter()
    with pytest.raises(DataError) as exc:
        c2mod.c2_uint8(bad, name="frame_0007.tif")
    assert time.perf_counter() - t0 < 0.5
    msg = str(exc.value)
    assert msg.startswith("frame_0007.tif: expected a non-empty 2-D (HxW) temperature map")
    assert expected in msg


def test_maps_with_no_or_too_few_valid_pixels_are_errors_naming_the_map():
    with pytest.raises(DataError, match=r"^a\.tif: no valid temperature: all 20 pixels"):
        c2mod.c2_uint8(np.full((4, 5), np.nan, np.float32), name="a.tif")
    t = scene(40, 50)
    t[:30] = np.nan  # 60 % missing
    with pytest.raises(DataError, match=r"^b\.tif: 1500 of 2000 pixels \(75\.0 %\) are NaN or infinite, more than"):
        c2mod.c2_uint8(t, name="b.tif")


def test_integer_maps_within_float32_range_are_accepted():
    t = np.rint(scene(40, 50) * 100).astype(np.int32)
    assert np.array_equal(c2mod.c2_uint8(t), c2mod.c2_uint8(t.astype(np.float32)))


def test_box_amplitude_averages_only_measured_pixels():
    t = scene()
    box = np.array([[60, 40, 100, 80]], np.float32)
    t1 = t.copy()
    t1[40:80, 60:80] = np.nan  # half of the box is missing
    amps = box_amplitudes(t1, box, shifts=(2,), name="holed")
    c = c2mod.c2(t1)
    valid = np.isfinite(t1)
    assert amps[0, 0] == pytest.approx(np.abs(c[40:80, 60:100][valid[40:80, 60:100]] - 0.5).mean())
    assert amps[0, 0] > 0.5 * box_amplitudes(t, box, shifts=(2,))[0, 0]  # not diluted by neutral pixels
    assert np.isfinite(amps).all()
