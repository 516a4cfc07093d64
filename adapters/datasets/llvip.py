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

from pathlib import Path
from typing import Any, Iterator

from adapters.datasets._eightbit import BoxStats, check_strict, file_stat, find_release_root, pair_sample, stat_digest
from adapters.datasets._paired import SPLITS, SplitSource, eightbit_spec, read_pair
from adapters.datasets.voc import VocStats, check_size, normalise_convention, normalise_difficult, read_known
from harness.api import PrepareReport
from harness.errors import DataError
from harness.hookspecs import hookimpl
from harness.sample import AlignedSample

DATASET = "llvip"
ROOT_ENV = "HARNESS_LLVIP"
DESCRIPTION = "LLVIP visible/infrared pedestrian pairs (VOC XML), 8-bit IR; official train/test split"
CATEGORIES = ("person",)
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


class LlvipSource(SplitSource):
    """An opened LLVIP release (see the module docstring)."""

    name = DATASET
    log_name = "LLVIP"
    categories = CATEGORIES

    def __init__(self, root: Path, strict: bool = False, voc_convention: str = "one-based", difficult: str = "drop"):
        self.root, self.strict, self.voc_convention, self.difficult = root, strict, voc_convention, difficult
        self.xml = {p.stem: p for p in sorted((root / "Annotations").glob("*.xml"))}
        #: (split, stem, infrared, visible, annotation) of every complete frame, in split then name order
        self.frames: list[tuple[str, str, Path, Path, Path]] = []
        self.dropped: list[tuple[str, str]] = []
        for split in SPLITS:
            ir, vis = _index(root / "infrared" / split), _index(root / "visible" / split)
            pairs = self._pairs_by_name(ir, vis, lambda modality, stem: f"{modality}/{split}/{stem}.jpg not found")
            for stem, ir_path, vis_path in pairs:
                if stem not in self.xml:
                    self.dropped.append((str(ir_path), f"no annotation: Annotations/{stem}.xml not found"))
                else:
                    self.frames.append((split, stem, ir_path, vis_path, self.xml[stem]))
        if not self.frames:
            raise DataError(
                f"dataset {DATASET!r}: no complete infrared/visible/Annotations triple under {root} "
                f"(expected infrared/{{train,test}}/<name>.jpg, visible/... and Annotations/<name>.xml)"
            )
        self.notes = [self._split_note()]
        self._check_drops()

    def fingerprint(self) -> str:
        parts = self._fingerprint_parts(ADAPTER_VERSION, self.strict, self.voc_convention, self.difficult)
        parts += [(s, stem, file_stat(i), file_stat(v), file_stat(a)) for s, stem, i, v, a in self.frames]
        return stat_digest(parts)

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        self._voc = VocStats(self.voc_convention, self.difficult)
        yield from self._samples(report, enumerate(self.frames), self._sample)

    def _closing_notes(self, report: PrepareReport, stats: BoxStats) -> None:
        report.note(stats.note())
        report.note(self._voc.note())

    def _sample(self, item: tuple[int, tuple[str, str, Path, Path, Path]]) -> tuple[AlignedSample, BoxStats]:
        k, (split, stem, ir_path, vis_path, xml_path) = item
        ann = read_known(xml_path, CATEGORIES, "person")
        ir8, _, rgb = read_pair(ir_path, vis_path, ir_path)
        h, w = ir8.shape
        check_size(ann, xml_path, w, h)
        meta = {
            "file_name": f"infrared/{split}/{ir_path.name}",
            "rgb_file": f"visible/{split}/{vis_path.name}",
            "annotation": f"Annotations/{xml_path.name}",
            "split": split,
        }
        return pair_sample(k + 1, rgb, ir8, *self._voc.targets(ann, CATEGORIES), split, meta)


def find_root(root: str | Path | None) -> Path:
    """Accept ``LLVIP/`` itself or the folder that holds it."""
    return find_release_root(root, ROOT_ENV, DATASET, ("LLVIP",), [("Annotations", "infrared", "visible")])


def open_llvip(
    root: str | Path | None = None, strict: bool = False, voc_convention: str = "one-based", difficult: str = "drop"
) -> LlvipSource:
    """Open an LLVIP release (the options are the ``dataset:`` config keys, see ``OPTIONS``)."""
    strict = check_strict(DATASET, strict)
    return LlvipSource(
        find_root(root),
        strict=strict,
        voc_convention=normalise_convention(DATASET, voc_convention),
        difficult=normalise_difficult(DATASET, difficult),
    )


SPEC = eightbit_spec(DATASET, open_llvip, CATEGORIES, DESCRIPTION, ROOT_ENV)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
