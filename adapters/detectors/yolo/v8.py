"""The YOLOv8 detection graph: backbone, SPPF, PAN neck and the decoupled anchor-free Detect head with DFL.

The graph is built from a small layer table written the way the public ``yolov8.yaml`` states it (unscaled widths
and repeats, ``from`` indices); a scale preset multiplies widths by ``width`` (capped at ``max_channels``, rounded up
to a multiple of 8) and repeats by ``depth``. Modules sit in ``self.model`` (an ``nn.ModuleList``) at the indices of
the table, so parameter names follow the public checkpoint layout (``model.0.conv.weight``,
``model.2.m.0.cv1.conv.weight``, ``model.22.cv2.0.0.conv.weight``, ``model.22.dfl.conv.weight`` ...).

The model contract (``harness.api.DetectorSpec``):

* ``model(x, targets)`` -> ``{"box", "cls", "dfl"}`` scalar losses (see ``loss_v8.V8DetectionLoss``);
* ``model(x)`` in eval mode -> one ``{"boxes", "scores", "labels"}`` dict per image after per-class NMS;
* ``model.forward_raw(x)`` -> the three raw head maps ``[B, 4*reg_max + nc, H/s, W/s]`` for s = 8, 16, 32;
* ``model.fuse()`` folds every BatchNorm into its convolution.
"""

from __future__ import annotations

import logging
import math
import operator
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import nn

from adapters.detectors.yolo.blocks import DFL, SPPF, C2f, Concat, Conv, fuse_model
from adapters.detectors.yolo.loss_v8 import LOSS_DEFAULTS
from adapters.detectors.yolo.postprocess import INFERENCE_DEFAULTS, inference_settings, postprocess
from harness.errors import ConfigError, HarnessError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Scale:
    """A model size: repeats are multiplied by ``depth``, widths by ``width`` after capping at ``max_channels``."""

    depth: float
    width: float
    max_channels: int


#: The public presets of the YOLOv8 family.
SCALES: dict[str, Scale] = {
    "n": Scale(0.33, 0.25, 1024),
    "s": Scale(0.33, 0.50, 1024),
    "m": Scale(0.67, 0.75, 768),
    "l": Scale(1.00, 1.00, 512),
    "x": Scale(1.00, 1.25, 512),
}

# (from, repeats, module, args); widths and repeats before scaling, as in the public yolov8.yaml.
#   Conv args: (out channels, kernel, stride); C2f: (out channels, shortcut); SPPF: (out channels, pool kernel).
LAYERS: tuple[tuple[int | tuple[int, ...], int, str, tuple], ...] = (
    # backbone
    (-1, 1, "Conv", (64, 3, 2)),  # 0   P1/2
    (-1, 1, "Conv", (128, 3, 2)),  # 1   P2/4
    (-1, 3, "C2f", (128, True)),  # 2
    (-1, 1, "Conv", (256, 3, 2)),  # 3   P3/8
    (-1, 6, "C2f", (256, True)),  # 4
    (-1, 1, "Conv", (512, 3, 2)),  # 5   P4/16
    (-1, 6, "C2f", (512, True)),  # 6
    (-1, 1, "Conv", (1024, 3, 2)),  # 7   P5/32
    (-1, 3, "C2f", (1024, True)),  # 8
    (-1, 1, "SPPF", (1024, 5)),  # 9
    # PAN neck
    (-1, 1, "Upsample", ()),  # 10
    ((-1, 6), 1, "Concat", ()),  # 11  + backbone P4
    (-1, 3, "C2f", (512, False)),  # 12
    (-1, 1, "Upsample", ()),  # 13
    ((-1, 4), 1, "Concat", ()),  # 14  + backbone P3
    (-1, 3, "C2f", (256, False)),  # 15  P3/8 out
    (-1, 1, "Conv", (256, 3, 2)),  # 16
    ((-1, 12), 1, "Concat", ()),  # 17  + neck P4
    (-1, 3, "C2f", (512, False)),  # 18  P4/16 out
    (-1, 1, "Conv", (512, 3, 2)),  # 19
    ((-1, 9), 1, "Concat", ()),  # 20  + SPPF P5
    (-1, 3, "C2f", (1024, False)),  # 21  P5/32 out
    ((15, 18, 21), 1, "Detect", ()),  # 22
)


def make_divisible(x: float, divisor: int = 8) -> int:
    """Smallest multiple of ``divisor`` that is >= ``x``."""
    return int(math.ceil(x / divisor) * divisor)


