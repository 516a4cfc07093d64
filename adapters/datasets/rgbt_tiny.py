"""RGBT-Tiny (Ying et al., TPAMI 2025): visible-thermal tiny-object detection with 8-bit thermal frames.

Release layout (``dataset.root`` or ``$HARNESS_RGBT_TINY`` points at the folder holding ``images/``)::

    images/<SEQ>/00/NNNNN.jpg          visible, already warped into the thermal frame (640x512)
    images/<SEQ>/01/NNNNN.jpg          thermal, 8-bit grey JPEG (640x512)
    annotations_coco/instances_00_{train,test}2017.json    visible ground truth (COCO)
    annotations_coco/instances_01_{train,test}2017.json    thermal ground truth (COCO)
    data_split/{train,test,00_train,...}.txt               optional frame lists (also accepted flattened in the root)

The release ships three archives (``images.zip``, ``annotations_coco.zip``, ``data_split.zip``) that unpack without
a top-level folder. Both ways of unpacking them are read (``find_layout``): each into its own folder
(``unzip images.zip -d images`` ..., the tree above), or all three into one folder ("flat": the sequence folders,
the ``instances_*.json`` files and the split lists side by side). Both give the same samples.

What the loader does, and why:

* **Pairs frames by file name** (``<SEQ>/00/<n>`` <-> ``<SEQ>/01/<n>``). The two modalities' JSON files number their
  images independently, so pairing by image id (or by position) mixes up frames.
* **Maps categories by name.** The JSON ids are 0-based (``0 = ship``); id 0 is a real class, not background. A
  category name that is not one of the seven classes is an error (the dataset version is not the one this adapter
  knows; silently dropping a class would change the support that every comparison rests on).
* **Keeps the two annotation sets apart.** Boxes differ between modalities by a few pixels and the counts differ;
  ``dataset.gt`` chooses the source: ``thermal`` (T, default) or ``visible`` (RGB). The source is part of the
  fold name (``test-T`` / ``test-RGB``) so results on the two sources never overwrite each other in the store.
* **Checks at load time that the visible and thermal sets match**: a frame listed in only one JSON, a frame whose
  file is missing on disk, or a pair whose two images differ in size is dropped, counted by reason, logged and
  written to the prepare report (``dataset.strict: true`` turns any drop into an error).
* **Split and groups from the dataset's files**: groups are the sequences; the one fold trains on the sequences
  of the ``train2017`` files and holds out those of ``test2017``. Optional ``data_split`` lists are cross-checked.
* The sample has no radiometric thermal (``thermal=None``); ``ir8`` is the 8-bit thermal frame. Single-stream
  detectors get the ``proxy8`` channel (local contrast of the 8-bit intensity), dual-stream detectors the 8-bit
  thermal frame itself.
"""

from __future__ import annotations

import logging
import math
import re
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from adapters.datasets._coco import coco_id
from adapters.datasets._eightbit import (
    BoxStats,
    check_strict,
    file_stat,
    option_choice,
    pair_sample,
    positive_int,
    resolve_root,
    stat_digest,
    xywh_to_xyxy,
)
from adapters.datasets._paired import PairedSource, eightbit_spec, read_pair
from harness.api import Fold, PrepareReport
from harness.errors import DataError
from harness.hookspecs import hookimpl
from harness.io import read_json
from harness.sample import AlignedSample

log = logging.getLogger(__name__)

