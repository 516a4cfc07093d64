"""What shaped a result: the versions of the packages that make the samples and train the models, torch's build, and
the CPU.

Prepared samples depend on the packages the sensing pipeline calls (OpenCV's warps and blurs above all: one OpenCV
release moved box corners by a float32 ulp and a few hundred RGB pixels by one grey level), training on torch, its
BLAS and oneDNN builds and the CPU their kernels dispatch on. ``sample_environment`` is recorded in every prepared
cache's manifest and in the reference results; ``environment_facts`` beside every run's metrics. ``differences``
names what differs between two such records, in words a reader can act on (``OpenCV 5.1.0, references 5.0.0``).
"""

from __future__ import annotations

import importlib.metadata as md
import platform
import re
import sys
from functools import lru_cache
from typing import Any, Iterable, Mapping

#: Packages whose release can change prepared samples: record key -> distribution names (the first installed wins).
SAMPLE_PACKAGES: dict[str, tuple[str, ...]] = {
    "numpy": ("numpy",),
    "opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless", "opencv-contrib-python"),
    "scipy": ("scipy",),
    "tifffile": ("tifffile",),
    "pillow": ("pillow",),
}
#: Packages whose release can change training or scoring, beyond those above.
TRAINING_PACKAGES: dict[str, tuple[str, ...]] = {
    "torch": ("torch",),
    "pycocotools": ("pycocotools",),
    "faster-coco-eval": ("faster-coco-eval",),
}
#: How a record key is named to a reader.
LABELS = {"opencv": "OpenCV", "numpy": "NumPy", "scipy": "SciPy", "pillow": "Pillow", "torch": "torch"}


def _dist_version(names: Iterable[str]) -> str | None:
    for name in names:
        try:
            return md.version(name)
        except md.PackageNotFoundError:
            continue
    return None


@lru_cache(maxsize=1)
def package_versions() -> dict[str, str]:
    """``{key: version}`` of every sample- or training-shaping package installed (OpenCV as the library reports
    itself, ``5.0.0``; the wheel's own version under ``opencv_wheel``)."""
    out: dict[str, str] = {}
    for key, names in {**SAMPLE_PACKAGES, **TRAINING_PACKAGES}.items():
        v = _dist_version(names)
        if v is not None:
            out[key] = v
    try:
        import cv2

        if "opencv" in out:
            out["opencv_wheel"] = out["opencv"]
        out["opencv"] = str(cv2.__version__)
    except ImportError:
        pass
    try:
        import torch

        out["torch"] = str(torch.__version__)
    except ImportError:
        pass
    return dict(sorted(out.items()))


def sample_environment() -> dict[str, Any]:
    """What shaped prepared samples: Python and the sample-shaping packages (recorded in a prepared manifest)."""
    versions = package_versions()
    return {"python": sys.version.split()[0]} | {
        k: versions[k] for k in (*SAMPLE_PACKAGES, "opencv_wheel") if k in versions
    }


@lru_cache(maxsize=1)
def torch_build() -> dict[str, Any]:
    """torch's BLAS, LAPACK and oneDNN builds and parallel backend, as ``torch.__config__`` reports them."""
    try:
        import torch

        shown = torch.__config__.show()
        parallel = torch.__config__.parallel_info()
    except Exception:
        return {}
    out: dict[str, Any] = {}
    m = re.search(r"Math Kernel Library Version ([\d.]+)", shown)
    if m:
        out["mkl"] = m.group(1)
    m = re.search(r"MKL-DNN v([\d.]+)", shown)
    if m:
        out["onednn"] = m.group(1)
    for key, field in (("blas", "BLAS_INFO"), ("lapack", "LAPACK_INFO")):
        m = re.search(rf"{field}=(\w+)", shown)
        if m:
            out[key] = m.group(1)
    m = re.search(r"ATen parallel backend: (\w+)", parallel)
    if m:
        out["parallel"] = m.group(1)
    return out


