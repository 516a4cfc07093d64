"""Plausible temperatures: the range a decoded map in degrees C must mostly lie in, and the rule that turns the few
pixels outside it into missing values (every decoder route uses it: DJI's correction, converters, sidecar units)."""

from __future__ import annotations

import numpy as np

from harness.errors import DataError

#: temperatures (C) a facade, a flight or any supported camera can give; values outside are not temperatures
PLAUSIBLE_C = (-100.0, 800.0)


def implausible_to_missing(temp: np.ndarray, name: str, what: str) -> int:
    """Pixels of ``temp`` (float, changed in place) outside ``PLAUSIBLE_C`` become missing (NaN); returns how many.
    When they are more than ``c2.MAX_INVALID_FRACTION`` of the finite pixels the map is not temperatures in C at all
    (a wrong unit or scale): a ``DataError`` naming ``name``, ``what`` produced it, the span and the count."""
    from harness.sensing.c2 import MAX_INVALID_FRACTION

    finite = np.isfinite(temp)
    bad = finite & ((temp < PLAUSIBLE_C[0]) | (temp > PLAUSIBLE_C[1]))
    n_bad, n_finite = int(bad.sum()), int(finite.sum())
    if not n_bad:
        return 0
    if n_bad > MAX_INVALID_FRACTION * n_finite:
        lo, hi = float(temp[finite].min()), float(temp[finite].max())
        raise DataError(
            f"{name}: {what} gives {n_bad} of {n_finite} values outside the plausible "
            f"{PLAUSIBLE_C[0]:g}..{PLAUSIBLE_C[1]:g} C (from {lo:.6g} to {hi:.6g} C); it is not "
            "temperatures in C: check its unit or scale"
        )
    temp[bad] = np.nan
    return n_bad
