"""Object sizes of a dataset: boxes per category and per SAFit size bin, shown by ``harness prepare`` and the report.

The bins are RGBT-Tiny's (SAFit evaluation, ``Params.areaRng``), on the box area ``w * h`` in pixels of the prepared
(thermal) frame:

==================  =====  ====================  ==========================
bin                 short  area (px^2)           side of a square box
==================  =====  ====================  ==========================
extremely tiny      ET     [0, 8^2)              below 8 px
tiny                T      [8^2, 16^2)           8 to 16 px
small               S      [16^2, 32^2)          16 to 32 px
medium              M      [32^2, 96^2)          32 to 96 px
large               L      [96^2, inf)           96 px and more
==================  =====  ====================  ==========================

Here every box falls in exactly one bin (lower edge included); the evaluation's area ranges include both edges, so
a box of area exactly 64, 256, 1024 or 9216 px^2 is scored in both neighbouring bins there. An extremely tiny box is
smaller than one cell of the finest feature map of the YOLO-style detectors (stride 8): the table says at once how
much of a dataset lies below what the detectors resolve. Sizes are in prepared-frame pixels; a detector trained at
``imgsz`` sees them scaled by ``imgsz / max(W, H)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

#: (name, short name, lower area edge, upper area edge) in px^2.
SIZE_BINS: tuple[tuple[str, str, float, float], ...] = (
    ("extremely tiny", "ET", 0.0, 8.0**2),
    ("tiny", "T", 8.0**2, 16.0**2),
    ("small", "S", 16.0**2, 32.0**2),
    ("medium", "M", 32.0**2, 96.0**2),
    ("large", "L", 96.0**2, math.inf),
)
#: Stride of the finest feature map of the built-in detectors (P3/8).
FINEST_STRIDE = 8


def size_bin(areas: Sequence[float] | np.ndarray) -> np.ndarray:
    """Index into ``SIZE_BINS`` of each area (lower edge included): 63.9 -> 0, 64 -> 1, 9216 -> 4."""
    edges = np.array([b[3] for b in SIZE_BINS[:-1]])
    return np.searchsorted(edges, np.asarray(areas, dtype=np.float64), side="right")


@dataclass
class SizeSummary:
    """Boxes per category (rows, label order) and per size bin (columns, ``SIZE_BINS`` order)."""

    categories: list[str]
    counts: np.ndarray = field(default=None)  # type: ignore[arg-type]
    images: int = 0

    def __post_init__(self) -> None:
        if self.counts is None:
            self.counts = np.zeros((len(self.categories), len(SIZE_BINS)), dtype=np.int64)

    def add(self, boxes: np.ndarray, labels: np.ndarray) -> None:
        """Count the xyxy ``boxes`` (Nx4) of one image with their 0-based ``labels``."""
        self.images += 1
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        if not len(boxes):
            return
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        np.add.at(self.counts, (np.asarray(labels, dtype=np.int64), size_bin(area)), 1)

    # ------------------------------------------------------------------ sources
    @classmethod
    def of_prepared(cls, prepared: Any, indices: Iterable[int] | None = None) -> "SizeSummary":
        """The summary of a ``PreparedDataset`` (all samples, or ``indices``); reads no image."""
        out = cls(list(prepared.categories))
        for i in range(len(prepared)) if indices is None else indices:
            out.add(*prepared.targets(i))
        return out

    @classmethod
    def of_coco(cls, gt: Mapping[str, Any]) -> "SizeSummary":
        """The summary of a COCO ground-truth dict (categories in ``categories`` order; crowd regions left out)."""
        cats = list(gt.get("categories") or [])
        index = {c["id"]: k for k, c in enumerate(cats)}
        out = cls([str(c["name"]) for c in cats])
        out.images = len(gt.get("images") or [])
        anns = [a for a in gt.get("annotations") or [] if not a.get("iscrowd") and a.get("category_id") in index]
        if anns:
            area = [float(a["bbox"][2]) * float(a["bbox"][3]) for a in anns]
            np.add.at(out.counts, (np.array([index[a["category_id"]] for a in anns]), size_bin(area)), 1)
        return out

    # ------------------------------------------------------------------ views
    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def shares(self) -> np.ndarray:
        """Fraction of all boxes in each bin (zeros when there are no boxes)."""
        per_bin = self.counts.sum(axis=0)
        return per_bin / per_bin.sum() if per_bin.sum() else np.zeros(len(SIZE_BINS))

    def headline(self) -> str:
        """One line: how much of the dataset is below the finest detector stride and below 16 px."""
        if not self.total:
            return "object sizes: no boxes"
        s = self.shares()
        return (
            f"object sizes: {100 * s[0]:.1f} % of {self.total:,} boxes are under {FINEST_STRIDE}x{FINEST_STRIDE} px "
            f"(the finest detector stride), {100 * (s[0] + s[1]):.1f} % under 16x16 px"
        )

    def rows(self) -> list[list[Any]]:
        """Per category: name, count per bin, total; then an ``all`` row and a ``share`` row (percent)."""
        out: list[list[Any]] = [[c, *map(int, row), int(row.sum())] for c, row in zip(self.categories, self.counts)]
        out.append(["all", *map(int, self.counts.sum(axis=0)), self.total])
        out.append(["share (%)", *(f"{100 * v:.1f}" for v in self.shares()), "100.0" if self.total else "-"])
        return out

    @staticmethod
    def header() -> list[str]:
        return ["category", *(bin_label(k) for k in range(len(SIZE_BINS))), "total"]

    def to_text(self) -> str:
        from harness.textable import text_table

        rows = [[f"{v:,}" if isinstance(v, int) else v for v in r] for r in self.rows()]
        return text_table(self.header(), rows)

    def to_dict(self) -> dict[str, Any]:
        return {
            "bins": [
                {"name": n, "short": s, "area": [lo, None if math.isinf(hi) else hi]} for n, s, lo, hi in SIZE_BINS
            ],
            "images": self.images,
            "counts": {c: [int(v) for v in row] for c, row in zip(self.categories, self.counts)},
        }


def bin_label(k: int) -> str:
    """Column label of bin ``k``: the short name and the side sqrt(w * h) in px, e.g. 'ET <8', 'T 8-16', 'L >=96'."""
    _, short, lo, hi = SIZE_BINS[k]
    if lo == 0:
        return f"{short} <{math.sqrt(hi):g}"
    if math.isinf(hi):
        return f"{short} >={math.sqrt(lo):g}"
    return f"{short} {math.sqrt(lo):g}-{math.sqrt(hi):g}"
