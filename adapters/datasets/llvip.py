"""LLVIP (Jia et al., ICCV workshops 2021): aligned visible/infrared pairs of pedestrians, mostly at night.

Release layout (``dataset.root`` or ``$HARNESS_LLVIP`` points at ``LLVIP/`` or at the folder holding it)::

    LLVIP/Annotations/<stem>.xml              Pascal VOC, class person, one label set shared by the pair
    LLVIP/infrared/train/<stem>.jpg ...       infrared, 8-bit (grey stored as three channels)
    LLVIP/infrared/test/<stem>.jpg ...
    LLVIP/visible/train/<stem>.jpg ...        visible, the same name as its infrared partner
    LLVIP/visible/test/<stem>.jpg ...

15,488 pairs: 12,025 train (names ``01...``), 3,463 test (names ``19...``); 1280x1024. ``Annotations/`` holds the
XMLs of both splits.

What the loader does:

* **Pairs by name** within a split: ``infrared/<split>/<stem>.jpg`` with ``visible/<split>/<stem>.jpg`` and
  ``Annotations/<stem>.xml``. A frame missing any of the three is a counted drop.
* **Boxes through the shared VOC reader** (``adapters.datasets.voc``): 1-based inclusive pixel indices become
  ``(xmin - 1, ymin - 1, xmax, ymax)``; ``voc_convention`` and ``difficult`` as for M3FD. A class other than
  ``person`` skips the pair (counted, ``unknown class``). The authors' YOLO conversion script reads the integer
  coordinates as written; ``voc_convention: zero-based`` reproduces those boxes.
* **The official split**: the groups are the two folders ``train`` and ``test``; the one fold ``test`` trains on
  ``train`` and holds ``test`` out.
* No radiometric thermal (``thermal=None``); ``ir8`` is the infrared image.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from adapters.datasets._eightbit import (
    BoxStats,
    ImageReadError,
    clip_boxes,
    file_stat,
    read_rgb,
    read_thermal8,
    resolve_root,
    stat_digest,
)
from adapters.datasets.voc import VocStats, normalise_convention, normalise_difficult, parse_voc, to_xyxy
from harness.api import DatasetSpec, Fold, PrepareReport
from harness.errors import ConfigError, DataError
from harness.hookspecs import hookimpl
from harness.sample import AlignedSample

log = logging.getLogger(__name__)

DATASET = "llvip"
ROOT_ENV = "HARNESS_LLVIP"
CATEGORIES = ("person",)
SPLITS = ("train", "test")
IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp")
OPTIONS = {
    "root": f"LLVIP/ or the folder holding it (default: ${ROOT_ENV})",
    "strict": "raise instead of skipping a pair that cannot be used (default false)",
    "voc_convention": "one-based (VOC/labelImg pixel indices, default) or zero-based (corners taken as written)",
    "difficult": "drop (left out of training and scoring, default) or keep <difficult>1</difficult> boxes",
}
ADAPTER_VERSION = 1


def _index(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_EXTS}


class LlvipSource:
    """An opened LLVIP release (see the module docstring)."""

    name = DATASET
    categories = CATEGORIES

    def __init__(self, root: Path, strict: bool = False, voc_convention: str = "one-based", difficult: str = "drop"):
        self.root, self.strict, self.voc_convention, self.difficult = root, strict, voc_convention, difficult
        self.xml = {p.stem: p for p in sorted((root / "Annotations").glob("*.xml"))}
        #: (split, stem, infrared, visible, annotation) of every complete frame, in split then name order
        self.frames: list[tuple[str, str, Path, Path, Path]] = []
        self.dropped: list[tuple[str, str]] = []
        for split in SPLITS:
            ir, vis = _index(root / "infrared" / split), _index(root / "visible" / split)
            for stem in sorted(set(ir) | set(vis)):
                if stem not in ir:
                    self.dropped.append((str(vis[stem]),
                                         f"missing infrared frame: infrared/{split}/{stem}.jpg not found"))
                elif stem not in vis:
                    self.dropped.append((str(ir[stem]), f"missing visible frame: visible/{split}/{stem}.jpg not found"))
                elif stem not in self.xml:
                    self.dropped.append((str(ir[stem]), f"no annotation: Annotations/{stem}.xml not found"))
                else:
                    self.frames.append((split, stem, ir[stem], vis[stem], self.xml[stem]))
        if not self.frames:
            raise DataError(f"dataset {DATASET!r}: no complete infrared/visible/Annotations triple under {root} "
                            f"(expected infrared/{{train,test}}/<name>.jpg, visible/... and Annotations/<name>.xml)")
        counts = {s: sum(f[0] == s for f in self.frames) for s in SPLITS}
        self.notes = [f"{counts['train']} train / {counts['test']} test pairs, {len(self.dropped)} dropped"]
        if self.dropped:
            log.warning("LLVIP: %s", self.notes[0])
            if strict:
                path, reason = self.dropped[0]
                raise DataError(f"dataset {DATASET!r} (strict): {path}: {reason}")

    def __len__(self) -> int:
        return len(self.frames)

    def groups(self) -> list[str]:
        return [s for s in SPLITS if any(f[0] == s for f in self.frames)]

    def folds(self) -> list[Fold]:
        return [Fold("test", ("train",), ("test",))] if self.groups() == list(SPLITS) else []

    def fingerprint(self) -> str:
        parts: list[Any] = [DATASET, ADAPTER_VERSION, str(self.root.resolve()), self.strict, self.voc_convention,
                            self.difficult]
        parts += [(s, stem, file_stat(i), file_stat(v), file_stat(a)) for s, stem, i, v, a in self.frames]
        return stat_digest(parts)

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        for path, reason in self.dropped:
            report.skip(path, reason)
        for note in self.notes:
            report.note(note)
        stats, voc = BoxStats(), VocStats(self.voc_convention, self.difficult)
        try:
            for k, frame in enumerate(self.frames):
                out = self._sample(k, frame, report, voc)
                if out is not None:
                    stats.add(out[1])
                    yield out[0]
        finally:
            report.note(f"boxes: {stats.kept} kept, {stats.clipped} clipped to the frame, "
                        f"{stats.degenerate} dropped with no area inside the frame")
            report.note(voc.note())

    def _skip(self, report: PrepareReport, path: Path, reason: str) -> None:
        if self.strict:
            raise DataError(f"{path}: {reason}")
        log.warning("LLVIP: skipped %s (%s)", path, reason)
        report.skip(path, reason)

    def _sample(self, k: int, frame: tuple[str, str, Path, Path, Path], report: PrepareReport,
                voc: VocStats) -> tuple[AlignedSample, BoxStats] | None:
        split, stem, ir_path, vis_path, xml_path = frame
        try:
            ann = parse_voc(xml_path)
        except DataError as exc:
            self._skip(report, xml_path, f"malformed annotation: {exc}")
            return None
        unknown = sorted({o.name for o in ann.objects if o.name.strip().lower() not in CATEGORIES})
        if unknown:
            self._skip(report, xml_path, f"unknown class: {', '.join(map(repr, unknown))} is not person")
            return None
        try:
            ir8, _ = read_thermal8(ir_path)
            rgb = read_rgb(vis_path)
        except ImageReadError as exc:
            self._skip(report, ir_path, f"unreadable image: {exc}")
            return None
        h, w = ir8.shape
        if rgb.shape[:2] != (h, w):
            self._skip(report, ir_path, f"size mismatch: visible {rgb.shape[1]}x{rgb.shape[0]}, infrared {w}x{h}")
            return None
        if ann.width and ann.height and (ann.width, ann.height) != (w, h):
            self._skip(report, xml_path, f"size mismatch: <size> says {ann.width}x{ann.height}, images are {w}x{h}")
            return None
        voc.add(ann.objects)
        objects = [o for o in ann.objects if not (o.difficult and self.difficult == "drop")]
        boxes, keep, clipped = clip_boxes(to_xyxy(objects, self.voc_convention), w, h)
        sample = AlignedSample(
            image_id=k + 1, rgb=rgb, thermal=None, ir8=ir8,
            boxes=np.ascontiguousarray(boxes[keep]), labels=np.zeros(int(keep.sum()), np.int64), group=split,
            meta={"file_name": f"infrared/{split}/{ir_path.name}", "rgb_file": f"visible/{split}/{vis_path.name}",
                  "annotation": f"Annotations/{xml_path.name}", "split": split},
        )
        return sample, BoxStats(kept=int(keep.sum()), clipped=clipped, degenerate=int((~keep).sum()))


def find_root(root: str | Path | None) -> Path:
    """Accept ``LLVIP/`` itself or the folder that holds it."""
    path = resolve_root(root, ROOT_ENV, DATASET, ())
    need = ("Annotations", "infrared", "visible")
    if all((path / d).is_dir() for d in need):
        return path
    if all((path / "LLVIP" / d).is_dir() for d in need):
        return path / "LLVIP"
    return resolve_root(path, ROOT_ENV, DATASET, need)  # raises, naming what is missing


def open_llvip(root: str | Path | None = None, strict: bool = False, voc_convention: str = "one-based",
               difficult: str = "drop") -> LlvipSource:
    """Open an LLVIP release (the options are the ``dataset:`` config keys, see ``OPTIONS``)."""
    if not isinstance(strict, bool):
        raise ConfigError(f"dataset {DATASET!r}: option 'strict' must be true or false, got {strict!r}")
    return LlvipSource(find_root(root), strict=strict, voc_convention=normalise_convention(DATASET, voc_convention),
                       difficult=normalise_difficult(DATASET, difficult))


SPEC = DatasetSpec(
    name=DATASET,
    open=open_llvip,
    categories=CATEGORIES,
    description="LLVIP visible/infrared pedestrian pairs (VOC XML), 8-bit IR; official train/test split",
    thermal="8bit",
    default_encoding="proxy8",
    protocol="llvip",
    root_env=ROOT_ENV,
)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
