"""The displacement study of C2 around boxes and its command (prepared data, results store, JSON)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from harness.api import AlignedSample
from harness.errors import DataError
from harness.sensing.analyses import box_amplitudes, displacement_study, format_displacement, shift_replicate
from harness.sensing.c2 import c2, contrast_amplitude

CATS = ("crack", "ac_unit")


def _blob_scene(blobs, h=96, w=128, seed=0) -> np.ndarray:
    """Warm Gaussian blobs (cx, cy, radius, amplitude) on a 25 C wall with slight noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    t = np.full((h, w), 25.0) + rng.normal(0, 0.02, (h, w))
    for cx, cy, r, amp in blobs:
        t += amp * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r**2))
    return t.astype(np.float32)


def _sample(image_id, blobs, boxes, labels, seed=0) -> AlignedSample:
    t = _blob_scene(blobs, seed=seed)
    return AlignedSample(
        image_id=image_id,
        rgb=np.zeros(t.shape + (3,), np.uint8),
        thermal=t,
        ir8=np.zeros(t.shape, np.uint8),
        boxes=np.asarray(boxes, np.float32),
        labels=np.asarray(labels, np.int64),
        group="P1",
        meta={"file_name": f"img{image_id}"},
    )


def _samples():
    # small hot spots (class 0, 'crack'-sized boxes) and large warm units (class 1)
    return [
        _sample(1, [(30, 30, 2.0, 2.0), (90, 60, 8.0, 3.0)], [[26, 26, 34, 34], [74, 44, 106, 76]], [0, 1], seed=1),
        _sample(2, [(60, 40, 2.0, 1.5)], [[56, 36, 64, 44]], [0], seed=2),
    ]


def test_shift_replicates_the_border():
    a = np.arange(12).reshape(3, 4)
    np.testing.assert_array_equal(shift_replicate(a, 1, 0), [[0, 0, 1, 2], [4, 4, 5, 6], [8, 8, 9, 10]])
    np.testing.assert_array_equal(shift_replicate(a, 0, -1), [[4, 5, 6, 7], [8, 9, 10, 11], [8, 9, 10, 11]])
    with pytest.raises(ValueError):
        shift_replicate(a, 4, 0)


def test_box_amplitudes_at_zero_shift_are_the_mean_absolute_contrast():
    s = _samples()[0]
    amps = box_amplitudes(s.thermal, s.boxes, shifts=(2, 5))
    c = c2(s.thermal)
    assert amps.shape == (2, 3)
    assert amps[0, 0] == pytest.approx(contrast_amplitude(c, s.boxes[0]))
    # shifting by 5 px moves a 2-px hot spot out of its 8-px box: the box keeps little of its contrast
    assert amps[0, 2] < 0.6 * amps[0, 0]
    # a direction average, computed by hand for d = 2
    by_hand = np.mean(
        [
            contrast_amplitude(c2(shift_replicate(s.thermal, dx, dy)), s.boxes[0])
            for dx, dy in ((2, 0), (-2, 0), (0, 2), (0, -2))
        ]
    )
    assert amps[0, 1] == pytest.approx(by_hand)


def test_displacement_study_weights_every_box_equally_within_its_class():
    samples = _samples()
    res = displacement_study(samples, CATS, shifts=(2, 5, 10, 15))
    assert res["shifts"] == [0, 2, 5, 10, 15] and res["images"] == 2 and res["boxes"] == 3
    crack, unit = res["classes"]["crack"], res["classes"]["ac_unit"]
    assert crack["boxes"] == 2 and unit["boxes"] == 1
    a1 = box_amplitudes(samples[0].thermal, samples[0].boxes[:1], (2, 5, 10, 15))[0]
    a2 = box_amplitudes(samples[1].thermal, samples[1].boxes, (2, 5, 10, 15))[0]
    np.testing.assert_allclose(crack["A"], (a1 + a2) / 2)
    np.testing.assert_allclose(crack["R"], 100 * (a1 + a2) / (a1[0] + a2[0]))
    assert crack["R"][0] == pytest.approx(100.0)
    # contrast retained falls with displacement, and small targets lose it faster than large ones
    assert crack["R"][1] > crack["R"][2] > crack["R"][3]
    assert unit["R"][2] > crack["R"][2]
    assert res["mean_over_classes"]["R"][0] == pytest.approx(100.0)


def test_displacement_table_lines_up_and_handles_empty_classes():
    res = displacement_study(_samples()[1:], CATS, shifts=(2, 5))
    text = format_displacement(res)
    lines = text.splitlines()
    assert "R(2 px)" in lines[1] and "R(5 px)" in lines[1]
    body = lines[1:2] + lines[3:]
    assert len({len(ln) for ln in body}) == 1  # aligned columns
    assert res["classes"]["ac_unit"] == {"boxes": 0, "A": None, "R": None}
    assert "ac_unit" in text and "100.0%" not in lines[1]


def test_displacement_study_refuses_8bit_samples_and_bad_shifts():
    s = _samples()[0]
    s.thermal = None
    with pytest.raises(DataError, match="needs temperatures"):
        displacement_study([s], CATS)
    with pytest.raises(DataError, match="positive"):
        displacement_study(_samples(), CATS, shifts=(0, 2))


def _prepared(tmp_path):
    from harness.cache import PreparedWriter

    folder = tmp_path / "prepared"
    with PreparedWriter(folder, "toy", CATS) as w:
        for s in _samples():
            w.add(s)
    return folder


def test_displacement_command_on_a_prepared_dataset(tmp_path, cli_runner):
    folder = _prepared(tmp_path)
    out = tmp_path / "disp.json"

    def displacement(*args: str):
        res = cli_runner(["sensing", "displacement", "--prepared", str(folder), *args])
        assert res.exit_code == 0, res.output
        return res

    res = displacement("--shifts", "2,5", "--store", str(tmp_path / "store"), "--out", str(out))
    data = json.loads(out.read_text())
    assert data["dataset"] == "toy" and data["shifts"] == [0, 2, 5] and data["classes"]["crack"]["boxes"] == 2
    stored = json.loads((tmp_path / "store" / "toy" / "_sensing" / "displacement.json").read_text())
    assert stored["classes"] == data["classes"]
    assert "R(5 px)" in res.output and "crack" in res.output
    # encoding parameters come from the config, like everywhere else
    displacement("--shifts", "2", "--no-store", "--set", "encoding.c2.sigma=5.0", "--out", str(tmp_path / "s5.json"))
    assert json.loads((tmp_path / "s5.json").read_text())["params"]["sigma"] == 5.0


def test_displacement_command_errors_are_clean(tmp_path, cli_runner):
    res = cli_runner(["sensing", "displacement", "--prepared", str(tmp_path)])
    assert res.exit_code == 2 and "not a prepared dataset" in res.output
    res = cli_runner(["sensing", "displacement", "--dataset", "no-such-dataset", "--no-store"])
    assert res.exit_code == 2 and "Traceback" not in res.output
    res = cli_runner(["sensing", "displacement"])
    assert res.exit_code == 2 and "exactly one of" in res.output
