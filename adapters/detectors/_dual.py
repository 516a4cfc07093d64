"""What the dual-stream YOLOv5-family plugins (ICAFusion, EME, CMA-Det) share: their spec and their weight loading.

Kept free of torch imports so that registering the plugins stays fast (``harness --help``, ``harness list``).
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

from harness.api import DetectorSpec, Reference


def load_weights(model: Any, state_dict: Mapping[str, Any] | Any, name: str) -> dict:
    """Load a YOLOv5-layout state dict (a mapping or a file path) into ``model``; returns the key report
    (``loaded``, ``missing``, ``unexpected``, ``mismatched``)."""
    from adapters.detectors.yolo.v5 import load_state_dict_report, read_weights

    return load_state_dict_report(model, read_weights(state_dict, name), name)


def dual_stream_spec(*, name: str, build: Callable[..., Any], description: str, label: str, reference: Reference,
                     nms_iou: float, load_official: Callable[..., dict] | None) -> DetectorSpec:
    """A dual-stream detector fed ``(rgb, thermal)``, the thermal encoding (ir8 by default, as the baselines' own
    code reads its thermal images) replicated to three channels."""
    return DetectorSpec(
        name=name,
        build=build,
        input_kind="dual",
        description=description,
        label=label,
        reference=reference,
        default_thermal_encoding="ir8",
        thermal_channels=3,
        defaults={"eval": {"iou": nms_iou}},
        load_official=load_official,
    )
