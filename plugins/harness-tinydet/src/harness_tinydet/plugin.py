"""The plugin module named by the ``harness`` entry point: it registers the detectors with the harness."""

from __future__ import annotations

from harness import DetectorSpec, hookimpl

from harness_tinydet.model import build_tinydet, build_tinydet_dual


@hookimpl
def register_detectors(register):
    register(DetectorSpec(
        name="tinydet",
        build=build_tinydet,
        input_kind="single",
        description="tiny anchor-free two-level detector (example plugin)",
        label="example plugin",
    ))
    register(DetectorSpec(
        name="tinydet-dual",
        build=build_tinydet_dual,
        input_kind="dual",
        description="two-stream TinyDet: RGB and thermal stems summed at stride 4 (example plugin)",
        label="example plugin",
        thermal_channels=1,
    ))
