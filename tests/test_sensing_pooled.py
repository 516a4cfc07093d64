"""Automatic registration pooled over an inspection group (``harness.sensing.registration.pooled``)."""

from __future__ import annotations

import numpy as np
import pytest

from harness.sensing.registration import (
    corner_error,
    estimate_homography_auto,
    homography_from_focal_lengths,
    homography_from_similarity,
    image_center,
    normalize,
)
from harness.sensing.registration.pooled import evenly, prior_error_px, register_pooled
from sensing_scenes import render_pair

RGB, TH = (480, 384), (160, 128)


def _truth() -> np.ndarray:
    H = homography_from_similarity(3.0, -2.0, 1.5, 0.4 * 1.02, image_center(RGB), image_center(TH))
    H[2, 0] = 2e-5
    return H / H[2, 2]


def _prior() -> np.ndarray:
    return homography_from_focal_lengths(1000.0, 400.0, RGB, TH)


@pytest.fixture(scope="module")
def weak_group():
    """Six frames of one rig whose thermal maps are noisy enough that most single frames fail ECC's check."""
    rng = np.random.default_rng(0)
    pairs = []
    for seed in range(1, 7):
        rgb, th = render_pair(seed, _truth(), RGB, TH)
        pairs.append((rgb, th + rng.normal(0.0, 3.0, th.shape).astype(np.float32)))
    return pairs


def test_a_group_registers_where_its_single_frames_fail(weak_group):
    H_true = _truth()
    single = [estimate_homography_auto(rgb, th, init=_prior()) for rgb, th in weak_group]
    assert sum(not r.ok for r in single) >= 3  # frame by frame, most of the group falls back to the prior
    res = register_pooled(weak_group, _prior())
    assert res.ok, res.reason
    assert res.frames == 6 and res.agreeing >= 3
    assert np.median(corner_error(res.H, H_true, TH)) < 0.6
    assert np.median(corner_error(_prior(), H_true, TH)) > 3.0
    assert res.correlation > res.prior_correlation
    q = res.quality()
    assert q["pooled"] is True and "expected_error_px" not in q


def test_a_group_of_wrong_pairs_keeps_the_prior_and_says_how_far_off_it_may_be(weak_group):
    scrambled = [(weak_group[i][0], weak_group[(i + 1) % 6][1]) for i in range(6)]
    res = register_pooled(scrambled, _prior())
    assert not res.ok and "agree" in res.reason and "correlation" in res.reason
    np.testing.assert_allclose(res.H, normalize(_prior()))
    assert res.expected_error_px == prior_error_px(TH) > 0
    assert res.quality()["expected_error_px"] == res.expected_error_px and res.quality()["reason"] == res.reason


def test_a_group_of_one_frame_takes_the_single_frame_check(weak_group):
    res = register_pooled(weak_group[2:3], _prior())
    single = estimate_homography_auto(*weak_group[2], init=_prior())
    assert not single.ok and not res.ok and "one frame only" in res.reason
    rgb, th = render_pair(1, _truth(), RGB, TH)
    assert register_pooled([(rgb, th)], _prior()).ok


def test_the_frames_looked_at_are_spread_over_the_group():
    assert evenly(5, 24) == [0, 1, 2, 3, 4]
    picked = evenly(100, 24)
    assert len(picked) == 24 and picked[0] == 0 and picked[-1] == 99
    assert max(np.diff(picked)) - min(np.diff(picked)) <= 1


def _shifted(a: np.ndarray, offset: int) -> np.ndarray:
    """A copy of ``a`` starting ``offset`` bytes into a fresh buffer (another memory alignment, same values)."""
    buf = np.zeros(a.nbytes + 64, np.uint8)
    out = buf[offset : offset + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def test_a_group_registers_to_the_same_digits_wherever_its_images_lie_in_memory(weak_group):
    """What lets a screen reproduce `harness score-route` exactly: OpenCV kernels whose path depends on a buffer's
    alignment would move the result between calls."""
    results = []
    for offset in (0, 4, 8, 12, 36):
        pairs = [(_shifted(rgb, offset), _shifted(th, offset)) for rgb, th in weak_group]
        results.append(register_pooled(pairs, _prior()))
    assert all(np.array_equal(r.H, results[0].H) and r.correlation == results[0].correlation for r in results)
