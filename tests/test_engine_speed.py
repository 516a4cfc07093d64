"""The CPU speed-ups of the engine: flat-buffer optimiser step, clipping and EMA (bit for bit against torch's
optimisers), the allocator setting, the BN-folded validation copy and channels-last 1x1 convolutions on oneDNN."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from harness.engine import optim
from harness.engine.ema import ModelEMA
from harness.engine.flat import FlatOptimizer, FlatState


class Net(nn.Module):
    """Convolutions, BatchNorm (float and integer buffers), a frozen layer and one layer the forward never uses."""

    def __init__(self, channels_last: bool = False):
        super().__init__()
        self.a = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1, bias=False), nn.BatchNorm2d(8), nn.SiLU())
        self.unused = nn.Conv2d(8, 8, 1)
        self.b = nn.Sequential(nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.BatchNorm2d(16), nn.SiLU())
        self.frozen = nn.Conv2d(16, 16, 1).requires_grad_(False)
        self.head = nn.Linear(16, 5)
        if channels_last:
            self.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.frozen(self.b(self.a(x)))
        return self.head(y.mean((2, 3)))


def _train(model: nn.Module, name: str, flat: bool, steps: int = 6, clip: float = 1.0, accumulate: int = 2):
    """Steps of the trainer's loop (accumulation, warm-up-like lr/momentum changes, clipping, EMA)."""
    torch.manual_seed(0)
    opt = optim.build_optimizer(model, name, 0.01, 0.9, 5e-4)
    state = None
    if flat:
        state = FlatState(model, [g["params"] for g in opt.param_groups])
        opt = FlatOptimizer(opt, state)
    ema = ModelEMA(model, 0.9, 3.0, flat=state)
    g = torch.Generator().manual_seed(1)
    norms = []
    for it in range(steps * accumulate):
        x = torch.randn(4, 3, 16, 16, generator=g) * (1 + it)  # growing inputs: the clip is active in later steps
        if next(model.parameters()).is_contiguous(memory_format=torch.channels_last):
            x = x.contiguous(memory_format=torch.channels_last)
        model(x).pow(2).sum().backward()
        if (it + 1) % accumulate == 0:
            for k, grp in enumerate(opt.param_groups):
                grp["lr"] = 0.01 * (1 + it) / (1 + k)
                optim.set_momentum(grp, 0.8 + 0.01 * it)
            if flat:
                norms.append(float(state.clip_grad_norm_(clip)))
            else:
                norms.append(float(torch.nn.utils.clip_grad_norm_(model.parameters(), clip)))
            opt.step()
            opt.zero_grad(set_to_none=True)
            ema.update(model)
    return opt, ema, norms


def _same(a: dict, b: dict) -> list[str]:
    return [k for k in a if not torch.equal(a[k], b[k])]


@pytest.mark.parametrize("name", ["AdamW", "SGD"])
@pytest.mark.parametrize("channels_last", [False, True])
def test_flat_step_clip_and_ema_are_bit_identical_to_torch(name, channels_last):
    torch.manual_seed(0)
    ref = Net(channels_last)
    new = copy.deepcopy(ref)
    opt_a, ema_a, norms_a = _train(ref, name, flat=False)
    opt_b, ema_b, norms_b = _train(new, name, flat=True)
    assert norms_a == norms_b and max(norms_a) > 1.0  # clipping did act
    assert _same(ref.state_dict(), new.state_dict()) == []
    assert _same(ema_a.module.state_dict(), ema_b.module.state_dict()) == []
    assert torch.equal(ref.unused.weight, new.unused.weight)  # no gradient: never stepped, never decayed
    sa, sb = opt_a.state_dict(), opt_b.state_dict()
    assert sa["param_groups"] == sb["param_groups"]
    assert sorted(sa["state"]) == sorted(sb["state"])  # the unused layer has no state in either
    for k in sa["state"]:
        assert _same(sa["state"][k], sb["state"][k]) == []


@pytest.mark.parametrize("name", ["AdamW", "SGD"])
def test_flat_state_dict_resumes_in_torch_and_back(name):
    """A checkpoint of the flat optimiser continues identically in torch's, and the other way round."""
    torch.manual_seed(0)
    base = Net()
    _train(base, name, flat=False, steps=2)
    a, b = copy.deepcopy(base), copy.deepcopy(base)
    opt_a = optim.build_optimizer(a, name, 0.01, 0.9, 5e-4)
    opt_t = optim.build_optimizer(b, name, 0.01, 0.9, 5e-4)
    fs = FlatState(a, [g["params"] for g in opt_a.param_groups])
    opt_f = FlatOptimizer(opt_a, fs)
    g = torch.Generator().manual_seed(3)
    for k in range(4):
        x = torch.randn(2, 3, 16, 16, generator=g)
        for m, o in ((a, opt_f), (b, opt_t)):
            m(x).sum().backward()
            o.step()
            o.zero_grad()
        if k == 1:  # swap optimiser states: flat -> torch and torch -> flat
            sf, st = copy.deepcopy(opt_f.state_dict()), copy.deepcopy(opt_t.state_dict())
            opt_f.load_state_dict(st)
            opt_t.load_state_dict(sf)
    assert _same(a.state_dict(), b.state_dict()) == []


