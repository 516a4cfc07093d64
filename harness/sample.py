"""The aligned-sample contract: what the sensing pipeline produces and every encoding and detector reads.

An ``AlignedSample`` is one image pair in the **thermal frame** after registration, warp and common-support crop:

==========  ======================  =============================================================
field       type                    meaning
==========  ======================  =============================================================
image_id    int                     unique within the dataset (COCO ``image_id``)
rgb         uint8 HxWx3             RGB warped into the thermal frame (R, G, B order)
thermal     float32 HxW or None     temperature in degrees C (None for 8-bit-only datasets); NaN = missing
ir8         uint8 HxW               8-bit thermal preview (or the dataset's 8-bit thermal frame)
boxes       float32 Nx4             xyxy pixels in the thermal frame, inside [0, W] x [0, H]
labels      int64 N                 0-based category indices
group       str                     project (M3T) or sequence (RGBT-Tiny); folds hold groups out
meta        dict                    file names, capture time, homography, anything provenance-related
==========  ======================  =============================================================

``validate_sample`` enforces the table and names the sample and the field in every error. Missing temperatures
(NaN or inf: masked or dead pixels) are allowed up to ``harness.sensing.c2.MAX_INVALID_FRACTION`` of the map;
the encodings leave them out (C2 gives them the neutral value) and ``prepare`` counts them per sample.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.errors import SampleError


@dataclass
class AlignedSample:
    image_id: int
    rgb: np.ndarray
    thermal: np.ndarray | None
    ir8: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    group: str
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def height(self) -> int:
        return int(self.ir8.shape[0])

    @property
    def width(self) -> int:
        return int(self.ir8.shape[1])

    @property
    def name(self) -> str:
        """How errors refer to this sample: its id and, when known, its file name."""
        fname = self.meta.get("file_name") if isinstance(self.meta, dict) else None
        return f"sample {self.image_id}" + (f" ({fname})" if fname else "")


def _fail(sample: Any, field_name: str, message: str) -> SampleError:
    name = sample.name if isinstance(sample, AlignedSample) else f"sample {getattr(sample, 'image_id', '?')}"
    return SampleError(f"{name}: field {field_name!r}: {message}")


def _check_array(sample: AlignedSample, name: str, value: Any, dtype: np.dtype, ndim: int) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise _fail(sample, name, f"expected a numpy array, got {type(value).__name__}")
    if value.dtype != dtype:
        raise _fail(sample, name, f"expected dtype {np.dtype(dtype).name}, got {value.dtype.name}")
    if value.ndim != ndim:
        raise _fail(sample, name, f"expected {ndim} dimensions, got shape {tuple(value.shape)}")
    return value


def validate_sample(sample: AlignedSample, num_classes: int | None = None, box_tolerance: float = 1e-3) -> AlignedSample:
    """Check ``sample`` against the contract; return it unchanged or raise ``SampleError`` naming the field."""
    if not isinstance(sample, AlignedSample):
        raise SampleError(f"expected an AlignedSample, got {type(sample).__name__}")
    if isinstance(sample.image_id, (bool, np.bool_)) or not isinstance(sample.image_id, (int, np.integer)):
        raise _fail(sample, "image_id", f"expected an int, got {type(sample.image_id).__name__}")
    if not isinstance(sample.group, str) or not sample.group:
        raise _fail(sample, "group", "expected a non-empty string (project or sequence)")
    if not isinstance(sample.meta, dict):
        raise _fail(sample, "meta", f"expected a dict, got {type(sample.meta).__name__}")

    ir8 = _check_array(sample, "ir8", sample.ir8, np.uint8, 2)
    h, w = ir8.shape
    if h < 1 or w < 1:
        raise _fail(sample, "ir8", f"empty image of shape {ir8.shape}")
    rgb = _check_array(sample, "rgb", sample.rgb, np.uint8, 3)
    if rgb.shape != (h, w, 3):
        raise _fail(sample, "rgb", f"expected shape {(h, w, 3)} (thermal frame, 3 channels), got {rgb.shape}")
    if sample.thermal is not None:
        th = _check_array(sample, "thermal", sample.thermal, np.float32, 2)
        if th.shape != (h, w):
            raise _fail(sample, "thermal", f"expected shape {(h, w)} like ir8, got {th.shape}")
        if not np.isfinite(th).all():
            from harness.sensing.c2 import MAX_INVALID_FRACTION

            bad = int((~np.isfinite(th)).sum())
            if bad > MAX_INVALID_FRACTION * th.size:
                raise _fail(sample, "thermal", f"{bad} of {th.size} pixels are non-finite temperature values (NaN "
                                               f"or inf), more than the {100 * MAX_INVALID_FRACTION:g} % a map may miss")

    boxes = _check_array(sample, "boxes", sample.boxes, np.float32, 2)
    if boxes.shape[1] != 4:
        raise _fail(sample, "boxes", f"expected shape (N, 4) xyxy, got {boxes.shape}")
    labels = _check_array(sample, "labels", sample.labels, np.int64, 1)
    if labels.shape[0] != boxes.shape[0]:
        raise _fail(sample, "labels", f"{labels.shape[0]} labels for {boxes.shape[0]} boxes")
    if len(boxes):
        if not np.isfinite(boxes).all():
            raise _fail(sample, "boxes", "non-finite coordinates")
        x1, y1, x2, y2 = boxes.T
        if (x2 <= x1).any() or (y2 <= y1).any():
            i = int(np.nonzero((x2 <= x1) | (y2 <= y1))[0][0])
            raise _fail(sample, "boxes", f"box {i} {boxes[i].tolist()} has zero or negative width/height")
        tol = box_tolerance
        outside = (x1 < -tol) | (y1 < -tol) | (x2 > w + tol) | (y2 > h + tol)
        if outside.any():
            i = int(np.nonzero(outside)[0][0])
            raise _fail(sample, "boxes", f"box {i} {boxes[i].tolist()} lies outside the {w}x{h} frame")
        if (labels < 0).any() or (num_classes is not None and (labels >= num_classes).any()):
            bad = labels[(labels < 0) | ((labels >= num_classes) if num_classes is not None else False)]
            raise _fail(sample, "labels", f"label {int(bad[0])} outside 0..{(num_classes or 0) - 1}")
    return sample
