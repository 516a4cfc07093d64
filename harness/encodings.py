"""The built-in encodings: how an aligned sample becomes the detector's fourth input channel.

============  =========  ==================================================================================
name          reads      channel
============  =========  ==================================================================================
``c2``        thermal    signed local radiometric contrast, ``round(255 * C2)`` (``harness.sensing.c2``)
``linear16``  thermal    temperature mapped linearly to 0..255: per-image min-max by default, or a fixed range
``ir8``       ir8        the 8-bit thermal preview the sample carries, unchanged
``none``      nothing    no channel: RGB-only detectors
``proxy8``    ir8        the C2 formula on 8-bit intensity, for datasets without radiometry
============  =========  ==================================================================================

Parameters are the ``EncodingSpec.params`` defaults, overridable per encoding from the config
(``encoding: {c2: {sigma: 11.0}}``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.api import AlignedSample, EncodingSpec
from harness.errors import PluginError
from harness.hookspecs import hookimpl
from harness.sensing import c2 as c2mod


def encode_c2(
    sample: AlignedSample, sigma: float = c2mod.SIGMA, percentile: float = c2mod.PERCENTILE, floor: float = c2mod.FLOOR
) -> np.ndarray:
    """``round(255 * C2(T))``: C2 of the temperature map in C (floor in C)."""
    # sample.thermal is present: the host checks what an encoding needs before calling it
    return c2mod.c2_uint8(
        sample.thermal,  # type: ignore[arg-type]
        sigma=sigma,
        percentile=percentile,
        floor=floor,
        name=sample.name,
    )


def linear_map(
    t: np.ndarray,
    mode: str = "minmax",
    t_min: float = 0.0,
    t_max: float = 60.0,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> np.ndarray:
    """Temperature to uint8 by ``round(255 * clip((T - lo) / (hi - lo), 0, 1))``.

    ``mode="minmax"``: ``lo, hi`` = the image's min and max (a flat image maps to 0);
    ``"percentile"``: the image's ``percentiles`` (robust to a few hot pixels);
    ``"fixed"``: ``lo, hi = t_min, t_max`` in C, the same for every image.
    ``lo, hi`` come from the measured pixels only; a missing temperature (NaN or inf) maps to the median of the
    measured ones, never to 0.
    """
    t = c2mod.check_map(t)
    if not np.isfinite(t.sum(dtype=np.float64)):
        valid = c2mod.valid_mask(t)
        t = np.where(valid, t, np.float32(np.median(t[valid])))
    if mode == "minmax":
        lo, hi = float(t.min()), float(t.max())
    elif mode == "percentile":
        lo, hi = (float(v) for v in np.percentile(t, list(percentiles)))
    elif mode == "fixed":
        lo, hi = float(t_min), float(t_max)
    else:
        raise PluginError(f"encoding 'linear16': unknown mode {mode!r}; use 'minmax', 'percentile' or 'fixed'")
    span = hi - lo
    if span <= 0:
        if mode == "fixed":
            raise PluginError(f"encoding 'linear16': t_max ({t_max}) must exceed t_min ({t_min})")
        return np.zeros(t.shape, np.uint8)
    out = (t - np.float32(lo)) * np.float32(255.0 / span)
    np.clip(out, 0, 255, out=out)
    return np.rint(out, out=out).astype(np.uint8)


def encode_linear16(
    sample: AlignedSample,
    mode: str = "minmax",
    t_min: float = 0.0,
    t_max: float = 60.0,
    percentiles: tuple[float, float] | list[float] = (1.0, 99.0),
) -> np.ndarray:
    return linear_map(
        sample.thermal,  # type: ignore[arg-type]
        mode=mode,
        t_min=t_min,
        t_max=t_max,
        percentiles=tuple(percentiles),  # type: ignore[arg-type]
    )


def encode_ir8(sample: AlignedSample) -> np.ndarray:
    """The 8-bit preview as it is."""
    return np.ascontiguousarray(sample.ir8, dtype=np.uint8)


def encode_none(sample: AlignedSample) -> None:
    """RGB only: no extra channel."""
    return None


def encode_proxy8(
    sample: AlignedSample, sigma: float = c2mod.SIGMA, percentile: float = c2mod.PERCENTILE, floor: float = 1.0
) -> np.ndarray:
    """C2 computed on 8-bit intensity ``I`` (0..255) instead of temperature.

    ``dI = I - G_sigma * I``, ``p_clip = max(P99(|dI|), floor)`` with ``floor`` in grey levels (default 1.0,
    one quantisation step), ``round(255 * clip(dI / (2 p_clip) + 0.5, 0, 1))``.
    """
    return c2mod.c2_uint8(np.asarray(sample.ir8, dtype=np.float32), sigma=sigma, percentile=percentile, floor=floor)


ENCODINGS: tuple[EncodingSpec, ...] = (
    EncodingSpec(
        "c2",
        encode_c2,
        channels=1,
        needs="thermal",
        description="signed local radiometric contrast (Gaussian background sigma 11, P99 clip, 0.05 C floor)",
        params={"sigma": c2mod.SIGMA, "percentile": c2mod.PERCENTILE, "floor": c2mod.FLOOR},
    ),
    EncodingSpec(
        "linear16",
        encode_linear16,
        channels=1,
        needs="thermal",
        description="temperature mapped linearly to 8 bit (per-image min-max by default)",
        params={"mode": "minmax", "t_min": 0.0, "t_max": 60.0, "percentiles": [1.0, 99.0]},
    ),
    EncodingSpec("ir8", encode_ir8, channels=1, needs="ir8", description="the 8-bit thermal preview"),
    EncodingSpec("none", encode_none, channels=0, needs=None, description="RGB only"),
    EncodingSpec(
        "proxy8",
        encode_proxy8,
        channels=1,
        needs="ir8",
        description="C2's local contrast on 8-bit intensity (floor in grey levels)",
        params={"sigma": c2mod.SIGMA, "percentile": c2mod.PERCENTILE, "floor": 1.0},
    ),
)


@hookimpl
def register_encodings(register: Any) -> None:
    for spec in ENCODINGS:
        register(spec)
