"""What the benchmarks print about the machine they ran on: CPU model, cores, the instruction sets NumPy, OpenCV and
torch dispatch to (after any ``NPY_DISABLE_CPU_FEATURES`` / ``OPENCV_CPU_DISABLE`` / ``ATEN_CPU_CAPABILITY``
restriction), and the load average (on a shared machine, CPU time is the figure to compare).

The AVX2 profile of an AVX-512 machine::

    ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL" \\
    OPENCV_CPU_DISABLE=AVX512-SKX .venv/bin/python benchmarks/bench_c2.py
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

PROFILE_VARS = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "NPY_DISABLE_CPU_FEATURES", "OPENCV_CPU_DISABLE")


def cpu_model() -> tuple[str, set[str]]:
    """The CPU's model name and flags (from /proc/cpuinfo where there is one)."""
    info = Path("/proc/cpuinfo")
    model, flags = platform.processor() or platform.machine(), set()
    if info.exists():
        for line in info.read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model in ("", platform.machine(), platform.processor()):
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    return model, flags


def numpy_isa() -> str:
    """The widest x86 SIMD level NumPy dispatches to here (its dispatch groups, which the disabling variable
    clears; the single-feature flags keep describing the hardware)."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as feats
    except ImportError:  # NumPy 1.x
        from numpy.core._multiarray_umath import __cpu_features__ as feats  # type: ignore[no-redef]
    for name, label in (("X86_V4", "AVX-512"), ("AVX512_SKX", "AVX-512"), ("X86_V3", "AVX2"), ("AVX2", "AVX2")):
        if feats.get(name):
            return label
    return "baseline"


def opencv_isa() -> str:
    import cv2

    line = cv2.getCPUFeaturesLine().split()
    enabled = [f.lstrip("*") for f in line if not f.endswith("?")]  # "?" marks a feature disabled at run time
    return "AVX-512" if any(f.startswith("AVX512") for f in enabled) else ("AVX2" if "AVX2" in enabled else "SSE")


def machine_lines() -> list[str]:
    model, flags = cpu_model()
    hw = "AVX-512" if "avx512f" in flags else ("AVX2" if "avx2" in flags else "no AVX2")
    parts = [f"numpy {numpy_isa()}"]
    try:
        parts.append(f"opencv {opencv_isa()}")
    except ImportError:
        pass
    if "torch" in sys.modules:
        import torch

        parts.append(f"torch {torch.backends.cpu.get_cpu_capability()}")
    env = ", ".join(f"{k}={os.environ[k]}" for k in PROFILE_VARS if k in os.environ) or "none"
    load = " ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    return [
        f"CPU: {model}, {os.cpu_count()} logical cores, {hw} hardware; dispatch: {', '.join(parts)}",
        f"ISA restrictions: {env}",
        f"load average {load}: a shared machine, so CPU (process) time is the figure to compare",
    ]
