"""Reading a prepared dataset: ``PreparedDataset`` opens a cache folder read-only and hands out samples, encoded
channels, COCO ground truth and support counts.

The raw form's arrays are opened with ``numpy.memmap`` (loading a sample is a slice, not a decode); the compact
form's are decoded per sample (``harness.cache.forms``), and an 8-bit sample recorded as a reference is read from
its source files and checked against the recorded digest the first time a process loads it. Every form returns the
same arrays. An encoding's channel is computed for the whole dataset on first use and kept under ``enc/``: raw
uint8 (raw form), or compressed per sample or recomputed, whichever measured cheaper (compact form).

COCO ground truth is derived from the same arrays (``coco()``): category ``id = label + 1``, boxes in the thermal
frame, ``area = w * h``, ``iscrowd = 0``, and 1 for a crowd region (the box indices a sample's ``meta["crowd"]`` names;
``targets`` leaves those out, so training never uses them as instances).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from harness.api import AlignedSample
from harness.cache import forms as CF
from harness.cache.forms import PREPARED_SCHEMA
from harness.contracts import encode
from harness.errors import DataError
from harness.io import atomic_write, atomic_write_json, read_json


def _frozen(a: np.ndarray) -> np.ndarray:
    """Read-only, like a slice of the raw form's read-only memory map."""
    a.flags.writeable = False
    return a


