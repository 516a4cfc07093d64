"""CMA-Det, reconstructed from the paper (Song et al., "Misaligned visible-thermal object detection: a drone-based
benchmark and baseline", IEEE T-IV 2024). No code of the authors is public: this is a design that follows the three
components the paper names and is sized to the seed's 33.47 M parameters / 33.67 GFLOPs (640 x 640, both inputs,
nc = 8, BatchNorm folded). It is labelled "reconstructed from the paper" wherever the harness lists or reports it.

    visible ─► CSPDarknet-s ─► V3, V4, V5        thermal ─► CSPDarknet-s ─► T3, T4, T5      (YOLOv5 v6.x, not shared)
    alignment network (moves the VISIBLE features into the thermal frame):
        phi   = FC(ReLU(FC(flatten(AvgPool_{g x g}(CBS1x1([V5; T5]))))))      global field, P5 cells (dx, dy)
        phi_l = up(phi_{l+1}) + Refine_l([warp(V_l, up(phi_{l+1})); T_l])       l = 5, 4, 3 (up: bilinear, x2)
        V~_l  = warp(V_l, phi_l)          warp(F, phi)(x) = F(x + phi(x)), bilinear, zero outside
    OSR (training only, no parameters): per ground-truth box, a 5 x 5 template of T3 inside the box is compared
        with V~3 sampled on the same grid shifted by every integer d in [-3, 3]^2: l_d = cos(T3, V~3 shifted) / 0.1;
        L_osr = mean over boxes of CrossEntropy(l, d = 0): after alignment each object must match best in place
    BFCFM per level (C channels):
        d = [GAP(V), GMP(V), GAP(T), GMP(T)];  (a_V, a_T) = sigmoid(W2 ReLU(W1 d))          W1: 4C -> 4C/r, W2: -> 2C
        (s_V, s_T) = sigmoid(Conv1x1(ReLU(Conv1x1([V; T]))))                                  2C -> C/r -> 2
        V' = V + a_T T / 2 + s_T T / 2,   T' = T + a_V V / 2 + s_V V / 2,   F = CBS1x1([V'; T'])  2C -> C
    YOLOv5 PAN neck on F3, F4, F5 -> anchor Detect (strides 8/16/32, standard anchors)

    L = L_box + L_obj + L_cls (YOLOv5) + lambda_osr L_osr + lambda_tv sum_l TV(phi_l)        (lambda 0.1, 0.01)

The last layers of the global regressor and of every refiner start at zero, so the network starts as the identity
warp (the harness's samples are already registered), and their outputs are scaled by ``flow_gain`` (0.1).
An earlier form of this reconstruction trained OSR with smooth-L1 toward "mean flow in the box + soft-argmax
offset" and had no output gain; measured on a toy batch it was unstable (the search on untrained features gives
noise offsets, and the flows reached 65 P3 cells within 12 SGD steps). The cross-entropy form above, with the 0.1
gain, keeps them under 0.2 cells on the same batch while every loss falls. Widths of the alignment network scale
with ``width``: refiner 320 w, reduction 128 w, regressor hidden 880 w (160, 64 and 440 at the YOLOv5s width 0.5).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from adapters.detectors.yolo import v5
from adapters.detectors.yolo.blocks import Conv
from adapters.detectors.yolo.loss_v5 import YOLOv5Loss

P3_STRIDE = 8


# ------------------------------------------------------------------------------------------------ flow maths
def warp(feat: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Backward warp: out(x) = feat(x + flow(x)), bilinear, zero outside; ``flow`` ``[B, 2, H, W]`` in cells
    (dx, dy)."""
    _, _, h, w = feat.shape
    ys = torch.arange(h, device=feat.device, dtype=feat.dtype).view(1, h, 1)
    xs = torch.arange(w, device=feat.device, dtype=feat.dtype).view(1, 1, w)
    gx = (2.0 * (xs + flow[:, 0]) + 1.0) / w - 1.0  # align_corners=False: cell i has its centre at (2i + 1)/w - 1
    gy = (2.0 * (ys + flow[:, 1]) + 1.0) / h - 1.0
    return F.grid_sample(feat, torch.stack((gx, gy), -1), mode="bilinear", padding_mode="zeros", align_corners=False)


