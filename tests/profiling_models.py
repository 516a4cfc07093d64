"""Small models following the detector contract, with parameters and FLOPs worked out by hand in the tests."""

from __future__ import annotations

import math

import torch
from torch import nn

from adapters.detectors.yolo.blocks import fuse_conv_bn


class TinyAttentionDetector(nn.Module):
    """Single-stream [B, 4, 16, 16]: conv stem (+BN, SiLU), self-attention over the 8x8 tokens, 1x1 head, upsample.

    Also holds a module that is never called (``unused``) and a parameter that is never used (``dead``).
    """

    def __init__(self):
        super().__init__()
        self.stem = nn.Conv2d(4, 8, 3, stride=2, padding=1, bias=False)
        self.bn = nn.BatchNorm2d(8)
        self.act = nn.SiLU()
        self.q, self.k, self.v = nn.Linear(8, 8), nn.Linear(8, 8), nn.Linear(8, 8)
        self.head = nn.Conv2d(8, 6, 1)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.unused = nn.Linear(8, 3)
        self.dead = nn.Parameter(torch.zeros(5))

    def forward_raw(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(self.bn(self.stem(x)))  # [B, 8, 8, 8]
        b, c, h, w = y.shape
        t = y.flatten(2).transpose(1, 2)  # [B, 64, 8]
        q, k, v = self.q(t), self.k(t), self.v(t)
        attn = torch.softmax(torch.matmul(q, k.transpose(1, 2)) / math.sqrt(c), dim=-1)
        t = torch.matmul(attn, v)  # [B, 64, 8]
        y = t.transpose(1, 2).reshape(b, c, h, w)
        return self.up(self.head(y))  # [B, 6, 16, 16]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward_raw(x)

    def fuse(self) -> "TinyAttentionDetector":
        if isinstance(self.bn, nn.BatchNorm2d):
            self.stem = fuse_conv_bn(self.stem, self.bn)
            self.bn = nn.Identity()
        return self


class TinyDualDetector(nn.Module):
    """Dual-stream (rgb [B,3,16,16], thermal [B,1,16,16]): one conv per stream, concat, 1x1 head; two outputs."""

    def __init__(self):
        super().__init__()
        self.rgb = nn.Conv2d(3, 4, 3, padding=1, bias=False)
        self.thermal = nn.Conv2d(1, 4, 3, padding=1, bias=False)
        self.head = nn.Conv2d(8, 2, 1)

    def forward_raw(self, inputs: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        rgb, thermal = inputs
        y = self.head(torch.cat([self.rgb(rgb), self.thermal(thermal)], 1))
        return y, y.amax(dim=(2, 3))

    def forward(self, inputs):
        return self.forward_raw(inputs)
