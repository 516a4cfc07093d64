"""Image and box augmentation for training, as small pure functions (array in, array out).

Every geometric operation (letterbox, mosaic placement, random affine, flips) is applied to **all channels of one
array at once**, so the RGB channels and the thermal-derived channel can never drift apart; boxes go through the
same matrix. Photometric jitter (``augment_hsv``) touches the first three channels (R, G, B) only: the fourth
channel carries a physical quantity (temperature contrast) that a colour jitter would corrupt.

Images are ``uint8 H x W x C`` with ``C = 3`` (RGB) or ``C = 4`` (RGB + encoding); boxes are ``float32 N x 4`` xyxy
in pixels. Randomness always comes from an explicit ``numpy.random.Generator`` so that a sample's augmentation is a
function of (seed, epoch, index) alone: the same with any number of data-loader workers and after a resume.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

PAD_VALUE = 114  # grey fill of letterbox borders and of areas the affine warp uncovers, on every channel


@dataclass(frozen=True)
class Letterbox:
    """How an image was letterboxed: ``x_input = x_original * ratio + pad``."""

    ratio: float
    pad: tuple[float, float]  # (left, top) in input pixels
    shape: tuple[int, int]  # original (height, width)

    def to_original(self, boxes: np.ndarray) -> np.ndarray:
        """Map xyxy boxes from the letterboxed input back to the original frame, clipped to it."""
        out = np.asarray(boxes, dtype=np.float32).copy()
        out[:, [0, 2]] = (out[:, [0, 2]] - self.pad[0]) / self.ratio
        out[:, [1, 3]] = (out[:, [1, 3]] - self.pad[1]) / self.ratio
        h, w = self.shape
        out[:, [0, 2]] = out[:, [0, 2]].clip(0, w)
        out[:, [1, 3]] = out[:, [1, 3]].clip(0, h)
        return out


def fill(channels: int) -> tuple[int, ...]:
    return (PAD_VALUE,) * channels


def resize_long_side(img: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """Resize so that the longer side is ``size`` (aspect kept); returns the image and the ratio."""
    h, w = img.shape[:2]
    r = size / max(h, w)
    if r != 1.0:
        nw, nh = max(1, round(w * r)), max(1, round(h * r))
        interp = cv2.INTER_AREA if r < 1 else cv2.INTER_LINEAR
        img = _as_hwc(cv2.resize(img, (nw, nh), interpolation=interp), img.shape[2])
    return img, r


def _as_hwc(img: np.ndarray, channels: int) -> np.ndarray:
    """OpenCV drops a trailing channel axis of size 1; put it back."""
    return img[:, :, None] if img.ndim == 2 and channels == 1 else img


def letterbox(img: np.ndarray, size: int, scaleup: bool = True) -> tuple[np.ndarray, Letterbox]:
    """Resize ``img`` to fit ``size x size`` keeping the aspect ratio, and pad the rest symmetrically.

    ``x_input = x * r + pad`` with ``r = min(size / h, size / w)`` (capped at 1 when ``scaleup`` is false).
    """
    h, w = img.shape[:2]
    r = min(size / h, size / w)
    if not scaleup:
        r = min(r, 1.0)
    nw, nh = max(1, round(w * r)), max(1, round(h * r))
    if (nw, nh) != (w, h):
        interp = cv2.INTER_AREA if r < 1 else cv2.INTER_LINEAR
        img = _as_hwc(cv2.resize(img, (nw, nh), interpolation=interp), img.shape[2])
    return pad_letterbox(img, r, (h, w), size)


def pad_letterbox(img: np.ndarray, ratio: float, shape: tuple[int, int], size: int) -> tuple[np.ndarray, Letterbox]:
    """The second half of ``letterbox``: ``img``, already resized by ``ratio`` from an image of ``shape``
    (e.g. by ``resize_long_side``, which resizes exactly as ``letterbox`` does), centred on a ``size x size``
    canvas of ``PAD_VALUE``."""
    nh, nw = img.shape[:2]
    dw, dh = (size - nw) / 2, (size - nh) / 2
    top, left = int(round(dh - 0.1)), int(round(dw - 0.1))
    out = np.full((size, size, img.shape[2]), PAD_VALUE, dtype=img.dtype)
    out[top : top + nh, left : left + nw] = img
    return out, Letterbox(ratio=ratio, pad=(float(left), float(top)), shape=(int(shape[0]), int(shape[1])))


def scale_boxes(boxes: np.ndarray, ratio: float, pad: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    out = np.asarray(boxes, dtype=np.float32) * ratio
    out[:, [0, 2]] += pad[0]
    out[:, [1, 3]] += pad[1]
    return out


# ------------------------------------------------------------------------------------------------ mosaic
def mosaic4(
    images: list[np.ndarray], boxes: list[np.ndarray], labels: list[np.ndarray], size: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four images (each already resized so its long side is ``size``) on a ``2size x 2size`` canvas.

    A centre ``(xc, yc)`` is drawn uniformly in ``[size/2, 3size/2]``; image 0 ends at the centre from the top-left,
    image 1 starts there to the top-right, image 2 to the bottom-left, image 3 to the bottom-right, each cropped by
    the canvas. Boxes are shifted with their image and clipped to the canvas. The canvas is usually passed on to
    ``random_affine(..., border=-size // 2)``, which crops it back to ``size x size``.
    """
    s = size
    c = images[0].shape[2]
    canvas = np.full((2 * s, 2 * s, c), PAD_VALUE, dtype=np.uint8)
    xc = int(rng.uniform(s * 0.5, s * 1.5))
    yc = int(rng.uniform(s * 0.5, s * 1.5))
    out_boxes, out_labels = [], []
    for k, (img, b, lab) in enumerate(zip(images, boxes, labels)):
        h, w = img.shape[:2]
        if k == 0:  # top-left
            x1a, y1a, x2a, y2a = max(xc - w, 0), max(yc - h, 0), xc, yc
            x1b, y1b, x2b, y2b = w - (x2a - x1a), h - (y2a - y1a), w, h
        elif k == 1:  # top-right
            x1a, y1a, x2a, y2a = xc, max(yc - h, 0), min(xc + w, 2 * s), yc
            x1b, y1b, x2b, y2b = 0, h - (y2a - y1a), min(w, x2a - x1a), h
        elif k == 2:  # bottom-left
            x1a, y1a, x2a, y2a = max(xc - w, 0), yc, xc, min(2 * s, yc + h)
            x1b, y1b, x2b, y2b = w - (x2a - x1a), 0, w, min(y2a - y1a, h)
        else:  # bottom-right
            x1a, y1a, x2a, y2a = xc, yc, min(xc + w, 2 * s), min(2 * s, yc + h)
            x1b, y1b, x2b, y2b = 0, 0, min(w, x2a - x1a), min(y2a - y1a, h)
        canvas[y1a:y2a, x1a:x2a] = img[y1b:y2b, x1b:x2b]
        if len(b):
            shifted = np.asarray(b, dtype=np.float32).copy()
            shifted[:, [0, 2]] += x1a - x1b
            shifted[:, [1, 3]] += y1a - y1b
            out_boxes.append(shifted)
            out_labels.append(np.asarray(lab, dtype=np.int64))
    if out_boxes:
        cat_b = np.concatenate(out_boxes).clip(0, 2 * s)
        cat_l = np.concatenate(out_labels)
    else:
        cat_b, cat_l = np.zeros((0, 4), np.float32), np.zeros(0, np.int64)
    keep = (cat_b[:, 2] - cat_b[:, 0] > 1) & (cat_b[:, 3] - cat_b[:, 1] > 1)
    return canvas, cat_b[keep].astype(np.float32), cat_l[keep]


