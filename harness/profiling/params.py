"""Parameter counts: total, trainable, and reachable in a forward pass (with the ones that never take part named).

Reachability is decided by autograd on a meta-device copy (no memory, no compute): every parameter is made to
require grad, ``forward_raw`` runs in eval mode, and a parameter is reachable when the gradient of the outputs
reaches it. A parameter of a module that is never called, of a branch whose output is discarded, or one that is
registered but never used, is unreachable and listed by name. Modules never called are listed as well (forward
hooks), since a module can be called and still not contribute to the outputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import torch
from torch import nn

from harness.profiling.model_io import ProfilingError, RawForward, as_tuple, is_dual, strip_prefix, to_meta


@dataclass
class ParamReport:
    total: int
    trainable: int
    buffers: int
    reachable: int | None = None
    unreachable: list[str] = field(default_factory=list)
    unreachable_count: int = 0
    modules_not_called: list[str] = field(default_factory=list)
    #: the unreachable parameters that were frozen (``requires_grad=False``) in the model, e.g. YOLOv8's fixed DFL
    #: projection, which is applied when boxes are decoded, after ``forward_raw``
    frozen_unreachable: list[str] = field(default_factory=list)
    frozen_unreachable_count: int = 0

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def count_parameters(model: nn.Module) -> tuple[int, int, int]:
    """(total, trainable, buffer elements); shared parameters are counted once."""
    params = list(model.parameters())
    total = sum(p.numel() for p in params)
    trainable = sum(p.numel() for p in params if p.requires_grad)
    buffers = sum(b.numel() for b in model.buffers())
    return total, trainable, buffers


def reachable_parameters(model: nn.Module, example_inputs: Any) -> ParamReport:
    """Counts plus the reachability analysis described in the module docstring."""
    total, trainable, buffers = count_parameters(model)
    dual = is_dual(example_inputs)
    wrapper = RawForward(to_meta(model), dual).eval()
    named = [(strip_prefix(n), p) for n, p in wrapper.named_parameters()]
    frozen = {n for n, p in named if not p.requires_grad}
    for _, p in named:
        p.requires_grad_(True)
    called: set[int] = set()
    handles = [m.register_forward_pre_hook(lambda mod, _inp: called.add(id(mod))) for m in wrapper.modules()]
    inputs = tuple(t.to("meta") for t in as_tuple(example_inputs))
    grads: Sequence[torch.Tensor | None]
    try:
        with torch.enable_grad():
            outputs = wrapper(*inputs)
            grads_of = [o for o in outputs if o.requires_grad]
            if grads_of:
                scalar = sum(o.float().sum() for o in grads_of)
                grads = torch.autograd.grad(scalar, [p for _, p in named], allow_unused=True)
            else:
                grads = [None] * len(named)
    except Exception as exc:
        raise ProfilingError(
            f"forward_raw failed on the meta device while tracing parameter use: {type(exc).__name__}: {exc}"
        ) from exc
    finally:
        for h in handles:
            h.remove()
    unreachable = [n for (n, _), g in zip(named, grads) if g is None]
    un_count = sum(p.numel() for (_, p), g in zip(named, grads) if g is None)
    # a module counts as called when it, or anything inside it, ran (forward_raw itself is a method, not a call)
    names = {id(m): n for n, m in wrapper.named_modules()}
    used: set[str] = set()
    for mid in called:
        parts = names.get(mid, "").split(".")
        used.update(".".join(parts[:k]) for k in range(len(parts) + 1))
    not_called = [n for n in names.values() if n not in used]
    outer = [strip_prefix(n) for n in not_called if not any(n.startswith(o + ".") for o in not_called)]
    frozen_un = [n for n in unreachable if n in frozen]
    frozen_count = sum(p.numel() for (n, p), g in zip(named, grads) if g is None and n in frozen)
    return ParamReport(
        total, trainable, buffers, total - un_count, unreachable, un_count, outer, frozen_un, frozen_count
    )
