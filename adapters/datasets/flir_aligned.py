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

import math
import re
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from adapters.datasets._eightbit import BoxStats, check_strict, file_stat, find_release_root, pair_sample, stat_digest
from adapters.datasets._paired import SPLITS, SkipPair, SplitSource, eightbit_spec, read_pair
from adapters.datasets.voc import VocStats, check_size, normalise_convention, normalise_difficult, read_known
from harness.api import PrepareReport
from harness.errors import ConfigError, DataError
from harness.hookspecs import hookimpl
from harness.sample import AlignedSample

DATASET = "flir-aligned"
ROOT_ENV = "HARNESS_FLIR_ALIGNED"
DESCRIPTION = (
    "FLIR-aligned visible/infrared pairs (ICAFusion's, YOLOv5's or the release layout), 3 classes, 8-bit IR; train/test"
)
CATEGORIES = ("person", "car", "bicycle")
MODALITIES = ("visible", "infrared")
#: How a frame's image of each modality is named after its frame key: ``FLIR_00002_RGB``, ``FLIR_00002_PreviewData``.
NAME_SUFFIX = {"visible": "RGB", "infrared": "PreviewData"}
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
    nested = sorted(
        str(p.relative_to(root)) for m in MODALITIES for s in SPLITS for p in [root / m / s / "labels"] if p.is_dir()
    )
    if nested:
        raise ConfigError(
            f"dataset {DATASET!r}: {root} holds labels in ICAFusion's layout (labels/) and in YOLOv5's "
            f"({', '.join(nested)}); set dataset.layout=icafusion or dataset.layout=yolov5"
        )
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


class FlirAlignedSource(SplitSource):
    """An opened FLIR-aligned copy (see the module docstring)."""

    name = DATASET
    log_name = "FLIR-aligned"

    def __init__(
        self,
        root: Path,
        labels: str = "visible",
        classes: Sequence[str] = CATEGORIES,
        strict: bool = False,
        voc_convention: str = "one-based",
        difficult: str = "drop",
        layout: str | None = None,
    ):
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
            pairs = self._pairs_by_name(ir, vis, lambda m, key: f"no {key}_{NAME_SUFFIX[m]} image in {m}/{split}")
            self.frames += [(split, key, vis_path, ir_path) for key, ir_path, vis_path in pairs]
        if not self.frames:
            raise DataError(
                f"dataset {DATASET!r}: no visible/infrared pair under {root} (expected "
                f"visible/{{train,test}}/[images/]FLIR_<n>_RGB.jpg and "
                f"infrared/.../[images/]FLIR_<n>_PreviewData.jpeg)"
            )
        self.notes = [
            f"{self._split_note()}; boxes from the {labels} labels ({self.layout} layout); "
            f"classes {', '.join(self.categories)}"
        ]
        self._check_drops()

    def _release_frames(self) -> None:
        if self.labels != "infrared":
            raise ConfigError(
                f"dataset {DATASET!r}: {self.root} is the release layout (JPEGImages/, Annotations/), "
                f"whose labels belong to the thermal images; set dataset.labels=infrared"
            )
        images = self.root / "JPEGImages"
        for split, name in RELEASE_SPLITS.items():
            listed = [self.root / name, self.root / "ImageSets" / "Main" / name]
            path = next((q for q in listed if q.is_file()), None)
            if path is None:
                raise DataError(
                    f"dataset {DATASET!r}: split list {name} not found (looked for {', '.join(str(q) for q in listed)})"
                )
            keys = [
                frame_key(Path(line.strip()).stem if "." in line.strip() else line.strip())
                for line in path.read_text(encoding="utf-8", errors="replace").splitlines()
                if line.strip()
            ]
            for key in keys:
                vis, ir, xml = (
                    images / f"{key}_RGB.jpg",
                    images / f"{key}_PreviewData.jpeg",
                    self.root / "Annotations" / f"{key}_PreviewData.xml",
                )
                if not ir.is_file():
                    self.dropped.append((str(ir), f"missing infrared frame: {ir.name} not found ({name})"))
                elif not vis.is_file():
                    self.dropped.append((str(vis), f"missing visible frame: {vis.name} not found ({name})"))
                elif not xml.is_file():
                    self.dropped.append((str(xml), f"no annotation: Annotations/{xml.name} not found"))
                else:
                    self.frames.append((split, key, vis, ir))

    def _label_file(self, vis: Path, ir: Path) -> Path:
        if self.layout == "release":
            return self.root / "Annotations" / f"{ir.stem}.xml"
        image = vis if self.labels == "visible" else ir
        return icafusion_label_path(image, self.root) if self.layout == "icafusion" else label_path(image)

    def fingerprint(self) -> str:
        parts = self._fingerprint_parts(
            ADAPTER_VERSION, self.labels, self.categories, self.strict, self.layout, self.voc_convention, self.difficult
        )
        parts += [(s, k, file_stat(v), file_stat(i), file_stat(self._label_file(v, i))) for s, k, v, i in self.frames]
        return stat_digest(parts)

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        self._voc = VocStats(self.voc_convention, self.difficult)
        yield from self._samples(report, enumerate(self.frames), self._sample)

    def _closing_notes(self, report: PrepareReport, stats: BoxStats) -> None:
        report.note(f"{stats.note()}; {stats.unlabelled} image(s) without a label file (no objects)")
        if self.layout == "release":
            report.note(self._voc.note())

    def _sample(self, item: tuple[int, tuple[str, str, Path, Path]]) -> tuple[AlignedSample, BoxStats]:
        k, (split, key, vis_path, ir_path) = item
        ir8, _, rgb = read_pair(ir_path, vis_path, ir_path)
        h, w = ir8.shape
        lab = self._label_file(vis_path, ir_path)
        missing = not lab.is_file()
        if self.layout == "release":
            ann = read_known(
                lab, [c.lower() for c in self.categories], f"one of {', '.join(self.categories)} (dataset.classes)"
            )
            check_size(ann, lab, w, h)
            xyxy, labels = self._voc.targets(ann, [c.lower() for c in self.categories])
        else:
            try:
                xyxy, labels = (
                    (np.zeros((0, 4)), np.zeros(0, np.int64))
                    if missing
                    else parse_yolo(lab, len(self.categories), w, h)
                )
            except DataError as exc:
                raise SkipPair(f"malformed labels: {exc}", lab) from None
        meta = {
            "file_name": ir_path.relative_to(self.root).as_posix(),
            "rgb_file": vis_path.relative_to(self.root).as_posix(),
            "frame": key,
            "split": split,
            "labels": self.labels,
        }
        sample, stats = pair_sample(k + 1, rgb, ir8, xyxy, labels, split, meta)
        stats.unlabelled = int(missing)
        return sample, stats


