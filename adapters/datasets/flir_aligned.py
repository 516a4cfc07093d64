"""FLIR-aligned: the aligned subset of the FLIR ADAS dataset (Zhang et al., ICIP 2020), in the layouts the
YOLOv5-based multispectral detectors train on, and as its authors distribute it.

``dataset.root`` or ``$HARNESS_FLIR_ALIGNED`` points at ``FLIR-align-3class/`` or the folder holding it.
ICAFusion's layout (its ``data/multispectral/FLIR-align-3class.yaml`` names ``visible/train`` and
``infrared/train``; its ``img2label_paths`` replaces the ``visible`` or ``infrared`` folder with ``labels``)::

    FLIR-align-3class/visible/train/FLIR_00002_RGB.jpg ...             visible, aligned to the thermal frame
    FLIR-align-3class/infrared/train/FLIR_00002_PreviewData.jpeg ...   thermal, 8-bit
    FLIR-align-3class/labels/train/FLIR_00002_RGB.txt ...              YOLO labels of the visible image
    FLIR-align-3class/labels/train/FLIR_00002_PreviewData.txt ...      ... and of the infrared image
    ... the same under test/

YOLOv5's layout (each modality folder has ``images/`` and ``labels/``; YOLOv5's ``img2label_paths`` replaces the
last ``/images/`` with ``/labels/``)::

    FLIR-align-3class/visible/train/images/FLIR_00002_RGB.jpg, visible/train/labels/FLIR_00002_RGB.txt
    FLIR-align-3class/infrared/train/images/FLIR_00002_PreviewData.jpeg, infrared/train/labels/...txt

A ``labels/`` folder at the root selects ICAFusion's layout (``dataset.layout`` names one explicitly). 4,129 train
and 1,013 test pairs, 640x512, classes ``person, car, bicycle`` (label ids 0, 1, 2). Each label line is
``<class> <cx> <cy> <w> <h>``, the box centre and size divided by the image width and height.

What the loader does:

* **Pairs by frame name** within a split: ``FLIR_<n>`` with the modality suffix (``_RGB``, ``_PreviewData``)
  removed, never by list position. A frame present in one modality only is a counted drop.
* **Which labels**: ``dataset.labels: visible`` (default: ICAFusion trains and evaluates on the visible side's
  labels, applied to both images) or ``infrared``. A missing label file is an image without objects (YOLO's rule),
  counted in the prepare report (and refused by the preparation's plausibility guard when it is more than a small
  share of the images); a malformed line (wrong column count, class out of range, coordinates outside 0..1) skips
  the pair, counted, naming the file and line.
* **Classes**: ``dataset.classes`` (default ``person, car, bicycle``; ``[person]`` for the one-class
  ``FLIR-align`` variant) gives the names of label ids 0, 1, ...
* **The official split**: groups ``train`` and ``test``; the one fold ``test`` holds ``test`` out.
* No radiometric thermal (``thermal=None``); ``ir8`` is the thermal image.

The release as its authors distribute it (``align/``) is read too::

    align/JPEGImages/FLIR_00002_RGB.jpg, FLIR_00002_PreviewData.jpeg     the pair, side by side
    align/Annotations/FLIR_00002_PreviewData.xml                         Pascal VOC, labels of the thermal image
    align/align_train.txt, align_validation.txt                          one name per line (also under
                                                                         ImageSets/Main/); validation = test

There the boxes come from the VOC XMLs of the thermal image (``labels: infrared``, the default for this layout)
through the shared VOC reader (``voc_convention``, ``difficult``), and a class outside ``classes`` skips the pair
(counted, ``unknown class``).
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any, Iterator, Sequence

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

DATASET = "flir-aligned"
ROOT_ENV = "HARNESS_FLIR_ALIGNED"
CATEGORIES = ("person", "car", "bicycle")
SPLITS = ("train", "test")
MODALITIES = ("visible", "infrared")
IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp")
#: Release folder names looked for under a root that holds the dataset folder.
FOLDER_NAMES = ("FLIR-align-3class", "FLIR-align", "FLIR_aligned", "FLIR-aligned")
_SUFFIX = re.compile(r"_(RGB|PreviewData)$", re.IGNORECASE)
OPTIONS = {
    "root": f"FLIR-align-3class/ or the folder holding it (default: ${ROOT_ENV})",
    "labels": "visible (default in the YOLO layouts) or infrared (default and only choice in the release layout)",
    "layout": "auto (default: found from the folders), icafusion (labels/<split>/), "
              "yolov5 (<modality>/<split>/labels/) or release (align/JPEGImages + Annotations)",
    "classes": "names of the label ids 0, 1, ... (default person, car, bicycle)",
    "strict": "raise instead of skipping a pair that cannot be used (default false)",
    "voc_convention": "release layout (align/) only: one-based (VOC, default) or zero-based VOC boxes",
    "difficult": "release layout (align/) only: drop (default) or keep <difficult>1</difficult> boxes",
}
#: Split lists of the release layout, and the group each names.
RELEASE_SPLITS = {"train": "align_train.txt", "test": "align_validation.txt"}
#: Where the labels are: ICAFusion's rule, YOLOv5's rule, or the authors' VOC release.
LAYOUTS = ("icafusion", "yolov5", "release")
ADAPTER_VERSION = 2


def frame_key(stem: str) -> str:
    """``FLIR_00002_RGB`` and ``FLIR_00002_PreviewData`` -> ``FLIR_00002`` (other names are kept as they are)."""
    return _SUFFIX.sub("", stem)


def label_path(image: Path) -> Path:
    """YOLOv5's rule: the last ``/images/`` of the path becomes ``/labels/``, the extension ``.txt``."""
    parts = list(image.parts)
    for i in range(len(parts) - 2, -1, -1):
        if parts[i] == "images":
            parts[i] = "labels"
            break
    return Path(*parts).with_suffix(".txt")


