"""Seeding, device selection and the environment record written beside every result."""

from __future__ import annotations

import os
import platform
import random
import sys
from typing import Any, Mapping

import numpy as np
import torch

from harness.errors import ConfigError

#: ``HARNESS_ONEDNN=0`` (or ``off``/``false``) turns torch's oneDNN (MKL-DNN) kernels off for the whole run
ENV_ONEDNN = "HARNESS_ONEDNN"
_OFF, _ON = ("0", "off", "false", "no"), ("1", "on", "true", "yes")


def onednn_setting(environ: Mapping[str, str] | None = None) -> bool | None:
    """What ``HARNESS_ONEDNN`` asks for: True (torch's oneDNN kernels on), False (off) or None (unset or empty:
    torch's own choice, on); any other value is a ``ConfigError`` naming the variable.

    Off, convolutions run on ATen's own kernels (im2col and the BLAS's GEMM), whose blocking does not depend on the
    CPU's caches; with ``MKL_CBWR`` fixing the BLAS's code path this is the setting that
    ``benchmarks/reproducibility.py`` measures."""
    value = (os.environ if environ is None else environ).get(ENV_ONEDNN, "").strip().lower()
    if not value:
        return None
    if value in _OFF:
        return False
    if value in _ON:
        return True
    raise ConfigError(f"{ENV_ONEDNN}={value!r}: use 1 (torch's oneDNN kernels, the default) or 0 (off)")


def apply_onednn_setting(environ: Mapping[str, str] | None = None) -> bool:
    """Turn torch's oneDNN kernels on or off as ``HARNESS_ONEDNN`` says (``onednn_setting``; unset leaves them as
    they are); returns whether they are on."""
    on = onednn_setting(environ)
    if on is not None:
        torch.backends.mkldnn.enabled = on
    return bool(torch.backends.mkldnn.enabled)


def seed_everything(seed: int, deterministic: bool = True) -> None:
    """Seed Python, NumPy and torch; with ``deterministic`` ask torch for deterministic kernels.

    On CPU a seeded run is bit-for-bit repeatable with the same torch build and thread count. On CUDA some kernels
    have no deterministic version; torch then warns instead of failing (``warn_only``). ``HARNESS_ONEDNN`` is applied
    here (``apply_onednn_setting``), so it holds for the whole run that is seeded.
    """
    apply_onednn_setting()
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)
    if deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.backends.cudnn.benchmark = False
        torch.backends.cudnn.deterministic = True


def select_device(name: str | None = "auto") -> torch.device:
    """``auto`` (CUDA when available, else CPU), ``cpu``, ``cuda`` or ``cuda:N``; a missing GPU is a clear error."""
    name = (name or "auto").lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError(f"train.device={name!r} but this torch build sees no CUDA device; use 'cpu' or 'auto'")
        return torch.device(name)
    if name == "cpu":
        return torch.device("cpu")
    raise ConfigError(f"train.device: unknown device {name!r}; use auto, cpu, cuda or cuda:N")


def set_threads(threads: int | None) -> None:
    if threads:
        torch.set_num_threads(int(threads))


#: ``HARNESS_MALLOC=default`` leaves glibc's allocator settings alone (see ``keep_freed_memory``)
ENV_MALLOC = "HARNESS_MALLOC"
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters of glibc's malloc.h


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed memory for reuse instead of returning it to the kernel (Linux only).

    A training step frees and re-allocates the same activation and gradient buffers; by default glibc maps every
    block over a few hundred kB freshly and unmaps it when freed, so each step pays a page fault per 4 kB page and
    the kernel zeroes the pages again (a tenth of a small detector's CPU time on two cores). With a 1 GiB trim
    threshold and a 32 MiB mmap threshold (glibc's largest) those blocks come from and return to the heap. The peak
    memory of a run is unchanged; it is held until the process exits. Numbers are unaffected. Returns whether the
    settings were applied; ``HARNESS_MALLOC=default`` opts out.
    """
    if os.environ.get(ENV_MALLOC, "").lower() == "default" or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt  # glibc; musl's mallopt does nothing and returns 0
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_TRIM_THRESHOLD, 1 << 30)) and bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20))


def environment(device: torch.device | None = None) -> dict[str, Any]:
    """Versions, device and threads: what a reader needs to judge whether two results are comparable."""
    import cv2

    from harness import __version__

    env: dict[str, Any] = {
        "harness": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "device": str(device) if device is not None else None,
    }
    try:  # the instruction set torch's CPU kernels use (AVX2 and AVX-512 round differently)
        env["cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    except Exception:
        pass
    from harness.provenance import environment_facts

    env.update(environment_facts())  # every package that shapes samples or training, torch's BLAS/oneDNN, the CPU
    if device is not None and device.type == "cuda":
        env["gpu"] = torch.cuda.get_device_name(device)
        env["cuda"] = torch.version.cuda
    return env
