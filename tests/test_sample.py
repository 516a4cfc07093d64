"""The aligned-sample contract: every rejected case names the sample and the field."""

from __future__ import annotations

import numpy as np
import pytest

from harness import AlignedSample, validate_sample
from harness.errors import SampleError


def good(**over):
    h, w = 8, 10
    fields = dict(
        image_id=7,
        rgb=np.zeros((h, w, 3), np.uint8),
        thermal=np.full((h, w), 20.0, np.float32),
        ir8=np.zeros((h, w), np.uint8),
        boxes=np.array([[1, 1, 4, 5], [0, 0, 10, 8]], np.float32),
        labels=np.array([0, 2], np.int64),
        group="P1",
        meta={"file_name": "DJI_0001_T.JPG"},
    )
    fields.update(over)
    return AlignedSample(**fields)


def test_valid_sample_passes():
    s = good()
    assert validate_sample(s, num_classes=3) is s
    assert validate_sample(good(thermal=None)).thermal is None
    assert validate_sample(good(boxes=np.zeros((0, 4), np.float32), labels=np.zeros(0, np.int64)))


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("rgb", np.zeros((8, 10, 3), np.float32), "expected dtype uint8"),
        ("rgb", np.zeros((8, 10), np.uint8), "expected 3 dimensions"),
        ("rgb", np.zeros((8, 11, 3), np.uint8), "expected shape (8, 10, 3)"),
        ("rgb", [[0]], "expected a numpy array"),
        ("thermal", np.zeros((8, 10), np.float64), "expected dtype float32"),
        ("thermal", np.zeros((9, 10), np.float32), "expected shape (8, 10)"),
        ("thermal", np.array([[np.nan] * 10] * 8, np.float32), "non-finite temperature"),
        ("thermal", np.full((8, 10), np.inf, np.float32), "non-finite temperature"),
        ("ir8", np.zeros((8, 10), np.uint16), "expected dtype uint8"),
        ("ir8", np.zeros((8, 10, 1), np.uint8), "expected 2 dimensions"),
        ("boxes", np.zeros((2, 5), np.float32), "expected shape (N, 4)"),
        ("boxes", np.zeros((2, 4), np.float64), "expected dtype float32"),
        ("boxes", np.array([[1, 1, 4, 5], [np.nan, 0, 1, 1]], np.float32), "non-finite"),
        ("boxes", np.array([[1, 1, 4, 5], [3, 3, 3, 6]], np.float32), "zero or negative width"),
        ("boxes", np.array([[1, 1, 4, 5], [5, 2, 11, 6]], np.float32), "outside the 10x8 frame"),
        ("boxes", np.array([[-2, 1, 4, 5], [5, 2, 9, 6]], np.float32), "outside the 10x8 frame"),
        ("labels", np.array([0], np.int64), "1 labels for 2 boxes"),
        ("labels", np.array([0, 1], np.int32), "expected dtype int64"),
        ("labels", np.array([0, 3], np.int64), "label 3 outside 0..2"),
        ("labels", np.array([-1, 0], np.int64), "label -1 outside"),
        ("image_id", "seven", "expected an int"),
        ("group", "", "non-empty string"),
        ("meta", None, "expected a dict"),
    ],
)
def test_rejected_cases_name_sample_and_field(field, value, message):
    with pytest.raises(SampleError) as err:
        validate_sample(good(**{field: value}), num_classes=3)
    text = str(err.value)
    assert f"field {field!r}" in text
    assert message in text
    if field not in ("meta", "image_id"):
        assert "sample 7 (DJI_0001_T.JPG)" in text
