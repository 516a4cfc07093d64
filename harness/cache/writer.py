"""Writing a prepared dataset: ``PreparedWriter`` streams validated samples into a temporary folder and renames it
into place when complete, so an interrupted preparation never leaves a half-written dataset behind.

A prepared dataset is a folder::

    manifest.json      dataset name, categories, fingerprint, count, skipped-file summary, creation time, form
    samples.json       one record per sample: image_id, group, height, width, offsets, box count, meta
    rgb.u8             every sample's RGB (HxWx3 uint8) back to back                   (raw form)
    ir8.u8             every sample's 8-bit thermal (HxW uint8)                        (raw form)
    thermal.f32        every sample's temperature in C (HxW float32); absent for 8-bit-only datasets
    rgb.pack, ir8.pack, thermal.pack   the same, compressed per sample (compact form, ``harness.cache.forms``)
    boxes.f32, labels.i64   all boxes (Nx4 xyxy) and labels, back to back
    enc/<name>-<hash>.*     an encoding's channel for every sample, computed on first use (``harness.cache.reader``)

In the compact form an 8-bit sample that is exactly what its source files decode to is recorded as a reference to
those files with a digest of their pixels, not copied.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from harness.api import AlignedSample
from harness.cache import forms as CF
from harness.cache.forms import PREPARED_SCHEMA
from harness.contracts import validate_sample
from harness.errors import SampleError
from harness.io import atomic_write_json, make_temp_dir
from harness.provenance import sample_environment


class PreparedWriter:
    """Write samples into ``folder`` (created atomically on ``close``). Use as a context manager."""

    def __init__(
        self,
        folder: str | Path,
        dataset: str,
        categories: Sequence[str],
        fingerprint: str = "",
        extra: dict[str, Any] | None = None,
        form: str = "raw",
        sources: Sequence[str | Path] = (),
        pixel_files: Any = None,
    ):
        """``form``: ``raw`` or ``compact``; ``sources``: folders whose files an 8-bit sample may reference
        (compact form); ``pixel_files(sample) -> (rgb path, thermal path) | None``: the dataset's own answer."""
        self.folder = Path(folder)
        self.form = CF.check_form(form)
        self.sources = [Path(p) for p in sources]
        self.pixel_files = pixel_files
        self.source_bytes = 0
        self.codec = CF.default_u8_codec()
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = make_temp_dir(prefix=f".{self.folder.name}.", suffix=".tmp", dir=self.folder.parent)
        self.dataset, self.categories = dataset, list(categories)
        self.fingerprint, self.extra = fingerprint, dict(extra or {})
        self.records: list[dict[str, Any]] = []
        names = ("rgb.u8", "ir8.u8", "thermal.f32") if form == "raw" else ("rgb.pack", "ir8.pack", "thermal.pack")
        self._files = {name: open(self.tmp / name, "wb") for name in (*names, "boxes.f32", "labels.i64")}
        self._pos = {name: 0 for name in names}
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
        packed: dict[str, Any] = {}
        if self.form == "raw":
            self._files["rgb.u8"].write(np.ascontiguousarray(sample.rgb).tobytes())
            self._files["ir8.u8"].write(np.ascontiguousarray(sample.ir8).tobytes())
            if has_thermal:
                self._files["thermal.f32"].write(np.ascontiguousarray(sample.thermal).tobytes())
        else:
            packed = self._pack(sample)
        self._files["boxes.f32"].write(np.ascontiguousarray(sample.boxes).tobytes())
        self._files["labels.i64"].write(np.ascontiguousarray(sample.labels).tobytes())
        n = int(len(sample.boxes))
        self.records.append(
            {
                "image_id": int(sample.image_id),
                "group": sample.group,
                "height": h,
                "width": w,
                "px": self._px,
                "box": self._nbox,
                "n": n,
                "meta": sample.meta,
                **packed,
            }
        )
        self._ids.add(int(sample.image_id))
        self._px += h * w
        self._nbox += n

    def _put(self, name: str, data: bytes) -> list[int]:
        self._files[name].write(data)
        at = self._pos[name]
        self._pos[name] += len(data)
        return [at, len(data)]

    def _pack(self, sample: AlignedSample) -> dict[str, Any]:
        """Compact form: a reference to the source files when they decode to exactly these pixels, else PNG."""
        out: dict[str, Any] = {}
        if sample.thermal is None and self.sources:
            files = self.pixel_files(sample) if self.pixel_files is not None else None
            ref = CF.find_reference(sample, self.sources, files)
            if ref is not None:
                self.source_bytes += ref.pop("bytes")
                ref["base"] = self.sources.index(ref["base"])
                return {"src": ref}
        out["rgb"] = self._put("rgb.pack", CF.encode_u8(sample.rgb, self.codec))
        out["ir8"] = self._put("ir8.pack", CF.encode_u8(sample.ir8, self.codec))
        if sample.thermal is not None:
            out["thermal"] = self._put("thermal.pack", CF.encode_f32(sample.thermal))
        return out

    def close(self, report: dict[str, Any] | None = None) -> Path:
        for f in self._files.values():
            f.flush()
            os.fsync(f.fileno())
            f.close()
        if not self._has_thermal:
            (self.tmp / "thermal.f32").unlink(missing_ok=True)
            (self.tmp / "thermal.pack").unlink(missing_ok=True)
        (self.tmp / "enc").mkdir(exist_ok=True)
        atomic_write_json(self.tmp / "samples.json", self.records, indent=None)
        manifest = {
            "schema": PREPARED_SCHEMA,
            "dataset": self.dataset,
            "categories": self.categories,
            "fingerprint": self.fingerprint,
            "count": len(self.records),
            "instances": self._nbox,
            "radiometric": bool(self._has_thermal),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "report": report or {},
            "form": self.form,
            # the packages that shaped these samples (a release of OpenCV can move them): harness.provenance
            "environment": sample_environment(),
            **self.extra,
        }
        if self.form != "raw":
            manifest["codec"] = {"u8": self.codec, "thermal": "table+png16"}
        if any("src" in r for r in self.records):
            manifest["sources"] = [str(p.resolve()) for p in self.sources]
            manifest["referenced_bytes"] = self.source_bytes
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
