"""The seed's detector, "ours": YOLOv8s with the input widened to four channels ``[R, G, B, C2]``.

Registered as a built-in plugin. Model options come from the ``model`` section of the config (``scale``, the loss
gains, ``weights`` to start from public-layout YOLOv8 weights ...); see ``build`` and docs/detectors.md.
"""

from __future__ import annotations

from typing import Any

from harness.api import DetectorSpec, Reference
from harness.hookspecs import hookimpl

DESCRIPTION = "YOLOv8s, 4-channel [R,G,B,C2] input (the seed's detector)"


def build(num_classes: int, in_channels: int = 4, weights: str | None = None, extra_channels: str = "zeros", **kw: Any):
    """Build "ours": a YOLOv8 (``scale`` n/s/m/l/x, default s) for ``in_channels`` = 3 + encoding channels.

    ``weights``: a public-layout YOLOv8 state dict file (``.pt`` of plain tensors or ``.safetensors``, 3 or 4 input
    channels, any number of classes) to initialise from; ``extra_channels`` says how input channels the weights lack
    start ("zeros", "mean" or "random", see ``adapters.detectors.yolo.weights``). The import report is kept in
    ``model.load_report``. Other keyword options (``build_yolov8``'s, with its defaults): ``scale``, ``conf``,
    ``iou``, ``max_det``, ``multi_label``, ``max_nms``, ``reg_max``, loss gains ``box``, ``cls``, ``dfl`` and assigner
    ``topk``, ``alpha``, ``beta``.
    """
    from adapters.detectors.yolo.v8 import build_yolov8
    from adapters.detectors.yolo.weights import load_yolov8_weights

    model = build_yolov8(num_classes, in_channels=in_channels, **kw)
    if weights:
        model.load_report = load_yolov8_weights(model, weights, extra_channels=extra_channels)
    return model


def load_official(model: Any, state_dict: Any, extra_channels: str = "zeros") -> dict:
    """Import a public-layout YOLOv8 state dict (mapping or file path) into ``model``; returns the report."""
    from adapters.detectors.yolo.weights import load_yolov8_weights

    return load_yolov8_weights(model, state_dict, extra_channels=extra_channels)


@hookimpl
def register_detectors(register):
    register(
        DetectorSpec(
            name="ours",
            build=build,
            input_kind="single",
            description=DESCRIPTION,
            reference=Reference(params_m=11.13, gflops=28.5, source="seed paper", num_classes=8),
            load_official=load_official,
        )
    )
