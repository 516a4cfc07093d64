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
from harness.weights.unpickle import CheckpointFormatError, CheckpointLimitError, Stub, brief, human, out_itemsize

#: Checkpoint keys that hold a model, most preferred first (EMA weights are what the trainers evaluate and ship).
MODEL_KEYS = ("ema", "model", "state_dict", "model_state_dict", "net", "module")


def is_module(obj: Any) -> bool:
    return (
        isinstance(obj, Stub)
        and isinstance(obj.state.get("_modules"), Mapping)
        and isinstance(obj.state.get("_parameters"), Mapping)
    )


def module_state_dict(root: Stub, max_bytes: int | None = None) -> dict[str, torch.Tensor]:
    """``prefix.name -> tensor`` for every parameter and persistent buffer of the placeholder module tree.

    The tree is walked with an explicit stack (a file can nest modules thousands deep), each module once (a module
    shared at two places, or one that contains itself, is listed at its first place, as ``state_dict()`` does).
    ``max_bytes`` bounds what the result would take as an imported file (key characters plus float32 tensor bytes):
    :class:`CheckpointLimitError` is raised as soon as the walk passes it."""
    out: dict[str, torch.Tensor] = {}
    seen: set[int] = set()
    stack: list[tuple[Stub, str]] = [(root, "")]
    total = 0
    while stack:
        m, prefix = stack.pop()
        if id(m) in seen:
            continue
        seen.add(id(m))
        st = m.state
        skip = st.get("_non_persistent_buffers_set")
        skip = {s for s in skip if isinstance(s, str)} if isinstance(skip, (set, frozenset, list, tuple)) else set()
        for group in ("_parameters", "_buffers"):
            entries = st.get(group)
            for name, value in entries.items() if isinstance(entries, Mapping) else ():
                if not isinstance(value, torch.Tensor) or (group == "_buffers" and name in skip):
                    continue
                if not isinstance(name, str):
                    raise CheckpointFormatError(
                        f"module {prefix or '<root>'} names a tensor {brief(name)}, not a string"
                    )
                key = prefix + name
                total += len(key) + value.numel() * out_itemsize(value.dtype)
                if max_bytes is not None and total > max_bytes:
                    raise CheckpointLimitError(
                        f"its model's tensors and names add up to more than {human(max_bytes)}"
                        f" as float32 (reached at {brief(key, 80)}); refused"
                    )
                out[key] = value
        children = st.get("_modules")
        children = list(children.items()) if isinstance(children, Mapping) else []
        for name, child in reversed(children):  # reversed onto the stack: visited in their own order
            if is_module(child):
                stack.append((child, f"{prefix}{name if isinstance(name, str) else brief(name)}."))
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
    if isinstance(obj, Mapping):
        keys = sorted(k if isinstance(k, str) else brief(k) for k in list(obj)[:1000])
        kinds = ", ".join(brief(k, 40)[1:-1] for k in keys[:12]) + (
            f" and {len(obj) - 12} more" if len(obj) > 12 else ""
        )
    else:
        kinds = brief(obj)
    raise HarnessError(
        f"{where}: no model found (looked for a module or a state dict at the top level and under "
        f"{', '.join(MODEL_KEYS)}; the file holds {kinds}){_why_no_model(obj)}"
    )


def _why_no_model(obj: Any) -> str:
    """What the file is instead, where it can be told: a TorchScript archive, or a dict of arrays that are not
    tensors (numpy arrays saved with torch.save)."""
    if isinstance(obj, Stub) and "__torch__" in brief(obj):
        return (
            "; it is a TorchScript archive (torch.jit.save): load it with torch.jit.load and torch.save its "
            "state_dict() instead"
        )
    if isinstance(obj, Mapping) and obj and not any(isinstance(v, (torch.Tensor, Mapping)) for v in obj.values()):
        kinds = sorted({brief(v, 40) if isinstance(v, Stub) else type(v).__name__ for v in list(obj.values())[:100]})
        return f"; its values are {', '.join(kinds[:3])}, not tensors: save torch tensors (torch.from_numpy)"
    return ""


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
