"""Inference over a subset: COCO-format detections in the thermal frame.

The model sees each held-out image letterboxed to the protocol size, exactly as in training; its boxes are mapped
back through the letterbox (``x = (x_input - pad) / ratio``), clipped to the image, and written as COCO results:
``{"image_id", "category_id": label + 1, "bbox": [x, y, w, h], "score"}`` in thermal-frame pixels, at the full
precision of the model's float32 output (``x``, ``y`` and the score are float32 values, ``w = x2 - x1`` and
``h = y2 - y1`` their exact differences), so that what is stored is exactly what was scored.

Degenerate boxes are dropped and counted by kind (``DEGENERATE``): ``non_finite`` (NaN or inf), ``inverted``
(``x2 < x1`` or ``y2 < y1``: e.g. ``x, y, w, h`` returned instead of ``x1, y1, x2, y2``), ``zero_size``
(``x2 == x1`` or ``y2 == y1``), and ``outside_image`` (nothing left after clipping to the image).

The box guard (``harness.scoring.plausibility``, shared with ``harness score``) looks at the boxes as returned: more
than half of them malformed, within 0..1 of the input (normalised coordinates), or lying mostly outside the image
(another scale) stops the run naming the detector (``DegenerateBoxes.check``), unless ``eval.allow_degenerate``,
which stores the result labelled. Malformed boxes under that rule are still said (``DegenerateBoxes.warning``): a
warning, and a label on the stored result when they are more than ``SHARE`` of the boxes.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import Subset

from harness.boxes import DEGENERATE, MALFORMED, degenerate_kinds  # the degenerate kinds live with the box ops
from harness.engine.data import LetterboxDataset, SampleSource, eval_loader, to_inputs
from harness.errors import PluginError
from harness.progress import bar as progress_bar
from harness.scoring import plausibility as guard

log = logging.getLogger(__name__)


def configure(model: nn.Module, conf: float, iou: float, max_det: int) -> None:
    """Set the model's own NMS settings (the ``conf``, ``iou`` and ``max_det`` attributes of the contract)."""
    model.conf, model.iou, model.max_det = float(conf), float(iou), int(max_det)


