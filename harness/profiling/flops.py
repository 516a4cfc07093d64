"""FLOP counts in three labelled conventions. Every figure is FLOPs with one multiply-add = 2 FLOPs.

``paper``  BatchNorm folded into the convolutions (the model's ``fuse()``), then a module-level count with the
           per-module rules of thop 0.1.1 (Lyken17/pytorch-OpCounter, MIT), doubled. This is how the seed (and the
           YOLOv5/Ultralytics tooling) made its table. Rules, per call of a module whose exact type is listed:

             Conv{1,2,3}d, ConvTranspose{1,2,3}d   numel(out) * (C_in / groups) * prod(kernel)   (bias not counted)
             Linear                                in_features * numel(out)
             BatchNorm*, LayerNorm, InstanceNorm*  2 * numel(in), doubled when affine
             Softmax                               rows * (3 * features - 1)
             AvgPool*                              numel(out)
             AdaptiveAvgPool*                      int((prod(in / out spatial) + 1) * numel(out))
             Upsample, Upsampling{Nearest,Bilinear}2d   numel(out) * {nearest 1, linear 5, bilinear 11, bicubic 259}
             PReLU (eval)                          numel(in)
             ReLU, ReLU6, LeakyReLU, MaxPool*, AdaptiveMaxPool*, Dropout, ZeroPad2d, PixelShuffle, Sequential   0

           Anything else (activations such as SiLU, functional calls such as ``torch.matmul``, ``F.interpolate``,
           ``F.scaled_dot_product_attention``, element-wise arithmetic) is not counted: attention matmuls are
           missing from this convention, exactly as in the seed's figures. A module with a rule is counted as a
           whole (its children are not visited), as thop does.
``exact``  ``torch.utils.flop_counter.FlopCounterMode`` on the meta device (model and inputs), which counts every
           matmul-type ATen op (mm, addmm, bmm, baddbmm, convolution, attention kernels) and nothing else (no
           norms, activations, pooling or upsampling). On real CPU tensors it misses fused CPU attention kernels;
           on meta they decompose into counted matmuls.
``fvcore`` fvcore's ``FlopCountAnalysis`` (jit trace), a third view with its per-module table; fvcore reports
           multiply-adds, shown here doubled. It counts conv, linear, matmul, einsum, norms and upsampling, and
           lists the operators it skipped.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Callable

import torch
from torch import nn

from harness.profiling.model_io import ProfilingError, RawForward, as_tuple, is_dual, strip_prefix, to_meta

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------- paper convention
def _conv(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    return y.numel() * (x.shape[1] // m.groups) * math.prod(m.weight.shape[2:])


def _norm(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    flops = 2 * x.numel()
    if getattr(m, "affine", False) or getattr(m, "elementwise_affine", False):
        flops *= 2
    return flops


def _softmax(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    dim = m.dim if m.dim is not None else -1
    features = x.shape[dim]
    return (x.numel() // features) * (3 * features - 1)


def _avgpool(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    return y.numel()


def _adaptive_avgpool(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    kernel = math.prod(float(a) / float(b) for a, b in zip(x.shape[2:], y.shape[2:]))
    return int((kernel + 1) * y.numel())


_UPSAMPLE = {"nearest": 1, "linear": 5, "bilinear": 11, "bicubic": 224 + 35}


def _upsample(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    if m.mode not in _UPSAMPLE:
        log.warning("paper FLOPs: upsample mode %r has no rule (counted as 0, as thop does)", m.mode)
        return 0
    return int(y.numel() * _UPSAMPLE[m.mode])


def _linear(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    return m.in_features * y.numel()


def _prelu(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    return 0 if m.training else x.numel()


def _zero(m: Any, x: torch.Tensor, y: torch.Tensor) -> int:
    return 0


#: exact module type -> MACs of one call (thop 0.1.1's table; RNN modules are not covered)
PAPER_RULES: dict[type, Callable[[nn.Module, torch.Tensor, torch.Tensor], int]] = {
    nn.ZeroPad2d: _zero,
    nn.Conv1d: _conv,
    nn.Conv2d: _conv,
    nn.Conv3d: _conv,
    nn.ConvTranspose1d: _conv,
    nn.ConvTranspose2d: _conv,
    nn.ConvTranspose3d: _conv,
    nn.BatchNorm1d: _norm,
    nn.BatchNorm2d: _norm,
    nn.BatchNorm3d: _norm,
    nn.SyncBatchNorm: _norm,
    nn.LayerNorm: _norm,
    nn.InstanceNorm1d: _norm,
    nn.InstanceNorm2d: _norm,
    nn.InstanceNorm3d: _norm,
    nn.PReLU: _prelu,
    nn.Softmax: _softmax,
    nn.ReLU: _zero,
    nn.ReLU6: _zero,
    nn.LeakyReLU: _zero,
    nn.MaxPool1d: _zero,
    nn.MaxPool2d: _zero,
    nn.MaxPool3d: _zero,
    nn.AdaptiveMaxPool1d: _zero,
    nn.AdaptiveMaxPool2d: _zero,
    nn.AdaptiveMaxPool3d: _zero,
    nn.AvgPool1d: _avgpool,
    nn.AvgPool2d: _avgpool,
    nn.AvgPool3d: _avgpool,
    nn.AdaptiveAvgPool1d: _adaptive_avgpool,
    nn.AdaptiveAvgPool2d: _adaptive_avgpool,
    nn.AdaptiveAvgPool3d: _adaptive_avgpool,
    nn.Linear: _linear,
    nn.Dropout: _zero,
    nn.Upsample: _upsample,
    nn.UpsamplingBilinear2d: _upsample,
    nn.UpsamplingNearest2d: _upsample,
    nn.Sequential: _zero,
    nn.PixelShuffle: _zero,
}


@dataclass
class FlopReport:
    convention: str
    flops: int
    #: FLOPs per module (paper: every counted module; exact and fvcore: the model's direct children)
    by_module: dict[str, int] = field(default_factory=dict)
    #: module types that ran with no rule (paper) or operators skipped (fvcore)
    not_counted: list[str] = field(default_factory=list)
    table: str = ""

    @property
    def gflops(self) -> float:
        return self.flops / 1e9


def paper_flops(model: nn.Module, example_inputs: Any, on_meta: bool = True) -> FlopReport:
    """The "paper" count of ``model`` as given (fold BN first: pass a fused model). 1 MAC = 2 FLOPs."""
    dual = is_dual(example_inputs)
    net = to_meta(model) if on_meta else model
    wrapper = RawForward(net, dual).eval()
    ops: dict[int, int] = defaultdict(int)
    no_rule: set[str] = set()
    handles = []

    def hook(rule: Callable) -> Callable:
        def _hook(m: nn.Module, inputs: tuple, output: Any) -> None:
            x = inputs[0] if inputs else None
            y = output[0] if isinstance(output, (tuple, list)) else output
            if isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor):
                ops[id(m)] += int(rule(m, x, y))

        return _hook

    def note(m: nn.Module, inputs: tuple) -> None:
        if not list(m.children()) and next(m.parameters(recurse=False), None) is not None:
            no_rule.add(type(m).__name__)  # a leaf with weights but no rule (e.g. a Linear subclass): counted as 0

    for m in wrapper.modules():
        rule = PAPER_RULES.get(type(m))
        if rule is not None:
            handles.append(m.register_forward_hook(hook(rule)))
        else:
            handles.append(m.register_forward_pre_hook(note))
    inputs = tuple(t.to("meta") for t in as_tuple(example_inputs)) if on_meta else as_tuple(example_inputs)
    try:
        with torch.no_grad():
            wrapper(*inputs)
    except Exception as exc:
        if on_meta:
            log.info("paper FLOPs: forward on the meta device failed (%s); counting on real tensors", exc)
            for h in handles:
                h.remove()
            return paper_flops(model, example_inputs, on_meta=False)
        raise ProfilingError(f"forward_raw failed while counting FLOPs: {type(exc).__name__}: {exc}") from exc
    finally:
        for h in handles:
            h.remove()

    by_module: dict[str, int] = {}

    def dfs(module: nn.Module, prefix: str) -> int:  # thop's traversal: a module with a rule is not descended into
        total = ops.get(id(module), 0) if prefix == "" else 0
        for name, child in module.named_children():
            full = f"{prefix}.{name}" if prefix else name
            if type(child) in PAPER_RULES and not isinstance(child, (nn.Sequential, nn.ModuleList)):
                n = ops.get(id(child), 0)
                if n:
                    by_module[strip_prefix(full)] = by_module.get(strip_prefix(full), 0) + 2 * n
            else:
                n = dfs(child, full)
            total += n
        return total

    macs = dfs(wrapper, "")
    return FlopReport("paper", 2 * macs, by_module, sorted(no_rule))


# --------------------------------------------------------------------------------------------- exact convention
def exact_flops(model: nn.Module, example_inputs: Any) -> FlopReport:
    """``FlopCounterMode`` with model and inputs on the meta device; counts attention matmuls."""
    from torch.utils.flop_counter import FlopCounterMode

    dual = is_dual(example_inputs)
    wrapper = RawForward(to_meta(model), dual).eval()
    inputs = tuple(t.to("meta") for t in as_tuple(example_inputs))
    counter = FlopCounterMode(display=False)
    try:
        with counter, torch.no_grad():
            wrapper(*inputs)
    except Exception as exc:
        raise ProfilingError(
            f"forward_raw failed on the meta device under FlopCounterMode: {type(exc).__name__}: {exc}"
        ) from exc
    by_module = {}
    for name, counts in counter.get_flop_counts().items():
        short = name.split(".", 1)[1] if "." in name else ""
        short = strip_prefix(short)
        if short and "." not in short:
            by_module[short] = int(sum(counts.values()))
    return FlopReport("exact", int(counter.get_total_flops()), by_module)


# --------------------------------------------------------------------------------------------- fvcore view
def fvcore_flops(model: nn.Module, example_inputs: Any, max_depth: int = 3) -> FlopReport:
    """fvcore's count (multiply-adds, doubled here) and its per-module table; needs real (CPU) tensors."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # fvcore.nn calls torch.jit.script at import time
        from fvcore.nn import FlopCountAnalysis, flop_count_table

    dual = is_dual(example_inputs)
    wrapper = RawForward(model, dual).eval()
    inputs = as_tuple(example_inputs)
    analysis = FlopCountAnalysis(wrapper, inputs)
    analysis.unsupported_ops_warnings(False)
    analysis.uncalled_modules_warnings(False)
    analysis.tracer_warnings("none")
    fv_logger = logging.getLogger("fvcore")
    level = fv_logger.level
    fv_logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), torch.no_grad():
            warnings.simplefilter("ignore")
            total = analysis.total()
            by_module = {
                strip_prefix(k): 2 * int(v)
                for k, v in analysis.by_module().items()
                if k and strip_prefix(k) and "." not in strip_prefix(k)
            }
            skipped = sorted(f"{op} (x{n})" for op, n in analysis.unsupported_ops().items())
            table = flop_count_table(analysis, max_depth=max_depth)
    except Exception as exc:
        raise ProfilingError(f"fvcore could not trace the model: {type(exc).__name__}: {exc}") from exc
    finally:
        fv_logger.setLevel(level)
    table = table.replace("| model.", "| ").replace("| model ", "|  ")
    return FlopReport(
        "fvcore",
        2 * int(total),
        by_module,
        skipped,
        "fvcore per-module table (fvcore units: multiply-adds; the harness reports 2x):\n" + table,
    )
