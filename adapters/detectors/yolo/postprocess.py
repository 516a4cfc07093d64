"""From decoded per-anchor predictions to detections: confidence filter, per-class NMS, ``max_det`` cap, clipping.

The same rules as the public YOLOv8 validator: with ``multi_label`` every (anchor, class) pair whose probability is
above ``conf`` is a candidate (otherwise only each anchor's best class); the ``max_nms`` highest-scoring candidates
go to exact greedy NMS per class (``harness.boxes.batched_nms``, boxes of different classes never suppress each
other); the first ``max_det`` survivors are kept and clipped to the image.
"""

from __future__ import annotations

from typing import Any

import torch

from harness.boxes import batched_nms

#: The inference settings a detector keeps as attributes and passes to ``postprocess``, with the public YOLOv8
#: validator's values (``postprocess``'s defaults).
INFERENCE_DEFAULTS: dict[str, Any] = {"conf": 0.001, "iou": 0.7, "max_det": 300, "multi_label": True, "max_nms": 30000}


def inference_settings(model: Any) -> dict[str, Any]:
    """The model's inference settings (its attributes named in ``INFERENCE_DEFAULTS``), as keywords for
    ``postprocess``."""
    return {k: getattr(model, k) for k in INFERENCE_DEFAULTS}


def clip_boxes(boxes: torch.Tensor, image_hw: tuple[int, int]) -> torch.Tensor:
    """Clip xyxy boxes to ``[0, W] x [0, H]``."""
    h, w = image_hw
    out = boxes.clone()
    out[..., 0::2] = out[..., 0::2].clamp(0, w)
    out[..., 1::2] = out[..., 1::2].clamp(0, h)
    return out


def select_candidates(
    scores: torch.Tensor, conf: float, multi_label: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``[A, C]`` probabilities -> (anchor index, class index, score) of every candidate above ``conf``."""
    if multi_label:
        anchor, label = torch.nonzero(scores > conf, as_tuple=True)
        return anchor, label, scores[anchor, label]
    best, label = scores.max(1)
    anchor = torch.nonzero(best > conf)[:, 0]
    return anchor, label[anchor], best[anchor]


def postprocess(
    boxes: torch.Tensor, scores: torch.Tensor, *, image_hw: tuple[int, int] | None = None, **settings: Any
) -> list[dict[str, torch.Tensor]]:
    """``boxes [B, A, 4]`` xyxy pixels, ``scores [B, A, C]`` probabilities -> per image ``{"boxes" [K,4],
    "scores" [K], "labels" [K] int64}`` sorted by decreasing score, ``K <= max_det``.

    ``settings``: any of ``INFERENCE_DEFAULTS`` (``conf``, ``iou``, ``max_det``, ``multi_label``, ``max_nms``), the
    rest keep their defaults."""
    unknown = sorted(set(settings) - set(INFERENCE_DEFAULTS))
    if unknown:
        raise TypeError(f"postprocess: unknown setting(s) {unknown}; known: {list(INFERENCE_DEFAULTS)}")
    s = {**INFERENCE_DEFAULTS, **settings}
    conf, iou, max_det, multi_label, max_nms = (s[k] for k in INFERENCE_DEFAULTS)
    out = []
    for bx, sc in zip(boxes, scores):
        anchor, label, score = select_candidates(sc, conf, multi_label)
        if score.numel() > max_nms:
            top = score.topk(max_nms).indices
            anchor, label, score = anchor[top], label[top], score[top]
        cand = bx[anchor].float()
        keep = batched_nms(cand, score, label, iou, max_keep=max_det)
        kept = cand[keep]
        if image_hw is not None:
            kept = clip_boxes(kept, image_hw)
        out.append({"boxes": kept, "scores": score[keep].float(), "labels": label[keep].long()})
    return out