@lru_cache(maxsize=1)
def cpu_facts() -> dict[str, Any]:
    """The CPU kernels dispatch on: vendor, model, the vector extensions it has, and its cache sizes (Linux reads
    ``/proc/cpuinfo`` and sysfs; elsewhere what ``platform`` says)."""
    out: dict[str, Any] = {"machine": platform.machine()}
    try:
        text = open("/proc/cpuinfo", encoding="utf-8", errors="replace").read()
    except OSError:
        text = ""
    first = text.split("\n\n", 1)[0]
    fields = dict(
        (k.strip(), v.strip()) for k, _, v in (line.partition(":") for line in first.splitlines()) if k.strip()
    )
    if fields.get("vendor_id"):
        out["vendor"] = fields["vendor_id"]
    if fields.get("model name"):
        out["model"] = re.sub(r"\s+", " ", fields["model name"])
    flags = set(fields.get("flags", "").split())
    if flags:
        out["isa"] = [f for f in ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_tile") if f in flags]
    caches = {}
    for level in range(4):
        base = f"/sys/devices/system/cpu/cpu0/cache/index{level}"
        try:
            kind = open(f"{base}/type").read().strip()
            lvl = open(f"{base}/level").read().strip()
            size = open(f"{base}/size").read().strip()
        except OSError:
            continue
        if kind != "Instruction":
            caches[f"L{lvl}"] = size
    if caches:
        out["cache"] = caches
    if "model" not in out:
        out["model"] = platform.processor() or "unknown"
    return out


#: Environment variables that choose the CPU kernels a run computes with (and so its last digits).
KERNEL_VARIABLES = (
    "ONEDNN_MAX_CPU_ISA",
    "ATEN_CPU_CAPABILITY",
    "MKL_CBWR",
    "HARNESS_ONEDNN",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
)


def kernel_settings() -> dict[str, Any]:
    """The kernel-choosing variables that are set, and whether torch's oneDNN kernels are on."""
    import os

    out: dict[str, Any] = {k: os.environ[k] for k in KERNEL_VARIABLES if os.environ.get(k)}
    try:
        import torch

        out["onednn_enabled"] = bool(torch.backends.mkldnn.enabled)
    except Exception:
        pass
    return out


def environment_facts() -> dict[str, Any]:
    """The package versions, torch build, kernel settings and CPU recorded beside a run's metrics
    (``environment``)."""
    return {
        "packages": package_versions(),
        "torch_build": torch_build(),
        "kernels": kernel_settings(),
        "cpu": cpu_facts(),
    }


def flat_versions(env: Mapping[str, Any]) -> dict[str, str]:
    """Package versions from any of the records above (a prepared manifest's ``environment``, a run's
    ``environment``, a reference manifest's), as one ``{key: version}`` map."""
    out: dict[str, str] = {}
    for key in ("python", "numpy", "opencv", "torch"):
        if env.get(key) is not None:
            out[key] = str(env[key])
    for key in (*SAMPLE_PACKAGES, *TRAINING_PACKAGES, "opencv_wheel"):
        if env.get(key) is not None:
            out[key] = str(env[key])
    packages = env.get("packages")
    if isinstance(packages, Mapping):
        out.update({str(k): str(v) for k, v in packages.items()})
    return out


def differences(
    mine: Mapping[str, Any], theirs: Mapping[str, Any], keys: Iterable[str] | None = None, theirs_name: str = "theirs"
) -> list[str]:
    """``["OpenCV 5.1.0, references 5.0.0", ...]``: the packages both records name whose versions differ (only
    ``keys`` when given)."""
    a, b = flat_versions(mine), flat_versions(theirs)
    wanted = list(keys) if keys is not None else sorted(set(a) & set(b))
    out = []
    for key in wanted:
        if key in a and key in b and a[key] != b[key] and key != "opencv_wheel":
            out.append(f"{LABELS.get(key, key)} {a[key]}, {theirs_name} {b[key]}")
    return out


__all__ = [
    "SAMPLE_PACKAGES",
    "TRAINING_PACKAGES",
    "cpu_facts",
    "differences",
    "environment_facts",
    "flat_versions",
    "kernel_settings",
    "package_versions",
    "sample_environment",
    "torch_build",
]