def icafusion_label_path(image: Path, root: Path) -> Path:
    """ICAFusion's rule: the modality folder (``visible`` or ``infrared``, the first folder under the dataset root)
    becomes ``labels``, the extension ``.txt``: ``visible/train/X.jpg`` -> ``labels/train/X.txt``."""
    rel = image.relative_to(root).parts
    return root.joinpath("labels", *rel[1:]).with_suffix(".txt")


def detect_layout(root: Path) -> str:
    """``release`` (``JPEGImages/``), ``icafusion`` (a ``labels/`` folder beside ``visible/`` and ``infrared/``) or
    ``yolov5``; a tree holding both kinds of label folder is a ``ConfigError`` asking for ``dataset.layout``."""
    if (root / "JPEGImages").is_dir():
        return "release"
    if not (root / "labels").is_dir():
        return "yolov5"
    nested = sorted(str(p.relative_to(root)) for m in MODALITIES for s in SPLITS for p in [root / m / s / "labels"]
                    if p.is_dir())
    if nested:
        raise ConfigError(f"dataset {DATASET!r}: {root} holds labels in ICAFusion's layout (labels/) and in YOLOv5's "
                          f"({', '.join(nested)}); set dataset.layout=icafusion or dataset.layout=yolov5")
    return "icafusion"


