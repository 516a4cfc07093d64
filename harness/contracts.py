"""Plugin outputs checked at the boundary: every error names the plugin, the field and what was expected.

* ``check_detections(det, detector, num_classes)``: one image's eval-mode output ``{"boxes" [K, 4] float,
  "scores" [K] float, finite, "labels" [K] int in 0..num_classes-1}``; degenerate boxes (NaN, inverted) pass here
  and are counted and dropped by ``harness.engine.predict``;
* ``check_losses(losses, detector)``: the train-mode output, a non-empty dict of scalar (one-element) tensors;
* ``fold_batchnorm(model)``: the host's call of a detector's BatchNorm fold. The host looks for the namespaced
  ``harness_fuse()`` first, then a ``fuse()`` *method defined on the model's class*; an attribute, a sub-module or
  anything else a plugin happens to call ``fuse`` is never called.

Dataset samples are checked by ``harness.sample.validate_sample`` when they are prepared.
"""

from __future__ import annotations

import inspect
from typing import Any, Mapping

from harness.errors import PluginError

#: The namespaced name of the BatchNorm fold the host calls on a model (``fuse`` is accepted as a class method).
FUSE_HOOK = "harness_fuse"


def _shape(t: Any) -> str:
    return str(list(t.shape)) if hasattr(t, "shape") else type(t).__name__


def check_detections(det: Any, detector: str, num_classes: int | None = None) -> tuple[Any, Any, Any]:
    """(boxes [K, 4], scores [K], labels [K]) as numpy arrays, or a ``PluginError`` naming the field."""
    import numpy as np
    import torch

    where = f"detector {detector!r}: eval-mode output"
    if not isinstance(det, Mapping):
        raise PluginError(f"{where} must be one dict per image with 'boxes', 'scores' and 'labels', got "
                          f"{type(det).__name__}")
    missing = [k for k in ("boxes", "scores", "labels") if k not in det]
    if missing:
        raise PluginError(f"{where} has no {', '.join(repr(k) for k in missing)} (keys: {sorted(map(str, det))})")
    for k in ("boxes", "scores", "labels"):
        if not isinstance(det[k], torch.Tensor):
            raise PluginError(f"{where} field {k!r} must be a tensor, got {type(det[k]).__name__}")
    boxes, scores, labels = det["boxes"], det["scores"], det["labels"]
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise PluginError(f"{where} field 'boxes' must have shape [K, 4] (x1, y1, x2, y2), got {_shape(boxes)}")
    k = boxes.shape[0]
    if scores.ndim != 1 or scores.shape[0] != k:
        raise PluginError(f"{where} field 'scores' must have shape [K] = [{k}], got {_shape(scores)}")
    if labels.ndim != 1 or labels.shape[0] != k:
        raise PluginError(f"{where} field 'labels' must have shape [K] = [{k}], got {_shape(labels)}")
    if labels.dtype.is_floating_point or labels.dtype.is_complex or labels.dtype == torch.bool:
        raise PluginError(f"{where} field 'labels' must be an integer tensor, got {labels.dtype}")
    b = boxes.detach().float().cpu().numpy()
    s = scores.detach().float().cpu().numpy()
    lab = labels.detach().cpu().numpy().astype(np.int64)
    if not np.isfinite(s).all():  # a NaN or inf box is a degenerate box: the caller counts and drops it
        raise PluginError(f"{where} field 'scores' must be finite, got {int((~np.isfinite(s)).sum())} NaN/inf value(s)")
    if num_classes is not None and k and (lab.min() < 0 or lab.max() >= num_classes):
        bad = int(lab.min()) if lab.min() < 0 else int(lab.max())
        raise PluginError(f"{where} field 'labels' must lie in 0..{num_classes - 1}, got {bad}")
    return b, s, lab


def check_losses(losses: Any, detector: str) -> Mapping[str, Any]:
    """The train-mode output: a non-empty dict of scalar tensors, else a ``PluginError`` naming the entry."""
    import torch

    where = f"detector {detector!r}: in train mode model(inputs, targets)"
    if not isinstance(losses, Mapping) or not losses:
        raise PluginError(f"{where} must return a non-empty dict of scalar loss tensors, got "
                          f"{type(losses).__name__}{' (empty)' if isinstance(losses, Mapping) else ''}")
    for k, v in losses.items():
        if not isinstance(v, torch.Tensor):
            raise PluginError(f"{where}: loss {k!r} must be a tensor, got {type(v).__name__}")
        if v.numel() != 1:
            raise PluginError(f"{where}: loss {k!r} must be a scalar (one element), got shape {_shape(v)}; "
                              f"reduce it over the batch (sum or mean) inside the detector")
    return losses


def fold_batchnorm(model: Any) -> tuple[Any, bool]:
    """Call the model's declared BatchNorm fold (see the module docstring): (folded model, whether it was folded).

    A fold returning a module replaces the model; one returning ``None`` folded in place.
    """
    fn = None
    for name in (FUSE_HOOK, "fuse"):
        attr = inspect.getattr_static(type(model), name, None)
        if inspect.isfunction(attr):
            fn = getattr(model, name)
            break
    if fn is None:
        return model, False
    out = fn()
    if out is not None and hasattr(out, "parameters"):
        return out, True
    return model, True
