"""Latency of the raw forward pass: torch eager and onnxruntime, warm-up excluded, median and p90 of many runs.

Protocol (both back-ends): the model is fused and in eval mode; ``warmup`` calls run first and are not timed
(the very first call is recorded separately as ``first_ms``); then ``runs`` single calls are timed one by one
with ``time.perf_counter`` (CUDA is synchronised around each call). Thread counts, device or execution provider
and library versions are recorded with the numbers. Compare latencies only between runs on the same machine.
"""

from __future__ import annotations

import contextlib
import platform
import time
from typing import Any, Callable, Iterator

import numpy as np
import torch
from torch import nn

from harness.profiling.model_io import RawForward, as_tuple, is_dual


def summarize_times(times_s: list[float]) -> dict[str, float]:
    """Median, p90, mean and min in milliseconds (p90 by linear interpolation, numpy's default)."""
    t = np.asarray(times_s, dtype=np.float64) * 1e3
    return {
        "median_ms": float(np.median(t)),
        "p90_ms": float(np.percentile(t, 90)),
        "mean_ms": float(t.mean()),
        "min_ms": float(t.min()),
    }


def _time(fn: Callable[[], Any], warmup: int, runs: int, sync: Callable[[], None] = lambda: None) -> dict[str, Any]:
    sync()
    t0 = time.perf_counter()
    fn()
    sync()
    first = time.perf_counter() - t0
    for _ in range(max(warmup - 1, 0)):
        fn()
    sync()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return {**summarize_times(times), "first_ms": first * 1e3, "warmup": warmup, "runs": runs}


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[int]:
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def torch_latency(
    model: nn.Module,
    example_inputs: Any,
    warmup: int = 10,
    runs: int = 50,
    threads: int | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """Eager latency of ``forward_raw`` (the model as given: pass a fused, eval-mode model)."""
    dev = torch.device(device)
    wrapper = RawForward(model, is_dual(example_inputs)).eval().to(dev)
    inputs = tuple(t.to(dev) for t in as_tuple(example_inputs))
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    with torch_threads(threads) as n_threads, torch.inference_mode():
        stats = _time(lambda: wrapper(*inputs), warmup, runs, sync)
    return {
        "backend": "torch-eager",
        **stats,
        "threads": n_threads,
        "device": str(dev),
        "torch": torch.__version__,
        **_machine(dev),
    }


def onnx_latency(
    path: str,
    example_inputs: Any,
    warmup: int = 10,
    runs: int = 50,
    threads: int | None = None,
    providers: list[str] | None = None,
) -> dict[str, Any]:
    """onnxruntime latency of an exported file (sequential execution, all graph optimisations)."""
    import onnxruntime as ort

    from harness.profiling.export import ort_session

    session = ort_session(path, threads=threads, providers=providers)
    feeds = {i.name: t.detach().cpu().numpy() for i, t in zip(session.get_inputs(), as_tuple(example_inputs))}
    stats = _time(lambda: session.run(None, feeds), warmup, runs)
    opts = session.get_session_options()
    return {
        "backend": "onnxruntime",
        **stats,
        "threads": opts.intra_op_num_threads or "ort default (one per core)",
        "provider": session.get_providers()[0],
        "onnxruntime": ort.__version__,
        **_machine(torch.device("cpu")),
    }


def _machine(dev: torch.device) -> dict[str, Any]:
    out: dict[str, Any] = {"cpu": platform.processor() or platform.machine()}
    if dev.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(dev)
    return out