# ------------------------------------------------------------------------------------------------ affine
#: The settings of the random geometric warp (``affine_matrix``'s keywords).
AFFINE_SETTINGS = ("degrees", "translate", "scale", "shear", "perspective")


def affine_matrix(
    in_shape: tuple[int, int],
    out_shape: tuple[int, int],
    rng: np.random.Generator,
    degrees: float = 0.0,
    translate: float = 0.1,
    scale: float = 0.5,
    shear: float = 0.0,
    perspective: float = 0.0,
) -> np.ndarray:
    """A random 3x3 matrix ``M = T @ Sh @ R @ P @ C`` mapping input pixels to output pixels.

    ``C`` moves the input centre to the origin, ``P`` adds perspective terms in ``[-perspective, perspective]``,
    ``R`` rotates by ``U(-degrees, degrees)`` and scales by ``U(1 - scale, 1 + scale)``, ``Sh`` shears by
    ``U(-shear, shear)`` degrees and ``T`` moves the origin to ``(0.5 + U(-translate, translate))`` of the output.
    """
    h, w = in_shape
    oh, ow = out_shape
    C = np.eye(3)
    C[0, 2], C[1, 2] = -w / 2, -h / 2
    P = np.eye(3)
    P[2, 0] = rng.uniform(-perspective, perspective)
    P[2, 1] = rng.uniform(-perspective, perspective)
    R = np.eye(3)
    a = rng.uniform(-degrees, degrees)
    s = rng.uniform(1 - scale, 1 + scale)
    R[:2] = cv2.getRotationMatrix2D(center=(0, 0), angle=a, scale=s)
    S = np.eye(3)
    S[0, 1] = math.tan(math.radians(rng.uniform(-shear, shear)))
    S[1, 0] = math.tan(math.radians(rng.uniform(-shear, shear)))
    T = np.eye(3)
    T[0, 2] = rng.uniform(0.5 - translate, 0.5 + translate) * ow
    T[1, 2] = rng.uniform(0.5 - translate, 0.5 + translate) * oh
    return T @ S @ R @ P @ C


