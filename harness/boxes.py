"""Box operations shared by detectors, the engine and evaluation: conversions, IoU variants and exact greedy NMS.

No torchvision: its wheel does not import beside the CPU torch used here, so NMS is the harness's own. The NMS is
exact greedy NMS (the same kept set as the classic algorithm), computed in blocks so that it stays fast with tens of
thousands of candidate boxes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch


def xyxy_to_xywh(b: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Corners to COCO (top-left x, top-left y, width, height)."""
    out: Any = b.clone() if isinstance(b, torch.Tensor) else np.array(b, copy=True)
    out[..., 2] = b[..., 2] - b[..., 0]
    out[..., 3] = b[..., 3] - b[..., 1]
    return out


def xywh_to_xyxy(b: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """COCO (top-left x, y, w, h) to corners."""
    out: Any = b.clone() if isinstance(b, torch.Tensor) else np.array(b, copy=True)
    out[..., 2] = b[..., 0] + b[..., 2]
    out[..., 3] = b[..., 1] + b[..., 3]
    return out


def cxcywh_to_xyxy(b: torch.Tensor) -> torch.Tensor:
    cx, cy, w, h = b.unbind(-1)
    return torch.stack((cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), -1)


def xyxy_to_cxcywh(b: torch.Tensor) -> torch.Tensor:
    x1, y1, x2, y2 = b.unbind(-1)
    return torch.stack(((x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1), -1)


def box_area(b: torch.Tensor) -> torch.Tensor:
    return (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)


def box_iou(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-9) -> torch.Tensor:
    """Pairwise IoU of xyxy boxes: ``[N,4] x [M,4] -> [N,M]``."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = (rb - lt).clamp(min=0)
    inter = wh[..., 0] * wh[..., 1]
    return inter / (box_area(a)[:, None] + box_area(b)[None, :] - inter + eps)


def bbox_iou(a: torch.Tensor, b: torch.Tensor, kind: str = "iou", eps: float = 1e-7) -> torch.Tensor:
    """Element-wise IoU of matching xyxy boxes ``[..., 4]``; ``kind`` is 'iou', 'giou', 'diou' or 'ciou'.

    CIoU = IoU - rho^2 / c^2 - alpha * v with v = 4/pi^2 (atan(w_g/h_g) - atan(w/h))^2 and
    alpha = v / (1 - IoU + v) (Zheng et al., 2020); rho is the centre distance, c the enclosing box diagonal.
    """
    ax1, ay1, ax2, ay2 = a.unbind(-1)
    bx1, by1, bx2, by2 = b.unbind(-1)
    w1, h1 = ax2 - ax1, (ay2 - ay1).clamp(min=eps)
    w2, h2 = bx2 - bx1, (by2 - by1).clamp(min=eps)
    inter = (torch.minimum(ax2, bx2) - torch.maximum(ax1, bx1)).clamp(min=0) * (
        torch.minimum(ay2, by2) - torch.maximum(ay1, by1)
    ).clamp(min=0)
    union = w1 * h1 + w2 * h2 - inter + eps
    iou = inter / union
    if kind == "iou":
        return iou
    cw = torch.maximum(ax2, bx2) - torch.minimum(ax1, bx1)
    ch = torch.maximum(ay2, by2) - torch.minimum(ay1, by1)
    if kind == "giou":
        c_area = cw * ch + eps
        return iou - (c_area - union) / c_area
    c2 = cw**2 + ch**2 + eps
    rho2 = ((bx1 + bx2 - ax1 - ax2) ** 2 + (by1 + by2 - ay1 - ay2) ** 2) / 4
    if kind == "diou":
        return iou - rho2 / c2
    if kind == "ciou":
        v = (4 / math.pi**2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)).pow(2)
        with torch.no_grad():
            alpha = v / (v - iou + (1 + eps))
        return iou - (rho2 / c2 + v * alpha)
    raise ValueError(f"unknown IoU kind {kind!r}")


def nms(
    boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float, block: int = 256, max_keep: int | None = None
) -> torch.Tensor:
    """Exact greedy NMS; returns kept indices sorted by decreasing score.

    Candidates are visited in blocks of ``block`` boxes: one IoU matrix of the block against the boxes kept so
    far removes most candidates at once, and the greedy pass inside the block runs on a small boolean matrix.
    ``max_keep`` stops after that many kept boxes (the result is the first ``max_keep`` of the full result).
    """
    if boxes.numel() == 0:
        return torch.empty(0, dtype=torch.long, device=boxes.device)
    order = scores.argsort(descending=True)
    b = boxes[order].float()
    kept_boxes: list[torch.Tensor] = []
    keep: list[int] = []
    for start in range(0, len(b), block):
        blk = b[start : start + block]
        if kept_boxes:
            alive = (box_iou(blk, torch.cat(kept_boxes)) <= iou_threshold).all(1)
        else:
            alive = torch.ones(len(blk), dtype=torch.bool, device=b.device)
        suppress = (box_iou(blk, blk) > iou_threshold).cpu().numpy()
        a = alive.cpu().numpy().copy()
        for i in range(len(a)):
            if a[i]:
                a[i + 1 :] &= ~suppress[i, i + 1 :]
        idx = np.nonzero(a)[0]
        if len(idx):
            kept_boxes.append(blk[torch.as_tensor(idx, device=b.device)])
            keep.extend((idx + start).tolist())
        if max_keep is not None and len(keep) >= max_keep:
            keep = keep[:max_keep]
            break
    return order[torch.as_tensor(keep, dtype=torch.long, device=boxes.device)]


def batched_nms(
    boxes: torch.Tensor, scores: torch.Tensor, classes: torch.Tensor, iou_threshold: float, max_keep: int | None = None
) -> torch.Tensor:
    """Per-class exact greedy NMS (boxes of different classes never suppress each other)."""
    if boxes.numel() == 0:
        return torch.empty(0, dtype=torch.long, device=boxes.device)
    kept = []
    for c in torch.unique(classes):
        idx = torch.nonzero(classes == c)[:, 0]
        kept.append(idx[nms(boxes[idx], scores[idx], iou_threshold, max_keep=max_keep)])
    k = torch.cat(kept)
    k = k[scores[k].argsort(descending=True)]
    return k[:max_keep] if max_keep is not None else k


#: The kinds of degenerate boxes a detector can return, in the order they are checked (``harness.engine.predict``).
DEGENERATE = ("non_finite", "inverted", "zero_size", "outside_image")
#: The kinds that mean the detector's boxes are malformed (``outside_image`` can be an honest, poor prediction).
MALFORMED = ("non_finite", "inverted", "zero_size")


def degenerate_kinds(boxes: np.ndarray) -> np.ndarray:
    """Per box (xyxy), the index into ``DEGENERATE`` of the first check it fails before clipping, or -1."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    kind = np.full(len(b), -1, dtype=np.int64)
    finite = np.isfinite(b).all(axis=1)
    kind[~finite] = 0
    with np.errstate(invalid="ignore"):
        inverted = finite & ((b[:, 2] < b[:, 0]) | (b[:, 3] < b[:, 1]))
        kind[inverted] = 1
        kind[finite & ~inverted & ((b[:, 2] == b[:, 0]) | (b[:, 3] == b[:, 1]))] = 2
    return kind