@dataclass
class DegenerateBoxes:
    """Boxes a detector returned and the degenerate ones left out, by kind, with up to three examples of each."""

    returned: int = 0
    counts: Counter = field(default_factory=Counter)
    examples: dict[str, list[list[float]]] = field(default_factory=dict)
    #: the box guard's counts of boxes as returned (input pixels): ``normalised`` (within 0..1 of an input at least
    #: ``guard.NORM_MIN_FRAME`` px wide) and ``mostly_outside`` (well-formed, more than half outside the image)
    guarded: Counter = field(default_factory=Counter)
    guard_examples: dict[str, list[list[float]]] = field(default_factory=dict)

    def add(self, kind: str, box: list[float]) -> None:
        self.counts[kind] += 1
        shown = self.examples.setdefault(kind, [])
        if len(shown) < 3:
            shown.append([round(float(v), 2) for v in box])

    def add_guarded(self, kind: str, boxes: np.ndarray) -> None:
        self.guarded[kind] += len(boxes)
        shown = self.guard_examples.setdefault(kind, [])
        shown += [[round(float(v), 4) for v in b] for b in boxes[: max(0, 3 - len(shown))].tolist()]

    def merge(self, other: DegenerateBoxes) -> None:
        self.returned += other.returned
        self.counts.update(other.counts)
        for kind, boxes in other.examples.items():
            self.examples[kind] = (self.examples.get(kind, []) + boxes)[:3]
        self.guarded.update(other.guarded)
        for kind, boxes in other.guard_examples.items():
            self.guard_examples[kind] = (self.guard_examples.get(kind, []) + boxes)[:3]

    @property
    def malformed(self) -> int:
        return sum(self.counts[k] for k in MALFORMED)

    def to_dict(self) -> dict[str, Any]:
        """What ``metrics.json`` records (``metrics.degenerate_detections``); the box guard's counts only when a
        box was normalised or mostly outside."""
        return {
            "returned": self.returned,
            **{k: int(self.counts[k]) for k in DEGENERATE},
            "examples": {k: v for k, v in self.examples.items()},
            **{k: int(v) for k, v in self.guarded.items() if v},
        }

    def _malformed_seen(self) -> tuple[str, str]:
        seen = ", ".join(f"{self.counts[k]} {k.replace('_', ' ')}" for k in MALFORMED if self.counts[k])
        shown = "; ".join(f"{k} {', '.join(map(str, v))}" for k, v in self.examples.items() if k in MALFORMED)
        return seen, shown

    def check(self, detector: str, allow: bool = False) -> str | None:
        """Stop (``PluginError`` naming the detector) when most of the returned boxes were malformed
        (``MALFORMED``), normalised, or mostly outside the image (module docstring); with ``allow``, return a note
        that labels the result instead. ``None`` when plausible."""
        bad = self.malformed
        n = self.returned
        if n == 0:
            return None
        if 2 * bad > n:
            seen, shown = self._malformed_seen()
            text = (
                f"detector {detector!r}: {bad} of the {n} boxes it returned in eval mode were degenerate ({seen}; "
                f"e.g. {shown})"
            )
            fix = "Eval-mode boxes must be x1, y1, x2, y2 in input pixels (not x, y, w, h)"
        elif guard.most(k := self.guarded["normalised"], n):
            text = (
                f"detector {detector!r}: {k} of the {n} boxes it returned in eval mode ({guard.pct(k, n)}) lie "
                f"within 0..1 of the input, e.g. {self._shown('normalised')}: normalised coordinates?"
            )
            fix = "Eval-mode boxes must be x1, y1, x2, y2 in input pixels: multiply by the input width and height"
        elif guard.most(k := self.guarded["mostly_outside"], n):
            text = (
                f"detector {detector!r}: {k} of the {n} boxes it returned in eval mode ({guard.pct(k, n)}) lie "
                f"mostly outside the image, e.g. {self._shown('mostly_outside')} (input pixels): boxes at "
                f"another scale, or of another input size?"
            )
            fix = "Eval-mode boxes must be x1, y1, x2, y2 in pixels of the input the model was given"
        else:
            return None
        if allow:
            return text + "; stored anyway because eval.allow_degenerate is set"
        sep = " " if text.endswith("?") else ". "
        raise PluginError(
            text + f"{sep}{fix}: fix the detector, or set eval.allow_degenerate=true to store the run labelled"
        )

    def _shown(self, kind: str) -> str:
        return "; ".join(str(b) for b in self.guard_examples.get(kind, []))

    def warning(self, detector: str) -> str | None:
        """Malformed boxes under the stop rule (``check``), said rather than dropped in silence: the line to log,
        ``None`` when there were none."""
        bad = self.malformed
        if not bad or 2 * bad > self.returned:
            return None
        seen, shown = self._malformed_seen()
        return (
            f"detector {detector!r}: {bad} of the {self.returned} boxes it returned in eval mode "
            f"({guard.pct(bad, self.returned)}) were malformed and left out ({seen}; e.g. {shown})"
        )

    def label(self, detector: str) -> str | None:
        """The warning as a label of the stored result, when the malformed boxes are more than ``guard.SHARE`` of
        those returned (fewer leave the numbers nearly as they are)."""
        text = self.warning(detector)
        return text if text and guard.too_many(self.malformed, self.returned) else None


def detections_to_coco(
    det: dict[str, torch.Tensor],
    image_id: int,
    letterbox: Any,
    num_classes: int | None = None,
    name: str = "model",
    degenerate: DegenerateBoxes | None = None,
) -> list[dict[str, Any]]:
    """One image's ``{"boxes", "scores", "labels"}`` (input pixels) -> COCO results in the original frame.

    Degenerate boxes are left out and, when ``degenerate`` is given, counted there."""
    from harness.contracts import check_detections

    boxes, scores, labels = check_detections(det, name, num_classes, counted=True)
    kind = degenerate_kinds(boxes)
    raw = boxes
    if degenerate is not None and letterbox is not None and len(raw):
        h, w = letterbox.shape
        norm = guard.normalised(raw) & (min(w, h) * letterbox.ratio >= guard.NORM_MIN_FRAME)
        if norm.any():
            degenerate.add_guarded("normalised", raw[norm])
        unpadded = np.asarray(raw, dtype=np.float64).copy()
        unpadded[:, [0, 2]] = (unpadded[:, [0, 2]] - letterbox.pad[0]) / letterbox.ratio
        unpadded[:, [1, 3]] = (unpadded[:, [1, 3]] - letterbox.pad[1]) / letterbox.ratio
        outside = (kind < 0) & ~norm & guard.mostly_outside(unpadded, w, h)
        if outside.any():
            degenerate.add_guarded("mostly_outside", raw[outside])
    if letterbox is not None:
        boxes = letterbox.to_original(np.where(np.isfinite(boxes), boxes, 0.0))
    out = []
    for k, ((x1, y1, x2, y2), s, lab) in enumerate(zip(boxes.tolist(), scores.tolist(), labels.tolist())):
        w, h = x2 - x1, y2 - y1
        if kind[k] < 0 and (w <= 0 or h <= 0):
            kind[k] = DEGENERATE.index("outside_image")
        if kind[k] >= 0:
            continue
        out.append({"image_id": int(image_id), "category_id": int(lab) + 1, "bbox": [x1, y1, w, h], "score": s})
    if degenerate is not None:
        degenerate.returned += len(kind)
        for k in np.flatnonzero(kind >= 0).tolist():
            degenerate.add(DEGENERATE[kind[k]], raw[k].tolist())
    return out


