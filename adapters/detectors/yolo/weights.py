"""Importing YOLOv8 weights in the public checkpoint layout (a plain mapping of parameter name -> tensor).

What is accepted:

* a state dict whose keys follow the public layout (``model.0.conv.weight`` ...), optionally wrapped in a dict under
  ``"model"``, ``"ema"`` or ``"state_dict"``, or with a ``"module."`` prefix;
* any number of input channels: the stem filters of the channels both sides have are copied, and extra model
  channels are initialised by ``extra_channels`` (below); extra checkpoint channels are dropped;
* any number of classes: when it differs, the last layer of every class branch (``model.22.cv3.{i}.2``) is
  re-initialised (default conv init, prior bias) and the report says so;
* BatchNorm-folded ("fused") checkpoints: ``conv.bias`` without ``bn.*`` is loaded exactly as a BN with unit
  scale, zero mean, variance ``1 - eps`` and the conv bias as shift.

Initialising extra input channels (the C2 channel when RGB weights are loaded into ``[R, G, B, C2]``):

* ``"zeros"`` (default): the new filters start at zero. The inflated model then computes exactly what the RGB
  model computed, whatever the fourth channel holds, so pretrained features and BatchNorm statistics are not
  disturbed at step 0; the gradient of these filters is not zero (it is the input times the upstream gradient), so
  the network learns to use the channel.
* ``"mean"``: every new filter is the mean of the RGB filters and all filters are scaled by ``3 / C`` (the usual
  inflation rule): a grey image replicated into all ``C`` channels gives the same response as before.
* ``"random"``: keep the model's fresh random init for the new filters (what the public trainer does).

Files are read as safetensors or with the harness's bounded weights-only reader
(``harness.weights.unpickle.load_plain``: tensors and plain containers only, as ``torch.load(weights_only=True)``
accepts); nothing else is unpickled.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn

from harness.errors import HarnessError

log = logging.getLogger(__name__)

EXTRA_CHANNEL_MODES = ("zeros", "mean", "random")
#: Stem width of each public scale, used to name the scale of a checkpoint that does not fit.
_STEM_WIDTH_TO_SCALE = {16: "n", 32: "s", 48: "m", 64: "l", 80: "x"}


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a plain state dict from ``.safetensors`` or a ``torch.save`` file of tensors (weights-only, bounded)."""
    path = Path(path)
    if not path.is_file():
        raise HarnessError(f"weights file {path} does not exist")
    from harness.weights import UnsafeCheckpointError, load_plain, read_safetensors

    try:
        if path.suffix == ".safetensors":
            return read_safetensors(path)
        obj = load_plain(path)
    except UnsafeCheckpointError as exc:
        raise HarnessError(
            f"weights file {path} cannot be read as plain tensors ({type(exc).__name__}). Checkpoints that pickle "
            f"whole model objects (Ultralytics, YOLOv5) are refused for safety; convert one with "
            f"`harness weights import {path} --out weights.safetensors` and pass that file"
        ) from None
    except HarnessError as exc:
        raise HarnessError(f"weights file {exc}") from None
    return unwrap_state_dict(obj, str(path))


def unwrap_state_dict(obj: Any, where: str = "state dict") -> dict[str, torch.Tensor]:
    """Find the mapping of tensors inside common checkpoint wrappers; strip a ``module.`` prefix."""
    for key in ("ema", "model", "state_dict"):
        if isinstance(obj, Mapping) and isinstance(obj.get(key), Mapping):
            obj = obj[key]
            break
    if not isinstance(obj, Mapping) or not obj:
        raise HarnessError(f"{where}: expected a mapping of parameter names to tensors, got {type(obj).__name__}")
    out = {}
    for k, v in obj.items():
        if not isinstance(v, torch.Tensor):
            raise HarnessError(f"{where}: entry {k!r} is a {type(v).__name__}, not a tensor")
        out[k[len("module.") :] if k.startswith("module.") else k] = v
    return out


def _unfuse(sd: dict[str, torch.Tensor], own: Mapping[str, torch.Tensor], eps_of: Mapping[str, float]) -> list[str]:
    """Turn folded ``X.conv.bias`` entries into the equivalent ``X.bn.*`` entries; returns the prefixes converted."""
    converted = []
    for key in own:
        if not key.endswith(".bn.weight"):
            continue
        prefix = key[: -len("bn.weight")]
        if key in sd or prefix + "conv.bias" not in sd:
            continue
        bias = sd.pop(prefix + "conv.bias")
        sd[prefix + "bn.weight"] = torch.ones_like(bias)
        sd[prefix + "bn.bias"] = bias
        sd[prefix + "bn.running_mean"] = torch.zeros_like(bias)
        sd[prefix + "bn.running_var"] = torch.ones_like(bias) - eps_of[prefix + "bn"]
        converted.append(prefix.rstrip("."))
    return converted


def inflate_stem(own: torch.Tensor, src: torch.Tensor, mode: str = "zeros") -> torch.Tensor:
    """Stem filters ``[O, C_src, k, k]`` -> ``[O, C_own, k, k]``: shared channels copied, extra ones per ``mode``."""
    if mode not in EXTRA_CHANNEL_MODES:
        raise HarnessError(f"extra_channels must be one of {EXTRA_CHANNEL_MODES}, got {mode!r}")
    c_own, c_src = own.shape[1], src.shape[1]
    out = own.detach().clone()
    n = min(c_own, c_src)
    out[:, :n] = src[:, :n]
    if c_own > c_src:
        if mode == "zeros":
            out[:, c_src:] = 0
        elif mode == "mean":
            out[:, c_src:] = src.mean(1, keepdim=True)
            out *= c_src / c_own
    return out


