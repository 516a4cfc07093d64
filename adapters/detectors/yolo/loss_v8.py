"""The YOLOv8 training loss: BCE classification with IoU-aware soft targets, CIoU and Distribution Focal Loss.

With the task-aligned assignment of ``tal.py`` (soft targets ``t_hat``, positives P) and ``S = max(sum t_hat, 1)``:

    L_cls = sum_{a, c} BCE(logit_{a,c}, t_hat_{a,c}) / S                 over all anchors and classes
    L_box = sum_{a in P} (1 - CIoU(b_a, g_a)) * w_a / S                  w_a = sum_c t_hat_{a,c}
    L_dfl = sum_{a in P} mean_{4 sides} DFL(p_a, y_a) * w_a / S
    DFL(p, y) = -((y_{i+1} - y) log p_i + (y - y_i) log p_{i+1}),  y_i = floor(y), y_{i+1} = y_i + 1

Box distances ``y`` (left, top, right, bottom from the anchor point) are in grid cells of the level, clamped to
``[0, reg_max - 1 - 0.01]``. The returned losses are ``gain * L * batch_size`` with gains box 7.5, cls 0.5, dfl 1.5:
the public YOLOv8 convention, under which the SGD hyper-parameters (lr0 0.01 with gradient accumulation to a nominal
batch of 64) were tuned. Divide their sum by the batch size for a per-image figure to log.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
import torch.nn.functional as F

from adapters.detectors.yolo.tal import TaskAlignedAssigner
from harness.boxes import bbox_iou
from harness.errors import HarnessError

#: Training hyper-parameters of the loss and the assigner: gains box/cls/dfl, assigner top-k, alpha, beta (the
#: public YOLOv8 defaults) and ``assign_min_side``: box sides shorter than this many pixels are widened to it when
#: choosing candidate anchors (0 = off, the original YOLOv8 rule; recent releases of the public trainer use the
#: middle stride, 16).
LOSS_DEFAULTS: dict[str, float] = {
    "box": 7.5,
    "cls": 0.5,
    "dfl": 1.5,
    "topk": 10,
    "alpha": 0.5,
    "beta": 6.0,
    "assign_min_side": 0.0,
}


def make_anchors(
    maps: Sequence[torch.Tensor], strides: Sequence[float], offset: float = 0.5
) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor points at cell centres, in grid units of each level ``[A, 2]`` (x, y), and each point's stride
    ``[A, 1]``; levels are concatenated in order, each row-major (y outer, x inner)."""
    points, stride_col = [], []
    dtype, device = maps[0].dtype, maps[0].device
    for m, s in zip(maps, strides):
        h, w = m.shape[-2:]
        sy, sx = torch.meshgrid(
            torch.arange(h, device=device, dtype=dtype) + offset,
            torch.arange(w, device=device, dtype=dtype) + offset,
            indexing="ij",
        )
        points.append(torch.stack((sx, sy), -1).reshape(-1, 2))
        stride_col.append(torch.full((h * w, 1), float(s), dtype=dtype, device=device))
    return torch.cat(points), torch.cat(stride_col)


