"""CMA-Det as a built-in detector plugin, reconstructed from the paper (no public code); network in
``adapters.detectors.cmadet_net``.

Model options (config section ``model``): ``scale`` (trunk size, default s) or explicit ``width``/``depth``,
``align_width``, ``hidden``, ``reduce``, ``grid``, ``flow_gain`` (alignment network), ``reduction`` (BFCFM),
``osr`` (object search rectification on/off), ``osr_weight``, ``tv_weight``, ``osr_points``, ``osr_radius``,
``osr_temperature``, ``prior_bias``, ``weights`` (a state dict of this reconstruction), and the NMS settings.
"""

from __future__ import annotations

from typing import Any

from adapters.detectors._dual import build_dual, dual_stream_spec
from harness.hookspecs import hookimpl

NAME = "cmadet"
DESCRIPTION = (
    "CMA-Det: dual YOLOv5s backbones, alignment network warping the visible features into the thermal "
    "frame (global FC field + residual refinement at P5/P4/P3), object search rectification (training "
    "only), bi-directional channel/spatial correction fusion, YOLOv5 PAN neck and anchor head"
)
LABEL = "reconstructed from the paper"
#: Options of the network itself (``CMADet``), beyond the trunk size, the weights and the NMS settings.
NET_OPTIONS = (
    "align_width",
    "hidden",
    "reduce",
    "grid",
    "flow_gain",
    "reduction",
    "osr",
    "osr_weight",
    "tv_weight",
    "osr_points",
    "osr_radius",
    "osr_temperature",
    "prior_bias",
)


def build(num_classes: int, in_channels: int = 3, **options: Any):
    """Build the CMA-Det reconstruction; ``in_channels`` is the thermal stream's (3: the encoding replicated);
    ``options``: ``scale`` (default s) or ``width``/``depth``, ``NET_OPTIONS`` (named in the error for an unknown
    option), the weights and the NMS settings (``adapters.detectors._dual.build_dual``)."""
    from adapters.detectors.cmadet_net import CMADet

    return build_dual(CMADet, num_classes, in_channels, {"scale": "s", **options}, known=NET_OPTIONS)


@hookimpl
def register_detectors(register):
    # no official checkpoint exists
    register(dual_stream_spec(NAME, build, DESCRIPTION, LABEL, seed=(33.47, 33.67), nms_iou=0.6, load_official=None))