DATASET = "rgbt-tiny"
ROOT_ENV = "HARNESS_RGBT_TINY"
DESCRIPTION = "RGBT-Tiny visible-thermal tiny objects, 8-bit thermal JPEGs, split by sequence (set dataset.gt)"
#: The seven classes in the order of the official JSON ids (0..6); our labels use the same order.
CATEGORIES = ("ship", "car", "cyclist", "pedestrian", "bus", "drone", "plane")
MODALITY_DIR = {"visible": "00", "thermal": "01"}
DIR_MODALITY = {v: k for k, v in MODALITY_DIR.items()}
#: Short names of the annotation sources, as the paper writes them.
SOURCE_LABEL = {"thermal": "T", "visible": "RGB"}
SPLITS = ("train", "test")
#: The spellings of each annotation source that the ``gt`` option accepts.
_GT_NAMES = {"thermal": ("thermal", "t", "ir", "01"), "visible": ("visible", "rgb", "vis", "00")}
OPTIONS = {
    "root": f"folder holding images/ and annotations_coco/ (default: ${ROOT_ENV})",
    "gt": "annotation source, thermal (T, default) or visible (RGB)",
    "train_stride": "keep every k-th paired frame of each training sequence (default 1: all; not the official "
    "protocol)",
    "test_stride": "keep every k-th paired frame of each test sequence (default 1: all; not the official protocol)",
    "strict": "raise instead of dropping frames whose visible and thermal sides do not match (default false)",
}
#: Version of this adapter's sample-making logic; part of the fingerprint so a change re-prepares the cache.
ADAPTER_VERSION = 1


# ---------------------------------------------------------------------------------------------- names and files
@dataclass(frozen=True, order=True)
class FrameKey:
    """A frame of a sequence, the same for both modalities: ``("DJI_0022_1", "00000")``."""

    sequence: str
    frame: str

    def __str__(self) -> str:
        return f"{self.sequence}/{self.frame}"


def annotation_path(folder: Path, modality: str, split: str) -> Path:
    """The annotation file of ``modality`` and ``split`` in ``folder`` (``annotations_coco/`` or a flat root)."""
    return folder / f"instances_{MODALITY_DIR[modality]}_{split}2017.json"


ARCHIVES = ("images", "annotations_coco", "data_split")


def _has_annotations(folder: Path) -> bool:
    return any(annotation_path(folder, m, s).is_file() for m in MODALITY_DIR for s in SPLITS)


def _sequence_dirs(folder: Path) -> list[Path]:
    """Sub-folders of ``folder`` that look like sequences (they hold a ``00`` or ``01`` folder)."""
    if not folder.is_dir():
        return []
    return [p for p in sorted(folder.iterdir()) if p.is_dir() and any((p / d).is_dir() for d in DIR_MODALITY)]


@dataclass(frozen=True)
class Layout:
    """Where an unpacked release keeps its images and annotation files."""

    images: Path
    annotations: Path
    #: "folders" (each archive in its own folder), "flat" (all three in one folder) or "mixed"
    kind: str


def find_layout(root: Path) -> Layout:
    """The images and annotation folders of the release under ``root``, in either unpacked layout.

    Raises ``DataError`` naming the folders expected and the ``unzip`` commands that produce them."""
    images = root / "images" if (root / "images").is_dir() else (root if _sequence_dirs(root) else None)
    annotations = (
        root / "annotations_coco"
        if (root / "annotations_coco").is_dir()
        else (root if _has_annotations(root) else None)
    )
    if images is None or annotations is None:
        missing = [name for name, found in (("images", images), ("annotations_coco", annotations)) if found is None]
        found = sorted(p.name for p in root.iterdir())[:12]
        commands = "; ".join(f"unzip {a}.zip -d {root / a}" for a in ARCHIVES)
        flat = "; ".join(f"unzip {a}.zip -d {root}" for a in ARCHIVES)
        raise DataError(
            f"dataset {DATASET!r}: {root} is not an unpacked RGBT-Tiny release: missing {', '.join(missing)} "
            f"(found: {', '.join(found) or 'nothing'}). Expected either the folders images/<SEQ>/00|01/, "
            f"annotations_coco/instances_0{{0,1}}_{{train,test}}2017.json and data_split/ ({commands}), or all three "
            f"archives unzipped into one folder, with the sequence folders and the JSON files side by side ({flat}); "
            f"point dataset.root or {ROOT_ENV} at that folder"
        )
    kind = {(True, True): "folders", (False, False): "flat"}.get((images != root, annotations != root), "mixed")
    return Layout(images, annotations, kind)


