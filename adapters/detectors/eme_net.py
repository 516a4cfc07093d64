"""EME as the seed profiles it: YOLOv5l with early fusion of RGB and thermal (6 input channels), plus ShaPE.

Zhang et al., "Rethinking Early-Fusion Strategies for Improved Multispectral Object Detection" (EME). The seed's
46.15 M / 109.20 GFLOPs are those of YOLOv5l (v6.x) at nc = 8 whose first convolution takes the 6-channel
concatenation [R, G, B, T, T, T]; that is the default here (layout ``model.0`` ... ``model.24`` of YOLOv5, so a
6-channel YOLOv5l checkpoint loads by key).

``shape=True`` adds the paper's shape-priority early-fusion stem (ShaPE) in front of a 3-channel YOLOv5l:

    g_v = |Sobel(mean_c RGB)|,  g_t = |Sobel(mean_c T)|          |g| = sqrt(gx^2 + gy^2 + 1e-6), kernels / 8
    E   = max over {g_v, g_t} and a 3x3 neighbourhood            (union edge map)
    s_m = SSIM_7(E / ||E||, g_m / ||g_m||)                        per-pixel SSIM map, Gaussian window 7, sigma 1.5
    [w_v, w_t] = softmax(s_v, s_t)                                 per pixel
    x   = Conv7x7_{6->3}(cat[RGB * w_v, T * w_t])                  no bias; 882 parameters

(norms ||.|| are L2 over H, W). What the public EME code has and this does not: its detector is MMDetection's
GFL with a ResNet-50 FPN (not YOLOv5), and its training adds weak supervision from CLIP and CoreKD distillation
from a ResNet-101 mid-fusion teacher, which need weights that cannot be obtained here.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from adapters.detectors.yolo import v5
from adapters.detectors.yolo.loss_v5 import YOLOv5Loss
from harness.errors import HarnessError

DETECT_LAYER = 24


def sobel_magnitude(x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Gradient magnitude of a ``[B, 1, H, W]`` map: Sobel kernels normalised by their L1 sum (8), replicate border."""
    k = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=x.dtype, device=x.device) / 8.0
    kernels = torch.stack((k, k.T)).unsqueeze(1)  # [2, 1, 3, 3]: d/dx, d/dy
    g = F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), kernels)
    return torch.sqrt(g[:, :1] ** 2 + g[:, 1:] ** 2 + eps)


def gaussian_kernel(
    size: int = 7, sigma: float = 1.5, dtype: torch.dtype = torch.float32, device: torch.device | None = None
) -> torch.Tensor:
    """Normalised 2-D Gaussian window ``[size, size]`` centred on the middle tap."""
    x = torch.arange(size, dtype=dtype, device=device) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_map(
    a: torch.Tensor, b: torch.Tensor, window: int = 7, sigma: float = 1.5, max_val: float = 1.0
) -> torch.Tensor:
    """Per-pixel SSIM of two ``[B, 1, H, W]`` maps (reflect padding, same size):

    SSIM = (2 mu_a mu_b + C1)(2 s_ab + C2) / ((mu_a^2 + mu_b^2 + C1)(s_a^2 + s_b^2 + C2)),
    C1 = (0.01 max_val)^2, C2 = (0.03 max_val)^2, moments from the Gaussian window.
    """
    w = gaussian_kernel(window, sigma, a.dtype, a.device)[None, None]
    p = window // 2

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.pad(x, (p, p, p, p), mode="reflect"), w)

    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    mu_a, mu_b = blur(a), blur(b)
    s_a = blur(a * a) - mu_a**2
    s_b = blur(b * b) - mu_b**2
    s_ab = blur(a * b) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * s_ab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (s_a + s_b + c2))


class ShaPE(nn.Module):
    """Shape-priority early fusion: weight each modality per pixel by how well its edges agree with the union edge."""

    def __init__(self, rgb_channels: int = 3, thermal_channels: int = 3, out_channels: int = 3):
        super().__init__()
        self.rgb_channels = rgb_channels
        self.conv = nn.Conv2d(rgb_channels + thermal_channels, out_channels, 7, 1, 3, bias=False)

    def fusion_weights(self, rgb: torch.Tensor, thermal: torch.Tensor) -> torch.Tensor:
        """Per-pixel softmax weights ``[B, 2, H, W]`` (visible, thermal)."""
        g_v = sobel_magnitude(rgb.mean(1, keepdim=True))
        g_t = sobel_magnitude(thermal.mean(1, keepdim=True))
        edge = F.max_pool2d(torch.maximum(g_v, g_t), 3, 1, 1)
        unit = lambda x: F.normalize(x, dim=(2, 3))  # noqa: E731
        s = torch.cat((ssim_map(unit(edge), unit(g_v)), ssim_map(unit(edge), unit(g_t))), 1)
        return torch.softmax(s, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rgb, thermal = x[:, : self.rgb_channels], x[:, self.rgb_channels :]
        w = self.fusion_weights(rgb, thermal)
        return self.conv(torch.cat((rgb * w[:, :1], thermal * w[:, 1:]), 1))


class EME(v5.AnchorDetector):
    """YOLOv5 early fusion; ``trunk`` width/depth 1.0 is YOLOv5l (the seed's EME figures), ``shape`` adds ShaPE."""

    name = "eme"

    def __init__(self, nc: int, trunk: v5.Trunk = v5.Trunk(3, 1.0, 1.0), shape: bool = False, prior_bias: bool = True):
        super().__init__(nc)
        in_channels, width, depth = trunk
        fused_channels = 3 + in_channels
        self.in_channels_total = fused_channels
        self.stem = ShaPE(3, in_channels, 3) if shape else None
        layers = v5.backbone_layers(3 if shape else fused_channels, width, depth) + v5.pan_layers(width, depth)
        layers.append(v5.Detect(nc, v5.level_channels(width)))
        self.model = nn.ModuleList(layers)
        if prior_bias:
            self.head.init_prior_bias()
        self.criterion = YOLOv5Loss(self.head)

    @property
    def head(self) -> v5.Detect:  # type: ignore[override]
        return self.model[DETECT_LAYER]

    def early_fusion(self, inputs: Any) -> torch.Tensor:
        """The 6-channel input [R, G, B, T...] (through ShaPE when enabled)."""
        if isinstance(inputs, torch.Tensor) and inputs.dim() == 4:
            x = inputs
        else:
            x = torch.cat(v5.as_pair(inputs, self.name), 1)
        if x.shape[1] != self.in_channels_total:
            raise HarnessError(
                f"detector {self.name!r}: early fusion expects {self.in_channels_total} channels "
                f"(RGB + {self.in_channels_total - 3} thermal), got {x.shape[1]}"
            )
        v5.check_size(x.shape[-2], x.shape[-1], self.name)
        return self.stem(x) if self.stem is not None else x

    def neck_features(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        p3, p4, p5 = v5.run_backbone(self.model[0:10], self.early_fusion(inputs))
        return v5.run_pan(self.model[10:24], p3, p4, p5)