def load_yolov8_weights(
    model: nn.Module, state_dict: Mapping[str, Any] | str | Path, extra_channels: str = "zeros", strict: bool = True
) -> dict[str, Any]:
    """Load public-layout YOLOv8 weights into ``model`` (a ``YOLOv8``); returns a JSON-ready report.

    ``strict``: a parameter of the model absent from the checkpoint is an error (otherwise it keeps its init and
    is listed under ``missing``). Shapes that differ anywhere but in the stem's input channels or the class layers
    are always an error (usually a checkpoint of another scale).
    """
    sd = read_state_dict(state_dict) if isinstance(state_dict, (str, Path)) else unwrap_state_dict(state_dict)
    sd = dict(sd)
    own = model.state_dict()
    eps_of = {n: m.eps for n, m in model.named_modules() if isinstance(m, nn.BatchNorm2d)}
    report: dict[str, Any] = {
        "loaded": 0,
        "fused_source": [],
        "stem": None,
        "reinitialised": [],
        "missing": [],
        "unexpected": [],
        "notes": [],
    }
    report["fused_source"] = _unfuse(sd, own, eps_of)

    head_idx = len(model.model) - 1
    stem_key = "model.0.conv.weight"
    cls_branch = re.compile(rf"^model\.{head_idx}\.cv3\.")
    cls_out = re.compile(rf"^model\.{head_idx}\.cv3\.\d+\.2\.weight$")
    new_sd: dict[str, torch.Tensor] = {}
    mismatched: list[str] = []
    reinit: list[str] = []
    for key, value in own.items():
        if key not in sd:
            if not key.endswith("num_batches_tracked"):
                report["missing"].append(key)
            continue
        src = sd[key]
        if src.shape == value.shape:
            new_sd[key] = src.to(value.dtype)
        elif key == stem_key and src.dim() == 4 and src.shape[0] == value.shape[0] and src.shape[2:] == value.shape[2:]:
            new_sd[key] = inflate_stem(value, src.to(value.dtype), extra_channels)
            report["stem"] = {
                "checkpoint_channels": int(src.shape[1]),
                "model_channels": int(value.shape[1]),
                "extra_channels": extra_channels if value.shape[1] > src.shape[1] else None,
            }
            if value.shape[1] > src.shape[1]:
                report["notes"].append(
                    f"stem inflated from {src.shape[1]} to {value.shape[1]} input channels: channels "
                    f"0..{src.shape[1] - 1} copied, the others initialised '{extra_channels}'"
                )
            else:
                report["notes"].append(
                    f"stem reduced from {src.shape[1]} to {value.shape[1]} input channels: the checkpoint's extra "
                    f"input channels were dropped"
                )
        elif cls_branch.match(key):  # another number of classes (and, for small scales, another branch width)
            reinit.append(key)
        else:
            mismatched.append(f"{key}: checkpoint {tuple(src.shape)} vs model {tuple(value.shape)}")
    if mismatched:
        hint = ""
        stem = sd.get(stem_key)
        if stem is not None and stem.dim() == 4 and int(stem.shape[0]) in _STEM_WIDTH_TO_SCALE:
            hint = f" The checkpoint looks like scale {_STEM_WIDTH_TO_SCALE[int(stem.shape[0])]!r}"
            hint += f" and the model is scale {getattr(model, 'scale', '?')!r}: build the model with that scale."
        raise HarnessError(
            f"{len(mismatched)} tensor(s) of the checkpoint do not fit the model: "
            + "; ".join(mismatched[:4])
            + (" ..." if len(mismatched) > 4 else "")
            + "."
            + hint
        )
    report["unexpected"] = sorted(k for k in sd if k not in own)
    if strict and report["missing"]:
        raise HarnessError(
            f"the checkpoint lacks {len(report['missing'])} tensor(s) of the model, e.g. "
            f"{', '.join(report['missing'][:4])}; is it a YOLOv8 detection checkpoint in the public layout? "
            f"(load with strict=False to keep the model's init for them)"
        )
    model.load_state_dict(new_sd, strict=False)
    if reinit:
        modules = dict(model.named_modules())
        for prefix in sorted({k.rsplit(".", 1)[0] for k in reinit}):
            modules[prefix].reset_parameters()  # type: ignore[operator]
        model.model[head_idx].reset_class_layer()
        report["reinitialised"] = sorted(reinit)
        ck_nc = [int(sd[k].shape[0]) for k in sd if cls_out.match(k)]
        report["checkpoint_nc"] = ck_nc[0] if ck_nc else None
        layers = (
            "the last layer of every class branch"
            if all(k.rsplit(".", 2)[-2] == "2" for k in reinit)
            else "the class branches"
        )
        report["notes"].append(
            f"the checkpoint has {report['checkpoint_nc']} classes and the model {model.nc}: {layers} "
            f"re-initialised (default init, prior bias on the class logits)"
        )
    report["loaded"] = len(new_sd)
    for note in report["notes"]:
        log.info("YOLOv8 weights: %s", note)
    return report
