"""What a checkpoint's tensors are: YOLOv8 (Ultralytics layout) or YOLOv5 (anchor head), its scale, classes,
input channels, and whether it has two input streams (ICAFusion's layout).

Everything is read from the tensors' names and shapes, cross-checked with the model's recorded ``yaml`` (the model
description Ultralytics and YOLOv5 keep on the model) where it has one. Stem widths per scale are the public ones:
n 16, s 32, m 48, l 64, x 80 output channels in the first convolution (YOLOv5 from v6.0 and YOLOv8 alike).
"""

from __future__ import annotations

import re
from typing import Any, Mapping

import torch

from harness.weights.unpickle import Stub

STEM_WIDTH_TO_SCALE = {16: "n", 32: "s", 48: "m", 64: "l", 80: "x"}
WIDTH_MULTIPLE_TO_SCALE = {0.25: "n", 0.5: "s", 0.75: "m", 1.0: "l", 1.25: "x"}
_TOP = re.compile(r"^model\.(\d+)\.")


def _simple(value: Any) -> Any:
    """JSON-ready copies of plain values (placeholders and tensors are named, not copied)."""
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, Mapping):
        return {str(k): _simple(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_simple(v) for v in value]
    if isinstance(value, torch.Tensor):
        return f"<tensor {tuple(value.shape)}>"
    if isinstance(value, Stub):
        return f"<{value.stub_name}>"
    return str(value)


def _stems(sd: Mapping[str, torch.Tensor]) -> list[tuple[int, torch.Tensor, bool]]:
    """Top-level layers that read an image: ``(index, conv weight, focus)``. Layer 0 always does; another layer
    does when its convolution takes as few channels as layer 0's (a second input stream: ICAFusion's layout)."""
    convs = []
    for key, w in sd.items():
        m = re.match(r"^model\.(\d+)\.conv\.(conv\.)?weight$", key)
        if m is not None and w.dim() == 4:
            convs.append((int(m.group(1)), w, m.group(2) is not None))
    convs.sort(key=lambda t: t[0])
    if not convs or convs[0][0] != 0:
        return []
    cin0 = int(convs[0][1].shape[1])
    return [c for c in convs if int(c[1].shape[1]) == cin0 and cin0 <= 12]


def detect_layout(model: Any, sd: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """``{"family", "scale", "nc", "in_channels", "two_stream", "head_index", "names", "suggested_detector", ...}``."""
    yaml = model.state.get("yaml") if isinstance(model, Stub) else None
    yaml = yaml if isinstance(yaml, Mapping) else {}
    cls = model.stub_name if isinstance(model, Stub) else None
    tops = sorted({int(m.group(1)) for k in sd for m in [_TOP.match(k)] if m})
    head = tops[-1] if tops else None
    out: dict[str, Any] = {"family": "unknown", "model_class": cls, "layers": len(tops), "head_index": head,
                           "scale": None, "nc": None, "in_channels": None, "two_stream": False, "names": None,
                           "suggested_detector": None, "notes": []}
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
    if isinstance(yaml.get("nc"), int):
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
    if isinstance(yaml.get("scale"), str) and yaml["scale"]:
        out["scale"] = yaml["scale"]
    elif isinstance(yaml.get("width_multiple"), (int, float)) and out["family"] == "yolov5":
        out["scale"] = WIDTH_MULTIPLE_TO_SCALE.get(float(yaml["width_multiple"]), out["scale"])
    names = model.state.get("names") if isinstance(model, Stub) else None
    if isinstance(names, Mapping):
        out["names"] = [str(names[k]) for k in sorted(names, key=lambda k: int(k) if str(k).isdigit() else str(k))]
    elif isinstance(names, (list, tuple)):
        out["names"] = [str(n) for n in names]
    if out["family"] == "yolov8" and not out["two_stream"]:
        out["suggested_detector"] = "ours"
    elif out["family"] == "yolov5" and out["two_stream"]:
        out["suggested_detector"] = "icafusion" if head == 37 else None
    elif out["family"] == "yolov5":
        out["suggested_detector"] = "eme"
    if yaml:
        out["yaml"] = _simple({k: v for k, v in yaml.items() if k in ("nc", "scale", "scales", "depth_multiple",
                                                                     "width_multiple", "ch", "anchors")})
    return out


def checkpoint_info(obj: Any) -> dict[str, Any]:
    """The plain training metadata beside the model (epoch, fitness, date, versions, training arguments)."""
    if not isinstance(obj, Mapping):
        return {}
    keep = ("epoch", "best_fitness", "date", "version", "updates", "train_args", "opt", "train_metrics", "license")
    return {k: _simple(obj[k]) for k in keep if k in obj}