def parse_file_name(name: str) -> tuple[str, FrameKey, str]:
    """``"DJI_0022_1/01/00000.jpg"`` -> (relative path under images/, key, modality folder ``"01"``).

    Back-slashes and a leading ``images/`` are tolerated. Raises ``ValueError`` when the name is not
    ``<SEQ>/<00|01>/<frame>.<ext>``.
    """
    rel = str(name).replace("\\", "/").lstrip("./")
    if rel.startswith("images/"):
        rel = rel[len("images/") :]
    parts = [p for p in rel.split("/") if p]
    if ".." in parts or (parts and ":" in parts[0]):  # "a/../../x", "C:/x": the file must be under images/
        raise ValueError(f"{name!r} leads outside the dataset's images folder; file names must stay inside it")
    if len(parts) < 3 or parts[-2] not in DIR_MODALITY or "." not in parts[-1]:
        raise ValueError(f"expected '<SEQ>/00|01/<frame>.jpg', got {name!r}")
    return "/".join(parts), FrameKey(parts[-3], parts[-1].rsplit(".", 1)[0]), parts[-2]


def normalise_gt(value: Any) -> str:
    return option_choice(DATASET, "gt", value, _GT_NAMES, "thermal (T) or visible (RGB)")


# ---------------------------------------------------------------------------------------------- COCO files
@dataclass
class ImageEntry:
    id: int | str  # as the annotation file numbers it (only used to join its annotations)
    file_name: str
    width: int | None
    height: int | None


@dataclass
class CocoFile:
    """One modality's annotation file for one split, indexed by frame key."""

    path: Path
    modality: str
    split: str
    images: dict[FrameKey, ImageEntry]
    #: image id -> (xyxy float64 Nx4, labels int64 N, crowd bool N)
    boxes: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
    instances: int


def _field(path: Path, where: str, record: Any, key: str) -> Any:
    if not isinstance(record, dict) or key not in record:
        raise DataError(f"{path}: {where}: missing field {key!r}")
    return record[key]


def load_coco_file(path: Path, modality: str, split: str) -> CocoFile:
    """Read and check one ``instances_0X_<split>2017.json``; every error names the file and the record."""
    data = read_json(path)  # a malformed file raises DataError with line and column
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a COCO object at the top level, got {type(data).__name__}")
    for key in ("images", "annotations", "categories"):
        if not isinstance(data.get(key), list):
            raise DataError(f"{path}: missing or non-list field {key!r}; is this a COCO detection file?")

    label_of: dict[int, int] = {}
    for i, cat in enumerate(data["categories"]):
        cid, name = _field(path, f"categories[{i}]", cat, "id"), _field(path, f"categories[{i}]", cat, "name")
        if not isinstance(coco_id(cid), int):
            raise DataError(f"{path}: categories[{i}]: category id {cid!r} is not an integer")
        cid = coco_id(cid)
        norm = str(name).strip().lower()
        if norm not in CATEGORIES:
            raise DataError(
                f"{path}: categories[{i}]: class {name!r} is not an RGBT-Tiny class ({', '.join(CATEGORIES)}); "
                f"this adapter knows the official seven classes only (refusing rather than dropping the class, "
                f"which would change the evaluated support); fix the file or use the official release"
            )
        if cid in label_of:
            raise DataError(f"{path}: categories[{i}]: duplicate category id {cid!r}")
        label_of[cid] = CATEGORIES.index(norm)

    want_dir = MODALITY_DIR[modality]
    images: dict[FrameKey, ImageEntry] = {}
    ids: set[int | str] = set()
    for i, im in enumerate(data["images"]):
        where = f"images[{i}]"
        iid = coco_id(_field(path, where, im, "id"))  # 12, "12" and 12.0 are one id, as in the evaluation
        if iid is None:
            raise DataError(f"{path}: {where}: image id {im['id']!r} is neither an integer nor a non-empty string")
        try:
            rel, key, mdir = parse_file_name(_field(path, where, im, "file_name"))
        except ValueError as exc:
            raise DataError(f"{path}: {where}: file_name: {exc}") from None
        if mdir != want_dir:
            raise DataError(
                f"{path}: {where}: file_name {rel!r} is in folder {mdir!r} but this is the {modality} annotation "
                f"file (folder {want_dir!r}); the 00/01 files may have been swapped"
            )
        if iid in ids:
            raise DataError(f"{path}: {where}: duplicate image id {iid!r}")
        if key in images:
            raise DataError(f"{path}: {where}: frame {key} is listed twice (ids {images[key].id} and {iid})")
        ids.add(iid)
        w, h = im.get("width"), im.get("height")
        images[key] = ImageEntry(iid, rel, int(w) if w is not None else None, int(h) if h is not None else None)

    per_image: dict[int, list[tuple[list[float], int, bool]]] = defaultdict(list)
    for i, ann in enumerate(data["annotations"]):
        where = f"annotations[{i}]"
        raw_iid, raw_cid = _field(path, where, ann, "image_id"), _field(path, where, ann, "category_id")
        iid, cid = coco_id(raw_iid), coco_id(raw_cid)
        bbox = _field(path, where, ann, "bbox")
        if iid not in ids:
            raise DataError(f"{path}: {where}: image_id {raw_iid!r} is not in 'images'")
        if cid not in label_of:
            raise DataError(f"{path}: {where}: category_id {raw_cid!r} is not in 'categories' (ids {sorted(label_of)})")
        if (
            not isinstance(bbox, (list, tuple))
            or len(bbox) != 4
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in bbox)
        ):
            raise DataError(f"{path}: {where}: bbox must be four finite numbers [x, y, w, h], got {bbox!r}")
        per_image[iid].append((list(bbox), label_of[cid], bool(ann.get("iscrowd", 0))))

    boxes: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for iid, anns in per_image.items():
        xywh = np.array([a[0] for a in anns], dtype=np.float64)
        boxes[iid] = (
            xywh_to_xyxy(xywh),
            np.array([a[1] for a in anns], np.int64),
            np.array([a[2] for a in anns], bool),
        )
    return CocoFile(path, modality, split, images, boxes, instances=len(data["annotations"]))