def parse_yolo(path: Path, num_classes: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """xyxy pixel boxes (float64 Nx4) and labels of a YOLO label file; a bad line is a ``DataError`` naming it."""
    boxes, labels = [], []
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 5:
            raise DataError(f"{path}: line {n}: expected '<class> <cx> <cy> <w> <h>', got {line.strip()!r}")
        try:
            cls_f, cx, cy, w, h = (float(v) for v in fields)
        except ValueError:
            raise DataError(f"{path}: line {n}: not numbers: {line.strip()!r}") from None
        if not all(math.isfinite(v) for v in (cx, cy, w, h)) or cls_f != int(cls_f):
            raise DataError(f"{path}: line {n}: class must be an integer and coordinates finite: {line.strip()!r}")
        if not 0 <= cls_f < num_classes:
            raise DataError(f"{path}: line {n}: class {int(cls_f)} outside 0..{num_classes - 1} (dataset.classes)")
        if not all(0 <= v <= 1 for v in (cx, cy, w, h)):
            raise DataError(f"{path}: line {n}: coordinates must be normalised to 0..1, got {line.strip()!r}")
        boxes.append([(cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width, (cy + h / 2) * height])
        labels.append(int(cls_f))
    return np.array(boxes, np.float64).reshape(-1, 4), np.array(labels, np.int64)


def _images(folder: Path) -> dict[str, Path]:
    """Frame key -> image, for the images anywhere under ``folder`` (YOLOv5 globs the folder recursively)."""
    out: dict[str, Path] = {}
    if folder.is_dir():
        for p in sorted(folder.rglob("*")):
            if p.is_file() and p.suffix.lower() in IMAGE_EXTS:
                out.setdefault(frame_key(p.stem), p)
    return out


class FlirAlignedSource:
    """An opened FLIR-aligned copy (see the module docstring)."""

    name = DATASET

    def __init__(self, root: Path, labels: str = "visible", classes: Sequence[str] = CATEGORIES, strict: bool = False,
                 voc_convention: str = "one-based", difficult: str = "drop", layout: str | None = None):
        self.root, self.labels, self.categories, self.strict = root, labels, tuple(classes), strict
        self.voc_convention, self.difficult = voc_convention, difficult
        #: "icafusion" (labels/<split>/), "yolov5" (<modality>/<split>/labels/) or "release" (align/)
        self.layout = layout or detect_layout(root)
        #: (split, key, visible image, infrared image)
        self.frames: list[tuple[str, str, Path, Path]] = []
        self.dropped: list[tuple[str, str]] = []
        if self.layout == "release":
            self._release_frames()
        for split in SPLITS if self.layout != "release" else ():
            vis, ir = (_images(root / m / split) for m in MODALITIES)
            for key in sorted(set(vis) | set(ir)):
                if key not in ir:
                    self.dropped.append((str(vis[key]), f"missing infrared frame: no {key}_PreviewData image in "
                                                        f"infrared/{split}"))
                elif key not in vis:
                    self.dropped.append((str(ir[key]), f"missing visible frame: no {key}_RGB image in visible/{split}"))
                else:
                    self.frames.append((split, key, vis[key], ir[key]))
        if not self.frames:
            raise DataError(f"dataset {DATASET!r}: no visible/infrared pair under {root} (expected "
                            f"visible/{{train,test}}/[images/]FLIR_<n>_RGB.jpg and "
                            f"infrared/.../[images/]FLIR_<n>_PreviewData.jpeg)")
        counts = {s: sum(f[0] == s for f in self.frames) for s in SPLITS}
        self.notes = [f"{counts['train']} train / {counts['test']} test pairs, {len(self.dropped)} dropped; "
                      f"boxes from the {labels} labels ({self.layout} layout); classes {', '.join(self.categories)}"]
        if self.dropped:
            log.warning("FLIR-aligned: %s", self.notes[0])
            if strict:
                path, reason = self.dropped[0]
                raise DataError(f"dataset {DATASET!r} (strict): {path}: {reason}")

    def _release_frames(self) -> None:
        if self.labels != "infrared":
            raise ConfigError(f"dataset {DATASET!r}: {self.root} is the release layout (JPEGImages/, Annotations/), "
                              f"whose labels belong to the thermal images; set dataset.labels=infrared")
        images = self.root / "JPEGImages"
        for split, name in RELEASE_SPLITS.items():
            listed = [self.root / name, self.root / "ImageSets" / "Main" / name]
            path = next((q for q in listed if q.is_file()), None)
            if path is None:
                raise DataError(f"dataset {DATASET!r}: split list {name} not found (looked for "
                                f"{', '.join(str(q) for q in listed)})")
            keys = [frame_key(Path(line.strip()).stem if "." in line.strip() else line.strip())
                    for line in path.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()]
            for key in keys:
                vis, ir, xml = (images / f"{key}_RGB.jpg", images / f"{key}_PreviewData.jpeg",
                                self.root / "Annotations" / f"{key}_PreviewData.xml")
                if not ir.is_file():
                    self.dropped.append((str(ir), f"missing infrared frame: {ir.name} not found ({name})"))
                elif not vis.is_file():
                    self.dropped.append((str(vis), f"missing visible frame: {vis.name} not found ({name})"))
                elif not xml.is_file():
                    self.dropped.append((str(xml), f"no annotation: Annotations/{xml.name} not found"))
                else:
                    self.frames.append((split, key, vis, ir))

    def __len__(self) -> int:
        return len(self.frames)

    def groups(self) -> list[str]:
        return [s for s in SPLITS if any(f[0] == s for f in self.frames)]

    def folds(self) -> list[Fold]:
        return [Fold("test", ("train",), ("test",))] if self.groups() == list(SPLITS) else []

    def _label_file(self, vis: Path, ir: Path) -> Path:
        if self.layout == "release":
            return self.root / "Annotations" / f"{ir.stem}.xml"
        image = vis if self.labels == "visible" else ir
        return icafusion_label_path(image, self.root) if self.layout == "icafusion" else label_path(image)

    def fingerprint(self) -> str:
        parts: list[Any] = [DATASET, ADAPTER_VERSION, str(self.root.resolve()), self.labels, self.categories,
                            self.strict, self.layout, self.voc_convention, self.difficult]
        parts += [(s, k, file_stat(v), file_stat(i), file_stat(self._label_file(v, i))) for s, k, v, i in self.frames]
        return stat_digest(parts)

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        for path, reason in self.dropped:
            report.skip(path, reason)
        for note in self.notes:
            report.note(note)
        stats, unlabelled = BoxStats(), 0
        self._voc = VocStats(self.voc_convention, self.difficult)
        try:
            for k, frame in enumerate(self.frames):
                out = self._sample(k, frame, report)
                if out is not None:
                    stats.add(out[1])
                    unlabelled += out[2]
                    yield out[0]
        finally:
            report.note(f"boxes: {stats.kept} kept, {stats.clipped} clipped to the frame, "
                        f"{stats.degenerate} dropped with no area inside the frame; {unlabelled} image(s) without a "
                        f"label file (no objects)")
            if self.layout == "release":
                report.note(self._voc.note())

    def _skip(self, report: PrepareReport, path: Path, reason: str) -> None:
        if self.strict:
            raise DataError(f"{path}: {reason}")
        log.warning("FLIR-aligned: skipped %s (%s)", path, reason)
        report.skip(path, reason)

    def _sample(self, k: int, frame: tuple[str, str, Path, Path],
                report: PrepareReport) -> tuple[AlignedSample, BoxStats, bool] | None:
        split, key, vis_path, ir_path = frame
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
        lab = self._label_file(vis_path, ir_path)
        missing = not lab.is_file()
        if self.layout == "release":
            out = self._voc_boxes(lab, w, h, report)
            if out is None:
                return None
            xyxy, labels = out
        else:
            try:
                xyxy, labels = (np.zeros((0, 4)), np.zeros(0, np.int64)) if missing else parse_yolo(
                    lab, len(self.categories), w, h)
            except DataError as exc:
                self._skip(report, lab, f"malformed labels: {exc}")
                return None
        boxes, keep, clipped = clip_boxes(xyxy, w, h)
        sample = AlignedSample(
            image_id=k + 1, rgb=rgb, thermal=None, ir8=ir8, boxes=np.ascontiguousarray(boxes[keep]),
            labels=np.ascontiguousarray(labels[keep]), group=split,
            meta={"file_name": ir_path.relative_to(self.root).as_posix(),
                  "rgb_file": vis_path.relative_to(self.root).as_posix(), "frame": key, "split": split,
                  "labels": self.labels},
        )
        return sample, BoxStats(kept=int(keep.sum()), clipped=clipped, degenerate=int((~keep).sum())), missing


    def _voc_boxes(self, xml: Path, w: int, h: int, report: PrepareReport) -> tuple[np.ndarray, np.ndarray] | None:
        try:
            ann = parse_voc(xml)
        except DataError as exc:
            self._skip(report, xml, f"malformed annotation: {exc}")
            return None
        names = [c.lower() for c in self.categories]
        unknown = sorted({o.name for o in ann.objects if o.name.strip().lower() not in names})
        if unknown:
            self._skip(report, xml, f"unknown class: {', '.join(map(repr, unknown))} is not one of "
                                    f"{', '.join(self.categories)} (dataset.classes)")
            return None
        if ann.width and ann.height and (ann.width, ann.height) != (w, h):
            self._skip(report, xml, f"size mismatch: <size> says {ann.width}x{ann.height}, images are {w}x{h}")
            return None
        self._voc.add(ann.objects)
        objects = [o for o in ann.objects if not (o.difficult and self.difficult == "drop")]
        labels = np.array([names.index(o.name.strip().lower()) for o in objects], np.int64)
        return to_xyxy(objects, self.voc_convention), labels


def find_root(root: str | Path | None) -> Path:
    """Accept the dataset folder (ICAFusion's ``visible/`` + ``infrared/``, or the release's ``JPEGImages/`` +
    ``Annotations/``) or the folder that holds it (``FLIR-align-3class/``, ``align/`` ...)."""
    path = resolve_root(root, ROOT_ENV, DATASET, ())
    layouts = (MODALITIES, ("JPEGImages", "Annotations"))
    for folder in (path, *(path / n for n in (*FOLDER_NAMES, "align"))):
        if any(all((folder / d).is_dir() for d in need) for need in layouts):
            return folder
    return resolve_root(path, ROOT_ENV, DATASET, MODALITIES)  # raises, naming what is missing


def _classes(value: Any) -> tuple[str, ...]:
    names = [s.strip() for s in value.split(",")] if isinstance(value, str) else [str(s).strip() for s in value]
    if not names or not all(names) or len(set(names)) != len(names):
        raise ConfigError(f"dataset {DATASET!r}: option 'classes' must list distinct class names, got {value!r}")
    return tuple(names)


def open_flir_aligned(root: str | Path | None = None, labels: str | None = None, classes: Any = CATEGORIES,
                      strict: bool = False, voc_convention: str = "one-based",
                      difficult: str = "drop", layout: str = "auto") -> FlirAlignedSource:
    """Open a FLIR-aligned copy (the options are the ``dataset:`` config keys, see ``OPTIONS``); ``labels``
    defaults to ``visible`` in the YOLO layouts and ``infrared`` in the release layout."""
    if not isinstance(strict, bool):
        raise ConfigError(f"dataset {DATASET!r}: option 'strict' must be true or false, got {strict!r}")
    if layout not in ("auto", *LAYOUTS):
        raise ConfigError(f"dataset {DATASET!r}: option 'layout' must be auto, {', '.join(LAYOUTS)}; got {layout!r}")
    path = find_root(root)
    chosen = detect_layout(path) if layout == "auto" else layout
    if chosen == "release" and not (path / "JPEGImages").is_dir():
        raise ConfigError(f"dataset {DATASET!r}: dataset.layout=release needs {path / 'JPEGImages'}")
    if labels is None:
        labels = "infrared" if chosen == "release" else "visible"
    side = str(labels).strip().lower()
    side = {"rgb": "visible", "ir": "infrared", "thermal": "infrared"}.get(side, side)
    if side not in MODALITIES:
        raise ConfigError(f"dataset {DATASET!r}: option 'labels' must be visible or infrared, got {labels!r}")
    return FlirAlignedSource(path, labels=side, classes=_classes(classes), strict=strict,
                             voc_convention=normalise_convention(DATASET, voc_convention),
                             difficult=normalise_difficult(DATASET, difficult), layout=chosen)


SPEC = DatasetSpec(
    name=DATASET,
    open=open_flir_aligned,
    categories=CATEGORIES,
    description="FLIR-aligned visible/infrared pairs (ICAFusion's, YOLOv5's or the release layout), 3 classes, "
                "8-bit IR; train/test",
    thermal="8bit",
    default_encoding="proxy8",
    protocol="flir-aligned",
    root_env=ROOT_ENV,
)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
