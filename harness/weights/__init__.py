"""Importing checkpoints from other codebases, safely: ``harness weights import SRC --out DST.safetensors``.

``import_checkpoint`` reads a pickled PyTorch checkpoint with the restricted unpickler (``harness.weights.unpickle``:
no code from the file runs, no package of the codebase that wrote it is needed), finds the model (EMA weights when
present, ``harness.weights.tree``), extracts its parameters and persistent buffers as a state dict (half precision
cast to float32), describes the layout (``harness.weights.layout``: YOLOv8 scale, classes, input channels; YOLOv5
scale; two input streams), and writes ``DST.safetensors`` in pieces of at most 16 MiB with a JSON sidecar
``DST.json`` of what was found. The work is bounded by the file's size (``harness.weights.unpickle``): the tensors
and their names as float32 may take at most ``SIZE_MULTIPLE`` (4) x the file's bytes, the sidecar's copy of the
metadata is bounded (``harness.weights.layout``), and an allocation that fails anyway is a one-line error naming
the file.

The result is a plain state dict in the codebase's own key layout, which ``harness run --init``, the
``model.weights`` option of the detectors and ``harness pretrain --init`` read through each detector's importer.
"""

from __future__ import annotations

import contextlib
import json
import logging
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Iterator

import torch

from harness.errors import HarnessError
from harness.io import atomic_write, atomic_write_json, file_digest
from harness.weights.layout import checkpoint_info, detect_layout
from harness.weights.tree import find_model, is_state_dict, module_state_dict, to_float32
from harness.weights.unpickle import (
    PIECE_BYTES,
    CheckpointFormatError,
    CheckpointLimitError,
    ForeignObjectError,
    Limits,
    UnsafeCheckpointError,
    human,
    load_checkpoint,
    load_plain,
    out_itemsize,
)

__all__ = [
    "ImportResult",
    "import_checkpoint",
    "read_checkpoint_weights",
    "read_safetensors",
    "write_safetensors",
    "CheckpointFormatError",
    "CheckpointLimitError",
    "ForeignObjectError",
    "UnsafeCheckpointError",
    "load_checkpoint",
    "load_plain",
]

log = logging.getLogger(__name__)


@dataclass
class ImportResult:
    weights: Path
    sidecar: Path
    info: dict[str, Any]


MAX_PLACEHOLDER_NAMES = 200


@contextlib.contextmanager
def _one_line(src: Path) -> Iterator[None]:
    """Allocation failures and other exhaustion become one-line errors naming the file."""
    try:
        yield
    except MemoryError:
        raise CheckpointLimitError(f"{src}: ran out of memory importing it ({human(_size(src))} on disk)") from None
    except RecursionError:
        raise CheckpointFormatError(f"{src}: nested too deeply to import") from None
    except RuntimeError as exc:
        if "alloc" not in str(exc).lower():
            raise
        raise CheckpointLimitError(
            f"{src}: ran out of memory importing it ({str(exc).splitlines()[0][:120]})"
        ) from None


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _read_raw(src: Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The model's tensors as stored (views on the file's storages) and the description; bounded by the file's
    size: the tensors and their names, as float32, may take at most ``SIZE_MULTIPLE`` x the file's bytes."""
    limits = Limits(_size(src))
    obj, stubs = load_checkpoint(src)
    model, where = find_model(obj, str(src))
    try:
        raw = dict(model) if is_state_dict(model) else module_state_dict(model, limits.tensor_bytes)
    except CheckpointLimitError as exc:
        raise CheckpointLimitError(f"{src}: {exc} (the limit is {limits.of_file()})") from None
    except HarnessError as exc:
        raise type(exc)(f"{src}: {exc}") from None
    if not raw:
        raise HarnessError(f"{src}: the model under {where!r} holds no parameters or buffers")
    if not all(isinstance(k, str) for k in raw):
        raise CheckpointFormatError(f"{src}: the state dict under {where!r} has keys that are not strings")
    total = sum(len(k) + t.numel() * out_itemsize(t.dtype) for k, t in raw.items())
    if total > limits.tensor_bytes:
        raise CheckpointLimitError(
            f"{src}: its model's tensors add up to {human(total)} as float32, over {limits.of_file()}; refused"
        )
    cast = [
        f"{k}: {str(t.dtype).replace('torch.', '')}"
        for k, t in raw.items()
        if t.is_floating_point() and t.dtype != torch.float32
    ]
    layout = detect_layout(model, raw)
    names = sorted(stubs)
    info = {
        "source": str(src),
        "source_sha256": file_digest(src, "sha256"),
        "weights_from": where,
        "tensors": len(raw),
        "parameters": int(sum(t.numel() for t in raw.values() if t.is_floating_point())),
        "cast_to_float32": len(cast),
        "source_dtypes": sorted({c.split(": ")[1] for c in cast}),
        "layout": layout,
        "checkpoint": checkpoint_info(obj),
        "placeholders": [n[:200] for n in names[:MAX_PLACEHOLDER_NAMES]]
        + ([f"... and {len(names) - MAX_PLACEHOLDER_NAMES} more"] if len(names) > MAX_PLACEHOLDER_NAMES else []),
    }
    return raw, info


