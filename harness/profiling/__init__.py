"""Profiling: parameters, FLOPs in labelled conventions, latency, ONNX export. Definitions in ``docs/evaluation.md``.

    profile_model(model, example_inputs) -> dict          any module following the detector contract
    profile_detector(name, imgsz=640, num_classes=8) -> dict   a registered detector, built and profiled
    export_onnx(model, example_inputs, path) -> dict       raw forward to ONNX, checked against torch

``example_inputs`` is a tensor ``[B, 3 + c, H, W]`` (single-stream) or a tuple ``(rgb, thermal)`` (dual-stream).
"""

from __future__ import annotations

import logging
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

from harness.profiling.model_io import ProfilingError, as_tuple, example_inputs, fused_copy, is_dual

log = logging.getLogger(__name__)

__all__ = ["ProfilingError", "example_inputs", "export_detector", "export_onnx", "profile_detector", "profile_model"]

CONVENTIONS = {
    "paper": "BatchNorm folded, module-level count with thop-0.1.1 rules, 1 MAC = 2 FLOPs (no attention matmuls)",
    "exact": "torch.utils.flop_counter.FlopCounterMode on the meta device: every matmul-type op incl. attention, "
    "1 MAC = 2 FLOPs; no norms, activations, pooling or upsampling",
    "fvcore": "fvcore FlopCountAnalysis (jit trace): conv, linear, matmul, einsum, norms, upsampling; MACs x 2",
}


def export_onnx(*args: Any, **kwargs: Any) -> dict[str, Any]:
    from harness.profiling.export import export_onnx as _export

    return _export(*args, **kwargs)


