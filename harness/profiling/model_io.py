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


def require_forward_raw(model: nn.Module, label: str) -> None:
    """Refuse (``ProfilingError`` naming ``label``, e.g. ``detector 'x' (plugin p)``) a detector model without
    ``forward_raw``: its ``forward`` decodes and runs NMS, which neither a FLOP count nor an exported graph may hold
    (``RawForward`` falls back to ``forward`` only for plain modules, not for a detector)."""
    fn = getattr(model, "forward_raw", None)
    if not callable(fn):
        raise ProfilingError(
            f"{label}: the model ({type(model).__name__}) has no forward_raw(inputs); profiling and ONNX export "
            f"count and capture the raw head outputs without decoding or NMS, so the detector contract asks for "
            f"model.forward_raw (docs/plugins.md, 'The detector contract')"
        )


def check_input_channels(
    model: nn.Module, label: str, input_kind: str, in_channels: int, thermal_channels: int, imgsz: int = 64
) -> None:
    """Run ``forward_raw`` once on the meta device (shapes only) with the input the host will give; a model built
    for another channel count stops with a ``PluginError`` naming ``label`` and the contract, instead of a
    traceback from inside torch at the first batch. Other failures on the meta device say nothing here."""
    from harness.errors import PluginError

    fn = getattr(model, "forward_raw", None)
    if not callable(fn):
        return
    inputs = example_inputs(input_kind, imgsz, 1, in_channels, thermal_channels, device="meta")
    shapes = [list(t.shape) for t in as_tuple(inputs)]
    try:
        with torch.no_grad():
            RawForward(to_meta(model), is_dual(inputs)).eval()(*as_tuple(inputs))
    except Exception as exc:  # noqa: BLE001 - only a channel mismatch is this check's business
        text = str(exc)
        if "channel" in text.lower():
            what = (
                f"in_channels={in_channels}"
                if input_kind == "single"
                else f"in_channels={thermal_channels} (the thermal stream; RGB has 3)"
            )
            raise PluginError(
                f"{label}: build(num_classes, {what}) made a model that does not take that input: forward_raw on "
                f"{' and '.join(map(str, shapes))} raised {type(exc).__name__}: {text.splitlines()[0]}. The model "
                f"must be built for the in_channels the host passes (docs/plugins.md, 'The detector contract')"
            ) from None


def to_meta(model: nn.Module) -> nn.Module:
    """A copy of ``model`` on the meta device (shapes only, no memory, no compute)."""
    return copy.deepcopy(model).to("meta")


def strip_prefix(name: str, prefix: str = "model.") -> str:
    return name[len(prefix) :] if name.startswith(prefix) else (name if name != "model" else "")