def read_checkpoint_weights(src: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The model's float32 state dict in a checkpoint and a JSON-ready description of what was found."""
    src = Path(src)
    with _one_line(src):
        raw, info = _read_raw(src)
        sd, _ = to_float32(raw)
    return sd, info


def import_checkpoint(src: str | Path, out: str | Path) -> ImportResult:
    """Convert ``src`` into ``out`` (``.safetensors``) plus ``out`` with suffix ``.json``; see the module docstring."""
    src, out = Path(src), Path(out)
    if out.suffix != ".safetensors":
        raise HarnessError(f"--out {out}: the output must be a .safetensors file")
    with _one_line(src):
        raw, info = _read_raw(src)
        lay = info["layout"]
        meta = {"format": "rgbt-harness-import", "family": str(lay["family"]), "source_sha256": info["source_sha256"]}
        atomic_write(out, lambda f: write_safetensors(f, raw, meta))
        sidecar = out.with_suffix(".json")
        info["weights"] = str(out)
        atomic_write_json(sidecar, info)
    log.debug(
        "%s: %d tensors (%s, scale %s, nc %s, %s input channel(s)%s) -> %s",
        src,
        info["tensors"],
        lay["family"],
        lay["scale"],
        lay["nc"],
        lay["in_channels"],
        ", two streams" if lay["two_stream"] else "",
        out,
    )
    return ImportResult(out, sidecar, json.loads(json.dumps(info)))


#: safetensors' names of the dtypes an import writes
_ST_DTYPES = {
    torch.float32: "F32",
    torch.float64: "F64",
    torch.float16: "F16",
    torch.bfloat16: "BF16",
    torch.int64: "I64",
    torch.int32: "I32",
    torch.int16: "I16",
    torch.int8: "I8",
    torch.uint8: "U8",
    torch.bool: "BOOL",
    torch.complex64: "C64",
}


def _pieces(t: torch.Tensor, limit: int) -> Iterator[torch.Tensor]:
    """Views of ``t`` that cover it in row-major order, each at most ``limit`` bytes as float32 (or one element):
    a tensor is converted and written piece by piece, whatever its strides."""
    stack = [t]
    while stack:
        p = stack.pop()
        if p.dim() == 0 or p.numel() * 4 <= limit:
            yield p
            continue
        step = max(1, limit // max(p[0].numel() * 4, 1))  # slices along the first dimension per piece
        stack.extend(reversed(p.unbind(0) if step == 1 else p.split(step)))


def read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    """Every tensor of the ``.safetensors`` file ``path``; a file the library cannot read is a
    ``CheckpointFormatError`` ``"<path>: not a readable safetensors file (<why>)"``, as ``load_plain``'s start."""
    from safetensors.torch import load_file

    try:
        return dict(load_file(str(path)))
    except Exception as exc:
        raise CheckpointFormatError(f"{path}: not a readable safetensors file ({exc})") from None


def write_safetensors(f: IO[bytes], tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    """Write ``tensors`` (floating ones cast to float32) in the safetensors format, one piece of at most
    ``PIECE_BYTES`` at a time: the import holds no converted copy of a whole tensor besides the file's storages."""
    header: dict[str, Any] = {"__metadata__": metadata}
    offset = 0
    for name, t in tensors.items():
        dtype = torch.float32 if t.is_floating_point() else t.dtype
        if dtype not in _ST_DTYPES:
            raise CheckpointFormatError(f"tensor {name!r} has dtype {dtype}, which safetensors cannot store")
        nbytes = t.numel() * dtype.itemsize
        header[name] = {"dtype": _ST_DTYPES[dtype], "shape": list(t.shape), "data_offsets": [offset, offset + nbytes]}
        offset += nbytes
    text = json.dumps(header, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned, as the reference writer aligns it
    f.write(struct.pack("<Q", len(text)))
    f.write(text)
    for t in tensors.values():
        if t.numel() == 0:
            continue
        for piece in _pieces(t.detach(), PIECE_BYTES):
            piece = piece.float() if piece.is_floating_point() and piece.dtype != torch.float32 else piece
            f.write(piece.contiguous().reshape(-1).view(torch.uint8).numpy().data)