def _guarded(what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
    """Run an optional view; a failure is recorded as {"error": ...} instead of losing the rest of the profile."""
    try:
        return fn(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001
        msg = f"{type(exc).__name__}: {exc}"
        log.warning("%s failed: %s", what, msg)
        return {"error": msg}


def profile_model(
    model: Any,
    example_inputs: Any,
    *,
    latency: bool = True,
    onnx: bool = True,
    fvcore: bool = True,
    warmup: int = 10,
    runs: int = 50,
    threads: int | None = None,
    device: str = "cpu",
    onnx_path: str | Path | None = None,
    table_depth: int = 3,
) -> dict[str, Any]:
    """Parameters, FLOPs ("paper", "exact", fvcore), torch-eager and onnxruntime latency of one model.

    The model is profiled as built for the parameter counts and the reachability analysis, and BN-folded (its
    ``fuse()``) for everything that describes inference: fused parameters, FLOPs, latency and export.
    """
    import torch

    from harness.profiling.flops import exact_flops, fvcore_flops, paper_flops
    from harness.profiling.params import count_parameters, reachable_parameters

    inputs = as_tuple(example_inputs)
    t_start = time.perf_counter()
    params = reachable_parameters(model, example_inputs)
    fused, did_fuse = fused_copy(model)
    fused_total, _, _ = count_parameters(fused)
    out: dict[str, Any] = {
        "input": {"kind": "dual" if is_dual(example_inputs) else "single", "shapes": [list(t.shape) for t in inputs]},
        "params": {**params.as_dict(), "fused": fused_total, "bn_folded": did_fuse},
    }
    paper = paper_flops(fused, example_inputs)
    exact = exact_flops(fused, example_inputs)
    flops: dict[str, Any] = {
        "paper": {
            "gflops": paper.gflops,
            "flops": paper.flops,
            "convention": CONVENTIONS["paper"],
            "modules_without_rule": paper.not_counted,
        },
        "exact": {"gflops": exact.gflops, "flops": exact.flops, "convention": CONVENTIONS["exact"]},
    }
    by_module = {"paper": _top_level(paper.by_module), "exact": _top_level(exact.by_module)}
    if fvcore:
        fv = _guarded("fvcore FLOP count", fvcore_flops, fused, example_inputs, table_depth)
        if isinstance(fv, dict):
            flops["fvcore"] = fv
        else:
            flops["fvcore"] = {
                "gflops": fv.gflops,
                "flops": fv.flops,
                "convention": CONVENTIONS["fvcore"],
                "skipped_ops": fv.not_counted,
                "table": fv.table,
            }
            by_module["fvcore"] = _top_level(fv.by_module)
    out["flops"] = flops
    out["by_module"] = by_module

    n_threads = threads or torch.get_num_threads()
    if latency:
        from harness.profiling.latency import onnx_latency, torch_latency

        lat: dict[str, Any] = {
            "torch": _guarded("torch latency", torch_latency, fused, example_inputs, warmup, runs, n_threads, device)
        }
        if onnx:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(onnx_path) if onnx_path else Path(tmp) / "model.onnx"
                record = _guarded("ONNX export", export_onnx, fused, example_inputs, path, fuse=False)
                out["onnx"] = record
                if "error" not in record:
                    providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if device.startswith("cuda") else None
                    lat["onnxruntime"] = _guarded(
                        "onnxruntime latency",
                        onnx_latency,
                        str(path),
                        example_inputs,
                        warmup,
                        runs,
                        n_threads,
                        providers,
                    )
        out["latency"] = lat
    out["environment"] = {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "profile_time_s": round(time.perf_counter() - t_start, 2),
    }
    return out


def _top_level(by_module: dict[str, int]) -> dict[str, int]:
    """Per-module FLOPs summed to the model's direct children (``backbone.0.conv`` -> ``backbone``)."""
    out: dict[str, int] = {}
    for name, flops in by_module.items():
        top = name.split(".")[0]
        out[top] = out.get(top, 0) + flops
    return out


def build_detector(
    name: str, num_classes: int = 8, in_channels: int = 4, host: Any = None, model_options: dict[str, Any] | None = None
) -> tuple[Any, Any]:
    """(spec, model) of a registered detector, built for ``num_classes``, the input the spec declares and the model
    options of a run configuration (``model`` section: ``--set model.scale=n``)."""
    from harness.plugins import get_host

    spec = (host or get_host()).detector(name)
    channels = spec.model_channels(in_channels)
    options = dict(model_options or {})
    try:
        model = spec.build(num_classes, in_channels=channels, **options)
    except Exception as exc:
        raise ProfilingError(
            f"detector {name!r} could not be built (num_classes={num_classes}, "
            f"in_channels={channels}, model options {options}): {type(exc).__name__}: {exc}"
        ) from exc
    from harness.contracts import check_built_model, plugin_label
    from harness.profiling.model_io import check_input_channels

    check_built_model(model, spec.name)
    check_input_channels(model, plugin_label("detector", spec.name), spec.input_kind, channels, spec.thermal_channels)
    return spec, model.eval()


def _raw_forward_of(spec: Any, model: Any) -> None:
    """Profiling and export of a registered detector need its ``forward_raw`` (``require_forward_raw``)."""
    from harness.contracts import plugin_label
    from harness.profiling.model_io import require_forward_raw

    require_forward_raw(model, plugin_label("detector", spec.name))


def profile_detector(
    name: str,
    imgsz: int = 640,
    num_classes: int = 8,
    in_channels: int = 4,
    host: Any = None,
    model_options: dict[str, Any] | None = None,
    **kwargs: Any,
) -> dict[str, Any]:
    """Build a registered detector and profile it at ``imgsz`` x ``imgsz``, batch 1, both inputs when dual-stream."""
    spec, model = build_detector(name, num_classes, in_channels, host, model_options)
    _raw_forward_of(spec, model)
    inputs = example_inputs(spec.input_kind, imgsz, 1, in_channels, spec.thermal_channels)
    result = profile_model(model, inputs, **kwargs)
    ref = spec.reference
    return {
        "detector": spec.name,
        "label": spec.label,
        "input_kind": spec.input_kind,
        "imgsz": imgsz,
        "num_classes": num_classes,
        "model_options": dict(model_options or {}),
        "reference": (
            None
            if ref is None or not ref.applies(num_classes, imgsz, model_options)
            else {"params_m": ref.params_m, "gflops": ref.gflops, "source": ref.source}
        ),
        **result,
    }


def export_detector(
    name: str,
    path: str | Path,
    imgsz: int = 640,
    num_classes: int = 8,
    in_channels: int = 4,
    host: Any = None,
    **kwargs: Any,
) -> dict[str, Any]:
    """``harness export``: a registered detector's raw forward to ONNX, checked against torch."""
    spec, model = build_detector(name, num_classes, in_channels, host)
    _raw_forward_of(spec, model)
    inputs = example_inputs(spec.input_kind, imgsz, 1, in_channels, spec.thermal_channels)
    return {"detector": spec.name, "input_kind": spec.input_kind, **export_onnx(model, inputs, path, **kwargs)}