# ---------------------------------------------------------------------------------------------- pairing
@dataclass(frozen=True)
class Pair:
    key: FrameKey
    split: str
    visible: ImageEntry
    thermal: ImageEntry


@dataclass
class SplitPairing:
    """How one split's visible and thermal annotation files matched up."""

    split: str
    listed_visible: int
    listed_thermal: int
    pairs: list[Pair]
    #: (path or frame, reason) for every frame that was dropped; reason is "<kind>: <detail>"
    dropped: list[tuple[str, str]] = field(default_factory=list)

    def reasons(self) -> dict[str, int]:
        return dict(Counter(r.split(":")[0] for _, r in self.dropped))

    def describe(self) -> str:
        v, t = (f"instances_{MODALITY_DIR[m]}_{self.split}2017.json" for m in ("visible", "thermal"))
        text = (
            f"{self.split}: {v} lists {self.listed_visible} images, {t} lists {self.listed_thermal}; "
            f"{len(self.pairs)} pairs kept"
        )
        if self.dropped:
            why = ", ".join(f"{n} {k}" for k, n in sorted(self.reasons().items()))
            text += f", {len(self.dropped)} frames dropped ({why})"
        return text


def pair_frames(visible: CocoFile, thermal: CocoFile, images_dir: Path) -> SplitPairing:
    """Pair the frames of one split by ``<SEQ>/<frame>``, checking both files exist and the sizes agree."""
    result = SplitPairing(visible.split, len(visible.images), len(thermal.images), [])
    for key in sorted(set(visible.images) | set(thermal.images)):
        v, t = visible.images.get(key), thermal.images.get(key)
        if t is None:
            result.dropped.append(
                (str(images_dir / v.file_name), f"only in visible annotations: {thermal.path.name} has no frame {key}")
            )
            continue
        if v is None:
            result.dropped.append(
                (str(images_dir / t.file_name), f"only in thermal annotations: {visible.path.name} has no frame {key}")
            )
            continue
        if file_stat(images_dir / t.file_name) is None:
            result.dropped.append((str(images_dir / t.file_name), f"missing thermal frame: {t.file_name} not found"))
            continue
        if file_stat(images_dir / v.file_name) is None:
            result.dropped.append((str(images_dir / v.file_name), f"missing visible frame: {v.file_name} not found"))
            continue
        if None not in (v.width, v.height, t.width, t.height) and (v.width, v.height) != (t.width, t.height):
            result.dropped.append(
                (
                    str(images_dir / t.file_name),
                    f"size mismatch: visible {v.width}x{v.height}, thermal {t.width}x{t.height} in the annotations",
                )
            )
            continue
        result.pairs.append(Pair(key, visible.split, v, t))
    return result