def find_root(root: str | Path | None) -> Path:
    """Accept the dataset folder (ICAFusion's ``visible/`` + ``infrared/``, or the release's ``JPEGImages/`` +
    ``Annotations/``) or the folder that holds it (``FLIR-align-3class/``, ``align/`` ...)."""
    layouts = (MODALITIES, ("JPEGImages", "Annotations"))
    return find_release_root(root, ROOT_ENV, DATASET, (*FOLDER_NAMES, "align"), layouts)


def _classes(value: Any) -> tuple[str, ...]:
    names = [s.strip() for s in value.split(",")] if isinstance(value, str) else [str(s).strip() for s in value]
    if not names or not all(names) or len(set(names)) != len(names):
        raise ConfigError(f"dataset {DATASET!r}: option 'classes' must list distinct class names, got {value!r}")
    return tuple(names)


def open_flir_aligned(
    root: str | Path | None = None,
    labels: str | None = None,
    classes: Any = CATEGORIES,
    strict: bool = False,
    voc_convention: str = "one-based",
    difficult: str = "drop",
    layout: str = "auto",
) -> FlirAlignedSource:
    """Open a FLIR-aligned copy (the options are the ``dataset:`` config keys, see ``OPTIONS``); ``labels``
    defaults to ``visible`` in the YOLO layouts and ``infrared`` in the release layout."""
    strict = check_strict(DATASET, strict)
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
    return FlirAlignedSource(
        path,
        labels=side,
        classes=_classes(classes),
        strict=strict,
        voc_convention=normalise_convention(DATASET, voc_convention),
        difficult=normalise_difficult(DATASET, difficult),
        layout=chosen,
    )


SPEC = eightbit_spec(DATASET, open_flir_aligned, CATEGORIES, DESCRIPTION, ROOT_ENV)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
