"""SAFit, the scale-adaptive fitness of RGBT-Tiny: a matching measure that blends IoU and NWD by object size.

For a detection box ``d`` and a ground-truth box ``g`` (COCO ``[x, y, w, h]``) and ``C = 32`` pixels::

    IoU(d, g)  = |d ∩ g| / |d ∪ g|                       (crowd GT: |d ∩ g| / |d|, as in COCO)
    NWD(d, g)  = exp(-||(px_d, py_d, w_d/2, h_d/2) - (px_g, py_g, w_g/2, h_g/2)||_2 / C)
    w(A_g)     = sigmoid((sqrt(A_g) - C) / C),  A_g = w_g * h_g (from the GT box, not its ``area`` field)
    SAFit(d,g) = w(A_g) * IoU(d, g) + (1 - w(A_g)) * NWD(d, g)

``(px, py)`` is the point of the box that NWD models as the Gaussian mean. The NWD paper and the SAFit paper define
it as the box centre ``(x + w/2, y + h/2)`` (``anchor="center"``, the default here). The official RGBT-Tiny
evaluation and training code use the top-left corner ``(x, y)`` instead (``anchor="topleft"``); choose that one to
reproduce numbers published with the official code. The two agree whenever the two boxes have the same size.

Where this implementation deliberately differs from the official evaluation code (see docs/evaluation.md):

* the NWD anchor defaults to the centre (top-left available, as above);
* boxes are converted to float64 before anything is computed, so integer GT boxes are never floored when halved
  (the official code halves widths and heights in place on the input arrays);
* IoU is the exact COCO IoU (no ``+1e-7`` in the denominator), so SAFit reduces to IoU when ``w = 1``;
* crowd GT keeps COCO's crowd IoU (intersection over detection area) in the IoU term;
* size bins are selected by their area range, never by label (the official summary mislabels two bins).

All functions are pure: arrays in, arrays out.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

SAFIT_C = 32.0
Anchor = Literal["center", "topleft"]
ANCHORS = ("center", "topleft")

#: RGBT-Tiny size bins on the GT ``area`` field, in pixels^2: extremely tiny, tiny, small, medium, large.
TINY_AREA_RANGES: dict[str, tuple[float, float]] = {
    "all": (0.0, 1e5**2),
    "extremely_tiny": (0.0, 8.0**2),
    "tiny": (8.0**2, 16.0**2),
    "small": (16.0**2, 32.0**2),
    "medium": (32.0**2, 96.0**2),
    "large": (96.0**2, 1e5**2),
}


def _as_boxes(boxes: np.ndarray | list) -> np.ndarray:
    arr = np.array(boxes, dtype=np.float64, copy=True)  # a private float64 copy: never modify or floor the input
    return arr.reshape(-1, 4)


# The equations, on broadcastable [..., 4] arrays (element-wise for matched pairs, [D,1,4] x [1,G,4] for matrices).
def iou_elementwise(d: np.ndarray, g: np.ndarray, crowd: np.ndarray | bool = False) -> np.ndarray:
    """COCO box IoU (``|d ∩ g| / |d ∪ g|``; ``|d ∩ g| / |d|`` for a crowd GT), same operation order as COCO's C code."""
    iw = np.minimum(d[..., 0] + d[..., 2], g[..., 0] + g[..., 2]) - np.maximum(d[..., 0], g[..., 0])
    ih = np.minimum(d[..., 1] + d[..., 3], g[..., 1] + g[..., 3]) - np.maximum(d[..., 1], g[..., 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    da = d[..., 2] * d[..., 3]
    ga = g[..., 2] * g[..., 3]
    union = np.where(crowd, da, da + ga - inter)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / union, 0.0)


def nwd_elementwise(d: np.ndarray, g: np.ndarray, c: float = SAFIT_C, anchor: Anchor = "center") -> np.ndarray:
    """``exp(-||(px_d - px_g, py_d - py_g, (w_d - w_g)/2, (h_d - h_g)/2)||_2 / C)``."""
    if anchor not in ANCHORS:
        raise ValueError(f"NWD anchor must be one of {ANCHORS}, got {anchor!r}")
    shift = 0.5 if anchor == "center" else 0.0  # centre (x + w/2, y + h/2) or top-left corner (x, y)
    dx = (d[..., 0] + shift * d[..., 2]) - (g[..., 0] + shift * g[..., 2])
    dy = (d[..., 1] + shift * d[..., 3]) - (g[..., 1] + shift * g[..., 3])
    dw = (d[..., 2] - g[..., 2]) / 2.0
    dh = (d[..., 3] - g[..., 3]) / 2.0
    return np.exp(-np.sqrt(dx * dx + dy * dy + dw * dw + dh * dh) / c)


def safit_weight(gt_area: np.ndarray | float, c: float = SAFIT_C) -> np.ndarray:
    """``w(A) = sigmoid((sqrt(A) - C) / C)``: 0.5 for a 32x32 box, 0.269 as A -> 0, 1 for large boxes."""
    a = np.asarray(gt_area, dtype=np.float64)
    return 1.0 / (1.0 + np.exp(-(np.sqrt(np.maximum(a, 0.0)) - c) / c))


def safit_elementwise(
    d: np.ndarray, g: np.ndarray, crowd: np.ndarray | bool = False, c: float = SAFIT_C, anchor: Anchor = "center"
) -> np.ndarray:
    """``SAFit = w(A_g) IoU + (1 - w(A_g)) NWD`` with ``A_g = w_g * h_g`` of the GT box."""
    w = safit_weight(g[..., 2] * g[..., 3], c)
    return w * iou_elementwise(d, g, crowd) + (1.0 - w) * nwd_elementwise(d, g, c, anchor)


# Matrix forms: detections [D, 4] x ground truth [G, 4] -> [D, G].
def iou_xywh(dt: np.ndarray, gt: np.ndarray, iscrowd: np.ndarray | None = None) -> np.ndarray:
    """COCO box IoU matrix; for a crowd GT the union is the detection's own area."""
    d, g = _as_boxes(dt), _as_boxes(gt)
    crowd = np.zeros(len(g), dtype=bool) if iscrowd is None else np.asarray(iscrowd, dtype=bool).reshape(-1)
    return iou_elementwise(d[:, None, :], g[None, :, :], crowd[None, :])


def nwd_xywh(dt: np.ndarray, gt: np.ndarray, c: float = SAFIT_C, anchor: Anchor = "center") -> np.ndarray:
    """Normalized Wasserstein distance matrix (see ``nwd_elementwise``)."""
    d, g = _as_boxes(dt), _as_boxes(gt)
    return nwd_elementwise(d[:, None, :], g[None, :, :], c, anchor)


def safit_xywh(
    dt: np.ndarray, gt: np.ndarray, iscrowd: np.ndarray | None = None, c: float = SAFIT_C, anchor: Anchor = "center"
) -> np.ndarray:
    """SAFit matrix, weight from each GT box's w*h."""
    d, g = _as_boxes(dt), _as_boxes(gt)
    crowd = np.zeros(len(g), dtype=bool) if iscrowd is None else np.asarray(iscrowd, dtype=bool).reshape(-1)
    return safit_elementwise(d[:, None, :], g[None, :, :], crowd[None, :], c, anchor)
