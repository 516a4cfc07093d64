"""The data pipeline: prepared samples + an encoding -> augmented, letterboxed tensors in the model contract.

``SampleSource`` reads a subset of a ``harness.cache.PreparedDataset`` (memory-mapped) and stacks each
sample's RGB with the encoding's channel: ``uint8 H x W x (3 + k)``, channels ``[R, G, B, enc]`` (``k = 0`` for RGB-only
encodings such as ``none``). ``TrainDataset`` augments (mosaic, random affine, flips on every channel, HSV on RGB
only) and letterboxes to the protocol size; ``LetterboxDataset`` only letterboxes (evaluation). ``collate`` stacks a
batch and ``to_inputs`` turns it into what a detector takes: one ``[B, 3 + k, H, W]`` float tensor in 0..1 for a
single-stream detector, or ``(rgb [B, 3, H, W], thermal [B, thermal_channels, H, W])`` for a dual-stream one, the
thermal stream being the encoding's channel replicated.

Every sample's augmentation draws from ``numpy.random.default_rng((seed, epoch, index))`` and the epoch's order
from a generator seeded by ``(seed, epoch)``: a run is reproducible, independent of the number of worker
processes, and resumes mid-run to exactly the batches it would have seen.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from harness.engine import augment as A
from harness.errors import ConfigError, HarnessError


@dataclass(frozen=True)
class AugmentSettings:
    """The ``augment`` section of the config (see ``configs/default.yaml``)."""

    mosaic: float = 1.0
    hsv_h: float = 0.015
    hsv_s: float = 0.7
    hsv_v: float = 0.4
    degrees: float = 0.0
    translate: float = 0.1
    scale: float = 0.5
    shear: float = 0.0
    perspective: float = 0.0
    fliplr: float = 0.5
    flipud: float = 0.0

    @classmethod
    def from_config(cls, section: Mapping[str, Any], extra_channels: int = 0) -> "AugmentSettings":
        """From the ``augment`` section; with an extra channel and ``hsv_4ch: false`` there is no HSV jitter at all
        (what the seed does for 4-channel input; by default the jitter acts on RGB only)."""
        known = {f.name for f in fields(cls)}
        values = {k: float(v) for k, v in section.items() if k in known and v is not None}
        if extra_channels and not section.get("hsv_4ch", True):
            values.update(hsv_h=0.0, hsv_s=0.0, hsv_v=0.0)
        return cls(**values)

    def affine(self) -> dict[str, float]:
        """The random-warp settings, as keywords for ``augment.random_affine``."""
        return {k: getattr(self, k) for k in A.AFFINE_SETTINGS}

    @classmethod
    def off(cls) -> "AugmentSettings":
        return cls(mosaic=0.0, hsv_h=0.0, hsv_s=0.0, hsv_v=0.0, translate=0.0, scale=0.0, fliplr=0.0)


def resized_long_side(full: np.ndarray, size: int) -> tuple[np.ndarray, float, tuple[int, int]]:
    """``(full resized so its long side is size, ratio, full's (height, width))``: the form augmentation and
    letterboxing start from (``SampleSource.resized``; ``harness screen`` reads its frames through it too)."""
    img, r = A.resize_long_side(full, size)
    return img, r, (int(full.shape[0]), int(full.shape[1]))


class SampleSource:
    """A subset of a prepared dataset seen through one encoding: images ``[R, G, B, enc]`` and their targets.

    ``resized(k, size)`` is image ``k`` with its long side at ``size``, the form both augmentation (mosaic) and
    letterboxing start from. With ``cache_mb`` it is kept, read-only, until the source holds that many megabytes,
    so a training epoch (where mosaic reads every image about four times) and every per-epoch validation decode a
    prepared sample once per run instead of once per use. The cache is per process (a data-loader worker fills its
    own); what it returns is what decoding again would return.
    """

    def __init__(
        self,
        prepared: Any,
        indices: Sequence[int] | None = None,
        encoding: Any = None,
        params: Mapping[str, Any] | None = None,
        cache_mb: float = 0.0,
    ):
        self.prepared = prepared
        self.indices = list(range(len(prepared))) if indices is None else [int(i) for i in indices]
        self.encoding = encoding
        self.params = dict(params or {})
        self.extra = int(getattr(encoding, "channels", 0)) if encoding is not None else 0
        self.channels = 3 + self.extra
        self.cache_bytes = int(max(0.0, float(cache_mb)) * 2**20)
        self._resized: dict[tuple[int, int], tuple[np.ndarray, float, tuple[int, int]]] = {}
        self._cached_bytes = 0

    def resized(self, k: int, size: int) -> tuple[np.ndarray, float, tuple[int, int]]:
        """``(image k resized so its long side is size, ratio, original (height, width))`` (``augment.
        resize_long_side``); read-only when it comes from the cache."""
        hit = self._resized.get((k, size))
        if hit is not None:
            return hit
        full = self.image(k)
        out = resized_long_side(full, size)
        img, r = out[0], out[1]
        if self._cached_bytes + img.nbytes <= self.cache_bytes:
            if img is full:  # no resize: keep a copy of our own, never a view into the prepared arrays
                img = img.copy()
                out = (img, r, out[2])
            img.flags.writeable = False
            self._resized[(k, size)] = out
            self._cached_bytes += img.nbytes
        return out

    def __getstate__(self) -> dict[str, Any]:  # a data-loader worker starts with an empty cache of its own
        state = dict(self.__dict__)
        state.update(_resized={}, _cached_bytes=0)
        return state

    def __len__(self) -> int:
        return len(self.indices)

    def warm(self) -> None:
        """Compute the encoding for the dataset now (once, cached beside the prepared arrays), before workers fork."""
        if self.extra and self.indices:
            self.prepared.channel(self.indices[0], self.encoding, self.params)

    def image(self, k: int) -> np.ndarray:
        i = self.indices[k]
        rgb = self.prepared.rgb(i) if hasattr(self.prepared, "rgb") else self.prepared[i].rgb
        if not self.extra:
            return np.ascontiguousarray(rgb)
        ch = self.prepared.channel(i, self.encoding, self.params)
        return np.dstack((rgb, ch))

    def targets(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        boxes, labels = self.prepared.targets(self.indices[k])
        return np.array(boxes, dtype=np.float32).reshape(-1, 4), np.array(labels, dtype=np.int64)

    def image_id(self, k: int) -> int:
        return int(self.prepared.records[self.indices[k]]["image_id"])

    def shape(self, k: int) -> tuple[int, int]:
        r = self.prepared.records[self.indices[k]]
        return int(r["height"]), int(r["width"])


def _item(
    img: np.ndarray, boxes: np.ndarray, labels: np.ndarray, image_id: int, letterbox: A.Letterbox | None = None
) -> dict[str, Any]:
    return {
        "image": torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))),
        "boxes": torch.from_numpy(np.asarray(boxes, dtype=np.float32).reshape(-1, 4)),
        "labels": torch.from_numpy(np.asarray(labels, dtype=np.int64)),
        "image_id": image_id,
        "letterbox": letterbox,
    }


class TrainDataset(Dataset):
    """Augmented training samples at ``imgsz x imgsz`` (see the module docstring for the order of operations).

    With probability ``mosaic`` a sample is a 4-image mosaic (``augment.mosaic4``) cropped back to ``imgsz`` by the
    random affine; otherwise it is letterboxed and then warped by the random affine. Then HSV jitter on RGB only,
    then up-down and left-right flips. ``set_epoch`` picks the epoch (and whether mosaic is on) before each pass.
    """

    def __init__(self, source: SampleSource, imgsz: int, augment: AugmentSettings, seed: int = 0):
        if len(source) == 0:
            raise HarnessError("no training images: the fold's training groups are empty")
        self.source, self.imgsz, self.aug, self.seed = source, int(imgsz), augment, int(seed)
        self.epoch = 0
        self.mosaic_on = augment.mosaic > 0

    def set_epoch(self, epoch: int, mosaic: bool = True) -> None:
        self.epoch = int(epoch)
        self.mosaic_on = bool(mosaic) and self.aug.mosaic > 0

    def __len__(self) -> int:
        return len(self.source)

    def rng(self, k: int) -> np.random.Generator:
        return np.random.default_rng((self.seed, self.epoch, int(k)))

    def _resized(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        img, r, _ = self.source.resized(k, self.imgsz)
        boxes, labels = self.source.targets(k)
        return img, boxes * r, labels

    def __getitem__(self, k: int) -> dict[str, Any]:
        aug, s = self.aug, self.imgsz
        rng = self.rng(k)
        use_mosaic = rng.random() < aug.mosaic and self.mosaic_on
        others = rng.integers(0, len(self.source), 3)
        if use_mosaic:
            parts = [self._resized(j) for j in (k, *others.tolist())]
            img, boxes, labels = A.mosaic4([p[0] for p in parts], [p[1] for p in parts], [p[2] for p in parts], s, rng)
            border = -s // 2
        else:
            boxes, labels = self.source.targets(k)
            img, lb = A.pad_letterbox(*self.source.resized(k, s), size=s)
            boxes = A.scale_boxes(boxes, lb.ratio, lb.pad)
            border = 0
        img, boxes, labels = A.random_affine(img, boxes, labels, rng, border=border, **aug.affine())
        img = A.augment_hsv(img, rng, aug.hsv_h, aug.hsv_s, aug.hsv_v)
        if rng.random() < aug.flipud:
            img, boxes = A.flip_ud(img, boxes)
        if rng.random() < aug.fliplr:
            img, boxes = A.flip_lr(img, boxes)
        return _item(img, boxes, labels, self.source.image_id(k))


class LetterboxDataset(Dataset):
    """Evaluation samples: letterboxed to ``imgsz x imgsz``, no augmentation, with the letterbox record to undo it."""

    def __init__(self, source: SampleSource, imgsz: int):
        self.source, self.imgsz = source, int(imgsz)

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, k: int) -> dict[str, Any]:
        img, lb = A.pad_letterbox(*self.source.resized(k, self.imgsz), size=self.imgsz)
        boxes, labels = self.source.targets(k)
        return _item(img, A.scale_boxes(boxes, lb.ratio, lb.pad), labels, self.source.image_id(k), lb)


@dataclass
class Batch:
    """A collated batch: images ``uint8 [B, C, H, W]``, per-image targets, ids and letterbox records."""

    images: torch.Tensor
    targets: list[dict[str, torch.Tensor]]
    image_ids: list[int]
    letterboxes: list[A.Letterbox | None]

    def __len__(self) -> int:
        return len(self.image_ids)


def collate(items: list[dict[str, Any]]) -> Batch:
    return Batch(
        images=torch.stack([it["image"] for it in items]),
        targets=[{"boxes": it["boxes"], "labels": it["labels"]} for it in items],
        image_ids=[it["image_id"] for it in items],
        letterboxes=[it["letterbox"] for it in items],
    )


def to_inputs(
    images: torch.Tensor,
    input_kind: str = "single",
    thermal_channels: int = 3,
    device: torch.device | str = "cpu",
    channels_last: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """uint8 ``[B, C, H, W]`` -> the detector's inputs, floats in 0..1 (see the module docstring)."""
    x = images.to(device, non_blocking=True).float().div_(255.0)
    if input_kind == "single":
        return x.contiguous(memory_format=torch.channels_last) if channels_last else x
    if input_kind != "dual":
        raise ConfigError(f"unknown detector input kind {input_kind!r}")
    if x.shape[1] != 4:
        raise ConfigError(
            f"a dual-stream detector needs an encoding with one channel for its thermal stream, got {x.shape[1] - 3} "
            f"extra channel(s); choose an encoding such as 'ir8' or 'c2' with --encoding"
        )
    rgb = x[:, :3].contiguous()
    thermal = x[:, 3:4].repeat(1, int(thermal_channels), 1, 1)
    if channels_last:
        rgb = rgb.contiguous(memory_format=torch.channels_last)
        thermal = thermal.contiguous(memory_format=torch.channels_last)
    return rgb, thermal


def targets_to(targets: list[dict[str, torch.Tensor]], device: torch.device | str) -> list[dict[str, torch.Tensor]]:
    return [{k: v.to(device, non_blocking=True) for k, v in t.items()} for t in targets]


class EpochSampler(Sampler[int]):
    """A shuffled order that depends only on ``(seed, epoch)``; ``max_images`` keeps the first N of it.

    Under ``torchrun`` (``world > 1``) process ``rank`` takes its share of that order
    (``harness.distributed.shard_order``: every ``world``-th index, padded by wrapping around so that every process
    runs the same number of iterations); together the processes see the order a single process would see.
    """

    def __init__(
        self, n: int, seed: int = 0, max_images: int | None = None, shuffle: bool = True, rank: int = 0, world: int = 1
    ):
        self.n, self.seed, self.shuffle = int(n), int(seed), shuffle
        self.max_images = None if max_images is None else max(1, int(max_images))
        self.rank, self.world = int(rank), int(world)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def full_order(self) -> list[int]:
        """The epoch's order over all processes."""
        if not self.shuffle:
            idx = list(range(self.n))
        else:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            idx = torch.randperm(self.n, generator=g).tolist()
        return idx[: self.max_images] if self.max_images is not None else idx

    def order(self) -> list[int]:
        """This process's part of the epoch's order (all of it for a single process)."""
        if self.world <= 1:
            return self.full_order()
        from harness.distributed import shard_order

        return shard_order(self.full_order(), self.rank, self.world)

    def __iter__(self) -> Iterator[int]:
        return iter(self.order())

    def __len__(self) -> int:
        total = self.n if self.max_images is None else min(self.n, self.max_images)
        return -(-total // self.world) if self.world > 1 else total


def train_loader(dataset: TrainDataset, batch: int, workers: int = 0, seed: int = 0, **order: Any) -> DataLoader:
    """Training batches of ``batch`` images for process ``rank`` of ``world`` (one process: the whole order);
    ``order``: the rest of ``EpochSampler``'s settings (``max_images``, ``rank``, ``world``)."""
    sampler = EpochSampler(len(dataset), seed=seed, **order)
    return DataLoader(
        dataset,
        batch_size=int(batch),
        sampler=sampler,
        num_workers=int(workers),
        collate_fn=collate,
        drop_last=False,
        generator=torch.Generator().manual_seed(int(seed)),
        persistent_workers=False,
    )


def eval_loader(dataset: Dataset, batch: int, workers: int = 0) -> DataLoader:
    return DataLoader(dataset, batch_size=int(batch), shuffle=False, num_workers=int(workers), collate_fn=collate)
