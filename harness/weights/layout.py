"""What a checkpoint's tensors are: YOLOv8 (Ultralytics layout) or YOLOv5 (anchor head), its scale, classes,
input channels, and whether it has two input streams (ICAFusion's layout).

Everything is read from the tensors' names and shapes, cross-checked with the model's recorded ``yaml`` (the model
description Ultralytics and YOLOv5 keep on the model) where it has one. Stem widths per scale are the public ones:
n 16, s 32, m 48, l 64, x 80 output channels in the first convolution (YOLOv5 from v6.0 and YOLOv8 alike).
"""

from __future__ import annotations

import datetime
import itertools
import re
from typing import Any, Mapping

import numpy as np
import torch

from harness.weights.unpickle import Stub, brief

STEM_WIDTH_TO_SCALE = {16: "n", 32: "s", 48: "m", 64: "l", 80: "x"}
WIDTH_MULTIPLE_TO_SCALE = {0.25: "n", 0.5: "s", 0.75: "m", 1.0: "l", 1.25: "x"}
_TOP = re.compile(r"^model\.(\d{1,9})\.")


#: Bounds of what the sidecar copies from a checkpoint's metadata (a hostile file can hold anything there).
DESCRIBE_VALUES = 2_000
DESCRIBE_DEPTH = 32
DESCRIBE_STRING = 500
_SMALL = 16


def _leaf(value: Any) -> Any:
    """A JSON-ready copy of a value that is not expanded (``None`` when it is a container to expand)."""
    if isinstance(value, str):
        return value if len(value) <= DESCRIBE_STRING else value[:DESCRIBE_STRING] + f"... ({len(value)} chars)"
    if isinstance(value, bool) or value is None or isinstance(value, float):
        return value
    if isinstance(value, int):
        return value if value.bit_length() < 64 else brief(value)
    if isinstance(value, torch.Tensor):
        return f"<tensor {tuple(value.shape)}>"
    if isinstance(value, Stub):
        return f"<{value.stub_name[:200]}>"
    if isinstance(value, (np.generic, datetime.date, datetime.timedelta, torch.dtype, torch.device, complex)):
        return str(value)
    if isinstance(value, np.ndarray):
        return str(value) if value.size <= _SMALL else f"<ndarray {value.shape} {value.dtype}>"
    if isinstance(value, (Mapping, list, tuple, set, frozenset)):
        return None
    return brief(value)


def _container(value: Any) -> bool:
    return isinstance(value, (Mapping, list, tuple, set, frozenset))


def _key(k: Any) -> str:
    if isinstance(k, str):
        return k
    return str(k) if isinstance(k, int) and k.bit_length() < 64 else brief(k)


def _simple(value: Any) -> Any:
    """JSON-ready copies of plain values (placeholders and tensors are named, not copied), walked with an explicit
    stack and bounded: at most ``DESCRIBE_VALUES`` values, ``DESCRIBE_DEPTH`` levels and ``DESCRIBE_STRING``
    characters a string. A container met again (shared, or containing itself) is written once; its later places
    say ``<same object as at PATH>``, so a structure doubled forty times stays small. Small flat containers
    (``_SMALL`` plain values) are simply repeated."""
    if not _container(value):
        return _leaf(value)
    seen: dict[int, str] = {}
    left = DESCRIBE_VALUES

    def open_(v: Any, path: str, depth: int) -> tuple[Any, Any]:
        """The empty output container for ``v`` and an iterator of its (key, child) pairs, or a marker and None."""
        head = list(itertools.islice(v.values() if isinstance(v, Mapping) else v, _SMALL + 1))
        shareable = len(head) > _SMALL or any(_container(c) for c in head)
        if shareable and id(v) in seen:
            return f"<same object as at {seen[id(v)] or '<top>'}>", None
        if depth >= DESCRIBE_DEPTH:
            return f"<{type(v).__name__} nested deeper than {DESCRIBE_DEPTH} levels>", None
        if shareable:
            seen[id(v)] = path[:200]
        if isinstance(v, Mapping):
            return {}, ((_key(k), c) for k, c in v.items())
        return [], enumerate(v)

    root, items = open_(value, "", 0)
    stack = [(root, items, "", 0)] if items is not None else []
    while stack:
        out, items, path, depth = stack[-1]
        pair = next(items, None)
        if pair is None:
            stack.pop()
            continue
        key, child = pair
        left -= 1
        if left < 0:
            _put(out, key, f"<truncated: more than {DESCRIBE_VALUES} values>")
            break
        if not _container(child):
            _put(out, key, _leaf(child))
            continue
        sub_path = f"{path}.{key}" if isinstance(key, str) else f"{path}[{key}]"
        sub, sub_items = open_(child, sub_path.lstrip("."), depth + 1)
        _put(out, key, sub)
        if sub_items is not None:
            stack.append((sub, sub_items, sub_path, depth + 1))
    return root


def _put(container: Any, key: Any, value: Any) -> None:
    if isinstance(container, dict):
        container[key] = value
    else:
        container.append(value)


def _stems(sd: Mapping[str, torch.Tensor]) -> list[tuple[int, torch.Tensor, bool]]:
    """Top-level layers that read an image: ``(index, conv weight, focus)``. Layer 0 always does; another layer
    does when its convolution takes as few channels as layer 0's (a second input stream: ICAFusion's layout)."""
    convs = []
    for key, w in sd.items():
        m = re.match(r"^model\.(\d{1,9})\.conv\.(conv\.)?weight$", key)
        if m is not None and w.dim() == 4:
            convs.append((int(m.group(1)), w, m.group(2) is not None))
    convs.sort(key=lambda t: t[0])
    if not convs or convs[0][0] != 0:
        return []
    cin0 = int(convs[0][1].shape[1])
    return [c for c in convs if int(c[1].shape[1]) == cin0 and cin0 <= 12]


