"""Missing temperatures through the sample contract, preparation and the encodings: counted, left out, never zero."""

from __future__ import annotations

import numpy as np
import pytest

from harness import AlignedSample, validate_sample
from harness.api import DatasetSpec, Fold
from harness.encodings import encode_c2, encode_linear16
from harness.errors import DataError, SampleError

H, W = 32, 40


def _sample(i: int, holes: int = 0, all_missing: bool = False) -> AlignedSample:
    rng = np.random.default_rng(i)
    t = (20 + rng.normal(0, 0.5, (H, W))).astype(np.float32)
    t.reshape(-1)[:holes] = np.nan
    if all_missing:
        t[:] = np.inf
    return AlignedSample(
        i,
        np.zeros((H, W, 3), np.uint8),
        t,
        np.zeros((H, W), np.uint8),
        np.array([[2, 2, 10, 10]], np.float32),
        np.array([0]),
        "g1" if i % 2 else "g2",
        meta={"file_name": f"frame_{i}.tif"},
    )


class _Source:
    def __init__(self, samples):
        self._samples = samples

    def __len__(self):
        return len(self._samples)

    def groups(self):
        return ["g1", "g2"]

    def folds(self):
        return [Fold("a", ("g1",), ("g2",))]

    def fingerprint(self):
        return "missing-temperatures-test"

    def samples(self, report):
        yield from self._samples


def test_a_sample_may_miss_some_temperatures_but_not_most():
    validate_sample(_sample(0, holes=10))
    with pytest.raises(SampleError, match=r"frame_0\.tif.*'thermal'.*1280 of 1280 pixels are non-finite"):
        validate_sample(_sample(0, all_missing=True))


def test_prepare_counts_missing_pixels_per_sample_and_skips_the_unusable(tmp_path):
    from harness.cache import prepare
    from harness.commands.data import prepare_summary

    samples = [_sample(0), _sample(1, holes=7), _sample(2, holes=30), _sample(3, all_missing=True)]
    spec = DatasetSpec("toy-missing", lambda root, **kw: _Source(samples), ("thing",))
    ds = prepare(spec, {}, cache_root=tmp_path, progress=False)
    rep = ds.manifest["report"]
    assert len(ds) == 3 and rep["skipped"] == 1 and "non-finite" in rep["skipped_files"][0][1]
    assert rep["missing_temperatures"] == {
        "samples": 2,
        "pixels": 37,
        "per_sample": {"sample 1 (frame_1.tif)": 7, "sample 2 (frame_2.tif)": 30},
    }
    assert "missing temperatures (NaN/inf, left out of the encodings): 37 pixels in 2 sample(s)" in prepare_summary(ds)
    kept = ds[1]
    assert int((~np.isfinite(kept.thermal)).sum()) == 7  # the cache keeps them missing, not zero


def test_encodings_leave_missing_temperatures_out():
    s = _sample(0, holes=40)
    c2 = encode_c2(s)
    assert (c2.reshape(-1)[:40] == 128).all()  # neutral
    assert np.abs(c2.reshape(-1)[40:].astype(int) - 128).mean() > 10
    lin = encode_linear16(s)
    clean = s.thermal.copy()
    valid = np.isfinite(clean)
    lo, hi = clean[valid].min(), clean[valid].max()
    assert lin.reshape(-1)[40:].min() == 0 and lin.max() == 255
    median = np.rint((np.median(clean[valid]) - lo) / (hi - lo) * 255)
    assert np.abs(lin.reshape(-1)[:40].astype(int) - median).max() <= 1  # the median, not the coldest level
    with pytest.raises(DataError, match=r"^sample 3 \(frame_3\.tif\): no valid temperature"):
        encode_c2(_sample(3, all_missing=True))


def test_registration_structure_ignores_missing_temperatures():
    from harness.sensing.registration import structure_image

    yy, xx = np.mgrid[0:60, 0:80]
    t = (20 + 5 * ((xx > 40) & (yy > 20))).astype(np.float32)  # one warm block: edges at x=40, y=20
    holed = t.copy()
    holed[5:10, 5:10] = np.nan
    s_clean, s_holed = structure_image(t), structure_image(holed)
    assert np.isfinite(s_holed).all()
    assert (s_holed[3:12, 3:12] == 0).all()  # no structure invented at the hole
    assert np.allclose(s_holed[:, 30:], s_clean[:, 30:], atol=1e-6)  # the real edges are untouched


def test_a_float_tiff_with_masked_pixels_reads_them_as_missing(tmp_path):
    """A float TIFF another tool exported with NaN/inf holes, and a PNG whose sidecar names a nodata value: the holes
    come back as NaN (counted), the other pixels unchanged; a file of mostly holes is an error naming it."""
    import cv2

    from harness.sensing.radiometry import read_thermal, write_thermal

    rng = np.random.default_rng(3)
    t = (25 + rng.normal(0, 1.0, (H, W))).astype(np.float32)
    holes = t.copy()
    holes[3, 4], holes[10, 11], holes[20, 30] = np.nan, np.inf, -np.inf
    assert cv2.imwrite(str(tmp_path / "holes.tif"), holes)
    got, info = read_thermal(tmp_path / "holes.tif")
    bad = ~np.isfinite(holes)
    assert info["missing"] == 3 and np.isnan(got[bad]).all() and np.array_equal(got[~bad], t[~bad])

    png = write_thermal(tmp_path / "masked.png", t, unit="centikelvin")
    side = png.with_name(png.name + ".json")
    import json

    meta = json.loads(side.read_text())
    raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    raw[0, :5] = 0
    assert cv2.imwrite(str(png), raw)
    side.write_text(json.dumps({**meta, "nodata": 0}))
    got, info = read_thermal(png)
    assert info["nodata"] == 5 and info["missing"] == 5 and np.isnan(got[0, :5]).all()
    assert np.isfinite(got[1:]).all()

    mostly = np.full((H, W), np.nan, np.float32)
    mostly[:2] = 20.0
    assert cv2.imwrite(str(tmp_path / "mostly.tif"), mostly)
    with pytest.raises(DataError, match="mostly.tif"):
        read_thermal(tmp_path / "mostly.tif")
