"""Detections packed as columns (``harness.io.pack_detections``, the shipped reference results' ``predictions.npz``)
give back every value of the JSON exactly, or are not packed; a damaged file is an error naming it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from harness.errors import DataError
from harness.io import pack_detections, read_json, unpack_detections
from harness.store import Run, RunKey


def _dets(n: int = 500, seed: int = 0) -> list[dict]:
    """Detections as the harness writes them: float32 corners and scores, ``w``, ``h`` their float64 differences."""
    rng = np.random.default_rng(seed)
    x1 = rng.uniform(-3, 600, n).astype(np.float32)
    y1 = rng.uniform(0, 500, n).astype(np.float32)
    x2 = (x1 + rng.uniform(0.5, 90, n)).astype(np.float32)
    y2 = (y1 + rng.uniform(0.5, 90, n)).astype(np.float32)
    score = rng.uniform(0.001, 1, n).astype(np.float32)
    return [
        {
            "image_id": int(rng.integers(1, 100)),
            "category_id": int(rng.integers(1, 9)),
            "bbox": [float(a), float(b), float(c) - float(a), float(d) - float(b)],
            "score": float(s),
        }
        for a, b, c, d, s in zip(x1, y1, x2, y2, score)
    ]


def test_packed_detections_come_back_value_for_value_and_smaller(tmp_path):
    dets = _dets()
    packed = pack_detections(dets)
    assert packed is not None and unpack_detections(packed) == dets
    text = json.dumps(dets).encode()
    import gzip

    assert len(packed) < 0.7 * len(gzip.compress(text))
    assert pack_detections([]) is not None and unpack_detections(pack_detections([]) or b"") == []


@pytest.mark.parametrize(
    "change",
    [
        lambda d: d[3].update(bbox=[0.1, 2.0, 3.0, 4.0]),  # a corner that is not a float32
        lambda d: d[5].update(score=0.123456789),  # a score that is not a float32
        lambda d: d[7].update(category_name="car"),  # a key the columns do not hold
        lambda d: d[2].update(image_id="a.png"),  # an id that is not a number
    ],
)
def test_detections_the_columns_would_not_give_back_exactly_are_not_packed(change):
    dets = _dets(50)
    change(dets)
    assert pack_detections(dets) is None


def test_a_run_folder_with_packed_detections_is_read_like_json_and_a_damaged_file_is_named(tmp_path):
    run = Run(tmp_path, RunKey("d", "det", "c2", "P1", 0))
    run.path.mkdir(parents=True)
    dets = _dets(40)
    (run.path / "predictions.npz").write_bytes(pack_detections(dets) or b"")
    assert run.predictions_path.name == "predictions.npz" and read_json(run.predictions_path) == dets
    (run.path / "predictions.npz").write_bytes((pack_detections(dets) or b"")[:300])  # cut short
    with pytest.raises(DataError, match=r"predictions.npz: cannot read the packed detections"):
        read_json(run.predictions_path)
    (run.path / "predictions.json").write_text(json.dumps(dets[:3]))  # a plain file comes first
    assert read_json(run.predictions_path) == dets[:3]
