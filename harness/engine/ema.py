"""Exponential moving average of the weights, the model that is validated and saved as ``best.pt``.

``ema = d * ema + (1 - d) * weights`` after every optimiser step, with a decay that ramps up as
``d(n) = decay * (1 - exp(-n / tau))`` over the number of updates ``n``, so that early in training the average
follows the weights closely. Integer buffers (BatchNorm's batch counter) are copied.

Given the model's ``harness.engine.flat.FlatState``, the copy is laid out the same way and one update is two
element-wise passes over flat buffers (``FlatEMA``) instead of two kernels per tensor; the numbers are the same.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import torch
from torch import nn


def ema_decay(updates: int, decay: float = 0.9999, tau: float = 2000.0) -> float:
    return decay * (1 - math.exp(-updates / tau))


class ModelEMA:
    def __init__(
        self, model: nn.Module, decay: float = 0.9999, tau: float = 2000.0, updates: int = 0, flat: Any = None
    ):
        self.module = copy.deepcopy(unwrap(model)).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, updates
        self._flat = None
        if flat is not None:
            from harness.engine.flat import FlatEMA

            self._flat = FlatEMA(self.module, flat)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """One EMA step towards ``model`` (with a flat layout: the model that layout belongs to)."""
        self.updates += 1
        d = ema_decay(self.updates, self.decay, self.tau)
        if self._flat is not None:
            self._flat.update(d)
            return
        current = unwrap(model).state_dict()
        for k, v in self.module.state_dict().items():
            if v.dtype.is_floating_point:
                v.mul_(d).add_(current[k].detach(), alpha=1 - d)
            else:
                v.copy_(current[k])

    def state_dict(self) -> dict[str, Any]:
        return {"module": self.module.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.module.load_state_dict(state["module"])
        self.updates = int(state["updates"])


def unwrap(model: nn.Module) -> nn.Module:
    """The model inside a DataParallel / DistributedDataParallel wrapper, or the model itself."""
    return model.module if isinstance(model, (nn.DataParallel, nn.parallel.DistributedDataParallel)) else model
