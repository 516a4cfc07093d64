"""How well boxes sit on image structure (``harness.box_fit``): the boxes as given against them read as centres and
against the neighbouring image's, on small prepared-like sets made here."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from coco_rgbt_helpers import H, W, boxes, temperature
from harness import box_fit


class _Set:
    """What ``box_fit`` reads of a prepared dataset: ``records``, ``targets(i)`` and ``self[i]`` (counted)."""

    def __init__(self, thermals, targets, rgb=True):
        self.thermals, self._targets, self.rgb, self.loads = thermals, targets, rgb, 0
        h, w = thermals[0].shape
        self.records = [{"image_id": 10 + i, "height": h, "width": w} for i in range(len(thermals))]

    def targets(self, i):
        b = np.asarray(self._targets[i], np.float32).reshape(-1, 4)
        return b, np.zeros(len(b), np.int64)

    def __getitem__(self, i):
        self.loads += 1
        t = self.thermals[i]
        grey = np.clip(np.nan_to_num(t, nan=18.0) * 8 - 80, 0, 255).astype(np.uint8)
        rgb = np.stack([grey] * 3, axis=2) if self.rgb else None
        return SimpleNamespace(thermal=t, ir8=grey, rgb=rgb)


def _xyxy(k: int) -> list[list[float]]:
    return [[x, y, x + w, y + h] for _, (x, y, w, h) in boxes(k)]


def _facades(n: int = 12, edit=None) -> _Set:
    """``n`` frames of the coco-rgbt fixture (a warm patch moving with the frame, a cool pane) and their boxes."""
    targets = [_xyxy(k) for k in range(n)]
    return _Set([temperature(k) for k in range(n)], edit(targets) if edit else targets)


def _as_centres(targets):
    """x1, y1, w, h written as centre x, centre y, w, h and read as x1, y1 (clipped to the frame)."""
    out = []
    for bs in targets:
        b = np.asarray(bs, float)
        b += np.concatenate([b[:, 2:] - b[:, :2]] * 2, axis=1) / 2
        out.append(np.minimum(b, [W, H, W, H]).tolist())
    return out


def _shifted(targets):
    """Every image's annotations moved to the next image (image ids + 1)."""
    return targets[-1:] + targets[:-1]


def test_boxes_as_given_fit_better_than_any_other_reading():
    readings = {r.name: r for r in box_fit.fit(_facades())}
    assert set(readings) == set(box_fit.READINGS)
    assert readings["centre"].compared == 24 and readings["previous"].compared == 11
    for r in readings.values():
        assert r.contrast < r.given and r.higher <= 1 and not r.better, r
    assert box_fit.misplaced(_facades()) is None


def test_boxes_written_as_centres_are_found_and_named():
    found = box_fit.misplaced(_facades(edit=_as_centres))
    assert found is not None and found.name == "centre"
    assert found.higher == found.compared == 24 and found.contrast > 10 * found.given
    message = found.message()
    assert message.startswith("boxes read as centre x, centre y, w, h sit on image structure better: in-box contrast")
    assert f"{found.contrast:.2f} vs {found.given:.2f} (given), higher for 100% of 24 boxes" in message


def test_annotations_moved_to_the_next_image_are_found_and_named():
    found = box_fit.misplaced(_facades(edit=_shifted))
    assert found is not None and found.name == "previous" and found.unit == "images"
    assert found.share >= box_fit.SHARE and found.contrast >= box_fit.FACTOR * found.given
    assert "read as the previous image's (image ids shifted by +1)" in found.message()


def test_near_identical_consecutive_frames_tie_and_are_no_finding():
    """A video's next frame is a near copy: its boxes fit this frame as well as its own, shifted or not."""
    frames = [temperature(0) + 0.01 * k for k in range(12)]
    targets = [_xyxy(0)] * 12
    for edit in (lambda t: t, _shifted):
        readings = {r.name: r for r in box_fit.fit(_Set(frames, edit(targets)))}
        assert readings["previous"].contrast == pytest.approx(readings["previous"].given, rel=0.05)
        assert box_fit.misplaced(_Set(frames, edit(targets))) is None


def test_missing_temperatures_are_left_out_not_read_as_zero():
    t = temperature(3)
    holey = t.copy()
    holey[5:10, :] = np.nan  # rows of the warm patch's ring with no reading
    box = np.array(_xyxy(3)[:1])
    plain, masked = (box_fit._Frame([a]).contrast(box)[0] for a in (t, holey))
    zeros = box_fit._Frame([np.nan_to_num(holey)]).contrast(box)[0]
    assert masked == pytest.approx(plain, rel=0.1) and abs(zeros - plain) > 0.5 * plain


def test_flat_frames_and_empty_images_give_no_reading():
    flat = _Set([np.full((H, W), 20.0, np.float32)] * 6, [_xyxy(0)] * 6)
    assert box_fit.fit(flat) == [] and box_fit.misplaced(flat) is None
    empty = _Set([temperature(k) for k in range(6)], [[] for _ in range(6)])
    assert box_fit.fit(empty) == []


def test_few_boxes_are_never_a_finding():
    found = box_fit.fit(_facades(n=3, edit=_as_centres))
    assert found[0].name == "centre" and found[0].compared == 6 and found[0].share == 1
    assert not found[0].better  # fewer than MIN_COMPARED boxes


def test_a_large_set_is_measured_on_a_bounded_subset_of_neighbours():
    big = _facades(n=300)
    pairs = box_fit.pairs(big)
    assert len({i for p in pairs for i in p}) <= box_fit.MAX_SAMPLES
    assert all(b == a + 1 for a, b in pairs) and pairs[0][0] == 0 and pairs[-1][1] == 299
    box_fit.fit(big)
    assert big.loads <= box_fit.MAX_SAMPLES


def test_neighbours_of_another_frame_size_are_not_compared():
    s = _facades(n=6)
    s.records[3] = {**s.records[3], "height": H + 1}
    assert (2, 3) not in box_fit.pairs(s) and (3, 4) not in box_fit.pairs(s) and (0, 1) in box_fit.pairs(s)
