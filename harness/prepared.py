"""Prepared samples on disk: the sensing pipeline's output, written once, memory-mapped by every run.

A prepared dataset is a folder::

    manifest.json      dataset name, categories, fingerprint, count, skipped-file summary, creation time
    samples.json       one record per sample: image_id, group, height, width, offsets, box count, meta
    rgb.u8             every sample's RGB (HxWx3 uint8) back to back
    ir8.u8             every sample's 8-bit thermal (HxW uint8)
    thermal.f32        every sample's temperature in C (HxW float32); absent for 8-bit-only datasets
    boxes.f32, labels.i64   all boxes (Nx4 xyxy) and labels, back to back
    enc/<name>-<hash>.u8    an encoding's channel for every sample, computed on first use and kept

``PreparedWriter`` streams samples into a temporary folder and renames it into place when complete, so an
interrupted preparation never leaves a half-written dataset behind. ``PreparedDataset`` opens the arrays with
``numpy.memmap``: loading a sample is a slice, not a decode.

COCO ground truth is derived from the same arrays (``coco()``): category ``id = label + 1``, boxes in the thermal
frame, ``area = w * h``, ``iscrowd = 0``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from harness.errors import DataError, SampleError
from harness.io import atomic_write, atomic_write_json, make_temp_dir, read_json
from harness.sample import AlignedSample, validate_sample

PREPARED_SCHEMA = 1


class PreparedWriter:
    """Write samples into ``folder`` (created atomically on ``close``). Use as a context manager."""

    def __init__(self, folder: str | Path, dataset: str, categories: Sequence[str], fingerprint: str = "",
                 extra: dict[str, Any] | None = None):
        self.folder = Path(folder)
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = make_temp_dir(prefix=f".{self.folder.name}.", suffix=".tmp", dir=self.folder.parent)
        self.dataset, self.categories = dataset, list(categories)
        self.fingerprint, self.extra = fingerprint, dict(extra or {})
        self.records: list[dict[str, Any]] = []
        self._files = {name: open(self.tmp / name, "wb") for name in ("rgb.u8", "ir8.u8", "thermal.f32", "boxes.f32", "labels.i64")}
        self._px = 0
        self._nbox = 0
        self._has_thermal: bool | None = None
        self._ids: set[int] = set()
        self._closed = False

    def add(self, sample: AlignedSample) -> None:
        validate_sample(sample, num_classes=len(self.categories))
        if sample.image_id in self._ids:
            raise SampleError(f"{sample.name}: duplicate image_id {sample.image_id}")
        has_thermal = sample.thermal is not None
        if self._has_thermal is None:
            self._has_thermal = has_thermal
        elif self._has_thermal != has_thermal:
            raise SampleError(f"{sample.name}: field 'thermal': some samples have radiometric thermal and some do not")
        h, w = sample.height, sample.width
        self._files["rgb.u8"].write(np.ascontiguousarray(sample.rgb).tobytes())
        self._files["ir8.u8"].write(np.ascontiguousarray(sample.ir8).tobytes())
        if has_thermal:
            self._files["thermal.f32"].write(np.ascontiguousarray(sample.thermal).tobytes())
        self._files["boxes.f32"].write(np.ascontiguousarray(sample.boxes).tobytes())
        self._files["labels.i64"].write(np.ascontiguousarray(sample.labels).tobytes())
        n = int(len(sample.boxes))
        self.records.append({
            "image_id": int(sample.image_id), "group": sample.group, "height": h, "width": w,
            "px": self._px, "box": self._nbox, "n": n, "meta": sample.meta,
        })
        self._ids.add(int(sample.image_id))
        self._px += h * w
        self._nbox += n

    def close(self, report: dict[str, Any] | None = None) -> Path:
        for f in self._files.values():
            f.flush()
            os.fsync(f.fileno())
            f.close()
        if not self._has_thermal:
            (self.tmp / "thermal.f32").unlink(missing_ok=True)
        (self.tmp / "enc").mkdir(exist_ok=True)
        atomic_write_json(self.tmp / "samples.json", self.records, indent=None)
        manifest = {
            "schema": PREPARED_SCHEMA, "dataset": self.dataset, "categories": self.categories,
            "fingerprint": self.fingerprint, "count": len(self.records), "instances": self._nbox,
            "radiometric": bool(self._has_thermal), "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "report": report or {}, **self.extra,
        }
        atomic_write_json(self.tmp / "manifest.json", manifest)
        if self.folder.exists():
            old = self.folder.with_name(f".{self.folder.name}.old-{os.getpid()}")
            os.replace(self.folder, old)
            os.replace(self.tmp, self.folder)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(self.tmp, self.folder)
        self._closed = True
        return self.folder

    def abort(self) -> None:
        for f in self._files.values():
            f.close()
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._closed = True

    def __enter__(self) -> "PreparedWriter":
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        if exc_type is not None and not self._closed:
            self.abort()
        elif not self._closed:
            self.close()


def _params_hash(params: dict[str, Any]) -> str:
    return hashlib.sha1(json.dumps(params, sort_keys=True, default=str).encode()).hexdigest()[:10]


class PreparedDataset:
    """Read-only, memory-mapped access to a prepared dataset folder."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        manifest_path = self.folder / "manifest.json"
        if not manifest_path.exists():
            raise DataError(f"{self.folder}: not a prepared dataset (no manifest.json); run `harness prepare`")
        self.manifest = read_json(manifest_path)
        if self.manifest.get("schema") != PREPARED_SCHEMA:
            raise DataError(f"{manifest_path}: prepared-data schema {self.manifest.get('schema')}, expected {PREPARED_SCHEMA}; prepare again")
        self.records: list[dict[str, Any]] = read_json(self.folder / "samples.json")
        self.categories: list[str] = list(self.manifest["categories"])
        self.name: str = self.manifest["dataset"]
        self.radiometric: bool = bool(self.manifest.get("radiometric"))
        self._index = {int(r["image_id"]): i for i, r in enumerate(self.records)}
        self._rgb = self._map("rgb.u8", np.uint8)
        self._ir8 = self._map("ir8.u8", np.uint8)
        self._thermal = self._map("thermal.f32", np.float32) if self.radiometric else None
        self._boxes = self._map("boxes.f32", np.float32)
        self._labels = self._map("labels.i64", np.int64)
        self._enc: dict[str, np.memmap] = {}

    def _map(self, name: str, dtype: Any) -> np.ndarray:
        path = self.folder / name
        if not path.exists():
            raise DataError(f"{path}: missing from the prepared dataset; prepare again")
        if path.stat().st_size == 0:
            return np.zeros(0, dtype=dtype)
        return np.memmap(path, dtype=dtype, mode="r")

    # ------------------------------------------------------------------ samples
    def __len__(self) -> int:
        return len(self.records)

    @property
    def image_ids(self) -> list[int]:
        return [int(r["image_id"]) for r in self.records]

    @property
    def groups(self) -> list[str]:
        return [r["group"] for r in self.records]

    def index_of(self, image_id: int) -> int:
        return self._index[int(image_id)]

    def indices(self, groups: Iterable[str]) -> list[int]:
        wanted = set(groups)
        return [i for i, r in enumerate(self.records) if r["group"] in wanted]

    def __getitem__(self, i: int) -> AlignedSample:
        r = self.records[i]
        h, w, px, b, n = r["height"], r["width"], r["px"], r["box"], r["n"]
        return AlignedSample(
            image_id=int(r["image_id"]),
            rgb=self._rgb[px * 3:(px + h * w) * 3].reshape(h, w, 3),
            thermal=None if self._thermal is None else self._thermal[px:px + h * w].reshape(h, w),
            ir8=self._ir8[px:px + h * w].reshape(h, w),
            boxes=self._boxes[b * 4:(b + n) * 4].reshape(n, 4),
            labels=self._labels[b:b + n],
            group=r["group"],
            meta=r["meta"],
        )

    def __iter__(self) -> Iterator[AlignedSample]:
        for i in range(len(self)):
            yield self[i]

    def targets(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(boxes, labels) of sample ``i`` without touching the image arrays."""
        r = self.records[i]
        b, n = r["box"], r["n"]
        return self._boxes[b * 4:(b + n) * 4].reshape(n, 4), self._labels[b:b + n]

    # ------------------------------------------------------------------ encodings
    def channel(self, i: int, encoding: Any, params: dict[str, Any] | None = None) -> np.ndarray | None:
        """The encoding's uint8 HxW channel of sample ``i`` (computed for the whole dataset on first use)."""
        if getattr(encoding, "channels", 1) == 0:
            return None
        arr = self._encoded(encoding, params or {})
        r = self.records[i]
        return arr[r["px"]:r["px"] + r["height"] * r["width"]].reshape(r["height"], r["width"])

    def _encoded(self, encoding: Any, params: dict[str, Any]) -> np.ndarray:
        full = {**dict(getattr(encoding, "params", {})), **params}
        key = f"{encoding.name}-{_params_hash(full)}"
        if key in self._enc:
            return self._enc[key]
        path = self.folder / "enc" / f"{key}.u8"
        if not path.exists():
            def write(f: Any) -> None:
                for s in self:
                    out = encoding.encode(s, **params)
                    if out is None or out.dtype != np.uint8 or out.shape != (s.height, s.width):
                        got = None if out is None else (out.dtype, out.shape)
                        raise SampleError(f"{s.name}: encoding {encoding.name!r} returned {got}, expected uint8 {(s.height, s.width)}")
                    f.write(np.ascontiguousarray(out).tobytes())
            atomic_write(path, write)
            atomic_write_json(path.with_suffix(".json"), {"encoding": encoding.name, "params": full})
        self._enc[key] = self._map(f"enc/{key}.u8", np.uint8)
        return self._enc[key]

    # ------------------------------------------------------------------ COCO
    def coco(self, indices: Sequence[int] | None = None) -> dict[str, Any]:
        """COCO ground truth (thermal frame) for the given sample indices (all when None)."""
        idx = range(len(self)) if indices is None else indices
        images, anns = [], []
        ann_id = 1
        for i in idx:
            r = self.records[i]
            images.append({"id": int(r["image_id"]), "width": r["width"], "height": r["height"],
                           "file_name": str(r["meta"].get("file_name", r["image_id"])), "group": r["group"]})
            boxes, labels = self.targets(i)
            for (x1, y1, x2, y2), lab in zip(boxes.tolist(), labels.tolist()):
                w, h = x2 - x1, y2 - y1
                anns.append({"id": ann_id, "image_id": int(r["image_id"]), "category_id": int(lab) + 1,
                             "bbox": [x1, y1, w, h], "area": w * h, "iscrowd": 0})
                ann_id += 1
        cats = [{"id": k + 1, "name": n} for k, n in enumerate(self.categories)]
        return {"info": {"dataset": self.name, "frame": "thermal"}, "images": images, "annotations": anns, "categories": cats}

    def support(self, indices: Sequence[int] | None = None) -> dict[str, Any]:
        """Images and instances (per category) of a subset: the 'support' recorded with every number."""
        idx = list(range(len(self))) if indices is None else list(indices)
        counts = np.zeros(len(self.categories), dtype=np.int64)
        for i in idx:
            _, labels = self.targets(i)
            counts += np.bincount(np.asarray(labels), minlength=len(self.categories))[: len(self.categories)]
        return {"images": len(idx), "instances": int(counts.sum()),
                "categories": {n: int(c) for n, c in zip(self.categories, counts)}}