MAX_NAMES = 10_000


def _names(names: Any) -> list[str] | None:
    """Class names from a ``{index: name}`` mapping (Ultralytics) or a list (YOLOv5); ``None`` when they are
    anything else (at most ``MAX_NAMES`` names, each cut at 200 characters)."""
    if isinstance(names, Mapping) and len(names) <= MAX_NAMES:
        index = {}
        for k in names:
            i = (
                k
                if isinstance(k, int) and not isinstance(k, bool)
                else (int(k) if isinstance(k, str) and k.isdigit() and len(k) < 10 else None)
            )
            if i is None or i in index:
                return None
            index[i] = k
        values = [names[index[i]] for i in sorted(index)]
    elif isinstance(names, (list, tuple)) and len(names) <= MAX_NAMES:
        values = list(names)
    else:
        return None
    if not all(
        isinstance(v, (str, int)) and not isinstance(v, bool) and (not isinstance(v, int) or v.bit_length() < 64)
        for v in values
    ):
        return None
    return [str(v)[:200] for v in values]


def detect_layout(model: Any, sd: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """``{"family", "scale", "nc", "in_channels", "two_stream", "head_index", "names", "suggested_detector", ...}``."""
    yaml = model.state.get("yaml") if isinstance(model, Stub) else None
    yaml = yaml if isinstance(yaml, Mapping) else {}
    cls = model.stub_name[:200] if isinstance(model, Stub) else None
    tops = sorted({int(m.group(1)) for k in sd for m in [_TOP.match(k)] if m})
    head = tops[-1] if tops else None
    out: dict[str, Any] = {
        "family": "unknown",
        "model_class": cls,
        "layers": len(tops),
        "head_index": head,
        "scale": None,
        "nc": None,
        "in_channels": None,
        "two_stream": False,
        "names": None,
        "suggested_detector": None,
        "notes": [],
    }
    if head is None:
        out["notes"].append("no 'model.<i>.' layers: not a YOLO-family module tree")
        return out
    h = f"model.{head}."
    if f"{h}dfl.conv.weight" in sd or any(k.startswith(f"{h}cv3.") for k in sd):
        out["family"] = "yolov8"
        cls_w = [sd[k] for k in sd if re.match(rf"^model\.{head}\.cv3\.\d+\.2\.weight$", k)]
        out["nc"] = int(cls_w[0].shape[0]) if cls_w else None
    elif f"{h}m.0.weight" in sd:
        out["family"] = "yolov5"
        anchors = sd.get(f"{h}anchors")
        na = int(anchors.shape[1]) if anchors is not None and anchors.dim() == 3 else 3
        out["anchors_per_level"] = na
        out["nc"] = int(sd[f"{h}m.0.weight"].shape[0]) // na - 5
    else:
        out["notes"].append(f"layer {head} is neither a YOLOv8 (cv2/cv3/dfl) nor a YOLOv5 (m.*, anchors) head")
    if isinstance(yaml.get("nc"), int) and not isinstance(yaml["nc"], bool) and 0 <= yaml["nc"] < 1_000_000:
        if out["nc"] is not None and yaml["nc"] != out["nc"]:
            out["notes"].append(f"the model's yaml says nc={yaml['nc']}, the head's tensors {out['nc']}")
        out["nc"] = out["nc"] if out["nc"] is not None else yaml["nc"]

    stems = _stems(sd)
    if stems:
        _, w, focus = stems[0]
        out["in_channels"] = int(w.shape[1]) // (4 if focus else 1)
        out["stem"] = "focus" if focus else "conv"
        width = int(w.shape[0])
        out["scale"] = STEM_WIDTH_TO_SCALE.get(width)
        out["two_stream"] = len(stems) > 1
        if out["two_stream"]:
            out["stream_stems"] = [i for i, _, _ in stems]
    if isinstance(yaml.get("scale"), str) and 0 < len(yaml["scale"]) <= 16:
        out["scale"] = yaml["scale"]
    elif isinstance(yaml.get("width_multiple"), (int, float)) and out["family"] == "yolov5":
        out["scale"] = WIDTH_MULTIPLE_TO_SCALE.get(float(yaml["width_multiple"]), out["scale"])
    names = _names(model.state.get("names") if isinstance(model, Stub) else None)
    if names is not None:
        out["names"] = names
    elif isinstance(model, Stub) and "names" in model.state:
        out["notes"].append(
            f"the model's names ({brief(model.state['names'])}) are not a list of at most {MAX_NAMES} class names"
        )
    if out["family"] == "yolov8" and not out["two_stream"]:
        out["suggested_detector"] = "ours"
    elif out["family"] == "yolov5" and out["two_stream"]:
        out["suggested_detector"] = "icafusion" if head == 37 else None
    elif out["family"] == "yolov5":
        out["suggested_detector"] = "eme"
    if yaml:
        out["yaml"] = _simple(
            {
                k: v
                for k, v in yaml.items()
                if k in ("nc", "scale", "scales", "depth_multiple", "width_multiple", "ch", "anchors")
            }
        )
    return out


def checkpoint_info(obj: Any) -> dict[str, Any]:
    """The plain training metadata beside the model (epoch, fitness, date, versions, training arguments)."""
    if not isinstance(obj, Mapping):
        return {}
    keep = ("epoch", "best_fitness", "date", "version", "updates", "train_args", "opt", "train_metrics", "license")
    return {k: _simple(obj[k]) for k in keep if k in obj}
