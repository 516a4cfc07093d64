"""C2 (the seed's signed local radiometric contrast) against hand-computed values, its invariances, and the
encodings registered by the built-in plugin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.api import AlignedSample
from harness.contracts import encode
from harness.errors import PluginError
from harness.sensing.c2 import (
    c2,
    c2_from_deviation,
    c2_uint8,
    clip_scale,
    contrast_amplitude,
    fast_percentile,
    gaussian_background,
    kernel_radius,
    local_deviation,
    to_uint8,
)


def _scene(h=64, w=80, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    t = 24.0 + 0.05 * xx + 2.0 * np.exp(-((xx - 30) ** 2 + (yy - 20) ** 2) / 40.0) - 1.5 * ((xx > 50) & (yy > 40))
    return (t + rng.normal(0, 0.1, (h, w))).astype(np.float32)


def test_deviation_to_c2_by_hand():
    dt = np.array([[-0.4, -0.1, 0.0], [0.1, 0.2, 0.4]], dtype=np.float32)
    # |dT| sorted: 0, .1, .1, .2, .4, .4; rank 0.99 * 5 = 4.95 -> .4 + .95 * (.4 - .4) = 0.4 = p_clip
    assert clip_scale(dt) == pytest.approx(0.4)
    expected = np.array([[0.0, 0.375, 0.5], [0.625, 0.75, 1.0]])  # dT / 0.8 + 0.5
    np.testing.assert_allclose(c2_from_deviation(dt), expected, atol=1e-6)
    # round(255 * C2), half to even: 95.625 -> 96, 127.5 -> 128, 159.375 -> 159, 191.25 -> 191
    np.testing.assert_array_equal(to_uint8(c2_from_deviation(dt)), [[0, 96, 128], [159, 191, 255]])


def test_values_beyond_the_clip_saturate_and_the_floor_holds():
    dt = np.full(101, 0.1, np.float32)
    dt[0] = -5.0
    dt[1] = 5.0  # two outliers in 101 values: sorted |dT| = 99 x .1, 5, 5, and rank 0.99 * 100 = 99 is a 5
    assert clip_scale(dt) == pytest.approx(5.0)
    dt[1] = 0.1  # one outlier: rank 99 of sorted |dT| (100 x .1, then 5) is 0.1
    assert clip_scale(dt) == pytest.approx(0.1)
    out = c2_from_deviation(dt)
    assert out[0] == 0.0 and out[2] == pytest.approx(1.0)  # -5 / 0.2 + .5 -> clipped; .1 / .2 + .5 = 1
    small = np.full(50, 0.01, np.float32)  # P99 = 0.01 < floor 0.05
    np.testing.assert_allclose(c2_from_deviation(small), 0.6, atol=1e-6)  # .01 / .1 + .5


def test_c2_of_an_impulse_by_hand_including_reflect_101_borders():
    # 5x5 at 20 C with +1 C at the centre, sigma = 0.5: radius int(4 * 0.5 + 0.5) = 2 taps each side,
    # weights exp(-k^2 / (2 * 0.25)) = exp(-2 k^2) normalised by S = 1 + 2 e^-2 + 2 e^-8
    t = np.full((5, 5), 20.0, np.float32)
    t[2, 2] = 21.0
    S = 1 + 2 * math.exp(-2) + 2 * math.exp(-8)
    g0, g1, g2 = 1 / S, math.exp(-2) / S, math.exp(-8) / S
    # response to the centre impulse along one axis: at index 0 the taps k = -2 and k = +2 both land on
    # index 2 under reflect-101 (-2 -> 2), hence 2 g2; at index 1 only k = +1 does
    r = np.array([2 * g2, g1, g0, g1, 2 * g2])
    background = 20.0 + np.outer(r, r)
    np.testing.assert_allclose(gaussian_background(t, 0.5), background, atol=2e-6)
    dev = t - background
    a = np.sort(np.abs(dev).ravel())
    # 25 values: rank 0.99 * 24 = 23.76 between the largest (1 - g0^2) and the next (g0 g1)
    assert a[24] == pytest.approx(1 - g0**2) and a[23] == pytest.approx(g0 * g1)
    p = a[23] + 0.76 * (a[24] - a[23])
    expected = np.clip(dev / (2 * p) + 0.5, 0, 1)
    got = c2(t, sigma=0.5)
    np.testing.assert_allclose(got, expected, atol=2e-6)
    assert got[2, 2] == 1.0  # (1 - g0^2) / (2 p) + 0.5 > 1: clipped
    assert got[2, 1] == pytest.approx(0.5 - g0 * g1 / (2 * p), abs=2e-6)
    np.testing.assert_array_equal(c2_uint8(t, sigma=0.5), np.rint(expected * 255).astype(np.uint8))


def test_background_matches_scipy_mirror_mode():
    import scipy.ndimage as ndi

    t = _scene()
    for sigma in (1.0, 3.0, 11.0):
        ref = ndi.gaussian_filter(t.astype(np.float64), sigma, mode="mirror", truncate=4.0)
        assert np.abs(gaussian_background(t, sigma) - ref).max() < 5e-6
        assert np.abs(gaussian_background(t, sigma, method="direct") - ref).max() < 5e-5
        assert np.abs(local_deviation(t, sigma) - (t - ref)).max() < 5e-6
    assert kernel_radius(11.0) == 44


def test_c2_agrees_with_a_plain_scipy_implementation():
    import scipy.ndimage as ndi

    t = _scene(seed=4)
    dt = t.astype(np.float64) - ndi.gaussian_filter(t.astype(np.float64), 11.0, mode="mirror")
    p = max(np.percentile(np.abs(dt), 99), 0.05)
    ref = np.clip(dt / (2 * p) + 0.5, 0, 1)
    assert np.abs(c2(t) - ref).max() < 1e-4
    diff = np.abs(c2_uint8(t).astype(int) - np.rint(ref * 255).astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01


def test_invariant_to_a_constant_temperature_offset():
    t = _scene(seed=1)
    base = c2(t)
    for offset in (-30.0, 7.3, 250.0):
        shifted = c2(t + np.float32(offset))
        assert np.abs(shifted - base).max() < 2e-4
        d = np.abs(c2_uint8(t + np.float32(offset)).astype(int) - c2_uint8(t).astype(int))
        assert d.max() <= 1 and (d > 0).mean() < 0.002


def test_odd_symmetry_negating_the_deviation_gives_one_minus_c2():
    t = _scene(seed=2)
    mirrored = np.float32(2 * 25.0) - t  # same background level, deviation negated
    np.testing.assert_allclose(c2(mirrored), 1.0 - c2(t), atol=2e-5)
    u, v = c2_uint8(t).astype(int), c2_uint8(mirrored).astype(int)
    assert np.abs(u + v - 255).max() <= 1  # up to the uint8 rounding of ties


def test_flat_image_is_neutral_thanks_to_the_floor():
    flat = np.full((40, 50), 31.7, np.float32)
    np.testing.assert_allclose(c2(flat), 0.5, atol=1e-6)
    assert np.all(c2_uint8(flat) == 128)
    rng = np.random.default_rng(0)
    whisper = flat + rng.normal(0, 0.001, flat.shape).astype(np.float32)  # |dT| << 0.05 C floor
    assert np.abs(c2(whisper) - 0.5).max() < 0.05


@pytest.mark.parametrize("n", [30_000, 327_680])
def test_fast_percentile_equals_numpy(n):
    rng = np.random.default_rng(n)
    for values in (
        np.abs(rng.normal(size=n)),
        rng.exponential(size=n) ** 3,
        np.round(rng.uniform(size=n), 2),
        np.concatenate([np.zeros(n - 10), np.ones(10)]),
    ):
        values = values.astype(np.float32)
        for q in (50.0, 95.0, 99.0, 99.9, 100.0):
            assert fast_percentile(values, q) == pytest.approx(float(np.percentile(values, q)), rel=1e-6, abs=1e-12)


def test_contrast_amplitude_uses_the_pixels_whose_centres_are_inside():
    c = np.full((10, 10), 0.5, np.float32)
    c[2:4, 3:6] = 0.9
    assert contrast_amplitude(c, (3.0, 2.0, 6.0, 4.0)) == pytest.approx(0.4)
    assert contrast_amplitude(c, (2.6, 1.6, 6.4, 4.4)) == pytest.approx(0.4)  # centres 3..5 x 2..3
    assert contrast_amplitude(c, (3.0, 2.0, 7.0, 4.0)) == pytest.approx(0.4 * 6 / 8)
    assert math.isnan(contrast_amplitude(c, (3.1, 2.1, 3.4, 2.4)))


# ---------------------------------------------------------------------------------------------- encodings
def _sample(thermal=True) -> AlignedSample:
    t = _scene(32, 40, seed=3)
    ir8 = np.clip((t - t.min()) / (t.max() - t.min()) * 255, 0, 255).astype(np.uint8)
    return AlignedSample(
        image_id=1,
        rgb=np.zeros((32, 40, 3), np.uint8),
        thermal=t if thermal else None,
        ir8=ir8,
        boxes=np.zeros((0, 4), np.float32),
        labels=np.zeros(0, np.int64),
        group="P1",
    )


def test_builtin_encodings_are_registered(host):
    enc = host.encodings()
    assert {"c2", "linear16", "ir8", "none", "proxy8"} <= set(enc)
    assert enc["none"].channels == 0 and enc["none"].needs is None
    assert enc["c2"].needs == "thermal" and enc["proxy8"].needs == "ir8" and enc["ir8"].needs == "ir8"
    assert enc["c2"].params == {"sigma": 11.0, "percentile": 99.0, "floor": 0.05}
    assert host.owner("encoding", "c2") == "harness.encodings"


def test_encodings_compute_what_they_document(host):
    s = _sample()
    enc = host.encodings()
    np.testing.assert_array_equal(encode(enc["c2"], s), c2_uint8(s.thermal))
    np.testing.assert_array_equal(encode(enc["c2"], s, sigma=3.0), c2_uint8(s.thermal, sigma=3.0))
    lin = encode(enc["linear16"], s)
    assert lin.dtype == np.uint8 and lin.min() == 0 and lin.max() == 255
    assert lin.flat[np.argmax(s.thermal)] == 255 and lin.flat[np.argmin(s.thermal)] == 0
    fixed = encode(enc["linear16"], s, mode="fixed", t_min=20.0, t_max=30.0)
    np.testing.assert_array_equal(fixed, np.rint(np.clip((s.thermal - 20) / 10, 0, 1) * 255).astype(np.uint8))
    with pytest.raises(PluginError, match="unknown mode"):
        encode(enc["linear16"], s, mode="log")
    np.testing.assert_array_equal(encode(enc["ir8"], s), s.ir8)
    assert encode(enc["none"], s) is None
    np.testing.assert_array_equal(encode(enc["proxy8"], s), c2_uint8(s.ir8.astype(np.float32), floor=1.0))
    flat = _sample()
    flat.ir8[:] = 77
    assert np.all(encode(enc["proxy8"], flat) == 128)


def test_radiometric_encodings_refuse_8bit_samples_but_8bit_ones_work(host):
    s = _sample(thermal=False)
    with pytest.raises(PluginError, match="proxy8"):
        encode(host.encoding("c2"), s)
    assert encode(host.encoding("proxy8"), s).shape == s.ir8.shape


def test_encoding_parameters_come_from_the_config():
    from harness.config import load_config

    cfg = load_config(overrides=["encoding.c2.sigma=5.0"])
    assert cfg["encoding"] == {"c2": {"sigma": 5.0}}