@torch.inference_mode()
def predict(
    model: nn.Module,
    source: SampleSource,
    imgsz: int,
    batch: int = 8,
    input_kind: str = "single",
    thermal_channels: int = 3,
    device: torch.device | str = "cpu",
    conf: float | None = None,
    iou: float | None = None,
    max_det: int | None = None,
    num_classes: int | None = None,
    workers: int = 0,
    progress: bool = False,
    name: str = "model",
    distributed: bool = False,
    visited: list[int] | None = None,
    degenerate: DegenerateBoxes | None = None,
) -> list[dict[str, Any]]:
    """Detections for every image of ``source`` (COCO results, see the module docstring).

    With ``distributed`` (under ``torchrun``) each process predicts one contiguous shard of the images
    (``harness.distributed.inference_shard``: every image exactly once, no padding duplicates) and rank 0 receives
    all detections, in the order a single process would produce them; the other ranks get an empty list. When
    given, ``visited`` receives the ids of the images predicted (on rank 0: by all processes), and ``degenerate``
    the counts of degenerate boxes left out (``detections_to_coco``; on rank 0: of all processes).
    """
    from harness import distributed as hd

    if conf is not None:
        configure(
            model,
            conf,
            iou if iou is not None else getattr(model, "iou", 0.7),
            max_det if max_det is not None else getattr(model, "max_det", 300),
        )
    d = hd.info() if distributed else hd.DistInfo()
    was_training = model.training
    model.eval()
    device = torch.device(device)
    dataset: Any = LetterboxDataset(source, imgsz)
    if d.active:
        dataset = Subset(dataset, list(hd.inference_shard(len(source), d.rank, d.world_size)))
    loader = eval_loader(dataset, batch, workers)
    results: list[dict[str, Any]] = []
    ids: list[int] = []
    counts = DegenerateBoxes()
    try:
        with progress_bar(f"predict {name}", len(dataset), enabled=progress and d.is_main) as bar:
            for b in loader:
                out = model(to_inputs(b.images, input_kind, thermal_channels, device))
                if not isinstance(out, (list, tuple)) or len(out) != len(b):
                    raise PluginError(
                        f"detector {name!r}: in eval mode model(inputs) must return one dict per image "
                        f"({len(b)}), got {type(out).__name__}"
                    )
                for det, image_id, lb in zip(out, b.image_ids, b.letterboxes):
                    results.extend(detections_to_coco(det, image_id, lb, num_classes, name, counts))
                ids.extend(int(i) for i in b.image_ids)
                bar.advance(len(b))
    finally:
        model.train(was_training)
    if d.active:
        parts = hd.gather_to_main((results, ids, counts))
        if parts is None:
            results, ids = [], []
        else:
            results = [r for part, _, _ in parts for r in part]
            ids = [i for _, part, _ in parts for i in part]
            counts = DegenerateBoxes()
            for _, _, c in parts:
                counts.merge(c)
            expected = [source.image_id(k) for k in range(len(source))]
            if ids != expected:  # the shards must partition the images exactly
                raise PluginError(
                    f"distributed prediction visited {len(ids)} images ({len(set(ids))} distinct), "
                    f"expected each of the {len(expected)} images once"
                )
    if visited is not None:
        visited.extend(ids)
    if degenerate is not None:
        degenerate.merge(counts)
    return results


