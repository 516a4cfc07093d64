"""ICAFusion as a built-in detector plugin (dual-stream; the network is in ``adapters.detectors.icafusion_net``).

Model options (config section ``model``): ``scale`` (YOLOv5 size n/s/m/l, default l as published) or explicit
``width``/``depth`` multiples, ``tokens`` (fusion token grids at P3/P4/P5, default 20/16/10), ``heads``,
``block_exp``, ``dropout``, ``prior_bias`` (YOLOv5's objectness/class bias prior; off as in the official code),
``sort_obj_iou``, ``weights`` (a state dict file in the official key layout), and the NMS settings ``conf``,
``iou``, ``max_det``, ``multi_label``, ``max_nms``.
"""

from __future__ import annotations

from typing import Any, Mapping

from adapters.detectors._dual import build_dual, dual_stream_spec, load_weights
from harness.hookspecs import hookimpl

NAME = "icafusion"
DESCRIPTION = (
    "ICAFusion: two YOLOv5l streams (RGB, thermal) fused by iterative cross-attention blocks at P3/P4/P5, "
    "YOLOv5 PAN neck and anchor head; official yolov5l_Transfusion layout"
)
LABEL = "official architecture and checkpoint layout"
#: Options of the network itself (``ICAFusion``, defaults as published: tokens 20/16/10, 8 heads, expansion 4,
#: dropout 0.1, no bias prior, IoU-sorted objectness), beyond the trunk size, the weights and the NMS settings.
NET_OPTIONS = ("tokens", "heads", "block_exp", "dropout", "prior_bias", "sort_obj_iou")


def build(num_classes: int, in_channels: int = 3, **options: Any):
    """Build ICAFusion for ``num_classes``; ``in_channels`` is the thermal stream's (3: the encoding replicated);
    ``options``: ``scale`` (default l) or ``width``/``depth``, ``NET_OPTIONS``, the weights and the NMS settings
    (``adapters.detectors._dual.build_dual``)."""
    from adapters.detectors.icafusion_net import ICAFusion

    return build_dual(ICAFusion, num_classes, in_channels, {"scale": "l", **options}, NET_OPTIONS)


def load_official(model: Any, state_dict: Mapping[str, Any] | Any) -> dict:
    """Load weights in the official ICAFusion layout (``model.0`` ... ``model.37``, incl. the unused modules).

    ``state_dict``: a mapping or a file path. Returns ``{"loaded", "missing", "unexpected", "mismatched"}``.
    """
    return load_weights(model, state_dict, NAME)


@hookimpl
def register_detectors(register):
    register(
        dual_stream_spec(
            NAME, build, DESCRIPTION, LABEL, seed=(120.24, 191.68), nms_iou=0.5, load_official=load_official
        )
    )
