"""A detectron2-style evaluator: ``reset()``, ``process(image_ids, outputs)`` per batch, ``evaluate()`` at the end.

``outputs`` are what a detector returns in eval mode, one dict per image with ``boxes`` (xyxy pixels of the
ground truth's frame), ``scores`` and ``labels`` (0-based); they become COCO results with
``category_id = label + 1`` (the harness's convention, see ``harness/cache/reader.py``). Every image is processed at
most once; an image the ground truth does not know is an error, and GT images never processed are counted.
"""

from __future__ import annotations

import logging
from typing import Any, Mapping, Sequence

import numpy as np

from harness.evaluation.coco import evaluate
from harness.evaluation.inputs import EvaluationError, _norm_id

log = logging.getLogger(__name__)


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def outputs_to_coco(image_id: Any, output: Mapping[str, Any], label_offset: int = 1) -> list[dict[str, Any]]:
    """One image's ``{"boxes" xyxy, "scores", "labels"}`` as COCO results (``category_id = label + label_offset``)."""
    boxes = _numpy(output["boxes"]).astype(np.float64).reshape(-1, 4)
    scores = _numpy(output["scores"]).astype(np.float64).reshape(-1)
    labels = _numpy(output["labels"]).astype(np.int64).reshape(-1)
    if not (len(boxes) == len(scores) == len(labels)):
        raise EvaluationError(f"image {image_id!r}: {len(boxes)} boxes, {len(scores)} scores and {len(labels)} labels")
    xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1).tolist()
    return [{"image_id": image_id, "category_id": int(lab) + label_offset, "bbox": b, "score": float(s)}
            for b, s, lab in zip(xywh, scores.tolist(), labels.tolist())]


class COCOEvaluator:
    """Collect a model's per-image outputs and score them with ``harness.evaluation.evaluate``."""

    def __init__(self, gt: Mapping[str, Any], engine: str = "faster-coco-eval", matching: str = "iou",
                 safit_anchor: str = "center", strict: bool = False):
        self.gt = gt
        self.engine, self.matching, self.safit_anchor, self.strict = engine, matching, safit_anchor, strict
        self._gt_ids = {_norm_id(im["id"], f"ground truth images[{i}]") for i, im in enumerate(gt.get("images", []))}
        self.reset()

    def reset(self) -> None:
        self._dets: list[dict[str, Any]] = []
        self._seen: set = set()

    def process(self, image_ids: Sequence[Any], outputs: Sequence[Mapping[str, Any]]) -> None:
        if len(image_ids) != len(outputs):
            raise EvaluationError(f"process(): {len(image_ids)} image ids but {len(outputs)} outputs")
        for image_id, out in zip(image_ids, outputs):
            key = _norm_id(image_id.item() if hasattr(image_id, "item") else image_id, "process()")
            if key not in self._gt_ids:
                raise EvaluationError(f"process(): image {image_id!r} is not in the ground truth being evaluated")
            if key in self._seen:
                raise EvaluationError(f"process(): image {image_id!r} was processed twice (a padded or repeating "
                                      f"sampler?); each image must be evaluated exactly once")
            self._seen.add(key)
            self._dets.extend(outputs_to_coco(key, out))

    @property
    def detections(self) -> list[dict[str, Any]]:
        """The COCO results collected so far (what ``predictions.json`` holds)."""
        return list(self._dets)

    def evaluate(self) -> dict[str, Any]:
        missing = len(self._gt_ids - self._seen)
        if missing:
            log.warning("%d of %d ground-truth images were never processed; their objects count as missed",
                        missing, len(self._gt_ids))
        result = evaluate(self.gt, self._dets, engine=self.engine, matching=self.matching,
                          safit_anchor=self.safit_anchor, strict=self.strict)
        result["metrics"]["unprocessed_images"] = missing
        return result
