"""Optimiser, parameter groups and learning-rate schedule, as small functions with the formulas in view.

Three parameter groups, in this order:

* ``decay``:    weights of convolutions, linear layers and any other parameter with more than one dimension,
                with weight decay ``wd * batch * accumulate / nominal_batch`` (decay per image stays constant when
                gradients are accumulated to the nominal batch);
* ``no_decay``: normalisation weights (BatchNorm, GroupNorm, LayerNorm ...) and other one-dimensional parameters;
* ``bias``:     every parameter named ``bias``, which also gets the warm-up bias learning rate.

Learning rate at epoch ``e`` of ``E`` (``lr = lr0 * f(e)``):

* linear:  ``f(e) = (1 - e / E) * (1 - lrf) + lrf``
* cosine:  ``f(e) = (1 - cos(pi * e / E)) / 2 * (lrf - 1) + 1``

Warm-up over the first ``nw`` iterations interpolates linearly, per iteration ``ni``: the bias group's lr from
``warmup_bias_lr`` down to ``lr0 * f(e)``, the other groups' lr from 0 up to ``lr0 * f(e)``, the momentum (SGD) or
beta1 (AdamW) from ``warmup_momentum`` to ``momentum``, and the accumulation count from 1 to
``nominal_batch / batch``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from harness.errors import ConfigError

GROUPS = ("decay", "no_decay", "bias")
OPTIMIZERS = ("SGD", "AdamW")


def is_norm(module: nn.Module) -> bool:
    return isinstance(module, (nn.modules.batchnorm._NormBase, nn.GroupNorm, nn.LayerNorm, nn.LocalResponseNorm))


def param_groups(model: nn.Module) -> dict[str, list[nn.Parameter]]:
    """Every trainable parameter exactly once, sorted into ``decay``, ``no_decay`` and ``bias``."""
    groups: dict[str, list[nn.Parameter]] = {g: [] for g in GROUPS}
    seen: set[int] = set()
    for module in model.modules():
        for name, p in module.named_parameters(recurse=False):
            if not p.requires_grad or id(p) in seen:
                continue
            seen.add(id(p))
            if name == "bias":
                groups["bias"].append(p)
            elif is_norm(module) or p.ndim <= 1:
                groups["no_decay"].append(p)
            else:
                groups["decay"].append(p)
    return groups


def accumulate_steps(batch: int, nominal_batch: int) -> int:
    """Iterations whose gradients are summed before one optimiser step: ``max(round(nominal / batch), 1)``."""
    return max(round(nominal_batch / batch), 1)


def scaled_weight_decay(weight_decay: float, batch: int, accumulate: int, nominal_batch: int) -> float:
    """``wd * batch * accumulate / nominal_batch``."""
    return weight_decay * batch * accumulate / nominal_batch


def build_optimizer(
    model: nn.Module, name: str, lr0: float, momentum: float, weight_decay: float
) -> torch.optim.Optimizer:
    """SGD (Nesterov) or AdamW over the three groups; each group records its ``name`` and ``initial_lr``."""
    groups = param_groups(model)
    if not any(groups.values()):
        raise ConfigError("the model has no trainable parameters")
    specs = [
        {"params": groups["decay"], "weight_decay": weight_decay, "name": "decay"},
        {"params": groups["no_decay"], "weight_decay": 0.0, "name": "no_decay"},
        {"params": groups["bias"], "weight_decay": 0.0, "name": "bias"},
    ]
    for s in specs:
        s["initial_lr"] = lr0
    if name == "SGD":
        return torch.optim.SGD(specs, lr=lr0, momentum=momentum, nesterov=True)
    if name == "AdamW":
        return torch.optim.AdamW(specs, lr=lr0, betas=(momentum, 0.999), weight_decay=0.0)
    raise ConfigError(f"train.optimizer: unknown optimizer {name!r}; use one of {', '.join(OPTIMIZERS)}")


def lr_factor(epoch: float, epochs: int, lrf: float, cosine: bool = False) -> float:
    """The schedule ``f(e)`` of the module docstring: 1 at epoch 0, ``lrf`` at epoch ``epochs``."""
    e = min(max(epoch / max(epochs, 1), 0.0), 1.0)
    if cosine:
        return (1 - math.cos(math.pi * e)) / 2 * (lrf - 1) + 1
    return (1 - e) * (1 - lrf) + lrf


def warmup_iterations(warmup_epochs: float, batches_per_epoch: int, minimum: int = 0) -> int:
    """``max(round(warmup_epochs * nb), minimum)``, or 0 when warm-up is off."""
    if warmup_epochs <= 0:
        return 0
    return max(round(warmup_epochs * batches_per_epoch), int(minimum))


def interp(ni: float, nw: float, start: float, end: float) -> float:
    """Linear interpolation from ``start`` at iteration 0 to ``end`` at iteration ``nw`` (held after)."""
    return float(np.interp(ni, [0, nw], [start, end]))


def set_momentum(group: dict, value: float) -> None:
    if "betas" in group:
        group["betas"] = (value, group["betas"][1])
    elif "momentum" in group:
        group["momentum"] = value
