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

The same module holds the **box guard** shared by every producer of boxes (predictions scored from elsewhere and a
detector plugin's eval-mode output, ``harness.engine.predict``): a misread box convention shows in most boxes at
once, where an honest weak detector shows in none.

* ``normalised``: more than ``MOST`` of the boxes lie within 0..1 (``NORM_TOL``) although the frame is many pixels
  wide: coordinates divided by the image size;
* ``outside``: more than ``MOST`` of the boxes lie mostly (more than half their area) outside the frame: boxes of
  another frame, or at another scale;
* ``box_format``: (scored predictions) corners ``x1, y1, x2, y2`` where COCO's ``x, y, w, h`` is expected: the
  corner reading agrees with the ground truth far better (``shift_found``), or nearly every box has ``w >= x`` and
  ``h >= y`` (``XYXY_SHARE``), and read as corners fewer lie outside the frame and none agree less;
* ``frame``: (scored predictions) the boxes agree with the ground truth far better read in another ``--frame``.

Each finding gives counts and examples, and says which option fixes the mapping. ``harness score`` stops on any
finding unless ``--allow-implausible`` is given, which scores the predictions as read and labels the stored result;
a run stops unless ``eval.allow_degenerate=true``, which stores it labelled.
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


def overlaps_truth(preds: Sequence[Pred], targets: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Per prediction: it overlaps an object of its category on its image with IoU >= 0.5 (``False`` without a
    sample or a category)."""
    out = np.zeros(len(preds), dtype=bool)
    by_image: dict[int, list[int]] = {}
    for k, (idx, _, _, label) in enumerate(preds):
        if idx is not None and label is not None:
            by_image.setdefault(idx, []).append(k)
    for idx, ks in by_image.items():
        gt_boxes, gt_labels = targets(idx)
        if len(gt_boxes) == 0:
            continue
        boxes = np.asarray([preds[k][1] for k in ks], dtype=np.float64).reshape(-1, 4)
        labels = np.asarray([preds[k][3] for k in ks])
        iou = _iou(boxes, np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4))
        same = labels[:, None] == np.asarray(gt_labels)[None, :]
        out[ks] = ((iou >= 0.5) & same).any(axis=1)
    return out


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


# ------------------------------------------------------------------------------------------------ the box guard
#: The share of boxes above which a box convention or frame counts as misread (a misreading shows in most boxes).
MOST = 0.5
#: Coordinates within this of 0..1 count as normalised.
NORM_TOL = 0.01
#: Frames narrower than this (px) are too small to tell normalised boxes from pixel boxes.
NORM_MIN_FRAME = 8
#: The share of ``[x, y, w, h]`` boxes with ``w >= x`` and ``h >= y`` from which they read as corners.
XYXY_SHARE = 0.9
#: At least this many boxes before the structural corner test says anything.
XYXY_MIN_BOXES = 20


def most(part: int, whole: int) -> bool:
    return whole > 0 and part > MOST * whole


def examples(boxes: np.ndarray, mask: np.ndarray, k: int = 3) -> str:
    """Up to ``k`` of ``boxes[mask]``, rounded, for a message."""
    shown = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)[np.asarray(mask, bool)][:k]
    return "; ".join("[" + ", ".join(f"{v:.4g}" for v in b) + "]" for b in shown.tolist())


def normalised(boxes: np.ndarray) -> np.ndarray:
    """Per box (any 4-number convention): every coordinate is finite and within 0..1 (``NORM_TOL``)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        inside = (b >= -NORM_TOL).all(axis=1) & (b <= 1 + NORM_TOL).all(axis=1)
    return np.asarray(np.isfinite(b).all(axis=1) & inside, dtype=bool)


def inside_share(boxes: np.ndarray, width: np.ndarray | float, height: np.ndarray | float) -> np.ndarray:
    """Per xyxy box, the share of its area inside the frame ``0..width x 0..height`` (a box of no area: 1 when its
    point lies inside, else 0; a non-finite box: 0)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    w = np.broadcast_to(np.asarray(width, dtype=np.float64), (len(b),))
    h = np.broadcast_to(np.asarray(height, dtype=np.float64), (len(b),))
    with np.errstate(invalid="ignore"):
        iw = np.clip(np.minimum(b[:, 2], w) - np.maximum(b[:, 0], 0.0), 0, None)
        ih = np.clip(np.minimum(b[:, 3], h) - np.maximum(b[:, 1], 0.0), 0, None)
        area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        point = ((b[:, 0] >= 0) & (b[:, 0] <= w) & (b[:, 1] >= 0) & (b[:, 1] <= h)).astype(np.float64)
        share = np.where(area > 0, iw * ih / np.where(area > 0, area, 1.0), point)
    return np.where(np.isfinite(b).all(axis=1), share, 0.0)


def mostly_outside(boxes: np.ndarray, width: np.ndarray | float, height: np.ndarray | float) -> np.ndarray:
    """Per xyxy box: more than half of its area lies outside the frame."""
    return inside_share(boxes, width, height) < 0.5


def corner_like(xywh: np.ndarray) -> np.ndarray:
    """Per ``[x, y, w, h]`` box: ``w >= x`` and ``h >= y``, as nearly every box of corners ``x1, y1, x2, y2`` is."""
    b = np.asarray(xywh, dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        return (b[:, 2] >= b[:, 0]) & (b[:, 3] >= b[:, 1])


def _size(width: np.ndarray | float, height: np.ndarray | float) -> str:
    w, h = np.atleast_1d(width), np.atleast_1d(height)
    if not (np.isfinite(w).all() and np.isfinite(h).all()):
        return "the"
    same = len(np.unique(w)) == 1 and len(np.unique(h)) == 1
    return f"the {w[0]:g}x{h[0]:g} px" if same else f"the {w.min():g}..{w.max():g} x {h.min():g}..{h.max():g} px"


def box_findings(
    boxes: np.ndarray,
    width: np.ndarray | float,
    height: np.ndarray | float,
    what: str,
    frame: str,
    fix_outside: str,
    fix_normalised: str,
    given: np.ndarray | None = None,
    only: Sequence[str] = ("normalised", "outside"),
) -> list[Finding]:
    """The structural findings of the box guard (``normalised``, ``outside``) on xyxy ``boxes`` in a frame of
    ``width x height`` px (per box or one for all); ``given``: the same boxes as they were written, when the
    normalised test is to look at those. ``what`` names the boxes ("predictions", "boxes detector 'x' returned"),
    ``frame`` the frame ("the prepared frame", "the 64x64 input"), the ``fix_*`` strings what to do; ``only``: the
    findings to look for. A normalised finding is the only one given (it explains the boxes outside)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    n = len(b)
    out: list[Finding] = []
    if n == 0:
        return out
    shown = b if given is None else np.asarray(given, dtype=np.float64).reshape(-1, 4)
    big = np.broadcast_to(np.minimum(width, height), (n,)) >= NORM_MIN_FRAME
    norm = normalised(shown) & big
    k = int(norm.sum())
    if "normalised" in only and most(k, n):
        out.append(
            Finding(
                "normalised",
                f"{k} of {n} {what} ({pct(k, n)}) lie within 0..1 of "
                f"{_size(width, height)} {frame}, e.g. {examples(shown, norm)}: normalised "
                f"coordinates? {fix_normalised}",
            )
        )
        return out
    if "outside" not in only:
        return out
    outside = mostly_outside(b, width, height)
    k = int(outside.sum())
    if most(k, n):
        out.append(
            Finding(
                "outside",
                f"{k} of {n} {what} ({pct(k, n)}) lie mostly outside "
                f"{_size(width, height)} {frame}, e.g. {examples(b, outside)}: {fix_outside}",
            )
        )
    return out