#: How much a detection may change when the same model predicts the same image within another batch (``eval.batch``):
#: the score, and each box coordinate in input pixels. Every image is letterboxed alone onto the same canvas, eval
#: mode uses BatchNorm's running statistics and NMS works per image, so what a batch changes is only kernel arithmetic:
#: oneDNN picks a convolution's blocking by the batch size, and a GEMM over the batch (attention, fully connected
#: layers) is blocked by its row count. Measured by ``benchmarks/prediction_batch.py`` for the built-in detectors and
#: TinyDet (batches 1, 2, 8): at most 5.1e-7 in a score and 6.1e-5 image pixels in a box; with ATen's convolutions
#: (``HARNESS_ONEDNN=0``) ours, EME and TinyDet predict identically, ICAFusion and CMA-Det change as much (CMA-Det
#: once traded one of its 3,200 detections for another). mAP moved by at most 3.6e-7.
#: The bounds leave about 20x that; a detector that mixes the images of a batch (BatchNorm in train mode, padding to
#: the batch's largest image, a batch-wide threshold) changes far more.
BATCH_SCORE_TOL = 1e-5
BATCH_BOX_TOL = 2e-3


@dataclass
class DetectionChanges:
    """How two predictions of the same images differ (``detection_changes``)."""

    #: the largest score change of a detection and its counterpart
    score: float = 0.0
    #: the largest change of a box coordinate of a detection and its counterpart (input or image pixels)
    box: float = 0.0
    #: detections (of either prediction) without a counterpart within ``tol`` pixels
    unmatched: int = 0
    #: detections in all, both predictions
    detections: int = 0

    def within(self, score_tol: float = BATCH_SCORE_TOL, box_tol: float = BATCH_BOX_TOL) -> bool:
        return self.unmatched == 0 and self.score <= score_tol and self.box <= box_tol


def detection_changes(
    a: list[dict[str, Any]] | tuple[dict[str, Any], ...],
    b: list[dict[str, Any]] | tuple[dict[str, Any], ...],
    tol: float = 1.0,
) -> DetectionChanges:
    """Compare two predictions of the same images, one ``{"boxes", "scores", "labels"}`` dict per image (tensors or
    arrays, boxes ``x1, y1, x2, y2``): each detection's counterpart is the detection of the other prediction of the
    same image and label whose box is nearest (the largest coordinate difference; among equally near boxes the
    nearest score), both ways; one farther than ``tol`` pixels counts as unmatched."""
    if len(a) != len(b):
        raise ValueError(f"detection_changes: {len(a)} images against {len(b)}")
    out = DetectionChanges()

    def arrays(d: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        def np_(v: Any) -> np.ndarray:
            return v.detach().cpu().double().numpy() if isinstance(v, torch.Tensor) else np.asarray(v, np.float64)

        return np_(d["boxes"]).reshape(-1, 4), np_(d["scores"]).reshape(-1), np_(d["labels"]).reshape(-1)

    for da, db in zip(a, b):
        pa, pb = arrays(da), arrays(db)
        out.detections += len(pa[1]) + len(pb[1])
        for (bx, sc, lb), (ob, os_, ol) in ((pa, pb), (pb, pa)):
            if not len(sc):
                continue
            if not len(os_):
                out.unmatched += len(sc)
                continue
            dist = np.abs(bx[:, None, :] - ob[None, :, :]).max(2)
            dist[lb[:, None] != ol[None, :]] = np.inf
            near = dist <= dist.min(1, keepdims=True)
            j = np.where(near, np.abs(sc[:, None] - os_[None, :]), np.inf).argmin(1)
            d = dist[np.arange(len(sc)), j]
            ok = d <= tol
            out.unmatched += int((~ok).sum())
            if ok.any():
                out.box = max(out.box, float(d[ok].max()))
                out.score = max(out.score, float(np.abs(sc[ok] - os_[j[ok]]).max()))
    return out


@torch.inference_mode()
def batch_changes(model: nn.Module, inputs: Any, batches: tuple[int, ...] = (1, 2, 8)) -> dict[int, DetectionChanges]:
    """Run ``model`` in eval mode over ``inputs`` (a ``[N, C, H, W]`` tensor, or a tuple of them for a dual-stream
    model) ``b`` images at a time for every ``b`` of ``batches`` and compare each with the first
    (``detection_changes``, input pixels): what ``eval.batch`` changes in its predictions."""
    was_training = model.training
    model.eval()
    try:
        parts = inputs if isinstance(inputs, (tuple, list)) else (inputs,)
        n = len(parts[0])

        def run(b: int) -> list[dict[str, Any]]:
            out: list[dict[str, Any]] = []
            for i in range(0, n, b):
                chunk = tuple(p[i : i + b] for p in parts)
                out.extend(model(chunk if isinstance(inputs, (tuple, list)) else chunk[0]))
            return out

        base = run(batches[0])
        return {b: detection_changes(base, run(b)) for b in batches}
    finally:
        model.train(was_training)
