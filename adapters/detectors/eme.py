"""EME as a built-in detector plugin: YOLOv5l early fusion of RGB and thermal, optionally through ShaPE.

The host feeds it as a dual-stream detector, ``(rgb [B,3,H,W], thermal [B,3,H,W])`` with the thermal encoding
replicated to three channels (ir8 by default, as the public code reads its thermal images), and the model
concatenates them into the 6-channel early-fusion input. The network is in ``adapters.detectors.eme_net``.

Model options (config section ``model``): ``scale`` (YOLOv5 size n/s/m/l, default l) or explicit
``width``/``depth``, ``shape`` (add the ShaPE stem, default off: the seed's figures are plain early fusion),
``prior_bias`` (YOLOv5's bias prior, on), ``weights`` (a YOLOv5-layout state dict file), and the NMS settings.
"""

from __future__ import annotations

from typing import Any, Mapping

from adapters.detectors._dual import build_dual, dual_stream_spec, load_weights
from harness.hookspecs import hookimpl

NAME = "eme"
DESCRIPTION = (
    "EME: YOLOv5l on the 6-channel early-fusion input [RGB, thermal x3] (the configuration the seed's "
    "46.15 M / 109.2 GFLOPs describe); model.shape=true adds the ShaPE shape-priority stem. The public "
    "EME code is MMDetection GFL-R50 with CLIP weak supervision and CoreKD distillation"
)
LABEL = "YOLOv5l early fusion (+ShaPE option); weak supervision and distillation omitted"
#: Options of the network itself (``EME``: ShaPE off, the bias prior on), beyond the trunk size, the weights and the
#: NMS settings.
NET_OPTIONS = ("shape", "prior_bias")


def build(num_classes: int, in_channels: int = 3, **options: Any):
    """Build EME for ``num_classes``; ``in_channels`` is the thermal stream's (concatenated after RGB);
    ``options``: ``scale`` (default l) or ``width``/``depth``, ``NET_OPTIONS``, the weights and the NMS settings
    (``adapters.detectors._dual.build_dual``)."""
    from adapters.detectors.eme_net import EME

    return build_dual(EME, num_classes, in_channels, {"scale": "l", **options}, NET_OPTIONS)


def load_official(model: Any, state_dict: Mapping[str, Any] | Any) -> dict:
    """Load weights in the YOLOv5 (v6.x) layout (``model.0`` ... ``model.24``; ShaPE as ``stem.conv.weight``)."""
    return load_weights(model, state_dict, NAME)


@hookimpl
def register_detectors(register):
    register(
        dual_stream_spec(NAME, build, DESCRIPTION, LABEL, seed=(46.15, 109.2), nms_iou=0.6, load_official=load_official)
    )
