"""Task-aligned assignment (TOOD, Feng et al. 2021), as YOLOv8 uses it: which anchor points learn which object.

For every ground-truth box g and anchor point a whose centre lies inside g:

    t(a, g) = s(a, c_g)^alpha * u(a, g)^beta          alignment metric (alpha 0.5, beta 6.0)

with ``s`` the predicted probability of g's class and ``u`` the CIoU (clamped at 0) of a's predicted box with g.
Each box keeps its ``topk`` (10) anchors by ``t``; an anchor kept by several boxes goes to the box, among all those
it lies in, that its predicted box overlaps most. A positive's soft classification target is the IoU-aware
normalised metric

    t_hat(a) = t(a, g) * max_a' u(a', g) / max_a' t(a', g)

(so every box's best anchor gets a target equal to that box's best IoU). Everything is batched over images with
padded ground truth ``[B, M, ...]`` and a validity mask; there is no Python loop over anchors or boxes. Only the
candidate test and the top-k need dense ``[B, M, A]`` tensors; the rest works on the ``B * M * topk`` kept pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from harness.boxes import bbox_iou


@dataclass
class Assignment:
    """Per anchor point: assigned class, box (xyxy pixels), soft class target, positive mask, assigned gt index."""

    labels: torch.Tensor  # [B, A] int64
    boxes: torch.Tensor  # [B, A, 4]
    scores: torch.Tensor  # [B, A, C] soft targets, 0 for background
    fg_mask: torch.Tensor  # [B, A] bool
    gt_index: torch.Tensor  # [B, A] int64 (meaningful where fg_mask)


def anchors_inside_boxes(
    points: torch.Tensor, gt_boxes: torch.Tensor, eps: float = 1e-9, min_side: float = 0.0
) -> torch.Tensor:
    """``[A, 2]`` points and ``[B, M, 4]`` xyxy boxes -> ``[B, M, A]`` True where the point is strictly inside.

    ``min_side > 0`` widens, for this test only, every box side shorter than ``min_side`` to ``min_side`` about the
    box centre, so that a thin or tiny box still contains anchor points (a box narrower than the finest stride may
    otherwise contain none and never be learned).
    """
    if min_side > 0:
        centre = (gt_boxes[..., :2] + gt_boxes[..., 2:]) / 2
        half = (gt_boxes[..., 2:] - gt_boxes[..., :2]).clamp(min=min_side) / 2
        gt_boxes = torch.cat((centre - half, centre + half), -1)
    x, y = points[:, 0], points[:, 1]
    x1, y1, x2, y2 = (gt_boxes[..., i, None] for i in range(4))  # [B, M, 1] each
    # x - x1 > eps written as x > x1 + eps: boolean comparisons only, no [B, M, A] float temporaries
    return (x > x1 + eps) & (y > y1 + eps) & (x < x2 - eps) & (y < y2 - eps)


@dataclass(eq=False)
class TaskAlignedAssigner:
    """Batched task-aligned assigner (no parameters; call it under ``torch.no_grad``)."""

    num_classes: int
    topk: int = 10
    alpha: float = 0.5
    beta: float = 6.0
    eps: float = 1e-9
    min_side: float = 0.0

    @torch.no_grad()
    def __call__(
        self,
        pd_scores: torch.Tensor,
        pd_boxes: torch.Tensor,
        anchor_points: torch.Tensor,
        gt_labels: torch.Tensor,
        gt_boxes: torch.Tensor,
        gt_mask: torch.Tensor,
    ) -> Assignment:
        """
        pd_scores ``[B, A, C]`` class probabilities; pd_boxes ``[B, A, 4]`` predicted xyxy; anchor_points ``[A, 2]``
        (same units as the boxes, pixels here); gt_labels ``[B, M]`` int64; gt_boxes ``[B, M, 4]`` xyxy; gt_mask
        ``[B, M]`` bool (False for padding).
        """
        b, a, c = pd_scores.shape
        m = gt_boxes.shape[1]
        device = pd_scores.device
        if m == 0 or not bool(gt_mask.any()):
            return Assignment(
                labels=torch.full((b, a), self.num_classes, dtype=torch.long, device=device),
                boxes=torch.zeros_like(pd_boxes),
                scores=torch.zeros_like(pd_scores),
                fg_mask=torch.zeros((b, a), dtype=torch.bool, device=device),
                gt_index=torch.zeros((b, a), dtype=torch.long, device=device),
            )
        gt_labels = gt_labels.long().clamp(0, self.num_classes - 1)

        # candidates: anchor centre inside a real box; metrics only where a candidate exists (sparse pairs)
        inside = anchors_inside_boxes(anchor_points, gt_boxes, self.eps, self.min_side) & gt_mask[..., None]
        bi, mi, ai = inside.nonzero(as_tuple=True)
        iou = bbox_iou(gt_boxes[bi, mi], pd_boxes[bi, ai], kind="ciou").clamp_(min=0).to(pd_scores.dtype)
        cls_score = pd_scores[bi, ai, gt_labels[bi, mi]]
        overlaps = pd_scores.new_zeros((b, m, a))
        overlaps[bi, mi, ai] = iou
        align = pd_scores.new_zeros((b, m, a))
        align[bi, mi, ai] = cls_score.pow(self.alpha) * iou.pow(self.beta)

        # each box keeps its top-k candidates by the alignment metric: from here on, only those B*M*k pairs
        k = min(self.topk, a)
        top_align, top_idx = align.topk(k, dim=-1)  # [B, M, k], distinct anchors per box
        pb, pm, pk = inside.gather(-1, top_idx).nonzero(as_tuple=True)
        pa = top_idx[pb, pm, pk]
        p_align = top_align[pb, pm, pk]
        p_iou = overlaps.gather(-1, top_idx)[pb, pm, pk]

        # an anchor chosen by several boxes goes to the box its prediction overlaps most, among all the boxes it lies
        # in (the public rule; first index on ties)
        anchor_key = pb * a + pa
        count = torch.zeros(b * a, dtype=torch.long, device=device).scatter_add_(0, anchor_key, torch.ones_like(pa))
        single = count[anchor_key] == 1
        contested = torch.nonzero(count > 1)[:, 0]
        cb, ca = contested // a, contested % a
        cm = overlaps[cb, :, ca].argmax(1)  # [K]
        pb, pm, pa = torch.cat((pb[single], cb)), torch.cat((pm[single], cm)), torch.cat((pa[single], ca))
        p_align = torch.cat((p_align[single], align[cb, cm, ca]))
        p_iou = torch.cat((p_iou[single], overlaps[cb, cm, ca]))
        anchor_key = pb * a + pa

        fg_mask = torch.zeros(b * a, dtype=torch.bool, device=device)
        fg_mask[anchor_key] = True
        gt_index = torch.zeros(b * a, dtype=torch.long, device=device)
        gt_index[anchor_key] = pm
        fg_mask, gt_index = fg_mask.view(b, a), gt_index.view(b, a)

        # IoU-aware soft target: t * max IoU / max t, per box, over the positives it finally keeps
        box_key = pb * m + pm
        best_align = p_align.new_zeros(b * m).scatter_reduce(0, box_key, p_align, "amax")
        best_iou = p_iou.new_zeros(b * m).scatter_reduce(0, box_key, p_iou, "amax")
        norm = pd_scores.new_zeros(b * a)
        norm[anchor_key] = p_align * best_iou[box_key] / (best_align[box_key] + self.eps)

        labels = gt_labels.gather(1, gt_index)  # [B, A]
        boxes = gt_boxes.gather(1, gt_index[..., None].expand(-1, -1, 4))  # [B, A, 4]
        scores = F.one_hot(labels, self.num_classes).to(pd_scores.dtype) * (norm.view(b, a) * fg_mask)[..., None]
        labels = torch.where(fg_mask, labels, torch.full_like(labels, self.num_classes))
        return Assignment(labels=labels, boxes=boxes, scores=scores, fg_mask=fg_mask, gt_index=gt_index)
