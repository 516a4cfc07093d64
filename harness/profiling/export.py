"""ONNX export of a detector's raw forward (NMS stays outside the graph) and the check against torch.

Single-stream models get one input ``images``; dual-stream models get two, ``rgb`` and ``thermal``. Outputs are
the tensors of ``forward_raw`` in order, named ``output0``, ``output1``, ... The exporter is torch's dynamo-based
one (``torch.onnx.export(..., dynamo=True)``, needs onnxscript); if it fails, the TorchScript-based exporter is
tried and the result says which one was used. After export, onnxruntime runs the file on the example inputs and
every output must match torch within ``atol`` (default 1e-4), otherwise ``ExportError`` names the output.
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from harness.profiling.model_io import ProfilingError, RawForward, as_tuple, fused_copy, is_dual

log = logging.getLogger(__name__)

DEFAULT_OPSET = 18


class ExportError(ProfilingError):
    """ONNX export failed or its outputs do not match torch."""


class _Export(NamedTuple):
    """What either exporter is given: the wrapped model, its example inputs, the output file, the graph's input and
    output names, the opset and whether the batch dimension is dynamic."""

    wrapper: nn.Module
    inputs: tuple
    path: Path
    names_in: list[str]
    names_out: list[str]
    opset: int
    dynamic_batch: bool

    def graph_options(self) -> dict[str, Any]:
        """The ``torch.onnx.export`` keywords both exporters pass alike: the graph's names and the opset."""
        return {"input_names": self.names_in, "output_names": self.names_out, "opset_version": self.opset}


def input_names(dual: bool) -> list[str]:
    return ["rgb", "thermal"] if dual else ["images"]


def export_onnx(
    model: nn.Module,
    example_inputs: Any,
    path: str | Path,
    opset: int = DEFAULT_OPSET,
    fuse: bool = True,
    dynamic_batch: bool = False,
    check: bool = True,
    atol: float = 1e-4,
) -> dict[str, Any]:
    """Export ``model.forward_raw`` to ``path``; returns a record of what was exported and how well it matches."""
    if opset < 17:
        raise ExportError(f"opset {opset} is too old: use 17 or newer")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    net, fused = fused_copy(model) if fuse else (model.eval(), False)
    dual = is_dual(example_inputs)
    wrapper = RawForward(net, dual).eval()
    inputs = tuple(t.detach().cpu() for t in as_tuple(example_inputs))
    with torch.no_grad():
        expected = wrapper(*inputs)
    names_in = input_names(dual)
    names_out = [f"output{i}" for i in range(len(expected))]
    exporter = "dynamo"
    job = _Export(wrapper, inputs, path, names_in, names_out, opset, dynamic_batch)
    try:
        _export_dynamo(job)
    except Exception as exc:  # noqa: BLE001 (any exporter failure: try the other exporter, then report both)
        first = re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).strip().splitlines()
        log.warning(
            "dynamo ONNX export failed (%s: %s); trying the TorchScript-based exporter",
            type(exc).__name__,
            first[0] if first else "",
        )
        exporter = "torchscript"
        try:
            _export_torchscript(job)
        except Exception as exc2:
            raise ExportError(
                f"ONNX export of the model failed with both exporters: dynamo: {exc}; "
                f"torchscript: {type(exc2).__name__}: {exc2}"
            ) from exc2
    record: dict[str, Any] = {
        "path": str(path),
        "opset": _file_opset(path),
        "exporter": exporter,
        "fused": fused,
        "inputs": {n: list(t.shape) for n, t in zip(names_in, inputs)},
        "outputs": {n: list(t.shape) for n, t in zip(names_out, expected)},
        "dynamic_batch": dynamic_batch,
        "nms_in_graph": False,
    }
    if check:
        record.update(check_onnx(path, inputs, expected, atol=atol))
    return record


def _export_dynamo(job: _Export) -> None:
    wrapper, inputs = job.wrapper, job.inputs
    kwargs: dict[str, Any] = {}
    if job.dynamic_batch:
        batch = torch.export.Dim("batch", min=1, max=1024)
        kwargs["dynamic_shapes"] = tuple({0: batch} for _ in inputs)
        if inputs[0].shape[0] == 1:  # torch.export specialises a dimension whose example size is 1
            inputs = tuple(t.expand(2, *t.shape[1:]).contiguous() for t in inputs)
    quiet = logging.getLogger("torch.onnx")  # e.g. "torchvision is not installed. Skipping torchvision::nms"
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), _restore_level(quiet, level):
        warnings.simplefilter("ignore")
        program = torch.onnx.export(wrapper, inputs, dynamo=True, verbose=False, **job.graph_options(), **kwargs)
        program.save(str(job.path))  # type: ignore[union-attr]


@contextlib.contextmanager
def _restore_level(logger: logging.Logger, level: int) -> Any:
    try:
        yield
    finally:
        logger.setLevel(level)


def _export_torchscript(job: _Export) -> None:
    axes = {n: {0: "batch"} for n in job.names_in + job.names_out} if job.dynamic_batch else None
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        torch.onnx.export(
            job.wrapper, job.inputs, str(job.path), dynamo=False, dynamic_axes=axes, **job.graph_options()
        )


def _file_opset(path: Path) -> int | None:
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return next((int(o.version) for o in model.opset_import if o.domain in ("", "ai.onnx")), None)


def ort_session(path: str | Path, threads: int | None = None, providers: list[str] | None = None) -> Any:
    """An onnxruntime session with pinned settings (sequential execution, all graph optimisations)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.inter_op_num_threads = 1
    if threads:
        opts.intra_op_num_threads = int(threads)
    opts.log_severity_level = 3
    available = ort.get_available_providers()
    wanted = providers or ["CPUExecutionProvider"]
    use = [p for p in wanted if p in available] or ["CPUExecutionProvider"]
    session = ort.InferenceSession(str(path), sess_options=opts, providers=use)
    return session


def check_onnx(
    path: str | Path, inputs: tuple[torch.Tensor, ...], expected: tuple[torch.Tensor, ...], atol: float = 1e-4
) -> dict[str, Any]:
    """Run the file in onnxruntime and compare every output with torch's; raises ``ExportError`` beyond ``atol``."""
    session = ort_session(path)
    feeds = {i.name: t.numpy() for i, t in zip(session.get_inputs(), inputs)}
    got = session.run(None, feeds)
    if len(got) != len(expected):
        raise ExportError(f"{path}: onnxruntime returned {len(got)} outputs, torch {len(expected)}")
    diffs = []
    for i, (a, b) in enumerate(zip(got, expected)):
        b_np = b.detach().cpu().numpy()
        if a.shape != b_np.shape:
            raise ExportError(
                f"{path}: output{i} has shape {list(a.shape)} in onnxruntime, {list(b_np.shape)} in torch"
            )
        diffs.append(float(np.max(np.abs(a.astype(np.float64) - b_np.astype(np.float64)))) if a.size else 0.0)
    worst = max(diffs) if diffs else 0.0
    if worst > atol:
        i = int(np.argmax(diffs))
        raise ExportError(
            f"{path}: output{i} differs from torch by up to {worst:.3g} (tolerance {atol:g}); "
            f"the exported graph does not reproduce the model"
        )
    return {"max_abs_diff": worst, "atol": atol, "matches_torch": True}
