"""The optimiser step, gradient clipping, zeroing and the EMA update on flat buffers (CPU, one process).

A small detector on a CPU spends more of its optimiser step in per-tensor kernel launches than in arithmetic: AdamW
runs eight element-wise kernels per parameter tensor, the EMA two per state tensor, clipping one norm and one multiply
per gradient, several hundred tensors each. Here the model's floating-point state (its parameters and buffers) is
re-pointed into views of one contiguous buffer, the gradients into another, the optimiser state into a third, in
the order of the optimiser's parameter groups; each operation then runs once per run of consecutive tensors, in
chunks that stay in the CPU cache, instead of once per tensor.

The arithmetic is torch's per-tensor ("single-tensor") arithmetic of ``torch.optim.AdamW`` and ``torch.optim.SGD``,
operation for operation, and every tensor starts on the same 64-byte boundary a fresh allocation has, so weights,
optimiser state and EMA are bit-identical to the torch optimisers' (``tests/test_engine_flat.py`` pins it). What
torch does with a parameter that got no gradient (``grad is None``: no update, no state, no step count, no norm) is
kept: a hook marks the parameters that received a gradient since the last zeroing, and only those are stepped,
clipped and counted. ``state_dict()`` and ``load_state_dict()`` are the wrapped torch optimiser's, in its format,
so a checkpoint written here resumes with torch's optimiser and the other way round.

``FlatState.reason(model, ...)`` says why a model cannot be flattened (a tensor shared by two modules, mixed float
dtypes, a GPU, several processes); the trainer then uses the torch optimiser and the per-tensor EMA as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator, Sequence

import torch
from torch import nn

#: every tensor starts on a multiple of this many elements (64 bytes of float32), as a fresh allocation does
ALIGN = 16
#: elements per chunk of an element-wise pass: the four AdamW arrays of a chunk (4 MB) stay in a CPU's L2/L3 cache
CHUNK = 1 << 18


@dataclass
class Slot:
    """One tensor of the model (a state-dict entry) and where it lives in the flat buffer of its dtype."""

    name: str
    tensor: torch.Tensor
    start: int
    numel: int

    @property
    def end(self) -> int:
        return self.start + self.numel


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def _view(buf: torch.Tensor, like: torch.Tensor, start: int) -> torch.Tensor:
    """A view of ``buf`` at ``start`` with ``like``'s shape and strides (channels-last tensors stay channels-last)."""
    return buf.as_strided(like.shape, like.stride(), start)


def _dense(t: torch.Tensor) -> bool:
    """Its elements fill exactly ``numel`` consecutive memory cells (any order: contiguous or channels-last)."""
    return t.is_contiguous() or t.is_contiguous(memory_format=torch.channels_last)


def chunks(start: int, end: int, size: int = CHUNK) -> Iterator[tuple[int, int]]:
    for s in range(start, end, size):
        yield s, min(end, s + size)


