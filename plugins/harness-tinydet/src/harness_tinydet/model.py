"""TinyDet: a small anchor-free detector with two output levels, built from the harness's public blocks.

Network (``w`` = width, default 16):

    stem   Conv(c_in, w, 3, s2) -> Conv(w, 2w, 3, s2) -> C2f(2w, 2w)                  stride 4
    P3     Conv(2w, 4w, 3, s2) -> C2f(4w, 4w)                                         stride 8
    P4     Conv(4w, 8w, 3, s2) -> C2f(8w, 8w) -> SPPF(8w, 8w)                          stride 16
    neck   P3' = C2f(cat(upsample(P4), P3) -> 4w)
    heads  per level: Conv(c, c, 3) -> 1x1 conv to 4 box distances + nc class logits

Every output cell is a point ``p`` at the centre of its cell. Its box is ``(p - d_lt, p + d_rb)`` with the four
distances ``d = softplus(raw) * stride``. Its class scores are ``sigmoid(logits)``.

Assignment (centre sampling): a point is a positive for a ground-truth box when it lies inside the box and within
``radius * stride`` of the box centre on both axes; the point nearest to the centre on each level is always
a positive, so tiny boxes are never lost; a point claimed by several boxes takes the smallest.

Loss, summed over the batch and divided by the number of positives, then multiplied by the batch size (the
YOLO convention the engine expects; gradients accumulated to the nominal batch are sums over images):

    box = box_gain * sum over positives of (1 - CIoU(predicted, assigned))
    cls = cls_gain * BCE(logits, y) summed over all points and classes, y = 1 at the assigned class of a
          positive and 0 elsewhere

Inference: best class per point, score threshold ``conf``, the 1,000 best candidates, per-class NMS at ``iou``
(``harness.boxes.batched_nms``), at most ``max_det`` boxes.

The two-stream variant ``TinyDetDual`` has one stem per stream (RGB and thermal) and sums them at stride 4.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from adapters.detectors.yolo.blocks import SPPF, C2f, Conv, fuse_model
from harness.boxes import batched_nms, bbox_iou
from harness.errors import ConfigError

#: TinyDet's settings besides its width, with their defaults: the centre-sampling radius (in strides), the loss
#: gains and the inference settings.
SETTINGS = {"radius": 2.5, "box_gain": 2.0, "cls_gain": 1.0, "conf": 0.25, "iou": 0.6, "max_det": 300}
OPTIONS = ("width", *SETTINGS)


def _stem(c_in: int, w: int) -> nn.Sequential:
    return nn.Sequential(Conv(c_in, w, 3, 2), Conv(w, 2 * w, 3, 2), C2f(2 * w, 2 * w, 1, True))


class Head(nn.Module):
    def __init__(self, c: int, nc: int, prior: float = 0.01):
        super().__init__()
        self.conv = Conv(c, c, 3)
        self.box = nn.Conv2d(c, 4, 1)
        self.cls = nn.Conv2d(c, nc, 1)
        nn.init.constant_(self.cls.bias, -math.log((1 - prior) / prior))  # every point starts as 'background'
        nn.init.zeros_(self.box.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv(x)
        return torch.cat((self.box(y), self.cls(y)), 1)


class TinyDet(nn.Module):
    strides = (8, 16)

    def __init__(self, num_classes: int, in_channels: int = 4, width: int = 16, **settings: float):
        """``settings``: any of ``SETTINGS``, the rest keep their defaults."""
        unknown = sorted(set(settings) - set(SETTINGS))
        if unknown:
            raise TypeError(f"TinyDet: unknown setting(s) {unknown}; known: {', '.join(SETTINGS)}")
        s = {**SETTINGS, **settings}
        super().__init__()
        w = int(width)
        self.nc = int(num_classes)
        self.in_channels = int(in_channels)
        self.radius, self.box_gain, self.cls_gain = float(s["radius"]), float(s["box_gain"]), float(s["cls_gain"])
        self.conf, self.iou, self.max_det = float(s["conf"]), float(s["iou"]), int(s["max_det"])
        self.stem = _stem(in_channels, w)
        self.p3 = nn.Sequential(Conv(2 * w, 4 * w, 3, 2), C2f(4 * w, 4 * w, 1, True))
        self.p4 = nn.Sequential(Conv(4 * w, 8 * w, 3, 2), C2f(8 * w, 8 * w, 1, True), SPPF(8 * w, 8 * w))
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.neck = C2f(12 * w, 4 * w, 1, False)
        self.heads = nn.ModuleList([Head(4 * w, self.nc), Head(8 * w, self.nc)])

    # ------------------------------------------------------------------ network
    def features(self, inputs: Any) -> torch.Tensor:
        return self.stem(inputs)

    def forward_raw(self, inputs: Any) -> torch.Tensor:
        """Raw outputs ``[B, 4 + nc, points]``: box-distance logits then class logits, level P3 then P4."""
        x = self.features(inputs)
        p3 = self.p3(x)
        p4 = self.p4(p3)
        p3 = self.neck(torch.cat((self.up(p4), p3), 1))
        return torch.cat([h(p).flatten(2) for h, p in zip(self.heads, (p3, p4))], 2)

    def points(self, h: int, w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell centres ``[points, 2]`` (x, y in input pixels) and their strides ``[points]``, P3 then P4."""
        pts, strides = [], []
        for s in self.strides:
            ny, nx = math.ceil(h / s), math.ceil(w / s)
            ys, xs = torch.meshgrid(torch.arange(ny, device=device), torch.arange(nx, device=device), indexing="ij")
            pts.append(torch.stack((xs, ys), -1).reshape(-1, 2).float().add(0.5).mul(s))
            strides.append(torch.full((ny * nx,), float(s), device=device))
        return torch.cat(pts), torch.cat(strides)

    def decode(self, raw: torch.Tensor, pts: torch.Tensor, strides: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes ``[B, points, 4]`` xyxy and class logits ``[B, points, nc]``."""
        raw = raw.transpose(1, 2).float()
        d = F.softplus(raw[..., :4]) * strides[None, :, None]
        boxes = torch.cat((pts[None] - d[..., :2], pts[None] + d[..., 2:]), -1)
        return boxes, raw[..., 4:]

    def forward(self, inputs: Any, targets: list[dict[str, torch.Tensor]] | None = None) -> Any:
        x0 = inputs[0] if isinstance(inputs, (tuple, list)) else inputs
        h, w = x0.shape[-2:]
        raw = self.forward_raw(inputs)
        if raw.shape[2] != sum(math.ceil(h / s) * math.ceil(w / s) for s in self.strides):
            raise ValueError(f"TinyDet needs input sizes divisible by {max(self.strides)}, got {h}x{w}")
        pts, strides = self.points(h, w, raw.device)
        boxes, logits = self.decode(raw, pts, strides)
        if self.training:
            if targets is None:
                raise ValueError("TinyDet in train mode needs targets")
            return self.loss(boxes, logits, pts, strides, targets)
        return self.postprocess(boxes, logits)

    # ------------------------------------------------------------------ training
    def assign(self, pts: torch.Tensor, strides: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """Index of the assigned ground-truth box for every point, -1 for background (centre sampling)."""
        n = len(pts)
        if len(gt) == 0:
            return torch.full((n,), -1, dtype=torch.long, device=pts.device)
        x, y = pts[:, 0:1], pts[:, 1:2]
        inside = (x > gt[:, 0]) & (x < gt[:, 2]) & (y > gt[:, 1]) & (y < gt[:, 3])
        cx, cy = (gt[:, 0] + gt[:, 2]) / 2, (gt[:, 1] + gt[:, 3]) / 2
        r = self.radius * strides[:, None]
        near = ((x - cx).abs() < r) & ((y - cy).abs() < r)
        cand = inside & near
        d2 = (x - cx) ** 2 + (y - cy) ** 2  # [points, boxes]
        for s in self.strides:  # the nearest point of every level is always a candidate
            on_level = strides == s
            idx = torch.nonzero(on_level)[:, 0]
            nearest = idx[d2[on_level].argmin(0)]
            cand[nearest, torch.arange(len(gt), device=pts.device)] = True
        area = ((gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1]))[None].expand(n, -1)
        cost = torch.where(cand, area, torch.full_like(area, float("inf")))
        best, which = cost.min(1)
        return torch.where(torch.isfinite(best), which, torch.full_like(which, -1))

    def loss(
        self,
        boxes: torch.Tensor,
        logits: torch.Tensor,
        pts: torch.Tensor,
        strides: torch.Tensor,
        targets: list[dict[str, torch.Tensor]],
    ) -> dict[str, torch.Tensor]:
        bsz = len(targets)
        box_sum = boxes.new_zeros(())
        cls_target = torch.zeros_like(logits)
        n_pos = 0
        for b, t in enumerate(targets):
            gt, labels = t["boxes"].to(boxes.dtype), t["labels"].long()
            which = self.assign(pts, strides, gt)
            pos = which >= 0
            if not pos.any():
                continue
            iou = bbox_iou(boxes[b, pos], gt[which[pos]], kind="ciou")
            box_sum = box_sum + (1 - iou).sum()
            cls_target[b, pos, labels[which[pos]]] = 1.0
            n_pos += int(pos.sum())
        norm = max(n_pos, 1)
        cls = F.binary_cross_entropy_with_logits(logits, cls_target, reduction="sum") / norm
        return {"box": self.box_gain * box_sum / norm * bsz, "cls": self.cls_gain * cls * bsz}

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def postprocess(self, boxes: torch.Tensor, logits: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        out = []
        for bx, lg in zip(boxes, logits):
            scores, labels = lg.sigmoid().max(1)
            keep = scores > self.conf
            bx, scores, labels = bx[keep], scores[keep], labels[keep]
            if len(scores) > 1000:
                top = scores.topk(1000).indices
                bx, scores, labels = bx[top], scores[top], labels[top]
            k = batched_nms(bx, scores, labels, self.iou, max_keep=self.max_det)
            out.append({"boxes": bx[k], "scores": scores[k], "labels": labels[k]})
        return out

    def fuse(self) -> "TinyDet":
        return fuse_model(self)


class TinyDetDual(TinyDet):
    """Two streams: an RGB stem and a thermal stem, summed at stride 4; the rest is TinyDet."""

    def __init__(self, num_classes: int, in_channels: int = 1, width: int = 16, **kw: Any):
        super().__init__(num_classes, in_channels=3, width=width, **kw)
        self.thermal_stem = _stem(in_channels, int(width))

    def features(self, inputs: Any) -> torch.Tensor:
        rgb, thermal = inputs
        return self.stem(rgb) + self.thermal_stem(thermal)


def check_options(model_cfg: dict[str, Any]) -> dict[str, Any]:
    """The ``model`` section of the config must hold TinyDet options only; anything else is a config error."""
    unknown = sorted(set(model_cfg) - set(OPTIONS))
    if unknown:
        raise ConfigError(f"model options {unknown} are not TinyDet options (known: {', '.join(OPTIONS)})")
    return dict(model_cfg)


def build_tinydet(num_classes: int, in_channels: int = 4, **model_cfg: Any) -> TinyDet:
    return TinyDet(num_classes, in_channels=in_channels, **check_options(model_cfg))


def build_tinydet_dual(num_classes: int, in_channels: int = 1, **model_cfg: Any) -> TinyDetDual:
    return TinyDetDual(num_classes, in_channels=in_channels, **check_options(model_cfg))
