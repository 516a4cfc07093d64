"""The plugin module named by the ``harness`` entry point: it registers the detectors with the harness.

The builders import the model (and torch) only when the harness actually builds a detector.
"""

from __future__ import annotations

from typing import Any

from harness import DetectorSpec, hookimpl


def build_tinydet(num_classes: int, in_channels: int = 4, **model_cfg: Any):
    from harness_tinydet.model import TinyDet, check_options

    return TinyDet(num_classes, in_channels=in_channels, **check_options(model_cfg))


def build_tinydet_dual(num_classes: int, in_channels: int = 1, **model_cfg: Any):
    from harness_tinydet.model import TinyDetDual, check_options

    return TinyDetDual(num_classes, in_channels=in_channels, **check_options(model_cfg))


@hookimpl
def register_detectors(register):
    register(
        DetectorSpec(
            name="tinydet",
            build=build_tinydet,
            input_kind="single",
            description="tiny anchor-free two-level detector (example plugin)",
            label="example plugin",
            defaults={"train": {"lr0": 0.04}},
        )
    )
    register(
        DetectorSpec(
            name="tinydet-dual",
            build=build_tinydet_dual,
            input_kind="dual",
            description="two-stream TinyDet: RGB and thermal stems summed at stride 4 (example plugin)",
            label="example plugin",
            thermal_channels=1,
            defaults={"train": {"lr0": 0.04}},
        )
    )
