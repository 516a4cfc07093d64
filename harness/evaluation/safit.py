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


def iou_xywh(dt: np.ndarray, gt: np.ndarray, iscrowd: np.ndarray | None = None) -> np.ndarray:
    """COCO box IoU, ``[D, 4] x [G, 4] -> [D, G]``; for a crowd GT the union is the detection's own area."""
    d, g = _as_boxes(dt), _as_boxes(gt)
    crowd = np.zeros(len(g), dtype=bool) if iscrowd is None else np.asarray(iscrowd, dtype=bool).reshape(-1)
    iw = np.minimum(d[:, None, 0] + d[:, None, 2], g[None, :, 0] + g[None, :, 2]) - np.maximum(d[:, None, 0], g[None, :, 0])
    ih = np.minimum(d[:, None, 1] + d[:, None, 3], g[None, :, 1] + g[None, :, 3]) - np.maximum(d[:, None, 1], g[None, :, 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    da = (d[:, 2] * d[:, 3])[:, None]
    ga = (g[:, 2] * g[:, 3])[None, :]
    union = np.where(crowd[None, :], da, da + ga - inter)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(union > 0, inter / union, 0.0)
    return out


def nwd_xywh(dt: np.ndarray, gt: np.ndarray, c: float = SAFIT_C, anchor: Anchor = "center") -> np.ndarray:
    """Normalized Wasserstein distance, ``exp(-W2 / C)``, ``[D, 4] x [G, 4] -> [D, G]``.

    ``W2 = ||(px_d - px_g, py_d - py_g, (w_d - w_g)/2, (h_d - h_g)/2)||_2`` with ``(px, py)`` the box centre
    (``anchor="center"``) or its top-left corner (``anchor="topleft"``, as the official RGBT-Tiny code).
    """
    if anchor not in ANCHORS:
        raise ValueError(f"NWD anchor must be one of {ANCHORS}, got {anchor!r}")
    d, g = _as_boxes(dt), _as_boxes(gt)
    if anchor == "center":
        d[:, :2] += d[:, 2:] / 2.0
        g[:, :2] += g[:, 2:] / 2.0
    d[:, 2:] /= 2.0
    g[:, 2:] /= 2.0
    diff = d[:, None, :] - g[None, :, :]
    w2 = np.sqrt(np.sum(diff * diff, axis=-1))
    return np.exp(-w2 / c)


def safit_weight(gt_area: np.ndarray | float, c: float = SAFIT_C) -> np.ndarray:
    """``w(A) = sigmoid((sqrt(A) - C) / C)``: 0.5 for a 32x32 box, 0.269 as A -> 0, 1 for large boxes."""
    a = np.asarray(gt_area, dtype=np.float64)
    return 1.0 / (1.0 + np.exp(-(np.sqrt(np.maximum(a, 0.0)) - c) / c))


def safit_xywh(dt: np.ndarray, gt: np.ndarray, iscrowd: np.ndarray | None = None, c: float = SAFIT_C,
               anchor: Anchor = "center") -> np.ndarray:
    """``SAFit = w(A_g) IoU + (1 - w(A_g)) NWD``, ``[D, 4] x [G, 4] -> [D, G]``, weight from each GT box's w*h."""
    g = _as_boxes(gt)
    w = safit_weight(g[:, 2] * g[:, 3], c)[None, :]
    return w * iou_xywh(dt, g, iscrowd) + (1.0 - w) * nwd_xywh(dt, g, c, anchor)
