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


def _sppf_reference(m: SPPF, x: torch.Tensor) -> torch.Tensor:
    """SPPF as it pooled before the channels-last copy: three NCHW max-pools."""
    y = [m.cv1(x)]
    for _ in range(3):
        y.append(m.m(y[-1]))
    return m.cv2(torch.cat(y, 1))


def test_sppf_pools_channels_last_with_the_same_values_indices_and_gradients():
    torch.manual_seed(0)
    m = SPPF(16, 16).train()
    m.cv1 = torch.nn.Identity()  # pool the input itself: ties (small integers), -inf and NaN reach the max-pools
    x = torch.randint(-3, 4, (2, 8, 11, 13)).float()  # SPPF(16, 16) pools 8 channels
    x[0, 0, 2:4, 2:4] = float("-inf")
    x[1, 3, 5, 6] = float("nan")
    seen = []
    m.m.register_forward_pre_hook(lambda mod, inp: seen.append(inp[0].is_contiguous(memory_format=torch.channels_last)))
    grads = []
    for fn in (m, lambda t: _sppf_reference(m, t)):
        xi = x.clone().requires_grad_(True)
        out = fn(xi)
        out.backward(torch.randn(out.shape, generator=torch.Generator().manual_seed(1)))
        grads.append((out.detach(), xi.grad, [p.grad.clone() for p in m.parameters()]))
        m.zero_grad(set_to_none=True)
    assert seen[:3] == [True] * 3 and seen[3:] == [False] * 3  # the block pooled channels-last, the reference not
    (a, ga, pa), (b, gb, pb) = grads
    assert torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())
    assert torch.equal(ga.isnan(), gb.isnan()) and torch.equal(ga.nan_to_num(), gb.nan_to_num())
    assert all(torch.equal(p.nan_to_num(), q.nan_to_num()) for p, q in zip(pa, pb))
    assert out.is_contiguous()  # the concatenation and cv2 still see NCHW tensors

    with torch.no_grad():  # inference (a fresh block: the NaN above reached the BatchNorm statistics)
        m, y = SPPF(16, 16).eval(), torch.randn(1, 16, 9, 9)
        assert torch.equal(m(y), _sppf_reference(m, y))
