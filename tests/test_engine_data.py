"""The data pipeline: [R, G, B, enc] stacking, the full training pipeline, collation to the model contract."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from engine_helpers import ENCODINGS, write_dataset
from harness import EncodingSpec
from harness.engine.data import (
    AugmentSettings,
    EpochSampler,
    LetterboxDataset,
    SampleSource,
    TrainDataset,
    collate,
    to_inputs,
)
from harness.errors import ConfigError

IR8, NONE = ENCODINGS
RED = EncodingSpec(name="red-copy", fn=lambda s, **_: np.ascontiguousarray(s.rgb[:, :, 0]), channels=1, needs=None)


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("shapes") / "ds", per_group=6)


def test_source_stacks_rgb_and_the_encoding(prepared):
    src = SampleSource(prepared, [0, 3], IR8)
    assert src.channels == 4 and len(src) == 2
    img = src.image(1)
    np.testing.assert_array_equal(img[:, :, :3], prepared[3].rgb)
    np.testing.assert_array_equal(img[:, :, 3], prepared[3].ir8)
    assert src.image_id(1) == prepared.records[3]["image_id"]
    rgb_only = SampleSource(prepared, [0], NONE)
    assert rgb_only.channels == 3 and rgb_only.image(0).shape[2] == 3


@pytest.mark.parametrize("mosaic", [0.0, 1.0])
def test_training_pipeline_applies_geometry_to_every_channel(prepared, mosaic):
    """The extra channel is a copy of R: after mosaic, affine and flips (no HSV) it must still equal R everywhere."""
    aug = AugmentSettings(
        mosaic=mosaic, hsv_h=0, hsv_s=0, hsv_v=0, degrees=15, translate=0.2, scale=0.5, shear=5, fliplr=0.5, flipud=0.5
    )
    ds = TrainDataset(SampleSource(prepared, None, RED), 64, aug, seed=3)
    for k in range(len(ds)):
        item = ds[k]
        img = item["image"]
        assert img.shape == (4, 64, 64) and img.dtype == torch.uint8
        assert torch.equal(img[3], img[0])
        b = item["boxes"]
        assert b.shape[1] == 4 and len(b) == len(item["labels"])
        if len(b):
            assert (b[:, 2] > b[:, 0]).all() and (b[:, 3] > b[:, 1]).all()
            assert b.min() >= 0 and b.max() <= 64


def test_training_pipeline_hsv_leaves_channel_4_alone(prepared):
    """With only HSV jitter on, RGB changes and the encoding channel is exactly the letterboxed encoding."""
    aug = AugmentSettings(mosaic=0, hsv_h=0.5, hsv_s=0.9, hsv_v=0.9, translate=0, scale=0, fliplr=0, flipud=0)
    plain = LetterboxDataset(SampleSource(prepared, None, IR8), 64)
    ds = TrainDataset(SampleSource(prepared, None, IR8), 64, aug, seed=0)
    rgb_changed = 0
    for k in range(len(ds)):
        a, b = ds[k]["image"], plain[k]["image"]
        assert torch.equal(a[3], b[3])
        rgb_changed += int(not torch.equal(a[:3], b[:3]))
    assert rgb_changed == len(ds)


def test_augmentation_depends_only_on_seed_epoch_and_index(prepared):
    aug = AugmentSettings()
    a = TrainDataset(SampleSource(prepared, None, IR8), 64, aug, seed=1)
    b = TrainDataset(SampleSource(prepared, None, IR8), 64, aug, seed=1)
    a.set_epoch(2)
    b.set_epoch(2)
    for k in (0, 5, 3):  # any order of access gives the same item
        assert torch.equal(a[k]["image"], b[k]["image"]) and torch.equal(a[k]["boxes"], b[k]["boxes"])
    b.set_epoch(3)
    assert not torch.equal(a[0]["image"], b[0]["image"])


def test_epoch_sampler_is_a_function_of_seed_and_epoch():
    s1, s2 = EpochSampler(10, seed=4), EpochSampler(10, seed=4)
    s1.set_epoch(1)
    s2.set_epoch(1)
    assert list(s1) == list(s2) and sorted(s1) == list(range(10))
    s2.set_epoch(2)
    assert list(s1) != list(s2)
    capped = EpochSampler(10, seed=4, max_images=3)
    capped.set_epoch(1)
    assert len(capped) == 3 and list(capped) == list(s1)[:3]


def test_collate_and_inputs_single_and_dual(prepared):
    ds = LetterboxDataset(SampleSource(prepared, [0, 1, 2], IR8), 64)
    batch = collate([ds[k] for k in range(3)])
    assert batch.images.shape == (3, 4, 64, 64) and len(batch.targets) == 3 and len(batch) == 3
    assert batch.image_ids == [prepared.records[k]["image_id"] for k in range(3)]
    x = to_inputs(batch.images, "single")
    assert x.dtype == torch.float32 and x.shape == (3, 4, 64, 64) and 0 <= x.min() and x.max() <= 1
    torch.testing.assert_close(x, batch.images.float() / 255)
    rgb, thermal = to_inputs(batch.images, "dual", thermal_channels=3)
    assert rgb.shape == (3, 3, 64, 64) and thermal.shape == (3, 3, 64, 64)
    for c in range(3):
        torch.testing.assert_close(thermal[:, c], x[:, 3])
    torch.testing.assert_close(rgb, x[:, :3])
    _, one = to_inputs(batch.images, "dual", thermal_channels=1)
    assert one.shape == (3, 1, 64, 64)


def test_dual_stream_without_a_thermal_channel_is_a_clear_error(prepared):
    ds = LetterboxDataset(SampleSource(prepared, [0], NONE), 64)
    with pytest.raises(ConfigError, match="dual-stream detector needs an encoding"):
        to_inputs(collate([ds[0]]).images, "dual")


def test_eval_letterbox_boxes_map_back_to_the_thermal_frame(prepared):
    ds = LetterboxDataset(SampleSource(prepared, [4], IR8), 96)
    item = ds[0]
    orig, _ = prepared.targets(4)
    np.testing.assert_allclose(item["letterbox"].to_original(item["boxes"].numpy()), orig, atol=1e-4)


def test_batches_do_not_depend_on_the_number_of_workers(prepared):
    from harness.engine.data import train_loader

    def epoch(workers):
        ds = TrainDataset(SampleSource(prepared, None, IR8), 64, AugmentSettings(), seed=7)
        ds.set_epoch(1)
        loader = train_loader(ds, 4, workers=workers, seed=7)
        loader.sampler.set_epoch(1)
        return [(b.image_ids, b.images, [t["boxes"] for t in b.targets]) for b in loader]

    serial, parallel = epoch(0), epoch(2)
    assert len(serial) == len(parallel) == 3
    for (ids_a, img_a, box_a), (ids_b, img_b, box_b) in zip(serial, parallel):
        assert ids_a == ids_b and torch.equal(img_a, img_b)
        assert all(torch.equal(x, y) for x, y in zip(box_a, box_b))


def test_augment_settings_from_config():
    section = {"mosaic": 0.5, "hsv_h": 0.015, "hsv_s": 0.7, "hsv_v": 0.4, "fliplr": 0.5, "hsv_4ch": False}
    rgb_only = AugmentSettings.from_config(section, extra_channels=0)
    assert (rgb_only.mosaic, rgb_only.hsv_s) == (0.5, 0.7)  # 3-channel input keeps its jitter
    four = AugmentSettings.from_config(section, extra_channels=1)
    assert (four.hsv_h, four.hsv_s, four.hsv_v) == (0.0, 0.0, 0.0) and four.mosaic == 0.5
    assert AugmentSettings.from_config({**section, "hsv_4ch": True}, extra_channels=1).hsv_v == 0.4


class CountingSource(SampleSource):
    """Counts how often each sample is decoded."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.decoded: list[int] = []

    def image(self, k):
        self.decoded.append(k)
        return super().image(k)


