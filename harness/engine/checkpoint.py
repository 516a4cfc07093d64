"""Checkpoints: written atomically (``harness.io``), read weights-only and bounded, resumable to the same state.

A training checkpoint (``last.pt``) holds everything a resumed run needs to continue exactly where the
interrupted one stopped: model and EMA weights, optimiser (and AMP scaler) state, the position in the schedule, the
random-number generators of Python, NumPy and torch, the best fitness so far and the per-epoch history. The best
checkpoint (``best.pt``) holds the weights that scored the best fitness. Both are plain dictionaries of tensors and
built-in types. ``load`` reads them (and ``--init`` files) with the harness's restricted unpickler in its plain mode
(``harness.weights.unpickle.load_plain``): what ``torch.load(..., weights_only=True)`` accepts, without unpickling
arbitrary objects, and with every size bounded by the file's own (a hostile file gets a one-line error, never a hang
or an allocation it cannot fill).
"""

from __future__ import annotations

import logging
import random
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import nn

from harness.errors import HarnessError
from harness.io import atomic_write

log = logging.getLogger(__name__)

FORMAT = "rgbt-harness-checkpoint"
VERSION = 1


class CheckpointError(HarnessError):
    """A checkpoint file is missing, unreadable, or does not fit the model."""


def save(path: str | Path, obj: Mapping[str, Any]) -> Path:
    """``torch.save`` into a temporary file beside ``path``, then rename: a crash never leaves half a checkpoint."""
    return atomic_write(path, lambda f: torch.save(dict(obj), f))


def load(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: checkpoint not found")
    from harness.weights import UnsafeCheckpointError, load_plain, read_safetensors

    try:
        if path.suffix == ".safetensors":  # what `harness weights import` writes: a plain state dict
            return read_safetensors(path)
        obj = load_plain(path)
    except UnsafeCheckpointError as exc:  # a pickled object or a call outside the tensor-rebuild list
        raise CheckpointError(
            f"{path}: cannot be read as a weights-only checkpoint ({_reason(exc, path)}). "
            f"If it pickles a whole model object (Ultralytics, YOLOv5, ICAFusion checkpoints), convert it safely with "
            f"`harness weights import {path} --out weights.safetensors` and use that file"
        ) from None
    except HarnessError as exc:  # unreadable, truncated, or asking for more than the file's size allows
        raise CheckpointError(str(exc)) from None
    if not isinstance(obj, dict):
        raise CheckpointError(
            f"{path}: expected a dictionary (a state dict or a harness checkpoint), got {type(obj).__name__}"
        )
    return obj


def _reason(exc: Exception, path: Path) -> str:
    """An error's message without the file name it starts with (the caller's message names the file)."""
    text = str(exc)
    return text[len(str(path)) + 2 :] if text.startswith(f"{path}: ") else text


def rng_state() -> dict[str, Any]:
    """Python, NumPy (legacy global) and torch generator states as weights-only-safe values."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": {
            "name": name,
            "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached": float(cached),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    n = state["numpy"]
    np.random.set_state((n["name"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def state_dict_of(obj: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """The weights in a checkpoint: a harness checkpoint's EMA (or model) weights, or a plain state dict."""
    if obj.get("format") == FORMAT:
        ema = obj.get("ema")
        return dict(ema["module"] if isinstance(ema, Mapping) and "module" in ema else obj["model"])
    for key in ("ema", "model", "state_dict"):
        inner = obj.get(key)
        if isinstance(inner, Mapping) and inner and all(isinstance(v, torch.Tensor) for v in inner.values()):
            return dict(inner)
    tensors = {k: v for k, v in obj.items() if isinstance(v, torch.Tensor)}
    if not tensors:
        raise CheckpointError("no tensors found: expected a state dict or a checkpoint with 'model' or 'ema' weights")
    return tensors


def load_matching(model: nn.Module, state: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """Load every tensor whose name and shape match the model; report what was loaded and what was not."""
    own = model.state_dict()
    matched = {k: v for k, v in state.items() if k in own and tuple(v.shape) == tuple(own[k].shape)}
    shape_mismatch = sorted(k for k, v in state.items() if k in own and tuple(v.shape) != tuple(own[k].shape))
    model.load_state_dict(matched, strict=False)
    return {
        "loaded": len(matched),
        "total": len(own),
        "missing": sorted(set(own) - set(matched)),
        "unexpected": sorted(set(state) - set(own)),
        "shape_mismatch": shape_mismatch,
    }


def init_from(
    model: nn.Module, path: str | Path, load_official: Callable[[nn.Module, Mapping[str, Any]], dict] | None = None
) -> dict[str, Any]:
    """Initialise ``model`` from a checkpoint (``--init``): the detector's own importer when it has one (it knows
    its official layout, e.g. inflating a 3-channel stem to 4 channels), else every tensor matching by name and
    shape."""
    try:
        state = state_dict_of(load(path))
    except CheckpointError as exc:
        raise CheckpointError(exc.args[0] if str(path) in str(exc) else f"{path}: {exc}") from None
    if load_official is not None:
        try:
            report = dict(load_official(model, state) or {})
        except HarnessError as exc:  # the detector's importer refuses the weights: say which file they came from
            raise CheckpointError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from None
        report.setdefault("importer", "detector")
    else:
        report = load_matching(model, state)
        report["importer"] = "name-and-shape"
    loaded, mismatched = _count(report.get("loaded")), _count(report.get("mismatched", report.get("shape_mismatch")))
    if loaded == 0:
        raise CheckpointError(
            f"{path}: none of its {len(state)} tensors matches the model's parameter names and shapes; "
            f"is it a checkpoint of this detector?"
        )
    if mismatched > loaded:  # a head for another number of classes mismatches a few tensors, not most of them
        shown = "; ".join(str(m) for m in list(report.get("mismatched") or report.get("shape_mismatch") or [])[:3])
        raise CheckpointError(
            f"{path}: {mismatched} of its tensors have the model's names but other shapes (e.g. {shown}), only "
            f"{loaded} loaded: a checkpoint of another detector, or of another size (model.scale)?"
        )
    report["path"] = str(path)
    counts = ", ".join(f"{k}={_count(v)}" for k, v in report.items() if k not in ("path", "importer"))
    if mismatched or _count(report.get("missing")):  # the model starts partly from its own initialisation
        log.warning("initialised in part from %s (%s; importer %s)", path, counts, report["importer"])
    else:
        log.info("initialised from %s (%s; importer %s)", path, counts, report["importer"])
    return report


def _count(v: Any) -> int:
    """A count of an importer's report: a number, or the length of a list of names."""
    return len(v) if isinstance(v, (list, tuple, set, dict)) else int(v or 0)