def dist2bbox(dist: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(left, top, right, bottom) distances ``[..., 4]`` from points ``[..., 2]`` -> xyxy boxes."""
    lt, rb = dist.chunk(2, -1)
    return torch.cat((points - lt, points + rb), -1)


def bbox2dist(points: torch.Tensor, boxes: torch.Tensor, max_dist: float) -> torch.Tensor:
    """xyxy boxes -> (left, top, right, bottom) distances from the points, clamped to ``[0, max_dist]``."""
    x1y1, x2y2 = boxes.chunk(2, -1)
    return torch.cat((points - x1y1, x2y2 - points), -1).clamp_(0, max_dist)


def dfl_expectation(logits: torch.Tensor, reg_max: int) -> torch.Tensor:
    """``[..., 4 * reg_max]`` bin logits -> ``[..., 4]`` expected distances: sum_i i * softmax(logits)_i."""
    proj = torch.arange(reg_max, dtype=logits.dtype, device=logits.device)
    return logits.unflatten(-1, (4, reg_max)).softmax(-1) @ proj


def dfl_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Distribution Focal Loss: ``[N, reg_max]`` logits, ``[N]`` continuous targets in [0, reg_max - 1) -> ``[N]``.

    DFL(p, y) = -((y_{i+1} - y) log p_i + (y - y_{i+1} + 1) log p_{i+1}) with y_i = floor(y) (Li et al., 2020).
    """
    left = target.long()
    right = left + 1
    w_left = right.to(target.dtype) - target
    w_right = 1 - w_left
    return (
        F.cross_entropy(logits, left, reduction="none") * w_left
        + F.cross_entropy(logits, right, reduction="none") * w_right
    )


def pad_targets(
    targets: Sequence[dict[str, torch.Tensor]], batch: int, nc: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-image ``{"boxes" [N,4] xyxy, "labels" [N]}`` -> padded ``boxes [B,M,4]``, ``labels [B,M]``,
    ``mask [B,M]``."""
    if not isinstance(targets, (list, tuple)) or len(targets) != batch:
        n = len(targets) if isinstance(targets, (list, tuple)) else type(targets).__name__
        raise HarnessError(f"targets must be a list with one dict per image ({batch}); got {n}")
    boxes_l, labels_l = [], []
    for i, t in enumerate(targets):
        try:
            bx = torch.as_tensor(t["boxes"], dtype=torch.float32)
            lb = torch.as_tensor(t["labels"], dtype=torch.long)
        except (KeyError, TypeError) as exc:
            raise HarnessError(f"targets[{i}] must be a dict with 'boxes' [N,4] and 'labels' [N]: {exc}") from None
        if bx.numel() == 0:
            bx = bx.reshape(0, 4)
        if bx.dim() != 2 or bx.shape[1] != 4 or lb.reshape(-1).shape[0] != bx.shape[0]:
            raise HarnessError(
                f"targets[{i}]: boxes must be [N,4] xyxy and labels [N]; got boxes {tuple(bx.shape)}, "
                f"labels {tuple(lb.shape)}"
            )
        boxes_l.append(bx)
        labels_l.append(lb.reshape(-1))
    counts = torch.tensor([len(lb) for lb in labels_l])
    m = int(counts.max()) if batch else 0
    boxes = torch.zeros((batch, m, 4), dtype=torch.float32)
    labels = torch.zeros((batch, m), dtype=torch.long)
    mask = torch.zeros((batch, m), dtype=torch.bool)
    if m:
        all_labels = torch.cat(labels_l)
        if bool((all_labels < 0).any() or (all_labels >= nc).any()):
            bad = all_labels[(all_labels < 0) | (all_labels >= nc)][0].item()
            raise HarnessError(f"targets: label {bad} is outside 0..{nc - 1} (labels are 0-based class indices)")
        img = torch.repeat_interleave(torch.arange(batch), counts)
        pos = torch.arange(len(img)) - torch.repeat_interleave(counts.cumsum(0) - counts, counts)
        boxes[img, pos] = torch.cat(boxes_l)
        labels[img, pos] = all_labels
        mask[img, pos] = True
    return boxes.to(device), labels.to(device), mask.to(device)


class V8DetectionLoss:
    """Loss of the YOLOv8 detector; ``strides`` is set by the model (its computed output strides).

    ``hyp``: any of ``LOSS_DEFAULTS`` (the gains and the assigner settings), the rest keep their defaults.
    """

    def __init__(self, nc: int, reg_max: int = 16, **hyp: float):
        unknown = sorted(set(hyp) - set(LOSS_DEFAULTS))
        if unknown:
            raise TypeError(f"V8DetectionLoss: unknown loss option(s) {unknown}; known: {sorted(LOSS_DEFAULTS)}")
        h = {**LOSS_DEFAULTS, **hyp}
        self.nc = nc
        self.reg_max = reg_max
        self.gains = {"box": h["box"], "cls": h["cls"], "dfl": h["dfl"]}
        self.assigner = TaskAlignedAssigner(
            nc, topk=int(h["topk"]), alpha=h["alpha"], beta=h["beta"], min_side=h["assign_min_side"]
        )
        self.strides: Sequence[float] = ()
        self._anchors: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def anchors(self, maps: Sequence[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        key = (tuple(tuple(m.shape[2:]) for m in maps), maps[0].device)
        if key not in self._anchors:
            proxy = [m.detach().float() for m in maps]
            self._anchors = {key: make_anchors(proxy, self.strides)}
        return self._anchors[key]

    def __call__(self, maps: Sequence[torch.Tensor], targets: Sequence[dict[str, Any]]) -> dict[str, torch.Tensor]:
        b = maps[0].shape[0]
        no = self.nc + 4 * self.reg_max
        # float32 whatever the autocast dtype of the network: the loss and the assignment are precision-sensitive
        flat = torch.cat([m.reshape(b, no, -1) for m in maps], 2).float()  # [B, no, A]
        pred_dist, pred_logits = flat.split((4 * self.reg_max, self.nc), 1)
        pred_dist = pred_dist.transpose(1, 2)  # [B, A, 4*reg_max]
        pred_logits = pred_logits.transpose(1, 2)  # [B, A, nc]
        points, stride_col = self.anchors(maps)  # grid units, [A, 1]

        gt_boxes, gt_labels, gt_mask = pad_targets(targets, b, self.nc, flat.device)
        pred_boxes = dist2bbox(dfl_expectation(pred_dist, self.reg_max), points)  # grid units
        with torch.no_grad():
            assigned = self.assigner(
                pred_logits.detach().sigmoid(),
                pred_boxes.detach() * stride_col,
                points * stride_col,
                gt_labels,
                gt_boxes,
                gt_mask,
            )
        target_sum = assigned.scores.sum().clamp(min=1)

        loss_cls = F.binary_cross_entropy_with_logits(pred_logits, assigned.scores, reduction="sum") / target_sum
        fg = assigned.fg_mask
        if bool(fg.any()):
            weight = assigned.scores.sum(-1)[fg]  # [P]
            target_boxes = assigned.boxes / stride_col  # grid units
            ciou = bbox_iou(pred_boxes[fg], target_boxes[fg], kind="ciou")
            loss_box = ((1.0 - ciou) * weight).sum() / target_sum
            target_dist = bbox2dist(points, target_boxes, self.reg_max - 1 - 0.01)[fg]  # [P, 4]
            dfl = dfl_loss(pred_dist[fg].reshape(-1, self.reg_max), target_dist.reshape(-1)).view(-1, 4).mean(-1)
            loss_dfl = (dfl * weight).sum() / target_sum
        else:  # no positives: zero box losses that stay attached to the graph
            loss_box = pred_dist.sum() * 0.0
            loss_dfl = pred_dist.sum() * 0.0
        g = self.gains
        return {"box": loss_box * g["box"] * b, "cls": loss_cls * g["cls"] * b, "dfl": loss_dfl * g["dfl"] * b}