def _encoding_key(encoding: Any, params: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """(``<name>-<hash of its full parameters>``, the full parameters): where an encoding's channel is kept."""
    full = {**dict(getattr(encoding, "params", {})), **params}
    digest = hashlib.sha1(json.dumps(full, sort_keys=True, default=str).encode()).hexdigest()[:10]
    return f"{encoding.name}-{digest}", full


class PreparedDataset:
    """Read-only, memory-mapped access to a prepared dataset folder."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        manifest_path = self.folder / "manifest.json"
        if not manifest_path.exists():
            raise DataError(f"{self.folder}: not a prepared dataset (no manifest.json); run `harness prepare`")
        self.manifest = read_json(manifest_path)
        if self.manifest.get("schema") != PREPARED_SCHEMA:
            raise DataError(
                f"{manifest_path}: prepared-data schema {self.manifest.get('schema')}, expected "
                f"{PREPARED_SCHEMA}; prepare again"
            )
        self.records: list[dict[str, Any]] = read_json(self.folder / "samples.json")
        self.categories: list[str] = list(self.manifest["categories"])
        self.name: str = self.manifest["dataset"]
        self.radiometric: bool = bool(self.manifest.get("radiometric"))
        self._index = {int(r["image_id"]): i for i, r in enumerate(self.records)}
        self.form: str = self.manifest.get("form", "raw")
        if self.form not in CF.FORMS:
            raise DataError(f"{manifest_path}: unknown cache form {self.form!r}; prepare again")
        if self.form == "raw":
            self._rgb = self._map("rgb.u8", np.uint8)
            self._ir8 = self._map("ir8.u8", np.uint8)
            self._thermal = self._map("thermal.f32", np.float32) if self.radiometric else None
        else:
            self._rgb = self._map("rgb.pack", np.uint8)
            self._ir8 = self._map("ir8.pack", np.uint8)
            self._thermal = self._map("thermal.pack", np.uint8) if self.radiometric else None
        self.sources = [Path(p) for p in self.manifest.get("sources", [])]
        self.codec: str = (self.manifest.get("codec") or {}).get("u8", "png")
        self._verified: set[tuple[int, str]] = set()
        self._last: tuple[int, AlignedSample] | None = None
        self._boxes = self._map("boxes.f32", np.float32)
        self._labels = self._map("labels.i64", np.int64)
        self._enc: dict[str, np.ndarray] = {}

    def _map(self, name: str, dtype: Any) -> np.ndarray:
        path = self.folder / name
        if not path.exists():
            raise DataError(f"{path}: missing from the prepared dataset; prepare again")
        if path.stat().st_size == 0:
            return np.zeros(0, dtype=dtype)
        return np.memmap(path, dtype=dtype, mode="r")

    def check_sizes(self) -> None:
        """The arrays hold exactly what ``samples.json`` describes (a truncated copy is a ``DataError`` naming the
        file), and what a compact cache needs is here: its codec's package and its referenced source folders."""
        px = sum(r["height"] * r["width"] for r in self.records)
        nb = sum(r["n"] for r in self.records)
        sizes = {"rgb.u8": px * 3, "ir8.u8": px, "boxes.f32": nb * 16, "labels.i64": nb * 8}
        if self.radiometric:
            sizes["thermal.f32"] = px * 4
        if self.form != "raw":
            ends = {
                name: max([sum(r[ch]) for r in self.records if ch in r], default=0)
                for name, ch in (("rgb.pack", "rgb"), ("ir8.pack", "ir8"), ("thermal.pack", "thermal"))
            }
            sizes = {
                "boxes.f32": nb * 16,
                "labels.i64": nb * 8,
                "rgb.pack": ends["rgb.pack"],
                "ir8.pack": ends["ir8.pack"],
            }
            if self.radiometric:
                sizes["thermal.pack"] = ends["thermal.pack"]
            if self.codec == "zstd":
                CF.zstd_module(str(self.folder))  # written with zstandard: a DataError (so prepared again) without it
            missing = [str(p) for p in self.sources if not p.is_dir()]
            if missing:
                raise DataError(f"the source folder(s) its samples refer to are gone: {', '.join(missing)}")
        for name, size in sizes.items():
            got = (self.folder / name).stat().st_size
            if got != size:
                raise DataError(f"{self.folder / name}: {got} bytes, expected {size}")

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

    def _pixels(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(rgb, ir8, thermal) of sample ``i``: memory-mapped slices (raw form) or decoded (compact form)."""
        r = self.records[i]
        h, w, px = r["height"], r["width"], r["px"]
        if self.form == "raw":
            return (
                self._rgb[px * 3 : (px + h * w) * 3].reshape(h, w, 3),
                self._ir8[px : px + h * w].reshape(h, w),
                None if self._thermal is None else self._thermal[px : px + h * w].reshape(h, w),
            )
        if "src" in r:
            ref = r["src"]
            rgb, ir8 = CF.load_reference(self.sources[ref["base"]], ref, (h, w), (i, "ir8") not in self._verified)
            self._verified.update(((i, "rgb"), (i, "ir8")))
            return _frozen(rgb), _frozen(ir8), None
        where = f"{self.folder} sample {r['image_id']}"
        rgb = CF.decode_u8(self._chunk(self._rgb, r["rgb"]), (h, w, 3), where, self.codec)
        ir8 = CF.decode_u8(self._chunk(self._ir8, r["ir8"]), (h, w), where, self.codec)
        th = None
        if self._thermal is not None:
            th = CF.decode_f32(self._chunk(self._thermal, r["thermal"]), (h, w), where)
        return _frozen(rgb), _frozen(ir8), None if th is None else _frozen(th)

    def rgb(self, i: int) -> np.ndarray:
        """Sample ``i``'s RGB alone (``self[i].rgb`` without decoding the other channels of a compact cache)."""
        r = self.records[i]
        if self.form == "raw" or (self._last is not None and self._last[0] == i):
            return self[i].rgb
        h, w = r["height"], r["width"]
        if "src" in r:  # the RGB file alone (its digest checked the first time this process reads it)
            ref = r["src"]
            verify = (i, "rgb") not in self._verified
            (rgb,) = CF.load_reference(self.sources[ref["base"]], ref, (h, w), verify, ("rgb",))
            self._verified.add((i, "rgb"))
            return _frozen(rgb)
        where = f"{self.folder} sample {r['image_id']}"
        return _frozen(CF.decode_u8(self._chunk(self._rgb, r["rgb"]), (h, w, 3), where, self.codec))

    @staticmethod
    def _chunk(arr: np.ndarray, at: Sequence[int]) -> np.ndarray:
        return arr[at[0] : at[0] + at[1]]

    def verify(self, indices: Iterable[int] | None = None) -> list[str]:
        """Decode every sample (all when None) and check referenced source files; the errors, one per sample."""
        errors = []
        for i in range(len(self)) if indices is None else indices:
            self._verified.difference_update(((i, "rgb"), (i, "ir8")))
            try:
                self._pixels(i)
            except DataError as exc:
                errors.append(str(exc))
        return errors

    def __getitem__(self, i: int) -> AlignedSample:
        r = self.records[i]
        b, n = r["box"], r["n"]
        if self._last is not None and self._last[0] == i:
            return self._last[1]
        rgb, ir8, thermal = self._pixels(i)
        sample = AlignedSample(
            image_id=int(r["image_id"]),
            rgb=rgb,
            thermal=thermal,
            ir8=ir8,
            boxes=self._boxes[b * 4 : (b + n) * 4].reshape(n, 4),
            labels=self._labels[b : b + n],
            group=r["group"],
            meta=r["meta"],
        )
        if self.form != "raw":
            self._last = (i, sample)  # the loader reads a sample's RGB and then its encoding: decode once
        return sample

    def __iter__(self) -> Iterator[AlignedSample]:
        for i in range(len(self)):
            yield self[i]

    def targets(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(boxes, labels) of sample ``i`` without touching the image arrays; crowd regions (``crowd_targets``) are
        left out: they are never training instances."""
        r = self.records[i]
        b, n = r["box"], r["n"]
        boxes, labels = self._boxes[b * 4 : (b + n) * 4].reshape(n, 4), self._labels[b : b + n]
        crowd = self._crowd(r)
        if crowd is None:
            return boxes, labels
        keep = np.ones(n, bool)
        keep[crowd] = False
        return boxes[keep], labels[keep]

    def crowd_targets(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(boxes, labels) of sample ``i``'s crowd regions (COCO ``iscrowd`` 1, the sample's ``meta["crowd"]``
        indices): the evaluation ignores detections on them."""
        r = self.records[i]
        b, n = r["box"], r["n"]
        crowd = self._crowd(r)
        boxes, labels = self._boxes[b * 4 : (b + n) * 4].reshape(n, 4), self._labels[b : b + n]
        if crowd is None:
            return boxes[:0], labels[:0]
        return boxes[crowd], labels[crowd]

    @staticmethod
    def _crowd(record: Mapping[str, Any]) -> np.ndarray | None:
        meta = record.get("meta")
        crowd = meta.get("crowd") if isinstance(meta, dict) else None
        if not crowd:
            return None
        idx = np.asarray(crowd, np.int64).reshape(-1)
        return idx[(idx >= 0) & (idx < int(record["n"]))]

    def content_digest(self, indices: Sequence[int], encoding: Any = None, params: dict[str, Any] | None = None) -> str:
        """blake2b of what a detector sees of the samples at ``indices``, in that order: image id, group, RGB pixels,
        the encoding's channel (none for RGB only; with ``encoding=None`` the temperatures, or the 8-bit thermal
        picture, of the aligned sample instead), boxes and labels. It identifies samples by their content, so a
        change to the code or the cache key that leaves the samples identical leaves it unchanged (reference results
        rest on it: ``harness.references``)."""
        h = hashlib.blake2b(digest_size=16)
        h.update(f"{getattr(encoding, 'name', 'none')}\n".encode())
        for i in indices:
            r = self.records[i]
            rgb = np.ascontiguousarray(self.rgb(i))
            h.update(f"{int(r['image_id'])}\t{r['group']}\t{rgb.shape}\n".encode())
            h.update(rgb.tobytes())
            ch: np.ndarray | None
            if encoding is None:  # the aligned sample itself: temperatures (or the 8-bit thermal picture)
                sample = self[i]
                ch = sample.thermal if sample.thermal is not None else sample.ir8
            else:
                ch = self.channel(i, encoding, params)
            if ch is not None:
                h.update(np.ascontiguousarray(ch).tobytes())
            boxes, labels = self.targets(i)
            h.update(np.ascontiguousarray(boxes, dtype=np.float32).tobytes())
            h.update(np.ascontiguousarray(labels, dtype=np.int64).tobytes())
        return h.hexdigest()

    # ------------------------------------------------------------------ encodings
    def channel(self, i: int, encoding: Any, params: dict[str, Any] | None = None) -> np.ndarray | None:
        """The encoding's uint8 HxW channel of sample ``i`` (computed for the whole dataset on first use)."""
        if getattr(encoding, "channels", 1) == 0:
            return None
        r = self.records[i]
        if self.form != "raw":
            return self._compact_channel(i, encoding, params or {})
        arr = self._encoded(encoding, params or {})
        return arr[r["px"] : r["px"] + r["height"] * r["width"]].reshape(r["height"], r["width"])

    def _compact_channel(self, i: int, encoding: Any, params: dict[str, Any]) -> np.ndarray:
        """Compact form: the encoding is either stored (compressed per sample) or recomputed from the decoded sample,
        whichever measured cheaper on the first samples when the encoding was first used (``enc/<key>.json``)."""
        key, full = _encoding_key(encoding, params)
        if key not in self._enc:
            self._enc[key] = self._compact_encoded(key, encoding, params, full)
        store = self._enc[key]
        r = self.records[i]
        if store is None:
            return _frozen(encode(encoding, self[i], **params))
        pack, idx = store  # type: ignore[misc]
        at = idx[i]
        return _frozen(
            CF.decode_u8(
                pack[int(at[0]) : int(at[0]) + int(at[1])],
                (r["height"], r["width"]),
                f"{self.folder / 'enc' / key}.pack sample {r['image_id']}",
                self.codec,
            )
        )

    def _compact_encoded(self, key: str, encoding: Any, params: dict[str, Any], full: dict[str, Any]) -> Any:
        info_path = self.folder / "enc" / f"{key}.json"
        pack_path = self.folder / "enc" / f"{key}.pack"
        idx_path = self.folder / "enc" / f"{key}.idx"
        if not info_path.exists():
            probe = range(min(len(self), 3))
            t_enc = t_dec = 0.0
            for i in probe:  # measure: recompute from the decoded sample vs decode the stored image
                s = self[i]
                t0 = time.perf_counter()
                out = encode(encoding, s, **params)
                t1 = time.perf_counter()
                data = CF.encode_u8(out, self.codec)
                t2 = time.perf_counter()
                CF.decode_u8(data, out.shape, key, self.codec)
                t_enc, t_dec = t_enc + t1 - t0, t_dec + time.perf_counter() - t2
            store = "recompute" if t_enc <= t_dec else "pack"
            if store == "pack":
                offsets = np.zeros((len(self), 2), np.int64)

                def write(f: Any) -> None:
                    pos = 0
                    for i in range(len(self)):
                        data = CF.encode_u8(encode(encoding, self[i], **params), self.codec)
                        f.write(data)
                        offsets[i] = (pos, len(data))
                        pos += len(data)

                atomic_write(pack_path, write)
                atomic_write(idx_path, lambda f: f.write(offsets.astype("<i8").tobytes()))
            ms = {"compute": round(t_enc * 1e3, 3), "decode": round(t_dec * 1e3, 3)}
            atomic_write_json(info_path, {"encoding": encoding.name, "params": full, "store": store, "probe_ms": ms})
        info = read_json(info_path)
        if info.get("store") == "recompute":
            return None
        return self._map(f"enc/{key}.pack", np.uint8), self._map(f"enc/{key}.idx", np.int64).reshape(-1, 2)

    def _encoded(self, encoding: Any, params: dict[str, Any]) -> np.ndarray:
        key, full = _encoding_key(encoding, params)
        if key in self._enc:
            return self._enc[key]
        path = self.folder / "enc" / f"{key}.u8"
        if not path.exists():

            def write(f: Any) -> None:
                for s in self:
                    f.write(np.ascontiguousarray(encode(encoding, s, **params)).tobytes())

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
            images.append(
                {
                    "id": int(r["image_id"]),
                    "width": r["width"],
                    "height": r["height"],
                    "file_name": str(r["meta"].get("file_name", r["image_id"])),
                    "group": r["group"],
                }
            )
            for crowd, (boxes, labels) in ((0, self.targets(i)), (1, self.crowd_targets(i))):
                for (x1, y1, x2, y2), lab in zip(boxes.tolist(), labels.tolist()):
                    w, h = x2 - x1, y2 - y1
                    anns.append(
                        {
                            "id": ann_id,
                            "image_id": int(r["image_id"]),
                            "category_id": int(lab) + 1,
                            "bbox": [x1, y1, w, h],
                            "area": w * h,
                            "iscrowd": crowd,
                        }
                    )
                    ann_id += 1
        cats = [{"id": k + 1, "name": n} for k, n in enumerate(self.categories)]
        return {
            "info": {"dataset": self.name, "frame": "thermal"},
            "images": images,
            "annotations": anns,
            "categories": cats,
        }

    def support(self, indices: Sequence[int] | None = None) -> dict[str, Any]:
        """Images and instances (per category) of a subset: the 'support' recorded with every number."""
        idx = list(range(len(self))) if indices is None else list(indices)
        counts = np.zeros(len(self.categories), dtype=np.int64)
        for i in idx:
            _, labels = self.targets(i)
            counts += np.bincount(np.asarray(labels), minlength=len(self.categories))[: len(self.categories)]
        return {
            "images": len(idx),
            "instances": int(counts.sum()),
            "categories": {n: int(c) for n, c in zip(self.categories, counts)},
        }