def scaled_width(c: int, scale: Scale) -> int:
    return make_divisible(min(c, scale.max_channels) * scale.width, 8)


def scaled_depth(n: int, scale: Scale) -> int:
    return max(round(n * scale.depth), 1) if n > 1 else n


class Detect(nn.Module):
    """Decoupled anchor-free head: per level a box branch (4 x reg_max DFL logits) and a class branch (nc logits).

    Box branch width ``c2 = max(16, ch[0] / 4, 4 * reg_max)``, class branch width ``c3 = max(ch[0], min(nc, 100))``;
    each branch is Conv3x3 -> Conv3x3 -> Conv2d 1x1 (with bias). ``stride`` is filled in by the model after a probe
    forward pass (it is not assumed).
    """

    def __init__(self, nc: int, ch: Sequence[int], reg_max: int = 16):
        super().__init__()
        self.nc = nc
        self.nl = len(ch)
        self.reg_max = reg_max
        self.no = nc + 4 * reg_max
        c2 = max(16, ch[0] // 4, 4 * reg_max)
        c3 = max(ch[0], min(nc, 100))
        self.cv2 = nn.ModuleList(
            nn.Sequential(Conv(c, c2, 3), Conv(c2, c2, 3), nn.Conv2d(c2, 4 * reg_max, 1)) for c in ch
        )
        self.cv3 = nn.ModuleList(nn.Sequential(Conv(c, c3, 3), Conv(c3, c3, 3), nn.Conv2d(c3, nc, 1)) for c in ch)
        self.dfl = DFL(reg_max) if reg_max > 1 else nn.Identity()
        # not persistent: official state dicts carry no stride, and .to(device) still moves it
        self.register_buffer("stride", torch.zeros(self.nl), persistent=False)

    def forward(self, xs: list[torch.Tensor]) -> list[torch.Tensor]:
        return [torch.cat((self.cv2[i](x), self.cv3[i](x)), 1) for i, x in enumerate(xs)]

    def init_bias(self) -> None:
        """Prior bias init of the official model: box logits 1.0; class logits log(5 / nc / (640 / stride)^2),
        i.e. about 5 objects per 640x640 image spread over nc classes and the level's cells."""
        for box, cls, s in zip(self.cv2, self.cv3, self.stride.tolist()):
            box[-1].bias.data.fill_(1.0)
            cls[-1].bias.data[: self.nc] = cls_bias_prior(self.nc, s)

    def reset_class_layer(self) -> list[str]:
        """Re-initialise the last layer of every class branch (a new number of classes); returns its key suffixes."""
        names = []
        for i, (cls, s) in enumerate(zip(self.cv3, self.stride.tolist())):
            cls[-1].reset_parameters()
            cls[-1].bias.data[:] = cls_bias_prior(self.nc, s)
            names += [f"cv3.{i}.2.weight", f"cv3.{i}.2.bias"]
        return names


def _positive_int(name: str, value: Any) -> int:
    try:
        v = operator.index(value)  # int, numpy integer; not float or bool-like strings
    except TypeError:
        v = 0
    if isinstance(value, bool) or v < 1:
        raise ConfigError(f"{name} must be a positive integer, got {value!r}")
    return v


def cls_bias_prior(nc: int, stride: float) -> float:
    return math.log(5 / nc / (640 / stride) ** 2)


class YOLOv8(nn.Module):
    """YOLOv8 detector for ``in_channels``-channel input (``[R, G, B, C2]`` for the seed), ``nc`` classes."""

    def __init__(
        self,
        nc: int = 8,
        in_channels: int = 4,
        scale: str = "s",
        reg_max: int = 16,
        loss: dict[str, float] | None = None,
        **inference: Any,
    ):
        """``inference``: any of ``postprocess.INFERENCE_DEFAULTS`` (``conf``, ``iou``, ``max_det``, ``multi_label``,
        ``max_nms``), the rest keep their defaults."""
        super().__init__()
        if scale not in SCALES:
            raise ConfigError(f"model.scale: unknown YOLOv8 scale {scale!r}; use one of {', '.join(SCALES)}")
        nc, in_channels = _positive_int("num_classes", nc), _positive_int("in_channels", in_channels)
        unknown_inference = sorted(set(inference) - set(INFERENCE_DEFAULTS))
        if unknown_inference:
            raise TypeError(
                f"YOLOv8: unknown inference setting(s) {unknown_inference}; known: {list(INFERENCE_DEFAULTS)}"
            )
        s = {**INFERENCE_DEFAULTS, **inference}
        self.nc = nc
        self.in_channels = in_channels
        self.scale = scale
        self.reg_max = reg_max
        self.conf, self.iou, self.max_det = float(s["conf"]), float(s["iou"]), int(s["max_det"])
        self.multi_label, self.max_nms = bool(s["multi_label"]), int(s["max_nms"])
        self.hyp = dict(LOSS_DEFAULTS)
        unknown = set(loss or {}) - set(LOSS_DEFAULTS)
        if unknown:
            raise ConfigError(f"model: unknown loss option(s) {sorted(unknown)}; known: {sorted(LOSS_DEFAULTS)}")
        self.hyp.update(loss or {})

        self.model, self.routes, self.saved = self._build_layers(SCALES[scale], in_channels, nc, reg_max)
        strides = self._probe_strides()
        self.head.stride.copy_(strides)
        self.strides: tuple[int, ...] = tuple(int(v) for v in strides.tolist())
        self.head.init_bias()
        self._criterion = None
        self._anchor_cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
        self.load_report: dict[str, Any] | None = None

    # ------------------------------------------------------------------ construction
    @staticmethod
    def _build_layers(scale: Scale, in_channels: int, nc: int, reg_max: int):
        layers: list[nn.Module] = []
        routes: list[int | tuple[int, ...]] = []
        channels: list[int] = []
        for i, (src, n, kind, args) in enumerate(LAYERS):
            c_in = channels[src] if isinstance(src, int) and channels else in_channels
            if kind == "Conv":
                c_out = scaled_width(args[0], scale)
                m: nn.Module = Conv(c_in, c_out, args[1], args[2])
            elif kind == "C2f":
                c_out = scaled_width(args[0], scale)
                m = C2f(c_in, c_out, scaled_depth(n, scale), shortcut=args[1])
            elif kind == "SPPF":
                c_out = scaled_width(args[0], scale)
                m = SPPF(c_in, c_out, args[1])
            elif kind == "Upsample":
                c_out = c_in
                m = nn.Upsample(scale_factor=2, mode="nearest")
            elif kind == "Concat":
                c_out = sum(channels[j] for j in src)  # type: ignore[union-attr]
                m = Concat(1)
            elif kind == "Detect":
                c_out = 0
                m = Detect(nc, [channels[j] for j in src], reg_max)  # type: ignore[union-attr]
            else:  # pragma: no cover - the table is fixed
                raise ValueError(kind)
            layers.append(m)
            routes.append(src if isinstance(src, int) else tuple(j if j >= 0 else i + j for j in src))
            channels.append(c_out)
        saved = {j for r in routes if isinstance(r, tuple) for j in r}
        return nn.ModuleList(layers), routes, saved

    @torch.no_grad()
    def _probe_strides(self, size: int = 64) -> torch.Tensor:
        """Strides of the head's levels, from the map sizes of one small forward pass (in eval mode, so the
        BatchNorm running statistics are left alone)."""
        was_training = self.training
        self.eval()
        try:
            maps = self._forward_levels(torch.zeros(1, self.in_channels, size, size))
        finally:
            self.train(was_training)
        return torch.tensor([size / m.shape[-2] for m in maps], dtype=torch.float32)

    @property
    def head(self) -> Detect:
        """The Detect module (the last layer of the table)."""
        return self.model[-1]  # type: ignore[return-value]

    @property
    def stride(self) -> torch.Tensor:
        """Strides of the three output levels (computed at build time, 8/16/32 for this graph)."""
        return self.head.stride

    @property
    def max_stride(self) -> int:
        return max(self.strides)

    # ------------------------------------------------------------------ forward passes
    def _forward_levels(self, x: torch.Tensor) -> list[torch.Tensor]:
        outputs: dict[int, torch.Tensor] = {}
        y: Any = x
        for i, (m, src) in enumerate(zip(self.model, self.routes)):
            if isinstance(src, tuple):
                y = [y if j == i - 1 else outputs[j] for j in src]
            y = m(y)
            if i in self.saved:
                outputs[i] = y
        return y

    def _check_input(self, x: Any) -> None:
        if torch.jit.is_tracing():  # shapes are fixed while tracing (ONNX export): nothing to check, no warnings
            return
        if not isinstance(x, torch.Tensor) or x.dim() != 4:
            raise HarnessError(
                f"YOLOv8 expects one float tensor [B, {self.in_channels}, H, W]; got "
                f"{type(x).__name__}{tuple(x.shape) if isinstance(x, torch.Tensor) else ''}"
            )
        if x.shape[1] != self.in_channels:
            raise HarnessError(
                f"YOLOv8 was built for {self.in_channels} input channels but got {x.shape[1]} "
                f"(input {tuple(x.shape)}); build it with in_channels = 3 + the encoding's channels"
            )
        s = self.max_stride
        if x.shape[2] % s or x.shape[3] % s:
            raise HarnessError(
                f"YOLOv8 input height and width must be multiples of {s}; got {x.shape[2]}x{x.shape[3]} "
                f"(letterbox to a multiple of {s})"
            )

    def forward_raw(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Raw head outputs, one ``[B, 4*reg_max + nc, H/s, W/s]`` map per level (box DFL logits first, then class
        logits): no decoding and no NMS. This is what profiling counts and what ONNX export captures."""
        self._check_input(x)
        return tuple(self._forward_levels(x))

    def forward(self, x: torch.Tensor, targets: list[dict[str, torch.Tensor]] | None = None) -> Any:
        """``targets`` given: loss dict (train or eval mode). Eval mode without targets: detections per image.
        Train mode without targets: the raw head maps (as ``forward_raw``)."""
        maps = self.forward_raw(x)
        if targets is not None:
            return self.criterion(list(maps), targets)
        if self.training:
            return maps
        return self.postprocess(maps, (x.shape[2], x.shape[3]))

    # ------------------------------------------------------------------ loss and inference
    @property
    def criterion(self):
        """The training loss, built on first use from ``model.hyp`` (change ``hyp`` before the first step)."""
        if self._criterion is None:
            from adapters.detectors.yolo.loss_v8 import V8DetectionLoss

            self._criterion = V8DetectionLoss(self.nc, self.reg_max, **self.hyp)
        self._criterion.strides = self.strides
        return self._criterion

    def decode(self, maps: Sequence[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes ``[B, A, 4]`` xyxy in input pixels and class probabilities ``[B, A, nc]`` for every anchor point."""
        from adapters.detectors.yolo.loss_v8 import dist2bbox, make_anchors

        key = (tuple(tuple(m.shape[2:]) for m in maps), maps[0].device, maps[0].dtype)
        if key not in self._anchor_cache:
            self._anchor_cache = {key: make_anchors(maps, self.strides)}
        anchors, strides = self._anchor_cache[key]
        b = maps[0].shape[0]
        flat = torch.cat([m.reshape(b, self.head.no, -1) for m in maps], 2)  # [B, no, A]
        box, cls = flat.split((4 * self.reg_max, self.nc), 1)
        dist = self.head.dfl(box)  # [B, 4, A] distances in grid cells
        boxes = dist2bbox(dist.transpose(1, 2), anchors) * strides
        return boxes, cls.sigmoid().transpose(1, 2)

    def postprocess(self, maps: Sequence[torch.Tensor], image_hw: tuple[int, int]) -> list[dict[str, torch.Tensor]]:
        boxes, scores = self.decode(maps)
        return postprocess(boxes, scores, **inference_settings(self), image_hw=image_hw)

    # ------------------------------------------------------------------ inference-time folding
    def fuse(self) -> "YOLOv8":
        """Fold every BatchNorm into the preceding convolution (inference only); returns ``self``."""
        fuse_model(self)
        return self

    def extra_repr(self) -> str:
        return f"scale={self.scale!r}, in_channels={self.in_channels}, nc={self.nc}, reg_max={self.reg_max}"


def build_yolov8(
    num_classes: int,
    in_channels: int = 4,
    scale: str = "s",
    conf: float = 0.001,
    iou: float = 0.7,
    max_det: int = 300,
    **kw: Any,
) -> YOLOv8:
    """Build a YOLOv8 model; ``kw`` may hold ``reg_max``, ``multi_label``, ``max_nms`` and the loss options
    ``box``, ``cls``, ``dfl`` (gains), ``topk``, ``alpha``, ``beta`` (assigner)."""
    loss = {k: kw.pop(k) for k in list(kw) if k in LOSS_DEFAULTS}
    known = {"reg_max", "multi_label", "max_nms"}
    unknown = set(kw) - known
    if unknown:
        raise ConfigError(
            f"model: unknown YOLOv8 option(s) {sorted(unknown)}; known: "
            f"{sorted(known | set(LOSS_DEFAULTS) | {'scale', 'conf', 'iou', 'max_det'})}"
        )
    return YOLOv8(
        nc=num_classes, in_channels=in_channels, scale=scale, conf=conf, iou=iou, max_det=max_det, loss=loss, **kw
    )
