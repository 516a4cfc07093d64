"""Automatic registration pooled over an inspection group (``harness.sensing.registration.pooled``)."""

from __future__ import annotations

import numpy as np
import pytest

from harness.sensing.registration import corner_error, estimate_homography_auto, normalize
from harness.sensing.registration.pooled import evenly, prior_error_px, register_pooled
from sensing_scenes import SCENE_RGB, SCENE_TH, focal_prior, render_pair, scene_truth


@pytest.fixture(scope="module")
def weak_group():
    """Six frames of one rig whose thermal maps are noisy enough that most single frames fail ECC's check."""
    rng = np.random.default_rng(0)
    pairs = []
    for seed in range(1, 7):
        rgb, th = render_pair(seed, scene_truth(), SCENE_RGB, SCENE_TH)
        pairs.append((rgb, th + rng.normal(0.0, 3.0, th.shape).astype(np.float32)))
    return pairs


def test_a_group_registers_where_its_single_frames_fail(weak_group):
    H_true = scene_truth()
    single = [estimate_homography_auto(rgb, th, init=focal_prior()) for rgb, th in weak_group]
    assert sum(not r.ok for r in single) >= 3  # frame by frame, most of the group falls back to the prior
    res = register_pooled(weak_group, focal_prior())
    assert res.ok, res.reason
    assert res.frames == 6 and res.agreeing >= 3
    assert np.median(corner_error(res.H, H_true, SCENE_TH)) < 0.6
    assert np.median(corner_error(focal_prior(), H_true, SCENE_TH)) > 3.0
    assert res.correlation > res.prior_correlation
    q = res.quality()
    assert q["pooled"] is True and "expected_error_px" not in q


def test_a_group_of_wrong_pairs_keeps_the_prior_and_says_how_far_off_it_may_be(weak_group):
    scrambled = [(weak_group[i][0], weak_group[(i + 1) % 6][1]) for i in range(6)]
    res = register_pooled(scrambled, focal_prior())
    assert not res.ok and "agree" in res.reason and "correlation" in res.reason
    np.testing.assert_allclose(res.H, normalize(focal_prior()))
    assert res.expected_error_px == prior_error_px(SCENE_TH) > 0
    assert res.quality()["expected_error_px"] == res.expected_error_px and res.quality()["reason"] == res.reason


def test_a_group_of_one_frame_takes_the_single_frame_check(weak_group):
    res = register_pooled(weak_group[2:3], focal_prior())
    single = estimate_homography_auto(*weak_group[2], init=focal_prior())
    assert not single.ok and not res.ok and "one frame only" in res.reason
    rgb, th = render_pair(1, scene_truth(), SCENE_RGB, SCENE_TH)
    assert register_pooled([(rgb, th)], focal_prior()).ok


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
        results.append(register_pooled(pairs, focal_prior()))
    assert all(np.array_equal(r.H, results[0].H) and r.correlation == results[0].correlation for r in results)
