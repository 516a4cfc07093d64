"""The plausibility guard on predictions made elsewhere (``harness score``): mappings left out stop with what was seen.

Another codebase's ids are easy to read wrongly without a word: Ultralytics 8.0 writes 0-based class ids, and
MMDetection's ``--format-only`` results carry the image and category ids of its own annotation file. Read as the
harness's ids, such predictions land on the wrong class or the wrong image and score near zero as an ordinary run.
Before anything is scored, ``findings`` lists what makes the matching implausible:

* more than ``SHARE`` of the predictions are on images the dataset does not have;
* with image ids read as the harness's own (no file names, no ``--images``), more than ``SHARE`` of the
  predictions name images of other folds;
* more than ``SHARE`` of the predictions on the fold's images are in categories the dataset does not have;
* category ids, or image ids read as the harness's, that match only after a shift by one: the ids fit the
  dataset's range only shifted, or the predictions agree with the ground truth far better shifted (``agreement``,
  recall at IoU 0.50: at least ``SHIFT_MIN_AGREEMENT`` shifted and ``SHIFT_FACTOR`` times the reading as given).

Each finding gives counts and examples, and says which option fixes the mapping. ``harness score`` stops on any
finding unless ``--allow-implausible`` is given, which scores the predictions as read and labels the stored result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

#: The share of predictions that may go unmatched (unknown images or categories) before the guard stops.
SHARE = 0.05
#: A shift is reported when the shifted reading agrees with the ground truth on at least this share of the
#: confident predictions and on at least ``SHIFT_FACTOR`` times the share of the reading as given.
SHIFT_MIN_AGREEMENT = 0.2
SHIFT_FACTOR = 3.0
#: Predictions per image (highest scores first) that the agreement looks at, as COCO's maxDets.
TOP_PER_IMAGE = 100

#: One prediction as the guard sees it: (sample index or None, box xyxy in the prepared frame, score, 0-based label
#: or None for a category the dataset does not have).
Pred = tuple["int | None", Sequence[float], float, "int | None"]


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix of xyxy boxes ``a`` [N, 4] and ``b`` [M, 4]."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(axis=2)
    area_a = np.clip(a[:, 2:] - a[:, :2], 0, None).prod(axis=1)
    area_b = np.clip(b[:, 2:] - b[:, :2], 0, None).prod(axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def agreement(
    preds: Sequence[Pred],
    targets: Callable[[int], tuple[np.ndarray, np.ndarray]],
    images: Sequence[int],
    top: int = TOP_PER_IMAGE,
) -> float | None:
    """Recall at IoU 0.50 over the ground truth of ``images``: the share of their objects that a prediction of the
    same category on the same image overlaps with IoU >= 0.5, counting each image's ``top`` highest-scoring
    predictions. ``None`` when the images hold no objects. One reading of the ids against another is judged on the
    same objects, so a misread that moves predictions to other images or classes shows as a collapse of this share;
    a weak detector scores low under every reading and raises nothing."""
    wanted = set(images)
    by_image: dict[int, list[tuple[float, Sequence[float], int]]] = {}
    for idx, box, score, label in preds:
        if idx in wanted and label is not None:
            by_image.setdefault(idx, []).append((score, box, label))
    objects = hits = 0
    for idx in wanted:
        gt_boxes, gt_labels = targets(idx)
        objects += len(gt_boxes)
        items = sorted(by_image.get(idx, []), key=lambda t: -t[0])[:top]
        if not items or len(gt_boxes) == 0:
            continue
        boxes = np.asarray([b for _, b, _ in items], dtype=np.float64).reshape(-1, 4)
        labels = np.asarray([lab for _, _, lab in items])
        iou = _iou(boxes, np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4))
        same = labels[:, None] == np.asarray(gt_labels)[None, :]
        hits += int(((iou >= 0.5) & same).any(axis=0).sum())
    return hits / objects if objects else None


def shift_found(given: float | None, shifted: float | None) -> bool:
    """Whether the shifted reading agrees with the ground truth so much better that the given one is a misreading."""
    if shifted is None or shifted < SHIFT_MIN_AGREEMENT:
        return False
    return shifted >= SHIFT_FACTOR * (given or 0.0)


def pct(part: int, whole: int) -> str:
    return f"{100.0 * part / whole:.0f}%" if whole else "-"


@dataclass
class Finding:
    """One reason the predictions look misread: ``kind`` (a short key stored with the result) and the message."""

    kind: str
    message: str

    def __str__(self) -> str:
        return self.message


def too_many(part: int, whole: int) -> bool:
    return whole > 0 and part > SHARE * whole
