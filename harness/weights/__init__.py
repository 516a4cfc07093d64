"""Importing checkpoints from other codebases, safely: ``harness weights import SRC --out DST.safetensors``.

``import_checkpoint`` reads a pickled PyTorch checkpoint with the restricted unpickler (``harness.weights.unpickle``:
no code from the file runs, no package of the codebase that wrote it is needed), finds the model (EMA weights when
present, ``harness.weights.tree``), extracts its parameters and persistent buffers as a state dict (half precision
cast to float32), describes the layout (``harness.weights.layout``: YOLOv8 scale, classes, input channels; YOLOv5
scale; two input streams), and writes ``DST.safetensors`` with a JSON sidecar ``DST.json`` of what was found.

The result is a plain state dict in the codebase's own key layout, which ``harness run --init``, the
``model.weights`` option of the detectors and ``harness pretrain --init`` read through each detector's importer.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from harness.errors import HarnessError
from harness.io import atomic_write, atomic_write_json, file_digest
from harness.weights.layout import checkpoint_info, detect_layout
from harness.weights.tree import find_model, is_state_dict, module_state_dict, to_float32
from harness.weights.unpickle import CheckpointFormatError, UnsafeCheckpointError, load_checkpoint

__all__ = ["ImportResult", "import_checkpoint", "read_checkpoint_weights", "CheckpointFormatError",
           "UnsafeCheckpointError", "load_checkpoint"]

log = logging.getLogger(__name__)


@dataclass
class ImportResult:
    weights: Path
    sidecar: Path
    info: dict[str, Any]


def read_checkpoint_weights(src: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The model's float32 state dict in a checkpoint and a JSON-ready description of what was found."""
    src = Path(src)
    obj, stubs = load_checkpoint(src)
    model, where = find_model(obj, str(src))
    raw = dict(model) if is_state_dict(model) else module_state_dict(model)
    if not raw:
        raise HarnessError(f"{src}: the model under {where!r} holds no parameters or buffers")
    sd, cast = to_float32(raw)
    layout = detect_layout(model, sd)
    info = {
        "source": str(src),
        "source_sha256": file_digest(src, "sha256"),
        "weights_from": where,
        "tensors": len(sd),
        "parameters": int(sum(t.numel() for t in sd.values() if t.is_floating_point())),
        "cast_to_float32": len(cast),
        "source_dtypes": sorted({c.split(": ")[1] for c in cast}),
        "layout": layout,
        "checkpoint": checkpoint_info(obj),
        "placeholders": sorted(stubs),
    }
    return sd, info


def import_checkpoint(src: str | Path, out: str | Path) -> ImportResult:
    """Convert ``src`` into ``out`` (``.safetensors``) plus ``out`` with suffix ``.json``; see the module docstring."""
    from safetensors.torch import save

    out = Path(out)
    if out.suffix != ".safetensors":
        raise HarnessError(f"--out {out}: the output must be a .safetensors file")
    sd, info = read_checkpoint_weights(src)
    lay = info["layout"]
    meta = {"format": "rgbt-harness-import", "family": str(lay["family"]), "source_sha256": info["source_sha256"]}
    payload = save(sd, metadata=meta)
    atomic_write(out, lambda f: f.write(payload))
    sidecar = out.with_suffix(".json")
    info["weights"] = str(out)
    atomic_write_json(sidecar, info)
    log.debug("%s: %d tensors (%s, scale %s, nc %s, %s input channel(s)%s) -> %s", src, info["tensors"],
             lay["family"], lay["scale"], lay["nc"], lay["in_channels"], ", two streams" if lay["two_stream"] else "",
             out)
    return ImportResult(out, sidecar, json.loads(json.dumps(info)))
