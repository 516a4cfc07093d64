"""CMA-Det as a built-in detector plugin, reconstructed from the paper (no public code); network in
``adapters.detectors.cmadet_net``.

Model options (config section ``model``): ``scale`` (trunk size, default s) or explicit ``width``/``depth``,
``align_width``, ``hidden``, ``reduce``, ``grid``, ``flow_gain`` (alignment network), ``reduction`` (BFCFM), ``osr`` (object search
rectification on/off), ``osr_weight``, ``tv_weight``, ``osr_points``, ``osr_radius``, ``osr_temperature``,
``prior_bias``, ``weights`` (a state dict of this reconstruction), and the NMS settings.
"""

from __future__ import annotations

from typing import Any, Mapping

from adapters.detectors._dual import dual_stream_spec, load_weights
from harness.api import Reference
from harness.hookspecs import hookimpl

NAME = "cmadet"
DESCRIPTION = ("CMA-Det: dual YOLOv5s backbones, alignment network warping the visible features into the thermal "
               "frame (global FC field + residual refinement at P5/P4/P3), object search rectification (training "
               "only), bi-directional channel/spatial correction fusion, YOLOv5 PAN neck and anchor head")
LABEL = "reconstructed from the paper"


def build(num_classes: int, in_channels: int = 3, scale: str = "s", width: float | None = None,
          depth: float | None = None, weights: Any = None, conf: float | None = None, iou: float | None = None,
          max_det: int | None = None, multi_label: bool | None = None, max_nms: int | None = None, **options: Any):
    """Build the CMA-Det reconstruction; ``in_channels`` is the thermal stream's (3: the encoding replicated)."""
    from adapters.detectors.cmadet_net import CMADet
    from adapters.detectors.yolo.v5 import check_options, resolve_scale, set_inference_options

    check_options(NAME, options, ("align_width", "hidden", "reduce", "grid", "flow_gain", "reduction", "osr", "osr_weight",
                                  "tv_weight", "osr_points", "osr_radius", "osr_temperature", "prior_bias"))
    w, d = resolve_scale(NAME, scale, width, depth)
    model = CMADet(num_classes, in_channels, width=w, depth=d, **options)
    set_inference_options(model, conf, iou, max_det, multi_label, max_nms)
    if weights is not None:
        model.load_report = load_reconstruction_weights(model, weights)
    return model


def load_reconstruction_weights(model: Any, state_dict: Mapping[str, Any] | Any) -> dict:
    """Load a state dict saved from this reconstruction (there is no official checkpoint); returns the key report."""
    return load_weights(model, state_dict, NAME)


@hookimpl
def register_detectors(register):
    register(dual_stream_spec(name=NAME, build=build, description=DESCRIPTION, label=LABEL,
                              reference=Reference(params_m=33.47, gflops=33.67, source="seed paper", num_classes=8),
                              nms_iou=0.6,
                              load_official=None))  # no official checkpoint exists