class FlatState:
    """A model's state-dict tensors re-pointed into flat buffers (one per dtype), trainable parameters first in the
    order of ``groups``; gradients of those parameters as views into ``grads``.

    ``touched`` marks the parameters that received a gradient since ``zero_grad()``.
    """

    def __init__(self, model: nn.Module, groups: Sequence[Sequence[nn.Parameter]]):
        why = self.reason(model, groups)
        if why:
            raise ValueError(f"cannot flatten the model: {why}")
        entries = model.state_dict(keep_vars=True)
        by_id = {id(t): k for k, t in entries.items()}
        ordered: list[tuple[str, torch.Tensor]] = [(by_id[id(p)], p) for g in groups for p in g]
        taken = {id(t) for _, t in ordered}
        ordered += [(k, t) for k, t in entries.items() if id(t) not in taken]
        self.params = [p for g in groups for p in g]
        self.slots: dict[torch.dtype, list[Slot]] = {}
        sizes: dict[torch.dtype, int] = {}
        for k, t in ordered:
            n = sizes.get(t.dtype, 0)
            self.slots.setdefault(t.dtype, []).append(Slot(k, t, n, t.numel()))
            sizes[t.dtype] = _aligned(n + t.numel())
        device = next(iter(entries.values())).device
        self.buffers = {dt: torch.zeros(n, dtype=dt, device=device) for dt, n in sizes.items()}
        self.float_dtype = next((dt for dt in self.slots if dt.is_floating_point), torch.float32)
        for dt, slots in self.slots.items():
            buf = self.buffers[dt]
            with torch.no_grad():
                for s in slots:
                    view = _view(buf, s.tensor, s.start)
                    view.copy_(s.tensor)
                    s.tensor.data = view
        fslots = self.slots.get(self.float_dtype, [])
        self.param_slots = fslots[: len(self.params)]
        self.trainable_end = _aligned(self.param_slots[-1].end) if self.param_slots else 0
        self.grads = torch.zeros(self.trainable_end, dtype=self.float_dtype, device=device)
        self.grad_views = []
        for s, p in zip(self.param_slots, self.params):
            g = _view(self.grads, p, s.start)
            p.grad = g
            self.grad_views.append(g)
        self.touched = [False] * len(self.params)
        at = {id(p): i for i, p in enumerate(self.params)}
        # clip_grad_norm_(model.parameters()) stacks the per-tensor norms in the model's order, not the groups'
        self.model_order = [at[id(p)] for p in model.parameters() if id(p) in at]
        self._hooks = [p.register_post_accumulate_grad_hook(self._marker(i)) for i, p in enumerate(self.params)]

    def _marker(self, i: int) -> Any:
        def mark(_: torch.Tensor) -> None:
            self.touched[i] = True

        return mark

    @staticmethod
    def reason(model: nn.Module, groups: Sequence[Sequence[nn.Parameter]]) -> str | None:
        """Why ``model`` cannot be flattened (None when it can)."""
        entries = model.state_dict(keep_vars=True)
        if not entries:
            return "it has no state"
        seen: set[int] = set()
        floats: set[torch.dtype] = set()
        for k, t in entries.items():
            if t.device.type != "cpu":
                return f"{k} is on {t.device} (flat buffers are for the CPU)"
            if id(t) in seen or t.untyped_storage().nbytes() != t.numel() * t.element_size() or not _dense(t):
                return f"{k} shares memory with another tensor or is a view"
            seen.add(id(t))
            if t.dtype.is_floating_point:
                floats.add(t.dtype)
            if t.is_sparse or t.is_quantized:
                return f"{k} is not a dense tensor"
        if len(floats) > 1:
            return f"it mixes floating-point dtypes ({sorted(str(d) for d in floats)})"
        params = [p for g in groups for p in g]
        if len({id(p) for p in params}) != len(params) or any(id(p) not in seen for p in params):
            return "a parameter of the optimiser is not a state-dict entry of the model, or appears twice"
        if any(p.grad is not None for p in params):
            return "its parameters already hold gradients"
        return None

    # ------------------------------------------------------------------ gradients
    def runs(self, lo: int, hi: int, key: Sequence[Any] | None = None) -> Iterator[tuple[int, int, int, int]]:
        """``(first, last + 1, flat start, flat end)`` of each maximal run of touched parameters among indices
        ``lo..hi-1`` that share ``key[i]`` (e.g. the step count)."""
        i = lo
        while i < hi:
            if not self.touched[i]:
                i += 1
                continue
            j = i + 1
            while j < hi and self.touched[j] and (key is None or key[j] == key[i]):
                j += 1
            yield i, j, self.param_slots[i].start, self.param_slots[j - 1].end
            i = j

    def zero_grad(self) -> None:
        self.grads.zero_()
        self.touched = [False] * len(self.params)

    @torch.no_grad()
    def clip_grad_norm_(self, max_norm: float) -> torch.Tensor:
        """``torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm)``: the 2-norm of the per-tensor norms of
        the gradients (in the model's parameter order, as that sum rounds), then every gradient times
        ``min(max_norm / (norm + 1e-6), 1)`` (skipped when that factor is 1)."""
        grads = [self.grad_views[i] for i in self.model_order if self.touched[i]]
        if not grads:
            return torch.tensor(0.0)
        total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2.0)), 2.0)
        coef = torch.clamp(float(max_norm) / (total + 1e-6), max=1.0)
        if float(coef) != 1.0:  # x * 1.0 == x exactly: the multiply only matters below 1 (or for NaN)
            for s, e in chunks(0, self.trainable_end):
                self.grads[s:e].mul_(coef)
        return total

    def same_layout(self, other: nn.Module) -> list[tuple[torch.Tensor, Slot]]:
        """``other``'s state-dict tensors paired with this layout's slots by name (a copy of the same model)."""
        entries = other.state_dict(keep_vars=True)
        return [(entries[s.name], s) for slots in self.slots.values() for s in slots]


