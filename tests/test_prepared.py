"""Prepared samples: streaming write, atomic folder, memory-mapped read, encodings cached, COCO derived."""

from __future__ import annotations

import numpy as np
import pytest

from harness.api import AlignedSample, EncodingSpec
from harness.cache import PreparedDataset, PreparedWriter
from harness.errors import SampleError


def sample(i, h=12, w=16, n=2, group="P1", thermal=True):
    rng = np.random.default_rng(i)
    boxes = np.array([[1 + j, 2, 6 + j, 9] for j in range(n)], np.float32).reshape(-1, 4)
    return AlignedSample(
        image_id=100 + i,
        rgb=rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
        thermal=rng.normal(20, 2, (h, w)).astype(np.float32) if thermal else None,
        ir8=rng.integers(0, 255, (h, w), dtype=np.uint8),
        boxes=boxes,
        labels=np.arange(n, dtype=np.int64) % 3,
        group=group,
        meta={"file_name": f"img{i}.jpg"},
    )


def write(tmp_path, samples, name="ds"):
    with PreparedWriter(tmp_path / name, "toy", ["a", "b", "c"], fingerprint="fp") as w:
        for s in samples:
            w.add(s)
    return PreparedDataset(tmp_path / name)


def test_round_trip_is_byte_identical(tmp_path):
    originals = [sample(0), sample(1, h=10, w=14, n=0, group="P2"), sample(2, n=3)]
    ds = write(tmp_path, originals)
    assert len(ds) == 3 and ds.image_ids == [100, 101, 102] and ds.groups == ["P1", "P2", "P1"]
    for a, b in zip(originals, ds):
        for f in ("rgb", "thermal", "ir8", "boxes", "labels"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        assert b.meta == a.meta and b.group == a.group
    assert isinstance(ds[0].rgb.base, np.memmap) or isinstance(ds[0].rgb, np.memmap)
    assert ds.indices(["P2"]) == [1]
    assert ds.manifest["count"] == 3 and ds.manifest["instances"] == 5


def test_eight_bit_only_dataset(tmp_path):
    ds = write(tmp_path, [sample(0, thermal=False), sample(1, thermal=False)])
    assert ds[0].thermal is None and not ds.radiometric


def test_mixed_radiometry_and_duplicates_are_refused(tmp_path):
    with pytest.raises(SampleError, match="some samples have radiometric thermal"):
        write(tmp_path, [sample(0), sample(1, thermal=False)])
    with pytest.raises(SampleError, match="duplicate image_id"):
        write(tmp_path, [sample(0), sample(0)], name="dup")


def test_interrupted_write_leaves_no_folder_and_keeps_previous(tmp_path):
    write(tmp_path, [sample(0)])
    with pytest.raises(RuntimeError):
        with PreparedWriter(tmp_path / "ds", "toy", ["a", "b", "c"]) as w:
            w.add(sample(5))
            raise RuntimeError("killed")
    ds = PreparedDataset(tmp_path / "ds")
    assert ds.image_ids == [100]  # the previous complete dataset is still there
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]


def test_encoding_channel_is_computed_once_and_cached(tmp_path):
    calls = []

    def inverted(s, offset=0):
        calls.append(s.image_id)
        return (255 - s.ir8).astype(np.uint8) + np.uint8(offset)

    enc = EncodingSpec(name="inv", fn=inverted, needs="ir8", params={"offset": 0})
    ds = write(tmp_path, [sample(0), sample(1)])
    np.testing.assert_array_equal(ds.channel(1, enc), 255 - ds[1].ir8)
    np.testing.assert_array_equal(ds.channel(0, enc), 255 - ds[0].ir8)
    assert calls == [100, 101]
    reopened = PreparedDataset(tmp_path / "ds")
    reopened.channel(0, enc)
    assert calls == [100, 101]  # read from the cache file
    np.testing.assert_array_equal(reopened.channel(0, enc, {"offset": 1}), 256 - ds[0].ir8.astype(int))
    assert len(list((tmp_path / "ds" / "enc").glob("*.u8"))) == 2
    assert ds.channel(0, EncodingSpec(name="none", fn=lambda s: None, channels=0, needs=None)) is None


def test_coco_ground_truth_and_support(tmp_path):
    ds = write(tmp_path, [sample(0), sample(1, n=0, group="P2"), sample(2, n=3)])
    gt = ds.coco([0, 1])
    assert [im["id"] for im in gt["images"]] == [100, 101]
    assert [c["id"] for c in gt["categories"]] == [1, 2, 3]
    a = gt["annotations"][0]
    assert a["bbox"] == [1.0, 2.0, 5.0, 7.0] and a["area"] == 35.0 and a["category_id"] == 1 and a["iscrowd"] == 0
    assert len(gt["annotations"]) == 2 and len({x["id"] for x in gt["annotations"]}) == 2
    assert ds.support() == {"images": 3, "instances": 5, "categories": {"a": 2, "b": 2, "c": 1}}