def apply_stride(pairs: list[Pair], stride: int) -> list[Pair]:
    """Every ``stride``-th pair of each sequence (in frame order), starting with the first."""
    if stride == 1:
        return pairs
    seen: Counter[str] = Counter()
    out = []
    for p in sorted(pairs, key=lambda p: p.key):
        if seen[p.key.sequence] % stride == 0:
            out.append(p)
        seen[p.key.sequence] += 1
    return out


_SPLIT_LINE = re.compile(r"^(?P<seq>[^/\s]+)/(?:(?P<mod>0[01])/)?(?P<frame>[^/\s]+?)(?:\.\w+)?$")


def read_split_file(path: Path) -> set[FrameKey]:
    """Frames listed in a ``data_split`` text file (lines like ``DJI_0022_1/00/00000``)."""
    keys: set[FrameKey] = set()
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        line = line.strip().replace("\\", "/")
        if not line:
            continue
        if line.startswith("images/"):
            line = line[len("images/") :]
        m = _SPLIT_LINE.match(line)
        if not m:
            raise DataError(f"{path}: line {n}: expected '<SEQ>/00|01/<frame>', got {line!r}")
        keys.add(FrameKey(m["seq"], m["frame"]))
    return keys


def find_split_files(root: Path) -> dict[str, list[Path]]:
    """``{"train": [...], "test": [...]}`` split lists present under ``data_split/`` or the root."""
    found: dict[str, list[Path]] = {s: [] for s in SPLITS}
    for folder in (root / "data_split", root):
        for split in SPLITS:
            for stem in (split, f"00_{split}", f"01_{split}"):
                p = folder / f"{stem}.txt"
                if p.is_file():
                    found[split].append(p)
    return found


