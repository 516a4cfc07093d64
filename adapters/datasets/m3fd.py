"""M3FD (Liu et al., CVPR 2022): registered visible/infrared pairs with six classes, used here for pretraining.

Layout (``dataset.root`` or ``$HARNESS_M3FD`` points at ``M3FD_Detection/`` or at the folder holding it)::

    M3FD_Detection/Annotation/00000.xml ...   Pascal VOC: <size>, <object><name>, <bndbox> (one label per pair)
    M3FD_Detection/Ir/00000.png ...           infrared, 8-bit grey (stored as three identical channels)
    M3FD_Detection/Vis/00000.png ...          visible

What the loader does, and why:

* **Per-image sizes.** The 4,200 pairs come in nine sizes: 1024x768 (3,926 pairs), 880x520 (49), 740x400 (43),
  780x420 (41), 800x480 (36), 480x360 (34), 440x320 (32), 400x280 (23) and 440x280 (16). Every pair is read at its
  own size and the ``<size>`` of its XML is checked against the images.
* **VOC pixel convention.** The XMLs were written by labelImg: 1-based inclusive pixel indices (``xmin`` is never
  0, ``xmax`` reaches the image width). Boxes become ``(xmin - 1, ymin - 1, xmax, ymax)`` through the shared VOC
  reader (``adapters.datasets.voc``); ``dataset.voc_convention: zero-based`` reads files known to hold 0-based
  corners as written, and ``<difficult>`` boxes are left out (``dataset.difficult: keep`` keeps them).
* **Six classes mapped by name** (case and surrounding spaces ignored), in our fixed order ``CATEGORIES``;
  projects disagree on the class order, so ids from elsewhere are never trusted. An XML naming any other class is
  a **counted skip of the whole pair** (reason ``unknown class``): dropping only that box would leave an unlabelled
  object that training treats as background, and one odd file should not stop 4,200 pairs from being prepared.
  ``dataset.strict: true`` turns every skip into an error.
* **A fixed, recorded train/val split.** M3FD ships no detection split. Files are numbered in capture order, and
  neighbouring frames are near-duplicates, so a random split leaks. Groups are blocks of ``BLOCK`` consecutive
  frame numbers (``00000-00099``, ``00100-00199``, ...), and every ``VAL_EVERY``-th block (the 5th, 10th, ...) is
  held out for validation: 3,400 train / 800 val pairs of the 4,200. The same split is written out, block by
  block, in docs/datasets.md and ``configs/protocols/m3fd.yaml``; every prepared copy records it in its manifest
  (``folds``) and every sample its ``split``.
* The sample has no radiometric thermal (``thermal=None``); ``ir8`` is the infrared image, which is the fourth
  input channel (encoding ``ir8``) during pretraining.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

from adapters.datasets._eightbit import BoxStats, check_strict, file_stat, find_release_root, pair_sample, stat_digest
from adapters.datasets._paired import PairedSource, eightbit_spec, read_pair
from adapters.datasets.voc import VocStats, check_size, normalise_convention, normalise_difficult, read_known
from harness.api import Fold, PrepareReport
from harness.errors import DataError
from harness.hookspecs import hookimpl
from harness.sample import AlignedSample

DATASET = "m3fd"
ROOT_ENV = "HARNESS_M3FD"
DESCRIPTION = "M3FD visible/infrared pairs, 6 classes, 8-bit IR; fixed recorded train/val split (pretraining)"
#: Our fixed class order (the README's); XML names are matched case-insensitively.
CATEGORIES = ("people", "car", "bus", "motorcycle", "lamp", "truck")
SUBDIRS = ("Annotation", "Ir", "Vis")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp")
#: Consecutive frame numbers per group, and every VAL_EVERY-th group is held out: the recorded split.
BLOCK = 100
VAL_EVERY = 5
FOLD = "val"
OPTIONS = {
    "root": f"M3FD_Detection/ or the folder holding it (default: ${ROOT_ENV})",
    "strict": "raise instead of skipping a pair that cannot be used (default false)",
    "voc_convention": "one-based (VOC/labelImg pixel indices, default) or zero-based (corners taken as written)",
    "difficult": "drop (left out of training and scoring, default) or keep <difficult>1</difficult> boxes",
}
ADAPTER_VERSION = 2


def block_of(number: int) -> str:
    """Group name of frame ``number``: its block of ``BLOCK`` consecutive numbers, e.g. 431 -> '00400-00499'."""
    start = (number // BLOCK) * BLOCK
    return f"{start:05d}-{start + BLOCK - 1:05d}"


def is_val_block(group: str) -> bool:
    """The recorded split: block k (0-based, by frame number) is held out when (k + 1) % VAL_EVERY == 0."""
    k = int(group.split("-")[0]) // BLOCK
    return (k + 1) % VAL_EVERY == 0


def recorded_split(count: int = 4200) -> dict[str, list[str]]:
    """The train and val groups of frames ``0 .. count-1`` (what configs/protocols/m3fd.yaml records)."""
    groups = sorted({block_of(n) for n in range(count)})
    return {"train": [g for g in groups if not is_val_block(g)], "val": [g for g in groups if is_val_block(g)]}


def _index(folder: Path, exts: tuple[str, ...]) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in exts:
            out.setdefault(p.stem, p)
    return out


class M3fdSource(PairedSource):
    """An opened M3FD detection release (see the module docstring)."""

    name = DATASET
    log_name = "M3FD"
    categories = CATEGORIES

    def __init__(self, root: Path, strict: bool = False, voc_convention: str = "one-based", difficult: str = "drop"):
        self.root, self.strict = root, strict
        self.voc_convention, self.difficult = voc_convention, difficult
        self.xml = _index(root / "Annotation", (".xml",))
        self.ir = _index(root / "Ir", IMAGE_EXTS)
        self.vis = _index(root / "Vis", IMAGE_EXTS)
        self.dropped: list[tuple[str, str]] = []
        self.notes: list[str] = []
        stems = sorted(set(self.xml) | set(self.ir) | set(self.vis))
        bad = [s for s in stems if not s.isdigit()]
        if bad:
            raise DataError(
                f"dataset {DATASET!r}: {root}: file name(s) {', '.join(bad[:5])} are not frame numbers; the release "
                f"names files 00000..04199 and the recorded split is defined on those numbers"
            )
        self.stems: list[str] = []
        for s in stems:
            if s not in self.xml:
                self.dropped.append(
                    (str(self.ir.get(s) or self.vis[s]), f"no annotation: Annotation/{s}.xml not found")
                )
            elif s not in self.ir:
                self.dropped.append((str(self.xml[s]), f"missing thermal frame: Ir/{s}.png not found"))
            elif s not in self.vis:
                self.dropped.append((str(self.xml[s]), f"missing visible frame: Vis/{s}.png not found"))
            else:
                self.stems.append(s)
        if not self.stems:
            raise DataError(f"dataset {DATASET!r}: no complete Annotation/Ir/Vis triple under {root}")
        self.notes.append(
            f"{len(self.xml)} annotations, {len(self.ir)} infrared, {len(self.vis)} visible images; "
            f"{len(self.stems)} complete pairs, {len(self.dropped)} dropped"
        )
        self._check_drops()
        n_val = sum(1 for s in self.stems if is_val_block(block_of(int(s))))
        self.notes.append(
            f"recorded split (blocks of {BLOCK} frames, every {VAL_EVERY}th held out): "
            f"{len(self.stems) - n_val} train / {n_val} val pairs"
        )

    # ------------------------------------------------------------------ DatasetSource
    def __len__(self) -> int:
        return len(self.stems)

    def groups(self) -> list[str]:
        return sorted({block_of(int(s)) for s in self.stems})

    def folds(self) -> list[Fold]:
        groups = self.groups()
        return [
            Fold(FOLD, tuple(g for g in groups if not is_val_block(g)), tuple(g for g in groups if is_val_block(g)))
        ]

    def fingerprint(self) -> str:
        parts = self._fingerprint_parts(
            ADAPTER_VERSION, self.strict, BLOCK, VAL_EVERY, self.voc_convention, self.difficult
        )
        for s in self.stems:
            parts.append((s, file_stat(self.xml[s]), file_stat(self.ir[s]), file_stat(self.vis[s])))
        return stat_digest(parts)

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        self._voc = VocStats(self.voc_convention, self.difficult)
        yield from self._samples(report, self.stems, self._sample)

    def _closing_notes(self, report: PrepareReport, stats: BoxStats) -> None:
        report.note(stats.note())
        report.note(self._voc.note())
        if stats.colour:
            report.note(f"{stats.colour} infrared image(s) were colour and were converted to luminance")

    def _sample(self, stem: str) -> tuple[AlignedSample, BoxStats]:
        xml_path = self.xml[stem]
        ann = read_known(xml_path, CATEGORIES, f"one of {', '.join(CATEGORIES)}")
        ir8, was_colour, rgb = read_pair(self.ir[stem], self.vis[stem], xml_path, names=("Vis", "Ir"))
        h, w = ir8.shape
        check_size(ann, xml_path, w, h)
        number = int(stem)
        group = block_of(number)
        meta = {
            "file_name": f"Ir/{self.ir[stem].name}",
            "rgb_file": f"Vis/{self.vis[stem].name}",
            "annotation": f"Annotation/{xml_path.name}",
            "split": "val" if is_val_block(group) else "train",
        }
        sample, stats = pair_sample(number + 1, rgb, ir8, *self._voc.targets(ann, CATEGORIES), group, meta)
        stats.colour = int(was_colour)
        return sample, stats


def find_root(root: str | Path | None) -> Path:
    """Accept ``M3FD_Detection/`` itself or the folder that holds it."""
    return find_release_root(root, ROOT_ENV, DATASET, ("M3FD_Detection",), [SUBDIRS])


def open_m3fd(
    root: str | Path | None = None, strict: bool = False, voc_convention: str = "one-based", difficult: str = "drop"
) -> M3fdSource:
    """Open an M3FD detection release (the options are the ``dataset:`` config keys, see ``OPTIONS``)."""
    strict = check_strict(DATASET, strict)
    convention, difficult = normalise_convention(DATASET, voc_convention), normalise_difficult(DATASET, difficult)
    return M3fdSource(find_root(root), strict=strict, voc_convention=convention, difficult=difficult)


SPEC = eightbit_spec(DATASET, open_m3fd, CATEGORIES, DESCRIPTION, ROOT_ENV, default_encoding="ir8")


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