@pytest.mark.parametrize("imgsz", [64, 96])  # 96 scales the 64x80 samples up, 64 down
def test_the_resized_image_cache_decodes_once_and_changes_nothing(prepared, imgsz):
    aug = AugmentSettings(mosaic=0.5, degrees=10, translate=0.2, scale=0.5, shear=3, fliplr=0.5, flipud=0.5)
    plain, cached = CountingSource(prepared, None, IR8), CountingSource(prepared, None, IR8, cache_mb=64)
    a, b = TrainDataset(plain, imgsz, aug, seed=1), TrainDataset(cached, imgsz, aug, seed=1)
    for epoch, mosaic in ((0, True), (1, True), (2, False)):
        a.set_epoch(epoch, mosaic)
        b.set_epoch(epoch, mosaic)
        for k in range(len(a)):
            x, y = a[k], b[k]
            assert torch.equal(x["image"], y["image"]) and torch.equal(x["boxes"], y["boxes"])
            assert torch.equal(x["labels"], y["labels"])
    for _ in range(2):  # validation epochs read the same cache
        for k in range(len(cached)):
            x, y = LetterboxDataset(plain, imgsz)[k], LetterboxDataset(cached, imgsz)[k]
            assert torch.equal(x["image"], y["image"]) and x["letterbox"] == y["letterbox"]
    assert sorted(cached.decoded) == list(range(len(cached)))  # each sample decoded once
    assert len(plain.decoded) > 3 * len(plain)
    img, _, _ = cached.resized(0, imgsz)
    assert not img.flags.writeable  # a consumer writing into it would corrupt every later epoch


def test_the_cache_stops_at_its_budget(prepared):
    src = CountingSource(prepared, None, IR8, cache_mb=64 * 80 * 4 * 2.5 / 2**20)  # room for two 64x80x4 images
    for _ in range(2):
        for k in range(4):
            src.resized(k, 80)
    assert src.decoded == [0, 1, 2, 3, 2, 3]


def test_letterbox_is_resize_then_pad():
    from harness.engine import augment as A

    rng = np.random.default_rng(0)
    for h, w, size in ((64, 80, 64), (64, 80, 128), (80, 80, 80), (31, 97, 64)):
        img = rng.integers(0, 255, (h, w, 4), dtype=np.uint8)
        ref, lb = A.letterbox(img, size)
        resized, r = A.resize_long_side(img, size)
        out, lb2 = A.pad_letterbox(resized, r, (h, w), size)
        np.testing.assert_array_equal(ref, out)
        assert lb == lb2