# ---------------------------------------------------------------------------------------------- the source
class RgbtTinySource(PairedSource):
    """An opened RGBT-Tiny release (see the module docstring). Opening reads and checks the annotation files and
    stats every image file; ``samples`` decodes the images."""

    name = DATASET
    log_name = "RGBT-Tiny"
    skip_verb = "dropped"
    categories = CATEGORIES

    def __init__(
        self, root: Path, gt: str = "thermal", train_stride: int = 1, test_stride: int = 1, strict: bool = False
    ):
        self.root = root
        self.layout = find_layout(root)
        self.images_dir = self.layout.images
        self.gt = gt
        self.strides = {"train": train_stride, "test": test_stride}
        self.strict = strict
        self.notes: list[str] = []
        ann = self.layout.annotations
        missing = [
            annotation_path(ann, m, s) for s in SPLITS for m in MODALITY_DIR if not annotation_path(ann, m, s).is_file()
        ]
        if missing:
            raise DataError(
                f"dataset {DATASET!r}: annotation file(s) missing: {', '.join(str(p) for p in missing)}; the release "
                f"ships annotations_coco/instances_{{00,01}}_{{train,test}}2017.json"
            )
        self.coco = {(m, s): load_coco_file(annotation_path(ann, m, s), m, s) for s in SPLITS for m in MODALITY_DIR}
        self.pairing = {
            s: pair_frames(self.coco["visible", s], self.coco["thermal", s], self.images_dir) for s in SPLITS
        }
        #: (path or frame, reason) of every frame that could not be paired
        self.dropped = [d for s in SPLITS for d in self.pairing[s].dropped]

        seqs = {s: {p.key.sequence for p in self.pairing[s].pairs} for s in SPLITS}
        both = seqs["train"] & seqs["test"]
        if both:
            raise DataError(
                f"dataset {DATASET!r}: sequence(s) {', '.join(sorted(both)[:5])} appear in both the train2017 and "
                f"test2017 annotation files; the split is by sequence, so the files are inconsistent"
            )
        self.pairs: list[Pair] = sorted(
            (p for s in SPLITS for p in apply_stride(self.pairing[s].pairs, self.strides[s])), key=lambda p: p.key
        )
        if not self.pairs:
            raise DataError(f"dataset {DATASET!r}: no usable frame pair under {root} ({self._drop_text()})")
        # stable ids: position in the sorted union of every frame any annotation file lists (independent of the
        # annotation source, of strides and of files missing on disk)
        every = sorted({k for c in self.coco.values() for k in c.images})
        self.image_ids = {k: i + 1 for i, k in enumerate(every)}
        self._describe()
        if self.strict and self.dropped:
            path, reason = self.dropped[0]
            raise DataError(
                f"dataset {DATASET!r} (strict): {len(self.dropped)} frame(s) cannot be paired, first: {path}: {reason}"
            )

    # ------------------------------------------------------------------ checks and notes
    def _drop_text(self) -> str:
        return "; ".join(self.pairing[s].describe() for s in SPLITS)

    def _describe(self) -> None:
        for s in SPLITS:
            sp = self.pairing[s]
            self.notes.append(sp.describe())
            if sp.listed_visible != sp.listed_thermal:
                log.warning(
                    "RGBT-Tiny %s: the visible and thermal annotation files list different numbers of images "
                    "(%d vs %d)",
                    s,
                    sp.listed_visible,
                    sp.listed_thermal,
                )
            if sp.dropped:
                log.warning("RGBT-Tiny %s", sp.describe())
            else:
                log.info("RGBT-Tiny %s", sp.describe())
            if self.strides[s] > 1:
                kept = sum(1 for p in self.pairs if p.split == s)
                self.notes.append(
                    f"{s}: every {self.strides[s]}th frame of each sequence kept ({kept} of {len(sp.pairs)} pairs); "
                    f"not the official protocol"
                )
        self.notes.append(
            {
                "folders": "layout: images/, annotations_coco/ and data_split/ folders",
                "flat": "layout: the three archives unzipped into one folder (flat)",
                "mixed": "layout: images and annotation files in different places (mixed)",
            }[self.layout.kind]
        )
        src = self.gt
        self.notes.append(
            f"annotation source: {src} ({SOURCE_LABEL[src]}), from instances_{MODALITY_DIR[src]}_*2017.json"
        )
        self._check_split_files()
        listed = {k.sequence for c in self.coco.values() for k in c.images}
        if self.images_dir.is_dir():
            on_disk = {p.name for p in _sequence_dirs(self.images_dir)}
            extra = sorted(on_disk - listed)
            if extra:
                self.notes.append(
                    f"{len(extra)} sequence folder(s) under images/ are in no annotation file and are not used: "
                    f"{', '.join(extra[:5])}{' ...' if len(extra) > 5 else ''}"
                )

    def _check_split_files(self) -> None:
        for split, files in find_split_files(self.root).items():
            annotated = {p.key for p in self.pairing[split].pairs} | {
                k for m in MODALITY_DIR for k in self.coco[m, split].images
            }
            for path in files:
                listed = read_split_file(path)
                other = SPLITS[1 - SPLITS.index(split)]
                crossed = {k.sequence for k in listed} & {p.key.sequence for p in self.pairing[other].pairs}
                if crossed:
                    raise DataError(
                        f"{path}: lists frames of sequence(s) {', '.join(sorted(crossed)[:5])} which the annotation "
                        f"files put in the {other} split; the split files and annotation files disagree"
                    )
                missing, extra = len(listed - annotated), len(annotated - listed)
                if missing or extra:
                    self.notes.append(
                        f"{path.name}: {missing} listed frame(s) have no annotation entry, "
                        f"{extra} annotated frame(s) are not listed"
                    )
                    log.warning("RGBT-Tiny %s", self.notes[-1])

    # ------------------------------------------------------------------ DatasetSource
    def __len__(self) -> int:
        """Pairs that ``samples`` will try to decode (for progress bars)."""
        return len(self.pairs)

    def groups(self) -> list[str]:
        return sorted({p.key.sequence for p in self.pairs})

    def split_groups(self, split: str) -> list[str]:
        return sorted({p.key.sequence for p in self.pairs if p.split == split})

    def fold_name(self) -> str:
        return f"test-{SOURCE_LABEL[self.gt]}"

    def folds(self) -> list[Fold]:
        return [Fold(self.fold_name(), tuple(self.split_groups("train")), tuple(self.split_groups("test")))]

    def fingerprint(self) -> str:
        parts = self._fingerprint_parts(
            ADAPTER_VERSION, self.gt, self.strides["train"], self.strides["test"], self.strict
        )
        for (m, s), c in sorted(self.coco.items()):
            parts.append((m, s, file_stat(c.path)))
        for s, files in sorted(find_split_files(self.root).items()):
            parts.extend((s, str(p), file_stat(p)) for p in files)
        for p in self.pairs:
            parts.append(
                (
                    p.thermal.file_name,
                    file_stat(self.images_dir / p.thermal.file_name),
                    p.visible.file_name,
                    file_stat(self.images_dir / p.visible.file_name),
                )
            )
        return stat_digest(parts)

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        yield from self._samples(report, self.pairs, self._sample)

    def _closing_notes(self, report: PrepareReport, stats: BoxStats) -> None:
        report.note(
            f"boxes ({self.gt} annotations): {stats.kept} kept, {stats.clipped} clipped to the frame, "
            f"{stats.degenerate} dropped with no area inside the frame, {stats.crowd} crowd boxes dropped"
        )
        if stats.colour:
            report.note(f"{stats.colour} thermal frame(s) were colour images and were converted to luminance")
            log.warning("RGBT-Tiny: %d thermal frame(s) were colour images, converted to luminance", stats.colour)

    def _sample(self, pair: Pair) -> tuple[AlignedSample, BoxStats]:
        t_path, v_path = self.images_dir / pair.thermal.file_name, self.images_dir / pair.visible.file_name
        ir8, was_colour, rgb = read_pair(t_path, v_path, t_path, names=("visible", "thermal"))
        entry = pair.thermal if self.gt == "thermal" else pair.visible
        xyxy, labels, crowd = self.coco[self.gt, pair.split].boxes.get(
            entry.id, (np.zeros((0, 4)), np.zeros(0, np.int64), np.zeros(0, bool))
        )
        meta = {
            "file_name": pair.thermal.file_name,
            "rgb_file": pair.visible.file_name,
            "sequence": pair.key.sequence,
            "frame": pair.key.frame,
            "split": pair.split,
            "gt": self.gt,
            "coco_image_ids": {"00": pair.visible.id, "01": pair.thermal.id},
        }
        sample, stats = pair_sample(
            self.image_ids[pair.key], rgb, ir8, xyxy[~crowd], labels[~crowd], pair.key.sequence, meta
        )
        stats.crowd, stats.colour = int(crowd.sum()), int(was_colour)
        return sample, stats


def open_rgbt_tiny(
    root: str | Path | None = None,
    gt: str = "thermal",
    train_stride: int = 1,
    test_stride: int = 1,
    strict: bool = False,
) -> RgbtTinySource:
    """Open an RGBT-Tiny release (the options are the ``dataset:`` config keys, see ``OPTIONS``)."""
    path = resolve_root(root, ROOT_ENV, DATASET, ())
    strict = check_strict(DATASET, strict)
    return RgbtTinySource(
        path,
        gt=normalise_gt(gt),
        train_stride=positive_int(DATASET, "train_stride", train_stride),
        test_stride=positive_int(DATASET, "test_stride", test_stride),
        strict=strict,
    )


SPEC = eightbit_spec(DATASET, open_rgbt_tiny, CATEGORIES, DESCRIPTION, ROOT_ENV)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
