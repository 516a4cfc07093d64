"""Parameter groups, weight-decay scaling, learning-rate schedule, warm-up and EMA against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from harness.engine import optim
from harness.engine.ema import ModelEMA, ema_decay
from harness.errors import ConfigError


class Toy(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, 4, 3, bias=False)
        self.bn = nn.BatchNorm2d(4)
        self.fc = nn.Linear(4, 2)
        self.ln = nn.LayerNorm(2)
        self.scale = nn.Parameter(torch.ones(2))  # a learnable 1-d scalar vector: no decay
        self.pos = nn.Parameter(torch.zeros(1, 5, 2))  # a multi-dimensional embedding: decay
        self.frozen = nn.Linear(2, 2)
        self.frozen.requires_grad_(False)
        self.tied = self.fc  # the same module twice: its parameters still appear once


def test_param_groups_cover_every_trainable_parameter_once():
    m = Toy()
    g = optim.param_groups(m)
    ids = {k: {id(p) for p in v} for k, v in g.items()}
    assert ids["decay"] == {id(m.conv.weight), id(m.fc.weight), id(m.pos)}
    assert ids["no_decay"] == {id(m.bn.weight), id(m.ln.weight), id(m.scale)}
    assert ids["bias"] == {id(m.bn.bias), id(m.fc.bias), id(m.ln.bias)}
    trainable = {id(p) for p in m.parameters() if p.requires_grad}
    assert set().union(*ids.values()) == trainable
    assert sum(len(v) for v in g.values()) == len(trainable)


@pytest.mark.parametrize("name", ["SGD", "AdamW"])
def test_build_optimizer_puts_decay_on_the_first_group_only(name):
    opt = optim.build_optimizer(Toy(), name, 0.01, 0.9, 5e-4)
    assert [g["name"] for g in opt.param_groups] == ["decay", "no_decay", "bias"]
    assert [g["weight_decay"] for g in opt.param_groups] == [5e-4, 0.0, 0.0]
    assert all(g["initial_lr"] == 0.01 for g in opt.param_groups)
    if name == "SGD":
        assert opt.param_groups[0]["nesterov"] and opt.param_groups[0]["momentum"] == 0.9
    else:
        assert opt.param_groups[0]["betas"] == (0.9, 0.999)
    with pytest.raises(ConfigError, match="unknown optimizer"):
        optim.build_optimizer(Toy(), "Lion", 0.01, 0.9, 0.0)


@pytest.mark.parametrize(
    "batch, nominal, accumulate, wd",
    [
        (16, 64, 4, 5e-4),
        (2, 64, 32, 5e-4),
        (24, 64, 3, 5e-4 * 24 * 3 / 64),
        (128, 64, 1, 1e-3),
        (8, 8, 1, 5e-4),
    ],
)
def test_accumulation_and_weight_decay_scaling(batch, nominal, accumulate, wd):
    assert optim.accumulate_steps(batch, nominal) == accumulate
    assert optim.scaled_weight_decay(5e-4, batch, accumulate, nominal) == pytest.approx(wd)


def test_lr_schedules():
    E, lrf = 100, 0.01
    assert optim.lr_factor(0, E, lrf) == 1.0
    assert optim.lr_factor(E, E, lrf) == pytest.approx(lrf)
    assert optim.lr_factor(50, E, lrf) == pytest.approx(0.5 * 0.99 + 0.01)
    assert optim.lr_factor(25, E, lrf) == pytest.approx(0.75 * 0.99 + 0.01)
    assert optim.lr_factor(0, E, lrf, cosine=True) == pytest.approx(1.0)
    assert optim.lr_factor(E, E, lrf, cosine=True) == pytest.approx(lrf)
    assert optim.lr_factor(25, E, lrf, cosine=True) == pytest.approx(1 - (1 - math.cos(math.pi / 4)) / 2 * 0.99)
    assert optim.lr_factor(50, E, lrf, cosine=True) == pytest.approx(0.505)


def test_warmup_interpolation():
    assert optim.warmup_iterations(3.0, 10) == 30
    assert optim.warmup_iterations(0.5, 10, minimum=100) == 100
    assert optim.warmup_iterations(0.0, 10, minimum=100) == 0
    # bias lr falls from 0.1 to the target, other groups rise from 0
    assert optim.interp(0, 30, 0.1, 0.01) == pytest.approx(0.1)
    assert optim.interp(15, 30, 0.1, 0.01) == pytest.approx(0.055)
    assert optim.interp(30, 30, 0.0, 0.01) == pytest.approx(0.01)
    assert optim.interp(45, 30, 0.0, 0.01) == pytest.approx(0.01)
    g = {"betas": (0.937, 0.999)}
    optim.set_momentum(g, 0.8)
    assert g["betas"] == (0.8, 0.999)


def test_ema_decay_ramp_and_update():
    assert ema_decay(0) == 0.0
    assert ema_decay(2000, 0.9999, 2000) == pytest.approx(0.9999 * (1 - math.exp(-1)))
    assert ema_decay(10**6) == pytest.approx(0.9999)
    m = nn.Sequential(nn.Linear(2, 2), nn.BatchNorm1d(2))
    ema = ModelEMA(m, decay=0.5, tau=1.0)
    start = ema.module[0].weight.clone()
    with torch.no_grad():
        m[0].weight.add_(1.0)
    m[1].num_batches_tracked += 7
    ema.update(m)
    d = 0.5 * (1 - math.exp(-1))
    torch.testing.assert_close(ema.module[0].weight, d * start + (1 - d) * m[0].weight)
    assert int(ema.module[1].num_batches_tracked) == 7  # integer buffers are copied
    assert not any(p.requires_grad for p in ema.module.parameters())
    state = ema.state_dict()
    other = ModelEMA(nn.Sequential(nn.Linear(2, 2), nn.BatchNorm1d(2)))
    other.load_state_dict(state)
    assert other.updates == 1 and torch.equal(other.module[0].weight, ema.module[0].weight)