def resize_flow(flow: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """Bilinear resize of a flow field, with the displacements rescaled to the new cell size."""
    h0, w0 = flow.shape[-2:]
    h, w = int(size[0]), int(size[1])
    if (h, w) == (h0, w0):
        return flow
    up = F.interpolate(flow, size=(h, w), mode="bilinear", align_corners=False)
    scale = torch.tensor([w / w0, h / h0], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    return up * scale


def total_variation(flow: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference between horizontally and vertically neighbouring flow vectors."""
    tv = flow.new_zeros(())
    if flow.shape[-1] > 1:
        tv = tv + (flow[..., :, 1:] - flow[..., :, :-1]).abs().mean()
    if flow.shape[-2] > 1:
        tv = tv + (flow[..., 1:, :] - flow[..., :-1, :]).abs().mean()
    return tv


def _sample(feat: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``feat`` ``[C, H, W]`` at continuous cell coordinates ``pts`` ``[..., 2]`` -> ``[C, ...]``.

    A cell coordinate u covers cell floor(u); the centre of cell i is u = i + 0.5.
    """
    c, h, w = feat.shape
    size = torch.tensor([w, h], dtype=pts.dtype, device=pts.device)
    grid = (2.0 * pts / size - 1.0).reshape(1, 1, -1, 2)
    out = F.grid_sample(feat[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.view(c, *pts.shape[:-1])


def osr_search(
    thermal: torch.Tensor,
    visible: torch.Tensor,
    boxes: torch.Tensor,
    points: int = 5,
    radius: int = 3,
    temperature: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Object search: similarity of each box's thermal template with the visible map at every integer shift.

    ``thermal``/``visible``: ``[C, H, W]``; ``boxes``: ``[n, 4]`` xyxy in cell units. A ``points x points``
    template of ``thermal`` inside each box is compared by cosine similarity with ``visible`` sampled on the same
    grid shifted by every d in [-radius, radius]^2 (row-major, dy outer, dx inner; d = 0 is the centre index).
    Returns (logits ``[n, S]`` = cos / temperature, shifts ``[S, 2]`` as (dx, dy)).
    """
    u = torch.linspace(0.0, 1.0, points, dtype=boxes.dtype, device=boxes.device)
    uy, ux = torch.meshgrid(u, u, indexing="ij")
    x1, y1, x2, y2 = boxes.unbind(1)
    px = x1[:, None] + ux.reshape(1, -1) * (x2 - x1)[:, None]
    py = y1[:, None] + uy.reshape(1, -1) * (y2 - y1)[:, None]
    pts = torch.stack((px, py), -1)  # [n, P, 2]
    r = torch.arange(-radius, radius + 1, dtype=boxes.dtype, device=boxes.device)
    sy, sx = torch.meshgrid(r, r, indexing="ij")
    shifts = torch.stack((sx.reshape(-1), sy.reshape(-1)), -1)  # [S, 2]
    template = _sample(thermal, pts)  # [C, n, P]
    search = _sample(visible, pts[:, None] + shifts[None, :, None])  # [C, n, S, P]
    c, n, p = template.shape
    t = F.normalize(template.permute(1, 0, 2).reshape(n, 1, c * p), dim=-1)
    s = F.normalize(search.permute(1, 2, 0, 3).reshape(n, -1, c * p), dim=-1)
    return (s * t).sum(-1) / temperature, shifts


def osr_offset(logits: torch.Tensor, shifts: torch.Tensor) -> torch.Tensor:
    """Soft-argmax of the search: the residual offset ``[n, 2]`` by which the visible map still has to move."""
    return torch.softmax(logits, -1) @ shifts


def osr_loss(
    thermal3: torch.Tensor,
    visible3: torch.Tensor,
    targets: Sequence[Mapping[str, torch.Tensor]],
    stride: int = P3_STRIDE,
    points: int = 5,
    radius: int = 3,
    temperature: float = 0.1,
) -> torch.Tensor:
    """Object Search Rectification: after alignment, each object's best match must be at zero shift.

    Cross-entropy over the (2 radius + 1)^2 shifts of :func:`osr_search` with the zero shift as the target,
    averaged over ground-truth boxes. Its gradient reaches the flow through the warped visible map (moving the
    visible object onto the thermal one) and both backbones (making their object features correspond).
    """
    total = visible3.sum() * 0.0
    count = 0
    for i, t in enumerate(targets):
        boxes = torch.as_tensor(t["boxes"], dtype=visible3.dtype, device=visible3.device).reshape(-1, 4)
        boxes = boxes[((boxes[:, 2:] - boxes[:, :2]) > 0).all(1)] / stride
        if not len(boxes):
            continue
        logits, shifts = osr_search(thermal3[i], visible3[i], boxes, points, radius, temperature)
        zero = torch.full((len(boxes),), len(shifts) // 2, dtype=torch.long, device=logits.device)
        total = total + F.cross_entropy(logits, zero, reduction="sum")
        count += len(boxes)
    return total / max(count, 1)


# ------------------------------------------------------------------------------------------------ modules
class FlowRefiner(nn.Module):
    """Residual flow at one level from [warped visible; thermal]: CBS1x1 2C->c, CBS3x3 c->c, Conv3x3 c->2 (zero init).

    The output is multiplied by ``gain``: a flow in cells is a sum over many activations, and without a small
    gain the first SGD steps move it by several cells (measured: 8 P3 cells after 4 steps at gain 1).
    """

    def __init__(self, c: int, width: int, gain: float = 1.0):
        super().__init__()
        self.gain = gain
        self.cv1 = Conv(2 * c, width, 1, 1)
        self.cv2 = Conv(width, width, 3, 1)
        self.flow = nn.Conv2d(width, 2, 3, 1, 1)
        nn.init.zeros_(self.flow.weight)
        nn.init.zeros_(self.flow.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.flow(self.cv2(self.cv1(x))) * self.gain


class AlignmentNetwork(nn.Module):
    """Global deformation regressor at P5, then coarse-to-fine residual refinement at P5, P4, P3."""

    def __init__(self, chans: Sequence[int], width: int, hidden: int, reduce: int, grid: int = 20, gain: float = 1.0):
        super().__init__()
        self.gain = gain
        c3, c4, c5 = chans
        self.grid = grid
        self.reduce = Conv(2 * c5, reduce, 1, 1)
        self.fc1 = nn.Linear(reduce * grid * grid, hidden)
        self.fc2 = nn.Linear(hidden, 2 * grid * grid)
        nn.init.zeros_(self.fc2.weight)
        nn.init.zeros_(self.fc2.bias)
        self.refine = nn.ModuleList([FlowRefiner(c, width, gain) for c in (c5, c4, c3)])

    def global_flow(self, v5: torch.Tensor, t5: torch.Tensor) -> torch.Tensor:
        x = self.reduce(torch.cat((v5, t5), 1))
        if tuple(x.shape[-2:]) != (self.grid, self.grid):
            x = F.adaptive_avg_pool2d(x, self.grid)
        phi = self.fc2(F.relu(self.fc1(x.flatten(1)))).view(-1, 2, self.grid, self.grid) * self.gain
        return resize_flow(phi, v5.shape[-2:])

    def forward(
        self, visible: Sequence[torch.Tensor], thermal: Sequence[torch.Tensor]
    ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """``visible``/``thermal``: (P3, P4, P5). Returns warped visible (P3, P4, P5) and flows (P3, P4, P5)."""
        phi = self.global_flow(visible[2], thermal[2])
        warped: list[torch.Tensor] = []
        flows: list[torch.Tensor] = []
        for refiner, v, t in zip(self.refine, visible[::-1], thermal[::-1]):  # P5, P4, P3
            phi = resize_flow(phi, v.shape[-2:])
            phi = phi + refiner(torch.cat((warp(v, phi), t), 1))
            warped.append(warp(v, phi))
            flows.append(phi)
        return warped[::-1], flows[::-1]


class BFCFM(nn.Module):
    """Bi-directional feature correction fusion: channel and spatial weights from both modalities, then 1x1 fuse."""

    def __init__(self, c: int, reduction: float = 1.0):
        super().__init__()
        hidden_c, hidden_s = int(4 * c / reduction), int(c / reduction)
        self.channel = nn.Sequential(nn.Linear(4 * c, hidden_c), nn.ReLU(), nn.Linear(hidden_c, 2 * c))
        self.spatial = nn.Sequential(nn.Conv2d(2 * c, hidden_s, 1), nn.ReLU(), nn.Conv2d(hidden_s, 2, 1))
        self.fuse = Conv(2 * c, c, 1, 1)

    def forward(self, v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        b, c = v.shape[:2]
        d = torch.cat((v.mean((2, 3)), v.amax((2, 3)), t.mean((2, 3)), t.amax((2, 3))), 1)
        a = torch.sigmoid(self.channel(d)).view(b, 2, c, 1, 1)
        s = torch.sigmoid(self.spatial(torch.cat((v, t), 1)))
        a_v, a_t = a[:, 0], a[:, 1]
        s_v, s_t = s[:, :1], s[:, 1:]
        v2 = v + 0.5 * a_t * t + 0.5 * s_t * t
        t2 = t + 0.5 * a_v * v + 0.5 * s_v * v
        return self.fuse(torch.cat((v2, t2), 1))


class CMADet(v5.AnchorDetector):
    """Dual YOLOv5 (``trunk`` width 0.5, depth 0.33: the s size) with alignment, OSR and BFCFM; see the module text."""

    name = "cmadet"

    def __init__(
        self,
        nc: int,
        trunk: v5.Trunk = v5.Trunk(3, 0.5, 0.33),
        align_width: int | None = None,
        hidden: int | None = None,
        reduce: int | None = None,
        grid: int = 20,
        flow_gain: float = 0.1,
        reduction: float = 1.0,
        osr: bool = True,
        osr_weight: float = 0.1,
        tv_weight: float = 0.01,
        osr_points: int = 5,
        osr_radius: int = 3,
        osr_temperature: float = 0.1,
        prior_bias: bool = True,
    ):
        super().__init__(nc)
        in_channels, width, depth = trunk
        chans = v5.level_channels(width)
        self.backbone_rgb = nn.ModuleList(v5.backbone_layers(3, width, depth))
        self.backbone_thermal = nn.ModuleList(v5.backbone_layers(in_channels, width, depth))
        self.align = AlignmentNetwork(
            chans,
            width=align_width or v5.scale_width(320, width),
            hidden=hidden or max(int(round(880 * width)), 8),
            reduce=reduce or v5.scale_width(128, width),
            grid=grid,
            gain=flow_gain,
        )
        self.fusion = nn.ModuleList(BFCFM(c, reduction) for c in chans)
        self.neck = nn.ModuleList(v5.pan_layers(width, depth))
        self.detect = v5.Detect(nc, chans)
        if prior_bias:
            self.detect.init_prior_bias()
        self.criterion = YOLOv5Loss(self.detect)
        self.osr, self.osr_weight, self.tv_weight = osr, osr_weight, tv_weight
        self.osr_points, self.osr_radius, self.osr_temperature = osr_points, osr_radius, osr_temperature

    @property
    def head(self) -> v5.Detect:  # type: ignore[override]
        return self.detect

    def _forward(self, inputs: Any) -> tuple[tuple[torch.Tensor, ...], dict[str, Any]]:
        vis, th = v5.run_two_backbones(self.backbone_rgb, self.backbone_thermal, inputs, self.name)
        warped, flows = self.align(vis, th)
        fused = [f(v, t) for f, v, t in zip(self.fusion, warped, th)]
        feats = v5.run_pan(self.neck, *fused)
        return feats, {"warped": warped, "thermal": th, "flows": flows}

    def neck_features(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        return self._forward(inputs)[0]

    def flows(self, inputs: Any) -> list[torch.Tensor]:
        """The alignment network's flow fields (P3, P4, P5), in cells of each level (for inspection)."""
        return self._forward(inputs)[1]["flows"]

    def compute_loss(self, inputs: Any, targets: Sequence[Mapping[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        feats, aux = self._forward(inputs)
        raw = self.detect(feats)
        losses = self.criterion(raw, self.target_rows(targets, raw[0].device), self.image_size(inputs))
        bs = raw[0].shape[0]
        losses["tv"] = self.tv_weight * sum(total_variation(f) for f in aux["flows"]) * bs
        if self.osr:
            l_osr = osr_loss(
                aux["thermal"][0],
                aux["warped"][0],
                targets,
                P3_STRIDE,
                self.osr_points,
                self.osr_radius,
                self.osr_temperature,
            )
        else:
            l_osr = aux["flows"][0].sum() * 0.0
        losses["osr"] = self.osr_weight * l_osr * bs
        return losses