class FlatOptimizer:
    """Steps a torch ``AdamW`` or ``SGD`` (its ``param_groups`` and ``state``) on the flat buffers of ``flat``.

    It stands in for the optimiser where the trainer uses one: ``param_groups``, ``step()``, ``zero_grad()``,
    ``state_dict()`` and ``load_state_dict()`` (the torch optimiser's format).
    """

    def __init__(self, opt: torch.optim.Optimizer, flat: FlatState):
        why = self.reason(opt)
        if why:
            raise ValueError(why)
        self.opt, self.flat = opt, flat
        self.adam = isinstance(opt, torch.optim.Adam)
        end, dt, dev = flat.trainable_end, flat.float_dtype, flat.grads.device
        self.steps: list[int] = []  # optimiser steps taken by each parameter (AdamW), torch's per-parameter "step"
        self.has_state: list[bool] = []  # whether the parameter has optimiser state yet (torch: created lazily)
        if self.adam:
            self.exp_avg = torch.zeros(end, dtype=dt, device=dev)
            self.exp_avg_sq = torch.zeros(end, dtype=dt, device=dev)
        else:
            self.momentum = torch.zeros(end, dtype=dt, device=dev)
        self.index = {id(p): i for i, p in enumerate(flat.params)}
        self.group_index: list[tuple[int, int]] = []
        at = 0
        for g in opt.param_groups:
            self.group_index.append((at, at + len(g["params"])))
            at += len(g["params"])
        if [p for g in opt.param_groups for p in g["params"]] != flat.params:
            raise ValueError("the optimiser's parameters are not the flat layout's, in order")
        self._adopt_state()

    @staticmethod
    def reason(opt: Any) -> str | None:
        """Why ``opt`` cannot be stepped here (None when it can): only the plain AdamW and (Nesterov) SGD."""
        if isinstance(opt, torch.optim.AdamW):
            for g in opt.param_groups:
                if (
                    g.get("amsgrad")
                    or g.get("maximize")
                    or g.get("capturable")
                    or g.get("differentiable")
                    or g.get("fused")
                    or not g.get("decoupled_weight_decay", True)
                ):
                    return "AdamW with amsgrad/maximize/capturable/differentiable/fused options"
            return None
        if type(opt) is torch.optim.SGD:
            for g in opt.param_groups:
                if g.get("maximize") or g.get("dampening") or g.get("differentiable") or g.get("fused"):
                    return "SGD with maximize/dampening/differentiable/fused options"
            return None
        return f"{type(opt).__name__} is not AdamW or SGD"

    # ------------------------------------------------------------------ the optimiser interface
    @property
    def param_groups(self) -> list[dict[str, Any]]:
        return self.opt.param_groups

    @property
    def state(self) -> Any:
        return self.opt.state

    def zero_grad(self, set_to_none: bool = True) -> None:  # noqa: ARG002 - gradients stay views, zeroed
        self.flat.zero_grad()

    def state_dict(self) -> dict[str, Any]:
        for i, p in enumerate(self.flat.params):
            if self.has_state[i] and self.adam:
                self.opt.state[p]["step"] = torch.tensor(float(self.steps[i]), dtype=torch.float32)
        return self.opt.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.opt.load_state_dict(state)
        self._adopt_state()

    def _adopt_state(self) -> None:
        """Copy the torch optimiser's per-parameter state into the flat buffers and point it at them."""
        slots = self.flat.param_slots
        self.steps = [0] * len(self.flat.params)
        self.has_state = [False] * len(self.flat.params)
        for i, p in enumerate(self.flat.params):
            st = self.opt.state.get(p)
            if self.adam:
                if st and "exp_avg" in st:
                    for key, buf in (("exp_avg", self.exp_avg), ("exp_avg_sq", self.exp_avg_sq)):
                        view = _view(buf, p, slots[i].start)
                        view.copy_(st[key])
                        st[key] = view
                    self.steps[i] = int(float(st["step"]))
                    self.has_state[i] = True
            elif st and st.get("momentum_buffer") is not None:
                view = _view(self.momentum, p, slots[i].start)
                view.copy_(st["momentum_buffer"])
                st["momentum_buffer"] = view
                self.has_state[i] = True

    @torch.no_grad()
    def step(self) -> None:
        f = self.flat
        for g, (lo, hi) in zip(self.opt.param_groups, self.group_index):
            if self.adam:
                for a, b, s, e in f.runs(lo, hi, self.steps):
                    self._adamw(g, a, b, s, e)
            else:
                for a, b, s, e in f.runs(lo, hi, self.has_state):
                    self._sgd(g, a, b, s, e)

    def _new_state(self, a: int, b: int) -> None:
        slots, params = self.flat.param_slots, self.flat.params
        for i in range(a, b):
            if self.has_state[i]:
                continue
            p, start = params[i], slots[i].start
            if self.adam:
                self.opt.state[p] = {
                    "step": torch.tensor(0.0),
                    "exp_avg": _view(self.exp_avg, p, start),
                    "exp_avg_sq": _view(self.exp_avg_sq, p, start),
                }
            else:
                self.opt.state[p] = {"momentum_buffer": _view(self.momentum, p, start)}
            self.has_state[i] = True

    def _adamw(self, g: dict[str, Any], a: int, b: int, s: int, e: int) -> None:
        """``torch.optim.adam._single_tensor_adam`` (decoupled weight decay), on ``[s, e)``."""
        self._new_state(a, b)
        step = self.steps[a] + 1
        for i in range(a, b):
            self.steps[i] = step
        lr, wd, eps = g["lr"], g["weight_decay"], g["eps"]
        beta1, beta2 = g["betas"]
        bias_correction1 = 1 - beta1 ** float(step)
        bias_correction2 = 1 - beta2 ** float(step)
        step_size = lr / bias_correction1
        bias_correction2_sqrt = bias_correction2**0.5
        p_all, g_all, m_all, v_all = (
            self.flat.buffers[self.flat.float_dtype],
            self.flat.grads,
            self.exp_avg,
            self.exp_avg_sq,
        )
        for c0, c1 in chunks(s, e):
            param, grad, exp_avg, exp_avg_sq = p_all[c0:c1], g_all[c0:c1], m_all[c0:c1], v_all[c0:c1]
            if wd != 0:
                param.mul_(1 - lr * wd)
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(eps)
            param.addcdiv_(exp_avg, denom, value=-step_size)

    def _sgd(self, g: dict[str, Any], a: int, b: int, s: int, e: int) -> None:
        """``torch.optim.sgd._single_tensor_sgd``, on ``[s, e)`` (all with or all without a momentum buffer)."""
        first = not self.has_state[a]
        lr, wd, momentum, nesterov = g["lr"], g["weight_decay"], g["momentum"], g["nesterov"]
        if momentum != 0:
            self._new_state(a, b)
        p_all, g_all, buf_all = self.flat.buffers[self.flat.float_dtype], self.flat.grads, self.momentum
        for c0, c1 in chunks(s, e):
            param, grad = p_all[c0:c1], g_all[c0:c1]
            if wd != 0:
                grad = grad.add(param, alpha=wd)
            if momentum != 0:
                buf = buf_all[c0:c1]
                if first:
                    buf.copy_(grad)
                else:
                    buf.mul_(momentum).add_(grad, alpha=1)
                grad = grad.add(buf, alpha=momentum) if nesterov else buf
            param.add_(grad, alpha=-lr)


class FlatEMA:
    """The EMA update ``ema = d * ema + (1 - d) * model`` (integer entries copied) over an EMA copy whose tensors were
    re-pointed into flat buffers laid out like the model's ``FlatState``: two kernels per chunk in all."""

    def __init__(self, ema_module: nn.Module, flat: FlatState):
        self.flat = flat
        self.buffers = {dt: torch.zeros_like(b) for dt, b in flat.buffers.items()}
        with torch.no_grad():
            for t, slot in flat.same_layout(ema_module):
                if t.shape != slot.tensor.shape or t.dtype != slot.tensor.dtype:
                    raise ValueError(f"the EMA copy's {slot.name} does not match the model's")
                view = _view(self.buffers[t.dtype], slot.tensor, slot.start)
                view.copy_(t)
                t.data = view

    @torch.no_grad()
    def update(self, d: float) -> None:
        for dt, buf in self.buffers.items():
            src = self.flat.buffers[dt]
            if dt.is_floating_point:
                for s, e in chunks(0, buf.numel()):
                    buf[s:e].mul_(d).add_(src[s:e], alpha=1 - d)
            else:
                buf.copy_(src)
