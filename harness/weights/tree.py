"""Finding the weights in a checkpoint read by ``harness.weights.unpickle``: module trees of placeholders, EMA first.

A pickled ``torch.nn.Module`` is recorded by its placeholder as the module's ``__dict__``: ``_parameters`` and
``_buffers`` (name -> tensor or ``None``), ``_non_persistent_buffers_set`` and ``_modules`` (name -> child). The
state dict of the tree is what ``Module.state_dict()`` would give: ``prefix.name`` for every parameter and
persistent buffer, children recursively.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch

from harness.errors import HarnessError
from harness.weights.unpickle import Stub

#: Checkpoint keys that hold a model, most preferred first (EMA weights are what the trainers evaluate and ship).
MODEL_KEYS = ("ema", "model", "state_dict", "model_state_dict", "net", "module")


def is_module(obj: Any) -> bool:
    return isinstance(obj, Stub) and isinstance(obj.state.get("_modules"), Mapping) \
        and isinstance(obj.state.get("_parameters"), Mapping)


def module_state_dict(root: Stub) -> dict[str, torch.Tensor]:
    """``prefix.name -> tensor`` for every parameter and persistent buffer of the placeholder module tree."""
    out: dict[str, torch.Tensor] = {}

    def walk(m: Stub, prefix: str, seen: set[int]) -> None:
        if id(m) in seen:  # a module shared at two places is listed at its first one, as state_dict() does
            return
        seen.add(id(m))
        st = m.state
        for name, value in (st.get("_parameters") or {}).items():
            if isinstance(value, torch.Tensor):
                out[prefix + name] = value
        skip = set(st.get("_non_persistent_buffers_set") or ())
        for name, value in (st.get("_buffers") or {}).items():
            if isinstance(value, torch.Tensor) and name not in skip:
                out[prefix + name] = value
        for name, child in (st.get("_modules") or {}).items():
            if is_module(child):
                walk(child, f"{prefix}{name}.", seen)

    walk(root, "", set())
    return out


def is_state_dict(obj: Any) -> bool:
    return isinstance(obj, Mapping) and bool(obj) and all(isinstance(v, torch.Tensor) for v in obj.values())


def find_model(obj: Any, where: str) -> tuple[Any, str]:
    """The model inside a checkpoint: ``(module placeholder or state dict, where it was found)``.

    Ultralytics' trainer writes ``{'model': None, 'ema': <model>}`` during training and ``{'model': <model>,
    'ema': None}`` after it finishes; YOLOv5 and ICAFusion write ``{'model': <model>, 'ema': <model> or None}``.
    The first non-empty entry of ``MODEL_KEYS`` wins, so EMA weights are taken when present.
    """
    if is_module(obj) or is_state_dict(obj):
        return obj, "<root>"
    if isinstance(obj, Mapping):
        for key in MODEL_KEYS:
            value = obj.get(key)
            if isinstance(value, Mapping) and is_module(value.get("module")):  # EMA wrappers that keep .module
                return value["module"], f"{key}.module"
            if is_module(value) or is_state_dict(value):
                return value, key
            if is_module(getattr(value, "state", {}).get("module") if isinstance(value, Stub) else None):
                return value.state["module"], f"{key}.module"  # type: ignore[union-attr]
    kinds = sorted(obj) if isinstance(obj, Mapping) else type(obj).__name__
    raise HarnessError(f"{where}: no model found (looked for a module or a state dict at the top level and under "
                       f"{', '.join(MODEL_KEYS)}; the file holds {kinds})")


def to_float32(sd: Mapping[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], list[str]]:
    """Contiguous, unshared copies; floating tensors of other precisions cast to float32 (returns the casts)."""
    out, cast = {}, []
    for k, v in sd.items():
        t = v.detach()
        if t.is_floating_point() and t.dtype != torch.float32:
            cast.append(f"{k}: {str(t.dtype).replace('torch.', '')}")
            t = t.float()
        out[k] = t.contiguous().clone()
    return out, cast
