"""Shared YOLO blocks: shapes, parameter counts from the published layer table, BatchNorm folding."""

from __future__ import annotations

import torch

from adapters.detectors.yolo.blocks import C3, SPPF, C2f, Conv, fuse_model


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def test_parameter_counts_match_the_published_layer_table():
    # YOLOv8s rows of the layer table: Conv 4->32 k3 s2: 1,216; C2f 64->64 n=1: 29,056; SPPF 512->512: 656,896
    assert n_params(Conv(4, 32, 3, 2)) == 1216
    assert n_params(C2f(64, 64, 1, True)) == 29056
    assert n_params(C2f(768, 512, 1, False)) == 1969152
    assert n_params(SPPF(512, 512, 5)) == 656896
    # YOLOv5l C3(128, n=3): 156,928
    assert n_params(C3(128, 128, 3)) == 156928


def test_fusing_batchnorm_keeps_outputs():
    torch.manual_seed(0)
    m = torch.nn.Sequential(Conv(4, 8, 3, 2), C2f(8, 8, 2, True), C3(8, 16, 1), SPPF(16, 16))
    for mod in m.modules():  # non-trivial BN statistics
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.5, 0.5)
            mod.running_var.uniform_(0.5, 2.0)
            mod.weight.data.uniform_(0.5, 1.5)
            mod.bias.data.uniform_(-0.2, 0.2)
    m.eval()
    x = torch.randn(2, 4, 32, 32)
    ref = m(x)
    fuse_model(m)
    assert not any(isinstance(mod, torch.nn.BatchNorm2d) for mod in m.modules())
    torch.testing.assert_close(m(x), ref, atol=1e-4, rtol=1e-4)