def test_models_that_cannot_be_flattened_say_why():
    class Tied(nn.Module):
        def __init__(self):
            super().__init__()
            self.fc = nn.Linear(2, 2)
            self.again = self.fc

    m = Tied()
    assert "shares memory" in FlatState.reason(m, [list(m.parameters())])
    half = Net().half()
    half.a[1].float()
    assert "mixes" in FlatState.reason(half, [list(half.parameters())])
    assert "not AdamW or SGD" in FlatOptimizer.reason(torch.optim.Adagrad(Net().parameters()))


def test_gradients_stay_views_of_the_flat_buffer():
    m = Net()
    opt = optim.build_optimizer(m, "AdamW", 0.01, 0.9, 5e-4)
    fs = FlatState(m, [g["params"] for g in opt.param_groups])
    m(torch.randn(2, 3, 8, 8)).sum().backward()
    for p, s in zip(fs.params, fs.param_slots):
        assert p.grad.data_ptr() == fs.grads.data_ptr() + s.start * 4
        assert p.data_ptr() % 64 == 0 and p.grad.data_ptr() % 64 == 0
    assert fs.touched.count(False) == 2  # the unused layer's weight and bias


def test_keep_freed_memory_applies_on_linux_and_can_be_refused(monkeypatch):
    import sys

    from harness.engine.runtime import ENV_MALLOC, keep_freed_memory

    monkeypatch.setenv(ENV_MALLOC, "default")
    assert keep_freed_memory() is False
    monkeypatch.delenv(ENV_MALLOC)
    if sys.platform.startswith("linux"):
        import ctypes.util

        if "libc.so" in (ctypes.util.find_library("c") or ""):
            assert keep_freed_memory() is True


class Folding(nn.Module):
    """A model whose fold builds new layers (drawing their initial weights from the global generator)."""

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, 4, 3, padding=1, bias=False)
        self.bn = nn.BatchNorm2d(4)
        self.drop = nn.Dropout(0.5)

    def forward(self, x):
        return self.drop(self.bn(self.conv(x)))

    def fuse(self):
        from adapters.detectors.yolo.blocks import fuse_conv_bn

        self.conv, self.bn = fuse_conv_bn(self.conv, self.bn), nn.Identity()
        return self


def test_inference_copy_folds_a_copy_and_leaves_the_random_generators_alone():
    from harness.engine.trainer import inference_copy

    torch.manual_seed(0)
    m = Folding()
    m.bn.running_mean.uniform_(-1, 1)
    m.bn.running_var.uniform_(0.5, 2)
    m.eval()
    state = torch.get_rng_state()
    folded = inference_copy(m)
    assert torch.equal(torch.get_rng_state(), state)  # training's dropout masks must not depend on validation
    assert isinstance(m.bn, nn.BatchNorm2d) and isinstance(folded.bn, nn.Identity) and not folded.training
    x = torch.randn(2, 3, 8, 8)
    torch.testing.assert_close(folded(x), m(x), rtol=1e-5, atol=1e-5)
    plain = nn.Sequential(nn.Conv2d(3, 3, 1), nn.BatchNorm2d(3))  # no declared fold: validated as it is
    assert inference_copy(plain) is plain


def test_pointwise_convolutions_move_to_onednn_for_channels_last_and_back():
    from harness.engine.trainer import pointwise_convs_on_onednn

    torch.manual_seed(0)
    m = Net(channels_last=True)
    x = torch.randn(2, 3, 16, 16).contiguous(memory_format=torch.channels_last)
    ref = m(x)
    assert pointwise_convs_on_onednn(m, True) == 2  # the unused and the frozen 1x1 convolutions
    assert m.frozen.dilation == (2, 2) and m.a[0].dilation == (1, 1)
    torch.testing.assert_close(m(x), ref, rtol=1e-5, atol=1e-5)
    assert pointwise_convs_on_onednn(m, False) == 2 and m.frozen.dilation == (1, 1)
