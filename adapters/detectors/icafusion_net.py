"""ICAFusion (Shen et al., Pattern Recognition 2024): two YOLOv5 streams fused by cross-attention at P3, P4 and P5.

Layer indices and parameter names follow the official two-stream configuration ``yolov5l_Transfusion`` so that its
checkpoints load by key (``model.N...``):

    0-9    RGB CSPDarknet (YOLOv5 v6.x, 6x6 stem), P3 = 4, P4 = 6, P5 = 9
    10-19  thermal CSPDarknet, same layout, not shared (P3 = 14, P4 = 16, P5 = 19)
    20     TransformerFusionBlock(d = 256,  token grid 20x20) on [4, 14]
    21     TransformerFusionBlock(d = 512,  token grid 16x16) on [6, 16]
    22     TransformerFusionBlock(d = 1024, token grid 10x10) on [9, 19]
    23-36  YOLOv5 PAN neck on the fused maps 20, 21, 22
    37     Detect (anchors and the pre-v6 ``anchor_grid`` buffer)

One fusion block, channels C, token grid h' x w', visible features F_v and thermal F_t (``[B, C, H, W]``):

    pool:     P_m = a_m AvgPool_(k,s)(F_m) + b_m MaxPool_(k,s)(F_m)       s = floor(H / h'), k = H - (h' - 1) s
    tokens:   T_m = flatten(P_m) + E_m                                    (E_m: [1, h'w', C], zeros at init)
    attend:   O_v = W_ov softmax(Q_t K_v^T / sqrt(C/8)) V_v                (8 heads; queries of the OTHER modality)
              O_t = W_ot softmax(Q_v K_t^T / sqrt(C/8)) V_t                (Q, K, V from LN1(T_v) and LN2(T_t))
    residual: R_v = c1 T_v + c2 O_v                     R_t = c3 T_t + c4 O_t
    MLP:      T_v' = c5 R_v + c6 MLP_v(LN2(R_v))        T_t' = c7 R_t + c8 MLP_t(LN2(R_t))   (one LN2, shared)
    back:     F_m' = F_m + Up(T_m')   nearest while training, bilinear in eval
    out:      Conv1x1(cat[F_v', F_t']) : 2C -> C  (+BN, SiLU)

The official block also holds modules its forward never calls: a third MLP ``mlp``, ``LN1``, ``ln_input`` and
``ln_output`` of ``CrossTransformerBlock`` (11,029,760 parameters at the published width). They are kept so that
checkpoints load and the parameter total matches the published 120,240,921; this forward never touches them, so
they receive no gradient and a reachable-parameter count leaves them out.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from adapters.detectors.yolo import v5
from adapters.detectors.yolo.blocks import Conv
from adapters.detectors.yolo.loss_v5 import YOLOv5Loss
from harness.errors import HarnessError

#: Token grids of the fusion blocks at P3, P4, P5 in the official configuration (for 640 px inputs).
TOKENS = (20, 16, 10)
#: Official layer indices.
RGB_LAYERS, THERMAL_LAYERS, FUSION_LAYERS, NECK_LAYERS, DETECT_LAYER = (
    range(0, 10),
    range(10, 20),
    range(20, 23),
    range(23, 37),
    37,
)


def pool_geometry(size: int, grid: int) -> tuple[int, int] | None:
    """ICAFusion's pooling rule along one axis: ``(kernel, stride)`` taking ``size`` cells to ``grid`` tokens.

    s = floor(size / grid), k = size - (grid - 1) s, so floor((size - k) / s) + 1 = grid exactly (80 -> 20: k 4,
    s 4; 40 -> 16: k 10, s 2, overlapping; 20 -> 10: k 2, s 2). ``None`` when ``size <= grid``.
    """
    if size <= grid:
        return None
    s = size // grid
    return size - (grid - 1) * s, s


def pool_to_grid(x: torch.Tensor, grid: tuple[int, int], kind: str) -> torch.Tensor:
    """Average or max pooling of ``x`` to the token grid with the rule of :func:`pool_geometry`.

    The official code pools both axes when either is larger than the grid and passes the map through otherwise;
    it cannot handle a map smaller than the grid (inputs under 320 px at the published grids). Here an axis that
    is smaller than its grid is first resized to it with nearest-neighbour interpolation, so small inputs work;
    at and above the published sizes the result is the official one.
    """
    h, w = x.shape[-2:]
    gh, gw = grid
    if h < gh or w < gw:
        x = F.interpolate(x, size=(max(h, gh), max(w, gw)), mode="nearest")
        h, w = x.shape[-2:]
    geo_h, geo_w = pool_geometry(h, gh), pool_geometry(w, gw)
    if geo_h is None and geo_w is None:
        return x
    kh, sh = geo_h or (1, 1)
    kw, sw = geo_w or (1, 1)
    if kind == "avg":
        return F.avg_pool2d(x, (kh, kw), (sh, sw))
    return F.max_pool2d(x, (kh, kw), (sh, sw))


class LearnableCoefficient(nn.Module):
    """A learnable scalar (stored as ``bias``, as in the official layout), initialised to 1."""

    def __init__(self) -> None:
        super().__init__()
        self.bias = nn.Parameter(torch.ones(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.bias


class LearnableWeights(nn.Module):
    """w1 * x1 + w2 * x2 with learnable scalars initialised to 0.5."""

    def __init__(self) -> None:
        super().__init__()
        self.w1 = nn.Parameter(torch.full((1,), 0.5))
        self.w2 = nn.Parameter(torch.full((1,), 0.5))

    def forward(self, x1: torch.Tensor, x2: torch.Tensor) -> torch.Tensor:
        return x1 * self.w1 + x2 * self.w2


def _mlp(d: int, expansion: int, dropout: float) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d, expansion * d), nn.GELU(), nn.Linear(expansion * d, d), nn.Dropout(dropout))


class CrossAttention(nn.Module):
    """Two-way multi-head attention where each modality's queries attend to the other modality's keys."""

    def __init__(self, d_model: int, heads: int = 8, attn_pdrop: float = 0.1, resid_pdrop: float = 0.1):
        super().__init__()
        if d_model % heads:
            raise HarnessError(f"ICAFusion: fusion width {d_model} is not divisible by {heads} heads")
        self.h = heads
        self.d_k = d_model // heads
        for m in ("vis", "ir"):
            for p in ("que", "key", "val"):
                setattr(self, f"{p}_proj_{m}", nn.Linear(d_model, d_model))
        self.out_proj_vis = nn.Linear(d_model, d_model)
        self.out_proj_ir = nn.Linear(d_model, d_model)
        self.attn_drop = nn.Dropout(attn_pdrop)
        self.resid_drop = nn.Dropout(resid_pdrop)
        self.LN1 = nn.LayerNorm(d_model)  # visible tokens
        self.LN2 = nn.LayerNorm(d_model)  # thermal tokens
        for m in self.modules():  # the official init of the projections: N(0, 0.001), zero bias
            if isinstance(m, nn.Linear):
                nn.init.normal_(m.weight, std=0.001)
                nn.init.zeros_(m.bias)

    def _heads(self, x: torch.Tensor) -> torch.Tensor:
        b, n, _ = x.shape
        return x.view(b, n, self.h, self.d_k).transpose(1, 2)  # [B, h, n, d_k]

    def forward(self, vis: torch.Tensor, ir: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, n, c = vis.shape
        xv, xt = self.LN1(vis), self.LN2(ir)
        q_v, k_v, v_v = (
            self._heads(self.que_proj_vis(xv)),
            self._heads(self.key_proj_vis(xv)),
            self._heads(self.val_proj_vis(xv)),
        )
        q_t, k_t, v_t = (
            self._heads(self.que_proj_ir(xt)),
            self._heads(self.key_proj_ir(xt)),
            self._heads(self.val_proj_ir(xt)),
        )
        scale = 1.0 / math.sqrt(self.d_k)
        att_v = self.attn_drop(torch.softmax(q_t @ k_v.transpose(-2, -1) * scale, -1))  # thermal queries, visible keys
        att_t = self.attn_drop(torch.softmax(q_v @ k_t.transpose(-2, -1) * scale, -1))  # visible queries, thermal keys
        out_v = (att_v @ v_v).transpose(1, 2).reshape(b, n, c)
        out_t = (att_t @ v_t).transpose(1, 2).reshape(b, n, c)
        return self.resid_drop(self.out_proj_vis(out_v)), self.resid_drop(self.out_proj_ir(out_t))


class Attention(NamedTuple):
    """The settings of a cross-attention block: heads, MLP expansion, attention and residual dropout."""

    heads: int = 8
    block_exp: int = 4
    attn_pdrop: float = 0.1
    resid_pdrop: float = 0.1


class CrossTransformerBlock(nn.Module):
    """Cross-attention, learnable-coefficient residuals and per-modality MLPs behind one shared LayerNorm (LN2).

    ``mlp``, ``LN1``, ``ln_input`` and ``ln_output`` exist in the official layout but are never used by its
    forward (nor by this one).
    """

    def __init__(self, d_model: int, attention: Attention = Attention(), loops: int = 1):
        super().__init__()
        a = attention
        self.loops = loops
        self.ln_input = nn.LayerNorm(d_model)  # unused by forward
        self.ln_output = nn.LayerNorm(d_model)  # unused by forward
        self.crossatt = CrossAttention(d_model, a.heads, a.attn_pdrop, a.resid_pdrop)
        self.mlp_vis = _mlp(d_model, a.block_exp, a.resid_pdrop)
        self.mlp_ir = _mlp(d_model, a.block_exp, a.resid_pdrop)
        self.mlp = _mlp(d_model, a.block_exp, a.resid_pdrop)  # unused by forward
        self.LN1 = nn.LayerNorm(d_model)  # unused by forward
        self.LN2 = nn.LayerNorm(d_model)  # shared by both modalities
        for i in range(1, 9):
            setattr(self, f"coefficient{i}", LearnableCoefficient())

    def forward(self, vis: torch.Tensor, ir: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        for _ in range(self.loops):
            o_v, o_t = self.crossatt(vis, ir)
            r_v = self.coefficient1(vis) + self.coefficient2(o_v)
            r_t = self.coefficient3(ir) + self.coefficient4(o_t)
            vis = self.coefficient5(r_v) + self.coefficient6(self.mlp_vis(self.LN2(r_v)))
            ir = self.coefficient7(r_t) + self.coefficient8(self.mlp_ir(self.LN2(r_t)))
        return vis, ir


class TransformerFusionBlock(nn.Module):
    """Pool both modalities to a fixed token grid, cross-attend, upsample back, add, and fuse with a 1x1 conv."""

    def __init__(
        self, d_model: int, vert_anchors: int = 16, horz_anchors: int = 16, n_layer: int = 1, **attention: Any
    ):
        """``attention``: the ``Attention`` settings of its blocks (``heads``, ``block_exp``, ``attn_pdrop``,
        ``resid_pdrop``), the rest keep their defaults."""
        super().__init__()
        self.grid = (vert_anchors, horz_anchors)
        self.pos_emb_vis = nn.Parameter(torch.zeros(1, vert_anchors * horz_anchors, d_model))
        self.pos_emb_ir = nn.Parameter(torch.zeros(1, vert_anchors * horz_anchors, d_model))
        self.vis_coefficient = LearnableWeights()
        self.ir_coefficient = LearnableWeights()
        settings = Attention(**attention)
        self.crosstransformer = nn.Sequential(*(CrossTransformerBlock(d_model, settings) for _ in range(n_layer)))
        self.conv1x1_out = Conv(2 * d_model, d_model, 1, 1, 0)

    def _tokens(self, x: torch.Tensor, weights: LearnableWeights, pos: torch.Tensor) -> torch.Tensor:
        pooled = weights(pool_to_grid(x, self.grid, "avg"), pool_to_grid(x, self.grid, "max"))
        return pooled.flatten(2).transpose(1, 2) + pos  # [B, h'w', C]

    def _back(self, tokens: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        b, _, c = tokens.shape
        maps = tokens.transpose(1, 2).reshape(b, c, *self.grid)
        if self.training:
            return F.interpolate(maps, size=like.shape[-2:], mode="nearest")
        return F.interpolate(maps, size=like.shape[-2:], mode="bilinear", align_corners=False)

    def forward(self, vis: torch.Tensor, ir: torch.Tensor) -> torch.Tensor:
        t_v = self._tokens(vis, self.vis_coefficient, self.pos_emb_vis)
        t_t = self._tokens(ir, self.ir_coefficient, self.pos_emb_ir)
        for block in self.crosstransformer:
            t_v, t_t = block(t_v, t_t)
        fused_v = vis + self._back(t_v, vis)
        fused_t = ir + self._back(t_t, ir)
        return self.conv1x1_out(torch.cat((fused_v, fused_t), 1))


class ICAFusion(v5.AnchorDetector):
    """Two-stream YOLOv5 with three TransformerFusionBlocks; ``trunk`` width/depth 1.0 is the published ``l`` size."""

    name = "icafusion"

    def __init__(
        self,
        nc: int,
        trunk: v5.Trunk = v5.Trunk(3, 1.0, 1.0),
        tokens: Iterable[int] = TOKENS,
        heads: int = 8,
        block_exp: int = 4,
        dropout: float = 0.1,
        prior_bias: bool = False,
        sort_obj_iou: bool = True,
    ):
        super().__init__(nc)
        in_channels, width, depth = trunk
        tokens = tuple(tokens)
        if len(tokens) != 3:
            raise HarnessError(f"ICAFusion: 'tokens' needs three grid sizes (P3, P4, P5), got {list(tokens)}")
        chans = v5.level_channels(width)
        layers: list[nn.Module] = []
        layers += v5.backbone_layers(3, width, depth)
        layers += v5.backbone_layers(in_channels, width, depth)
        layers += [
            TransformerFusionBlock(
                c, int(t), int(t), heads=heads, block_exp=block_exp, attn_pdrop=dropout, resid_pdrop=dropout
            )
            for c, t in zip(chans, tokens)
        ]
        layers += v5.pan_layers(width, depth)
        layers.append(v5.Detect(nc, chans, anchor_grid_buffer=True))
        self.model = nn.ModuleList(layers)
        self.iou = 0.5  # the official test.py NMS IoU
        if prior_bias:  # the official model leaves this out (commented out in its model builder)
            self.head.init_prior_bias()
        self.criterion = YOLOv5Loss(self.head, sort_obj_iou=sort_obj_iou)

    @property
    def head(self) -> v5.Detect:  # type: ignore[override]
        return self.model[DETECT_LAYER]

    def neck_features(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        m = self.model
        (r3, r4, r5), (t3, t4, t5) = v5.run_two_backbones(m[0:10], m[10:20], inputs, self.name)
        f3, f4, f5 = m[20](r3, t3), m[21](r4, t4), m[22](r5, t5)
        return v5.run_pan(m[23:37], f3, f4, f5)

    def unused_parameter_names(self) -> list[str]:
        """Names of the parameters the official forward never uses (kept for checkpoint compatibility)."""
        dead = ("mlp.", "LN1.", "ln_input.", "ln_output.")
        out = []
        for name, _ in self.named_parameters():
            parts = name.split("crosstransformer.")
            if len(parts) == 2:
                rest = parts[1].split(".", 1)[1]  # after the block index
                if rest.startswith(dead):
                    out.append(name)
        return out


def yolov5_backbone_to_two_stream(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """What the official training does with single-stream COCO YOLOv5 weights: layers 0-9 initialise both streams.

    Every ``model.N...`` key with N < 10 is kept and copied to ``model.(N+10)...``; every other key is dropped (the
    fusion blocks, neck and head start from scratch).
    """
    out: dict[str, torch.Tensor] = {}
    for k, v in state_dict.items():
        parts = k.split(".")
        if len(parts) > 2 and parts[0] == "model" and parts[1].isdigit() and int(parts[1]) < 10:
            out[k] = v
            out[".".join(["model", str(int(parts[1]) + 10), *parts[2:]])] = v
    return out