def warp_image(img: np.ndarray, M: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
    """Warp every channel of ``img`` with the same 3x3 matrix (affine when the last row is [0, 0, 1])."""
    oh, ow = out_shape
    c = img.shape[2]
    if c > 4:  # OpenCV's border value has four components
        return np.concatenate([warp_image(img[:, :, k : k + 4], M, out_shape) for k in range(0, c, 4)], axis=2)
    if np.allclose(M[2], (0.0, 0.0, 1.0)):
        out = cv2.warpAffine(img, M[:2], dsize=(ow, oh), flags=cv2.INTER_LINEAR, borderValue=fill(4))
    else:
        out = cv2.warpPerspective(img, M, dsize=(ow, oh), flags=cv2.INTER_LINEAR, borderValue=fill(4))
    return _as_hwc(out, c)


def transform_boxes(boxes: np.ndarray, M: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
    """Move xyxy boxes by ``M``: transform the four corners, take their bounding box, clip to the output."""
    n = len(boxes)
    if n == 0:
        return np.zeros((0, 4), np.float32)
    b = np.asarray(boxes, dtype=np.float64)
    xy = np.ones((n * 4, 3))
    xy[:, :2] = b[:, [0, 1, 2, 3, 0, 3, 2, 1]].reshape(n * 4, 2)  # x1y1, x2y2, x1y2, x2y1
    xy = xy @ M.T
    xy = xy[:, :2] / xy[:, 2:3]
    x, y = xy[:, 0].reshape(n, 4), xy[:, 1].reshape(n, 4)
    out = np.stack([x.min(1), y.min(1), x.max(1), y.max(1)], axis=1)
    oh, ow = out_shape
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, ow)
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, oh)
    return out.astype(np.float32)


