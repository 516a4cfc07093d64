"""YOLOv5 detection loss (``ComputeLoss`` of the public YOLOv5 code, restated).

For level l with raw outputs p (``[B, na, ny, nx, 5 + nc]``) and the positives matched below:

    box_l = mean over positives of (1 - CIoU(pred, target))
        pred xy = 2 sigma(t_xy) - 0.5 (offset from the cell corner),  pred wh = (2 sigma(t_wh))^2 * anchor  (grid units)
    obj_l = BCE(t_obj, tobj) over every cell and anchor; tobj = CIoU of the positive (detached, clamped at 0), else 0
    cls_l = BCE(t_cls, one-hot(class)) over positives (only when nc > 1)

    L_box = g_box * sum_l box_l      L_obj = g_obj * sum_l balance_l * obj_l      L_cls = g_cls * sum_l cls_l
    g_box = 0.05 * 3/nl     g_cls = 0.5 * nc/80 * 3/nl     g_obj = 1.0 * (imgsz/640)^2 * 3/nl
    balance = 4.0, 1.0, 0.4

Each loss is multiplied by the batch size, as YOLOv5 returns it (its learning rates assume that scale).

Matching: a target goes to every anchor of a level whose width and height ratios r satisfy max(r, 1/r) < anchor_t
(4.0); besides its own cell, it also goes to the two neighbouring cells nearest to its centre (the centre lies
less than half a cell from their shared edge), so up to three cells per anchor.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from harness.boxes import bbox_iou, cxcywh_to_xyxy

#: Cell offsets for the positives: own cell, then left, up, right, down neighbours (times 0.5).
_NEIGHBOURS = ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))


def match_targets(
    targets: torch.Tensor, anchors: torch.Tensor, grid_hw: tuple[int, int], stride: float, anchor_t: float = 4.0
) -> tuple[torch.Tensor, ...]:
    """Positives of one level.

    ``targets``: ``[n, 6]`` rows (image, class, cx, cy, w, h) in input pixels; ``anchors``: ``[na, 2]`` in grid
    units. Returns ``(b, a, gj, gi, tbox, anchors, cls)``: image, anchor and cell indices of every positive, its
    target box (cx, cy relative to the cell corner, w, h; grid units), its anchor and its class.
    """
    device = targets.device
    na, nt = anchors.shape[0], targets.shape[0]
    ny, nx = grid_hw
    if nt == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty, empty, empty, torch.zeros(0, 4, device=device), torch.zeros(0, 2, device=device), empty
    t = targets.clone()
    t[:, 2:6] /= stride
    ai = torch.arange(na, device=device).view(na, 1).expand(na, nt)
    t = torch.cat((t.unsqueeze(0).expand(na, nt, 6), ai.unsqueeze(-1).to(t.dtype)), 2)  # [na, nt, 7]
    r = t[..., 4:6] / anchors[:, None]
    t = t[torch.max(r, 1.0 / r).max(2).values < anchor_t]  # [m, 7]

    gxy = t[:, 2:4]
    gxi = torch.tensor([nx, ny], device=device, dtype=t.dtype) - gxy
    g = 0.5
    left, up = ((gxy % 1.0 < g) & (gxy > 1.0)).T
    right, down = ((gxi % 1.0 < g) & (gxi > 1.0)).T
    keep = torch.stack((torch.ones_like(left), left, up, right, down))  # [5, m]
    off = torch.tensor(_NEIGHBOURS, device=device, dtype=t.dtype) * g
    t = t.unsqueeze(0).expand(5, -1, -1)[keep]
    offsets = (torch.zeros_like(gxy)[None] + off[:, None])[keep]

    b, cls = t[:, 0].long(), t[:, 1].long()
    gxy, gwh = t[:, 2:4], t[:, 4:6]
    gij = (gxy - offsets).long()
    gi, gj = gij[:, 0].clamp(0, nx - 1), gij[:, 1].clamp(0, ny - 1)
    a = t[:, 6].long()
    tbox = torch.cat((gxy - torch.stack((gi, gj), 1).to(gxy.dtype), gwh), 1)
    return b, a, gj, gi, tbox, anchors[a], cls


class YOLOv5Loss:
    """Callable ``loss(raw, targets, image_size) -> {"box", "obj", "cls"}`` for a
    :class:`~adapters.detectors.yolo.v5.Detect`.

    ``raw``: per-level ``[B, na, ny, nx, 5 + nc]``; ``targets``: ``[n, 6]`` rows (image, class, cx, cy, w, h)
    in input pixels; ``image_size``: (h, w) of the input, whose longer side sets the objectness gain unless
    ``imgsz`` is given. ``sort_obj_iou`` sorts positives by IoU so that, where several land on one cell, the
    highest IoU is the objectness target (ICAFusion turns it on; YOLOv5 leaves it off).
    """

    def __init__(
        self,
        head: nn.Module,
        box: float = 0.05,
        obj: float = 1.0,
        cls: float = 0.5,
        anchor_t: float = 4.0,
        balance: Sequence[float] = (4.0, 1.0, 0.4),
        sort_obj_iou: bool = False,
        label_smoothing: float = 0.0,
        imgsz: int | None = None,
    ):
        self.head = head
        self.box, self.obj, self.cls = box, obj, cls
        self.anchor_t = anchor_t
        self.balance = tuple(balance) if head.nl == 3 else (4.0, 1.0, 0.25, 0.06, 0.02)[: head.nl]
        self.sort_obj_iou = sort_obj_iou
        self.cp, self.cn = 1.0 - 0.5 * label_smoothing, 0.5 * label_smoothing
        self.imgsz = imgsz
        self.bce = nn.BCEWithLogitsLoss()

    def __call__(
        self, raw: Sequence[torch.Tensor], targets: torch.Tensor, image_size: tuple[int, int]
    ) -> dict[str, torch.Tensor]:
        head = self.head
        nl, nc = head.nl, head.nc
        device = raw[0].device
        lbox = torch.zeros((), device=device)
        lobj = torch.zeros((), device=device)
        lcls = torch.zeros((), device=device)
        for i, p in enumerate(raw):
            b, a, gj, gi, tbox, anch, tcls = match_targets(
                targets, head.anchors[i], (p.shape[2], p.shape[3]), head.strides[i], self.anchor_t
            )
            tobj = torch.zeros(p.shape[:4], dtype=p.dtype, device=device)
            n = b.shape[0]
            if n:
                ps = p[b, a, gj, gi]
                pxy = ps[:, :2].sigmoid() * 2.0 - 0.5
                pwh = (ps[:, 2:4].sigmoid() * 2.0) ** 2 * anch
                iou = bbox_iou(cxcywh_to_xyxy(torch.cat((pxy, pwh), 1)), cxcywh_to_xyxy(tbox), kind="ciou")
                lbox = lbox + (1.0 - iou).mean()
                score = iou.detach().clamp(0).to(tobj.dtype)
                if self.sort_obj_iou:
                    order = score.argsort()
                    b, a, gj, gi, score = b[order], a[order], gj[order], gi[order], score[order]
                tobj[b, a, gj, gi] = score
                if nc > 1:
                    t = torch.full_like(ps[:, 5:], self.cn)
                    t[torch.arange(n, device=device), tcls] = self.cp
                    lcls = lcls + self.bce(ps[:, 5:], t)
            lobj = lobj + self.bce(p[..., 4], tobj) * self.balance[i]
        imgsz = self.imgsz or max(image_size)
        bs = raw[0].shape[0]
        return {
            "box": lbox * (self.box * 3.0 / nl) * bs,
            "obj": lobj * (self.obj * (imgsz / 640.0) ** 2 * 3.0 / nl) * bs,
            "cls": lcls * (self.cls * nc / 80.0 * 3.0 / nl) * bs,
        }
