"""YOLOv5 (v6.x) pieces shared by the anchor-based detectors: backbone, PAN neck, Detect head, decoding, NMS.

The layer table is the one of the public ``yolov5l.yaml`` (v6.0 and later), scaled by ``width`` (channel
multiple) and ``depth`` (repeat multiple) exactly as YOLOv5's model parser does:

    c' = ceil(c * width / 8) * 8                        n' = max(round(n * depth), 1) if n > 1 else n

    idx  module                     idx  module (PAN neck; inputs P3 = layer 4, P4 = layer 6, P5 = layer 9)
    0    Conv 6x6/2  c_in -> 64     10   Conv 1x1   1024 -> 512
    1    Conv 3x3/2  64 -> 128      11   Upsample x2 (nearest)
    2    C3 128, n=3                12   Concat [11, P4]
    3    Conv 3x3/2  128 -> 256     13   C3 1024 -> 512, n=3, no shortcut
    4    C3 256, n=6   (P3, /8)     14   Conv 1x1   512 -> 256
    5    Conv 3x3/2  256 -> 512     15   Upsample x2
    6    C3 512, n=9   (P4, /16)    16   Concat [15, P3]
    7    Conv 3x3/2  512 -> 1024    17   C3 512 -> 256, n=3, no shortcut   (out P3)
    8    C3 1024, n=3               18   Conv 3x3/2 256 -> 256
    9    SPPF 1024, k=5 (P5, /32)   19   Concat [18, 14]
                                    20   C3 512 -> 512, n=3, no shortcut   (out P4)
                                    21   Conv 3x3/2 512 -> 512
                                    22   Concat [21, 10]
                                    23   C3 1024 -> 1024, n=3, no shortcut (out P5)
                                    24   Detect: per level a 1x1 conv to na * (5 + nc)

Detect decodes a cell's raw outputs t (sigmoid s = sigma(t)) with the YOLOv5 v4+ rule

    xy = (2 s_xy - 0.5 + cell) * stride          wh = (2 s_wh)^2 * anchor           score = s_obj * s_cls

The ``anchors`` buffer holds the anchors in grid units (pixels / stride), as the official checkpoints store them.
Module and parameter names follow the official checkpoint layout (``model.24.m.0.weight``); the code is our own.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, NamedTuple, Sequence

import torch
from torch import nn

from adapters.detectors.yolo.blocks import C3, SPPF, Concat, Conv, fuse_model
from adapters.detectors.yolo.postprocess import inference_settings
from adapters.detectors.yolo.postprocess import postprocess as nms_candidates
from harness.boxes import cxcywh_to_xyxy
from harness.errors import HarnessError

#: The standard YOLOv5 anchors (pixels at 640), P3/8, P4/16, P5/32: three (w, h) pairs per level.
ANCHORS_P3_P5: tuple[tuple[int, ...], ...] = (
    (10, 13, 16, 30, 33, 23),
    (30, 61, 62, 45, 59, 119),
    (116, 90, 156, 198, 373, 326),
)
STRIDES: tuple[int, int, int] = (8, 16, 32)
#: YOLOv5 size presets: (depth multiple, width multiple).
SCALES: dict[str, tuple[float, float]] = {
    "n": (0.33, 0.25),
    "s": (0.33, 0.50),
    "m": (0.67, 0.75),
    "l": (1.0, 1.0),
    "x": (1.33, 1.25),
}
#: Backbone layers whose outputs feed the neck (P3, P4); P5 is the last layer.
BACKBONE_TAPS = (4, 6)


class Trunk(NamedTuple):
    """What a dual-stream YOLOv5 network is built on: the thermal stream's input channels and the width and depth
    multiples of its YOLOv5 trunk (1.0 / 1.0 is the l size)."""

    in_channels: int
    width: float
    depth: float


# ------------------------------------------------------------------------------------------------ scaling
def make_divisible(x: float, divisor: int = 8) -> int:
    """Smallest multiple of ``divisor`` that is >= x (YOLOv5's channel rounding)."""
    return int(math.ceil(x / divisor) * divisor)


def scale_width(channels: int, width: float) -> int:
    """Channels of a layer whose yaml width is ``channels`` at width multiple ``width``."""
    return make_divisible(channels * width, 8)


def scale_depth(n: int, depth: float) -> int:
    """Repeats of a block whose yaml repeat is ``n`` at depth multiple ``depth``."""
    return max(round(n * depth), 1) if n > 1 else n


def level_channels(width: float) -> tuple[int, int, int]:
    """Channels of P3, P4, P5 (yaml 256, 512, 1024) at a width multiple."""
    return scale_width(256, width), scale_width(512, width), scale_width(1024, width)


# ------------------------------------------------------------------------------------------------ backbone
def backbone_layers(c_in: int, width: float = 1.0, depth: float = 1.0) -> list[nn.Module]:
    """CSPDarknet (v6.x, 6x6 stem): layers 0-9 of the table above, for a ``c_in``-channel input."""
    c1, c2, c3, c4, c5 = (scale_width(c, width) for c in (64, 128, 256, 512, 1024))
    return [
        Conv(c_in, c1, 6, 2, 2),
        Conv(c1, c2, 3, 2),
        C3(c2, c2, scale_depth(3, depth)),
        Conv(c2, c3, 3, 2),
        C3(c3, c3, scale_depth(6, depth)),
        Conv(c3, c4, 3, 2),
        C3(c4, c4, scale_depth(9, depth)),
        Conv(c4, c5, 3, 2),
        C3(c5, c5, scale_depth(3, depth)),
        SPPF(c5, c5, 5),
    ]


def run_backbone(layers: Sequence[nn.Module], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Run layers 0-9 and return (P3, P4, P5)."""
    taps = []
    for i, layer in enumerate(layers):
        x = layer(x)
        if i in BACKBONE_TAPS:
            taps.append(x)
    return taps[0], taps[1], x


def run_two_backbones(
    rgb_layers: Sequence[nn.Module], thermal_layers: Sequence[nn.Module], inputs: Any, name: str
) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """A two-stream detector's start: ``(rgb, thermal)`` from ``inputs`` (``as_pair``, size checked), each through
    its own backbone; returns (P3, P4, P5) of the visible stream and of the thermal stream."""
    rgb, thermal = as_pair(inputs, name)
    check_size(rgb.shape[-2], rgb.shape[-1], name)
    return run_backbone(rgb_layers, rgb), run_backbone(thermal_layers, thermal)


# ------------------------------------------------------------------------------------------------ neck
def pan_layers(width: float = 1.0, depth: float = 1.0) -> list[nn.Module]:
    """PAN neck: layers 10-23 of the table above (14 modules), for P3/P4/P5 inputs of ``level_channels(width)``."""
    c3, c4, c5 = level_channels(width)
    n = scale_depth(3, depth)
    return [
        Conv(c5, c4, 1, 1),
        nn.Upsample(scale_factor=2.0, mode="nearest"),
        Concat(1),
        C3(2 * c4, c4, n, shortcut=False),
        Conv(c4, c3, 1, 1),
        nn.Upsample(scale_factor=2.0, mode="nearest"),
        Concat(1),
        C3(2 * c3, c3, n, shortcut=False),
        Conv(c3, c3, 3, 2),
        Concat(1),
        C3(2 * c3, c4, n, shortcut=False),
        Conv(c4, c4, 3, 2),
        Concat(1),
        C3(2 * c4, c5, n, shortcut=False),
    ]


def run_pan(
    layers: Sequence[nn.Module], p3: torch.Tensor, p4: torch.Tensor, p5: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Top-down then bottom-up path; returns the three detection maps (P3 out, P4 out, P5 out)."""
    lat5 = layers[0](p5)  # 10
    x = layers[3](layers[2]([layers[1](lat5), p4]))  # 11-13
    lat4 = layers[4](x)  # 14
    out3 = layers[7](layers[6]([layers[5](lat4), p3]))  # 15-17
    out4 = layers[10](layers[9]([layers[8](out3), lat4]))  # 18-20
    out5 = layers[13](layers[12]([layers[11](out4), lat5]))  # 21-23
    return out3, out4, out5


# ------------------------------------------------------------------------------------------------ head
class Detect(nn.Module):
    """Anchor-based head: one 1x1 conv per level to ``na * (5 + nc)`` channels (x, y, w, h, obj, classes).

    ``anchor_grid_buffer=True`` also registers the pixel anchors as the ``anchor_grid`` buffer of shape
    ``[nl, 1, na, 1, 1, 2]``, as YOLOv5 releases before v6.0 (and the ICAFusion code built on them) did; v6.0 and
    later keep only ``anchors``. ``stride`` is a non-persistent buffer (not part of official checkpoints).
    """

    def __init__(
        self,
        nc: int,
        ch: Sequence[int],
        anchors: Sequence[Sequence[float]] = ANCHORS_P3_P5,
        strides: Sequence[int] = STRIDES,
        anchor_grid_buffer: bool = False,
    ):
        super().__init__()
        if len(anchors) != len(ch) or len(strides) != len(ch):
            raise HarnessError(
                f"Detect: {len(ch)} input levels but {len(anchors)} anchor sets and {len(strides)} strides"
            )
        self.nc = nc
        self.no = nc + 5
        self.nl = len(anchors)
        self.na = len(anchors[0]) // 2
        self.m = nn.ModuleList(nn.Conv2d(c, self.no * self.na, 1) for c in ch)
        stride = torch.tensor([float(s) for s in strides])
        pixels = torch.tensor([[float(v) for v in a] for a in anchors]).view(self.nl, -1, 2)
        self.strides = tuple(float(s) for s in strides)
        self.register_buffer("stride", stride, persistent=False)
        self.register_buffer("anchors", pixels / stride.view(-1, 1, 1))
        if anchor_grid_buffer:
            self.register_buffer("anchor_grid", pixels.clone().view(self.nl, 1, -1, 1, 1, 2))

    def forward(self, xs: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """Raw outputs per level, ``[B, na, ny, nx, 5 + nc]`` (the layout the loss and the decoder read)."""
        out = []
        for conv, x in zip(self.m, xs):
            y = conv(x)
            b, _, ny, nx = y.shape
            out.append(y.view(b, self.na, self.no, ny, nx).permute(0, 1, 3, 4, 2).contiguous())
        return out

    def pixel_anchors(self, i: int) -> torch.Tensor:
        """Anchors of level ``i`` in pixels, ``[na, 2]`` (from ``anchor_grid`` when the layout has it)."""
        if hasattr(self, "anchor_grid"):
            return self.anchor_grid[i].reshape(self.na, 2)
        return self.anchors[i] * self.stride[i]

    def decode(self, raw: Sequence[torch.Tensor]) -> torch.Tensor:
        """Raw outputs to ``[B, N, 5 + nc]``: cx, cy, w, h in input pixels, then sigmoid objectness and classes."""
        out = []
        for i, p in enumerate(raw):
            b, na, ny, nx, no = p.shape
            gy, gx = torch.meshgrid(
                torch.arange(ny, device=p.device, dtype=p.dtype),
                torch.arange(nx, device=p.device, dtype=p.dtype),
                indexing="ij",
            )
            cell = torch.stack((gx, gy), -1).view(1, 1, ny, nx, 2)
            s = p.sigmoid()
            xy = (s[..., :2] * 2.0 - 0.5 + cell) * self.stride[i]
            wh = (s[..., 2:4] * 2.0) ** 2 * self.pixel_anchors(i).to(p.dtype).view(1, na, 1, 1, 2)
            out.append(torch.cat((xy, wh, s[..., 4:]), -1).view(b, -1, no))
        return torch.cat(out, 1)

    @torch.no_grad()
    def init_prior_bias(self, image_size: int = 640) -> None:
        """YOLOv5's prior: objectness bias += log(8 / (image_size / stride)^2), classes += log(0.6 / (nc - 0.99999))."""
        for conv, s in zip(self.m, self.strides):
            b = conv.bias.view(self.na, -1)
            b[:, 4] += math.log(8.0 / (image_size / s) ** 2)
            b[:, 5 : 5 + self.nc] += math.log(0.6 / (self.nc - 0.99999))


# ------------------------------------------------------------------------------------------------ NMS
def postprocess(
    pred: torch.Tensor, *, iou: float = 0.6, image_size: tuple[int, int] | None = None, **settings: Any
) -> list[dict[str, torch.Tensor]]:
    """YOLOv5 non-maximum suppression of decoded predictions ``[B, N, 5 + nc]`` (cxcywh pixels, obj, classes).

    A class score is obj * cls; a (box, class) pair is a candidate when its score exceeds ``conf`` (which implies
    obj > conf, YOLOv5's first filter). With ``multi_label`` every such class of a box is a candidate (what
    YOLOv5's validation does), otherwise only its best class. The ``max_nms`` highest-scoring candidates enter
    exact per-class NMS (``harness.boxes.batched_nms``) and the first ``max_det`` survivors are kept, then clipped
    to ``image_size`` (h, w) when given. Returns one ``{"boxes" [K,4] xyxy, "scores" [K], "labels" [K] int64}`` per
    image, sorted by decreasing score. The candidate selection and NMS are the ones the anchor-free head uses
    (``adapters.detectors.yolo.postprocess``), fed with the YOLOv5 scores; ``settings`` are its other keywords
    (``conf`` 0.001, ``max_det`` 300, ``multi_label`` on, ``max_nms`` 30000 by default).
    """
    boxes = cxcywh_to_xyxy(pred[..., :4])
    scores = pred[..., 5:] * pred[..., 4:5]
    return nms_candidates(boxes, scores, iou=iou, image_hw=image_size, **settings)


# ------------------------------------------------------------------------------------------------ inputs
def as_pair(inputs: Any, name: str, rgb_channels: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rgb, thermal)`` from a tuple or from one stacked tensor ``[B, 3 + Ct, H, W]``, checked."""
    if isinstance(inputs, torch.Tensor):
        if inputs.dim() != 4 or inputs.shape[1] <= rgb_channels:
            raise HarnessError(
                f"detector {name!r}: expected (rgb, thermal) or a stacked [B, 3 + Ct, H, W] tensor, "
                f"got a tensor of shape {tuple(inputs.shape)}"
            )
        return inputs[:, :rgb_channels], inputs[:, rgb_channels:]
    if not isinstance(inputs, (tuple, list)) or len(inputs) != 2:
        raise HarnessError(f"detector {name!r} is dual-stream: pass (rgb [B,3,H,W], thermal [B,Ct,H,W])")
    rgb, thermal = inputs
    if rgb.dim() != 4 or thermal.dim() != 4 or rgb.shape[0] != thermal.shape[0] or rgb.shape[2:] != thermal.shape[2:]:
        raise HarnessError(
            f"detector {name!r}: rgb {tuple(rgb.shape)} and thermal {tuple(thermal.shape)} must be "
            f"[B, C, H, W] with the same batch size and image size"
        )
    if rgb.shape[1] != rgb_channels:
        raise HarnessError(f"detector {name!r}: the RGB stream must have {rgb_channels} channels, got {rgb.shape[1]}")
    return rgb, thermal


def check_size(h: int, w: int, name: str, multiple: int = 32) -> None:
    if h % multiple or w % multiple:
        raise HarnessError(
            f"detector {name!r}: input size {h}x{w} must be a multiple of {multiple} "
            f"(letterbox to a multiple of {multiple}, e.g. imgsz 640 or 256)"
        )


def targets_to_tensor(targets: Sequence[Mapping[str, torch.Tensor]], device: torch.device, name: str) -> torch.Tensor:
    """Harness targets (per image ``boxes`` xyxy pixels, ``labels``) to YOLO rows ``[n, 6]``: image, class, cx, cy,
    w, h.

    Boxes with zero width or height are dropped (no anchor can match them).
    """
    rows = []
    for i, t in enumerate(targets):
        try:
            boxes = torch.as_tensor(t["boxes"], dtype=torch.float32, device=device).reshape(-1, 4)
            labels = torch.as_tensor(t["labels"], device=device).reshape(-1).float()
        except (KeyError, TypeError, RuntimeError) as exc:
            raise HarnessError(f"detector {name!r}: target {i} needs 'boxes' [N,4] and 'labels' [N] ({exc})") from None
        if len(boxes) != len(labels):
            raise HarnessError(f"detector {name!r}: target {i} has {len(boxes)} boxes but {len(labels)} labels")
        wh = boxes[:, 2:] - boxes[:, :2]
        ok = (wh > 0).all(1)
        cxcy = (boxes[:, :2] + boxes[:, 2:]) / 2
        img = torch.full((len(boxes), 1), float(i), device=device)
        rows.append(torch.cat((img, labels[:, None], cxcy, wh), 1)[ok])
    return torch.cat(rows) if rows else torch.zeros(0, 6, device=device)


# ------------------------------------------------------------------------------------------------ detector base
class AnchorDetector(nn.Module):
    """The harness model contract for YOLOv5-style anchor detectors.

    Subclasses build ``self.head`` (a :class:`Detect`) and implement ``neck_features(inputs)`` (the maps fed to
    the head). Train mode with targets returns the loss dict of ``self.criterion``; eval mode returns detections
    after NMS using ``conf``, ``iou``, ``max_det`` and ``multi_label``; ``forward_raw`` returns the head outputs.
    """

    name = "anchor-detector"

    def __init__(self, nc: int):
        super().__init__()
        self.nc = nc
        self.conf = 0.001
        self.iou = 0.6
        self.max_det = 300
        self.multi_label = True
        self.max_nms = 30000

    # subclasses: the Detect module, the neck maps and the loss
    head: Detect
    criterion: Any

    def neck_features(self, inputs: Any) -> Sequence[torch.Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError

    def image_size(self, inputs: Any) -> tuple[int, int]:
        x = inputs if isinstance(inputs, torch.Tensor) else inputs[0]
        return int(x.shape[-2]), int(x.shape[-1])

    def forward_raw(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        """Raw head outputs per level, ``[B, na, ny, nx, 5 + nc]`` (no decoding, no NMS)."""
        return tuple(self.head(self.neck_features(inputs)))

    def forward(self, inputs: Any, targets: Sequence[Mapping[str, torch.Tensor]] | None = None) -> Any:
        if self.training:
            if targets is None:
                return self.forward_raw(inputs)
            return self.compute_loss(inputs, targets)
        return self.predict(inputs)

    def target_rows(self, targets: Sequence[Mapping[str, torch.Tensor]], device: torch.device) -> torch.Tensor:
        """Targets as YOLO rows (image, class, cx, cy, w, h), with the labels checked against ``nc``."""
        rows = targets_to_tensor(targets, device, self.name)
        if len(rows) and (rows[:, 1].min() < 0 or rows[:, 1].max() >= self.nc):
            raise HarnessError(
                f"detector {self.name!r}: target labels must be 0..{self.nc - 1} (built for "
                f"{self.nc} classes), got labels {sorted(set(rows[:, 1].long().tolist()))}"
            )
        return rows

    def compute_loss(self, inputs: Any, targets: Sequence[Mapping[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        raw = self.forward_raw(inputs)
        return self.criterion(raw, self.target_rows(targets, raw[0].device), self.image_size(inputs))

    @torch.no_grad()
    def predict(self, inputs: Any) -> list[dict[str, torch.Tensor]]:
        raw = self.forward_raw(inputs)
        return postprocess(self.head.decode(raw), **inference_settings(self), image_size=self.image_size(inputs))

    def fuse(self) -> "AnchorDetector":
        """Fold every Conv's BatchNorm (inference only)."""
        fuse_model(self)
        return self


# ------------------------------------------------------------------------------------------------ weights
def load_state_dict_report(model: nn.Module, state_dict: Mapping[str, Any], name: str) -> dict[str, Any]:
    """Load ``state_dict`` by key and shape, non-strictly, and report what matched.

    Accepts a plain state dict or a checkpoint dict holding one under ``model``/``state_dict``/``ema`` (an
    ``nn.Module`` there is turned into its state dict). Tensors are cast to the model's dtypes. Keys whose shape
    differs (e.g. a head trained for another number of classes) are skipped and listed under ``mismatched``.
    Returns ``{"loaded", "missing", "unexpected", "mismatched"}``.
    """
    sd = state_dict
    for key in ("ema", "model", "state_dict"):
        if isinstance(sd, Mapping) and key in sd and not isinstance(sd[key], torch.Tensor) and sd[key] is not None:
            sd = sd[key]
            break
    if isinstance(sd, nn.Module):
        sd = sd.state_dict()
    if not isinstance(sd, Mapping):
        raise HarnessError(
            f"detector {name!r}: load_official expects a state dict (name -> tensor), got {type(sd).__name__}"
        )
    own = model.state_dict()
    if any(k.endswith(".bn.weight") for k in sd) and not any(k.endswith(".bn.weight") for k in own):
        raise HarnessError(
            f"detector {name!r}: the model's BatchNorm is already folded (fuse()); load weights "
            f"into an unfused model, then call fuse()"
        )
    loaded: dict[str, torch.Tensor] = {}
    mismatched: list[tuple[str, tuple[int, ...], tuple[int, ...]]] = []
    for k, v in sd.items():
        if k not in own or not isinstance(v, torch.Tensor):
            continue
        if tuple(v.shape) != tuple(own[k].shape):
            mismatched.append((k, tuple(own[k].shape), tuple(v.shape)))
            continue
        loaded[k] = v.detach().to(dtype=own[k].dtype)
    model.load_state_dict(loaded, strict=False)
    return {
        "loaded": sorted(loaded),
        "missing": sorted(k for k in own if k not in sd),
        "unexpected": sorted(k for k in sd if k not in own),
        "mismatched": mismatched,
    }


def check_options(name: str, options: Mapping[str, Any], known: Sequence[str]) -> None:
    unknown = sorted(set(options) - set(known))
    if unknown:
        from harness.errors import ConfigError

        raise ConfigError(
            f"detector {name!r}: unknown model option(s) {', '.join(unknown)}; "
            f"known: {', '.join(sorted(known))} (config section 'model')"
        )


def resolve_scale(name: str, scale: str, width: float | None, depth: float | None) -> tuple[float, float]:
    """(width, depth) from a YOLOv5 size letter, each overridable by an explicit multiple."""
    if scale not in SCALES:
        from harness.errors import ConfigError

        raise ConfigError(f"detector {name!r}: model.scale must be one of {', '.join(SCALES)}, got {scale!r}")
    d, w = SCALES[scale]
    return (float(width) if width is not None else w), (float(depth) if depth is not None else d)


def read_weights(source: Any, name: str) -> Mapping[str, Any]:
    """A state dict from a mapping or a file (``.safetensors``, or a ``.pt`` holding plain tensors)."""
    if isinstance(source, Mapping) or isinstance(source, nn.Module):
        return source  # type: ignore[return-value]
    from pathlib import Path

    path = Path(source)
    if not path.is_file():
        raise HarnessError(f"detector {name!r}: weights file {path} not found")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        try:
            return load_file(str(path))
        except Exception as exc:  # the library's own errors for a malformed header or truncated data
            raise HarnessError(
                f"detector {name!r}: weights file {path}: not a readable safetensors file "
                f"({str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__})"
            ) from None
    from harness.weights.unpickle import UnsafeCheckpointError, load_plain

    try:
        return load_plain(path)
    except UnsafeCheckpointError as exc:  # pickled model objects need the code that defined them
        raise HarnessError(
            f"detector {name!r}: {path} is not a plain state dict ({type(exc).__name__}). Official YOLOv5-style "
            f"checkpoints pickle the whole model; convert one safely (no code from the file runs) with "
            f"`harness weights import {path} --out weights.safetensors` and pass that file"
        ) from None
    except HarnessError as exc:
        raise HarnessError(f"detector {name!r}: {exc}") from None


def set_inference_options(
    model: AnchorDetector,
    conf: float | None = None,
    iou: float | None = None,
    max_det: int | None = None,
    multi_label: bool | None = None,
    max_nms: int | None = None,
) -> None:
    """Override the NMS attributes the evaluation uses (``None`` keeps the model's default)."""
    for key, value in (
        ("conf", conf),
        ("iou", iou),
        ("max_det", max_det),
        ("multi_label", multi_label),
        ("max_nms", max_nms),
    ):
        if value is not None:
            setattr(model, key, value)