def box_candidates(
    before: np.ndarray,
    after: np.ndarray,
    wh_thr: float = 2.0,
    ar_thr: float = 100.0,
    area_thr: float = 0.1,
    eps: float = 1e-16,
) -> np.ndarray:
    """Keep boxes still at least ``wh_thr`` px wide and high, with ``area_thr`` of their (scaled) area left and an
    aspect ratio under ``ar_thr``; ``before`` are the boxes scaled by the warp's scale, ``after`` the warped ones."""
    w1, h1 = before[:, 2] - before[:, 0], before[:, 3] - before[:, 1]
    w2, h2 = after[:, 2] - after[:, 0], after[:, 3] - after[:, 1]
    ar = np.maximum(w2 / (h2 + eps), h2 / (w2 + eps))
    return (w2 > wh_thr) & (h2 > wh_thr) & (w2 * h2 / (w1 * h1 + eps) > area_thr) & (ar < ar_thr)


def random_affine(
    img: np.ndarray,
    boxes: np.ndarray,
    labels: np.ndarray,
    rng: np.random.Generator,
    *,
    border: int = 0,
    **affine: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warp image and boxes by one random matrix (``affine_matrix``, ``affine`` its settings ``AFFINE_SETTINGS``
    with its defaults for those not given); ``border < 0`` crops (mosaic: ``-size/2``).

    The output is ``(H + 2 border) x (W + 2 border)``. Boxes that leave the image or shrink too much are dropped
    (``box_candidates``).
    """
    h, w = img.shape[:2]
    out_shape = (h + 2 * border, w + 2 * border)
    M = affine_matrix((h, w), out_shape, rng, **affine)
    if border != 0 or not np.allclose(M, np.eye(3)):
        img = warp_image(img, M, out_shape)
    new = transform_boxes(boxes, M, out_shape)
    if len(new):
        s = math.sqrt(abs(np.linalg.det(M[:2, :2])))  # the isotropic scale of the warp
        keep = box_candidates(np.asarray(boxes, np.float32) * s, new)
        new, labels = new[keep], np.asarray(labels)[keep]
    return img, new, np.asarray(labels, dtype=np.int64)


# ------------------------------------------------------------------------------------------------ photometric
def augment_hsv(
    img: np.ndarray, rng: np.random.Generator, hgain: float = 0.015, sgain: float = 0.7, vgain: float = 0.4
) -> np.ndarray:
    """Random hue, saturation and value gains on the RGB channels (0, 1, 2) only; other channels are copied as is.

    Gains are ``1 + U(-1, 1) * gain``; hue is rotated modulo 180 (OpenCV's 8-bit hue range), saturation and value
    are multiplied and clipped to 0..255, through one lookup table per component.
    """
    if not (hgain or sgain or vgain):
        return img
    r = rng.uniform(-1, 1, 3) * (hgain, sgain, vgain) + 1
    hue, sat, val = cv2.split(cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2HSV))
    x = np.arange(256, dtype=np.float64)
    lut_h = ((x * r[0]) % 180).astype(np.uint8)
    lut_s = np.clip(x * r[1], 0, 255).astype(np.uint8)
    lut_v = np.clip(x * r[2], 0, 255).astype(np.uint8)
    hsv = cv2.merge((cv2.LUT(hue, lut_h), cv2.LUT(sat, lut_s), cv2.LUT(val, lut_v)))
    out = img.copy()
    out[:, :, :3] = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    return out


# ------------------------------------------------------------------------------------------------ flips
def flip_lr(img: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror left-right: every channel, and ``x -> W - x`` for the boxes."""
    w = img.shape[1]
    b = np.asarray(boxes, dtype=np.float32).copy()
    b[:, [0, 2]] = w - b[:, [2, 0]]
    return np.ascontiguousarray(img[:, ::-1]), b


def flip_ud(img: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror top-bottom: every channel, and ``y -> H - y`` for the boxes."""
    h = img.shape[0]
    b = np.asarray(boxes, dtype=np.float32).copy()
    b[:, [1, 3]] = h - b[:, [3, 1]]
    return np.ascontiguousarray(img[::-1]), b
