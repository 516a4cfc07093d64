"""ICAFusion as a built-in detector plugin (dual-stream; the network is in ``adapters.detectors.icafusion_net``).

Model options (config section ``model``): ``scale`` (YOLOv5 size n/s/m/l, default l as published) or explicit
``width``/``depth`` multiples, ``tokens`` (fusion token grids at P3/P4/P5, default 20/16/10), ``heads``,
``block_exp``, ``dropout``, ``prior_bias`` (YOLOv5's objectness/class bias prior; off as in the official code),
``sort_obj_iou``, ``weights`` (a state dict file in the official key layout), and the NMS settings ``conf``,
``iou``, ``max_det``, ``multi_label``, ``max_nms``.
"""

from __future__ import annotations

from typing import Any, Mapping

from adapters.detectors._dual import dual_stream_spec, finish_build, finish_options, load_weights
from harness.hookspecs import hookimpl

NAME = "icafusion"
DESCRIPTION = (
    "ICAFusion: two YOLOv5l streams (RGB, thermal) fused by iterative cross-attention blocks at P3/P4/P5, "
    "YOLOv5 PAN neck and anchor head; official yolov5l_Transfusion layout"
)
LABEL = "official architecture and checkpoint layout"


def build(
    num_classes: int,
    in_channels: int = 3,
    scale: str = "l",
    width: float | None = None,
    depth: float | None = None,
    tokens: Any = (20, 16, 10),
    heads: int = 8,
    block_exp: int = 4,
    dropout: float = 0.1,
    prior_bias: bool = False,
    sort_obj_iou: bool = True,
    **options: Any,
):
    """Build ICAFusion for ``num_classes``; ``in_channels`` is the thermal stream's (3: the encoding replicated);
    ``options``: the weights and the NMS settings (``adapters.detectors._dual.FINISH_OPTIONS``)."""
    from adapters.detectors.icafusion_net import ICAFusion
    from adapters.detectors.yolo.v5 import resolve_scale

    finish = finish_options(NAME, options)
    w, d = resolve_scale(NAME, scale, width, depth)
    model = ICAFusion(
        num_classes,
        in_channels,
        width=w,
        depth=d,
        tokens=tuple(tokens),
        heads=heads,
        block_exp=block_exp,
        dropout=dropout,
        prior_bias=prior_bias,
        sort_obj_iou=sort_obj_iou,
    )
    return finish_build(model, NAME, **finish)


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
