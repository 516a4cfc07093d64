"""How profiling sees a detector: example inputs of the detector contract and a tensor-in, tensors-out wrapper.

A single-stream detector takes ``[B, 3 + c, H, W]``; a dual-stream one takes a tuple ``(rgb [B,3,H,W],
thermal [B,Ct,H,W])``. ``RawForward`` turns ``model.forward_raw(inputs)`` (raw head outputs, no decoding, no NMS)
into ``forward(*tensors) -> tuple[Tensor, ...]``, the shape every counter, tracer and exporter wants.
"""

from __future__ import annotations

import copy
from typing import Any, Iterator, Sequence

import torch
from torch import nn

from harness.errors import HarnessError


class ProfilingError(HarnessError):
    """A model cannot be profiled or exported as asked (no forward_raw, an op that fails, outputs that differ)."""


def flatten_tensors(out: Any) -> Iterator[torch.Tensor]:
    """Every tensor in a (nested) tuple, list or dict of outputs, in order."""
    if isinstance(out, torch.Tensor):
        yield out
    elif isinstance(out, dict):
        for v in out.values():
            yield from flatten_tensors(v)
    elif isinstance(out, (list, tuple)):
        for v in out:
            yield from flatten_tensors(v)


class _Raw(nn.Module):
    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def _raw(self, inputs: Any) -> tuple[torch.Tensor, ...]:
        fn = getattr(self.model, "forward_raw", None) or self.model.forward
        return tuple(flatten_tensors(fn(inputs)))


class RawForwardSingle(_Raw):
    """``forward(images)`` -> ``model.forward_raw(images)`` as a flat tuple of tensors."""

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self._raw(images)


class RawForwardDual(_Raw):
    """``forward(rgb, thermal)`` -> ``model.forward_raw((rgb, thermal))`` as a flat tuple of tensors."""

    def forward(self, rgb: torch.Tensor, thermal: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self._raw((rgb, thermal))


def RawForward(model: nn.Module, dual: bool) -> nn.Module:  # noqa: N802 (reads as a class at call sites)
    """The tensor-in, tensors-out wrapper of ``model.forward_raw`` for a single- or dual-stream detector."""
    return RawForwardDual(model) if dual else RawForwardSingle(model)


def as_tuple(example_inputs: Any) -> tuple[torch.Tensor, ...]:
    """Example inputs as a tuple of tensors: a tensor (single-stream) or a (rgb, thermal) pair (dual-stream)."""
    if isinstance(example_inputs, torch.Tensor):
        return (example_inputs,)
    if isinstance(example_inputs, (list, tuple)) and all(isinstance(t, torch.Tensor) for t in example_inputs):
        return tuple(example_inputs)
    raise ProfilingError("example inputs must be a tensor [B, C, H, W] or a tuple (rgb, thermal) of tensors")


def is_dual(example_inputs: Any) -> bool:
    return not isinstance(example_inputs, torch.Tensor)


def example_inputs(
    input_kind: str,
    imgsz: int | Sequence[int] = 640,
    batch: int = 1,
    channels: int = 4,
    thermal_channels: int = 3,
    device: str | torch.device = "cpu",
    seed: int = 0,
) -> Any:
    """Inputs of the detector contract in 0..1: ``[B, channels, H, W]`` or ``(rgb, thermal)``."""
    h, w = (imgsz, imgsz) if isinstance(imgsz, int) else tuple(imgsz)
    if str(device) == "meta":
        make = lambda c: torch.empty(batch, c, h, w, device="meta")  # noqa: E731
    else:
        gen = torch.Generator().manual_seed(seed)
        make = lambda c: torch.rand(batch, c, h, w, generator=gen).to(device)  # noqa: E731
    if input_kind == "dual":
        return (make(3), make(thermal_channels))
    return make(channels)


def fused_copy(model: nn.Module) -> tuple[nn.Module, bool]:
    """An eval-mode deep copy with BatchNorm folded by the model's declared fold (``harness.contracts.fold_batchnorm``:
    ``harness_fuse()`` or a ``fuse()`` method of its class; never an attribute that happens to be named ``fuse``)."""
    from harness.contracts import fold_batchnorm

    m, folded = fold_batchnorm(copy.deepcopy(model).eval())
    return m.eval(), folded


def to_meta(model: nn.Module) -> nn.Module:
    """A copy of ``model`` on the meta device (shapes only, no memory, no compute)."""
    return copy.deepcopy(model).to("meta")


def strip_prefix(name: str, prefix: str = "model.") -> str:
    return name[len(prefix) :] if name.startswith(prefix) else (name if name != "model" else "")
