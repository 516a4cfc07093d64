"""Plausible temperatures: one check for every thermal input (decoded files, DJI R-JPEGs, converter outputs, a dataset
plugin's samples, a screen's captures).

``classify(temp)`` reads a map that should hold degrees C and says what it looks like:

* ``plausible``: degrees C, perhaps with a few values outside ``PLAUSIBLE_C``;
* ``garbage``: more than ``GARBAGE_FRACTION`` of the finite values are no temperature at all: outside
  ``PLAUSIBLE_C`` (-100..800 C) or of a magnitude no temperature has (nonzero and below ``TINY``, what bytes read as
  the wrong type give), e.g. random bytes;
* ``byteswapped``: garbage whose bytes, swapped, are plausible temperatures (big-endian floats read as little-endian);
* ``counts8``: whole numbers within 0..255 spanning at least ``COUNTS8_MIN_SPAN``: an 8-bit image (a palette or a
  preview) declared as degrees C;
* ``kelvin``: the coolest percent above ``KELVIN_P1_MIN`` and the median within ``KELVIN_MEDIAN``: Kelvin read as C;
* ``fahrenheit``: the median within ``FAHRENHEIT_MEDIAN`` and the hottest percent below ``FAHRENHEIT_P99_MAX``: as C
  a scene hotter than a sunlit facade, as Fahrenheit an ordinary one.

Kelvin and Fahrenheit are readings of the values alone (a furnace at 300 C reads as Kelvin): where the unit was
stated (a sidecar's ``unit``, a sample's ``meta["thermal_unit"]``) ``check`` warns instead of refusing.
``check(temp, name, what)`` is what the entry points call: garbage and unit mix-ups are a ``DataError`` naming the
input, the count and the fix; a few values outside the range become missing (NaN) and their count is a warning on
the console (logger ``harness.sensing.plausible``), not only a number in a sidecar.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from harness.errors import DataError

log = logging.getLogger(__name__)

#: temperatures (C) a facade, a flight or any supported camera can give; values outside are not temperatures
PLAUSIBLE_C = (-100.0, 800.0)
#: a map with more than this share of its finite values outside ``PLAUSIBLE_C`` (or below ``TINY``) is no temperature
#: map: refused; fewer become missing, counted on the console
GARBAGE_FRACTION = 0.05
#: nonzero magnitudes below this are no temperature: the mark of bytes read in the wrong order or as the wrong type
TINY = 1e-6
#: Kelvin read as C: the coolest percent above -100 C + 273.15 and the median within -50..+100 C + 273.15
KELVIN_P1_MIN = PLAUSIBLE_C[0] + 273.15
KELVIN_MEDIAN = (223.15, 373.15)
#: Fahrenheit read as C: a median of 50..115 (10..46 C) and the hottest percent below 250 (121 C)
FAHRENHEIT_MEDIAN = (50.0, 115.0)
FAHRENHEIT_P99_MAX = 250.0
#: 8-bit counts: whole numbers in 0..255 spanning at least this much
COUNTS8_MIN_SPAN = 32.0
#: the values the percentiles are taken on (an even subsample of larger maps)
_SAMPLE = 1 << 16

KINDS = ("plausible", "garbage", "byteswapped", "counts8", "kelvin", "fahrenheit")
#: the kinds that are a unit mix-up (a warning where the unit was stated), not garbage
UNIT_KINDS = ("counts8", "kelvin", "fahrenheit")


@dataclass(frozen=True)
class Reading:
    """What a map looks like: ``kind`` (one of ``KINDS``), ``finite`` values, ``outside`` (of them outside
    ``PLAUSIBLE_C`` or below ``TINY``), the finite span ``lo``..``hi``, the 1/50/99th percentiles, and ``detail``
    (one line saying why) and ``fix`` (what to do)."""

    kind: str
    finite: int
    outside: int
    lo: float
    hi: float
    p1: float
    median: float
    p99: float
    detail: str = ""
    fix: str = ""

    @property
    def message(self) -> str:
        """``detail: fix``."""
        return f"{self.detail}: {self.fix}" if self.fix else self.detail

    @property
    def refused(self) -> bool:
        return self.kind != "plausible"


def _not_temperature(v: np.ndarray) -> np.ndarray:
    a = np.abs(v)
    return (v < PLAUSIBLE_C[0]) | (v > PLAUSIBLE_C[1]) | ((a < TINY) & (a > 0))


def _swapped_plausible(v: np.ndarray) -> tuple[bool, float, float]:
    """Whether ``v`` (finite float32 values), byte-swapped, is almost all plausible temperatures, and their span."""
    if v.dtype != np.float32 or not v.size:
        return False, 0.0, 0.0
    with np.errstate(all="ignore"):
        sw = v.byteswap()
        ok = np.isfinite(sw)
        sw = sw[ok]
    if ok.sum() < 0.95 * v.size or not sw.size or _not_temperature(sw).mean() > 0.01:
        return False, 0.0, 0.0
    return True, float(sw.min()), float(sw.max())


def classify(temp: np.ndarray, units: bool | tuple[str, ...] = True) -> Reading:
    """What ``temp`` (a map that should hold degrees C; NaN = missing) looks like (the module's rules). ``units``:
    the unit mix-ups looked for (``UNIT_KINDS`` when True; False looks for garbage only, for a decoder whose unit is
    C by construction)."""
    kinds = UNIT_KINDS if units is True else tuple(units or ())
    t = np.asarray(temp)
    v = t[np.isfinite(t)] if t.dtype.kind == "f" else t.ravel()
    n = int(v.size)
    if not n:
        return Reading("plausible", 0, 0, np.nan, np.nan, np.nan, np.nan, np.nan)
    with np.errstate(all="ignore"):
        bad = _not_temperature(v)
    outside = int(np.count_nonzero(bad))
    lo, hi = float(v.min()), float(v.max())
    sub = v[:: max(1, n // _SAMPLE)].astype(np.float64)
    p1, med, p99 = (float(x) for x in np.percentile(sub, (1, 50, 99)))

    def reading(kind: str, detail: str = "", fix: str = "") -> Reading:
        return Reading(kind, n, outside, lo, hi, p1, med, p99, detail, fix)

    if outside > GARBAGE_FRACTION * n:
        swapped, slo, shi = _swapped_plausible(v)
        if swapped:
            return reading(
                "byteswapped",
                f"{outside} of {n} values that are no temperature ({lo:.6g} to {hi:.6g}), byte-swapped "
                f"{slo:.1f}..{shi:.1f} C: big-endian floats read as little-endian",
                "write little-endian float32",
            )
        return reading(
            "garbage",
            f"{outside} of {n} values outside the plausible {PLAUSIBLE_C[0]:g}..{PLAUSIBLE_C[1]:g} C "
            f"(from {lo:.6g} to {hi:.6g} C)",
        )
    if "counts8" in kinds and lo >= 0 and hi <= 255 and hi - lo >= COUNTS8_MIN_SPAN and bool(np.all(v == np.round(v))):
        return reading(
            "counts8",
            f"all {n} values are whole numbers within 0..255 ({lo:g}..{hi:g}): 8-bit counts (a palette or preview "
            "image), not temperatures",
            "give the radiometric temperatures, or treat the data as 8-bit thermal (no temperatures)",
        )
    if "kelvin" in kinds and p1 >= KELVIN_P1_MIN and KELVIN_MEDIAN[0] <= med <= KELVIN_MEDIAN[1]:
        return reading(
            "kelvin",
            f"values {p1:.1f}..{p99:.1f} (1-99 %, median {med:.1f}) look like Kelvin",
            f"subtract 273.15 (median {med - 273.15:.1f} C) or declare the unit",
        )
    if "fahrenheit" in kinds and FAHRENHEIT_MEDIAN[0] <= med <= FAHRENHEIT_MEDIAN[1] and p99 <= FAHRENHEIT_P99_MAX:
        return reading(
            "fahrenheit",
            f"values {p1:.1f}..{p99:.1f} (1-99 %, median {med:.1f}) look like degrees Fahrenheit (as C, a scene "
            "hotter than a sunlit facade)",
            f"convert with C = (F - 32) / 1.8 (median {(med - 32) / 1.8:.1f} C) or declare the unit",
        )
    return reading("plausible")


def check(temp: np.ndarray, name: str, what: str, units: bool | tuple[str, ...] = True, declared: bool = False) -> int:
    """The check every thermal entry point calls on ``temp`` (float, changed in place), read by ``what`` from
    ``name``: garbage (``classify``) is a ``DataError`` naming ``name``, ``what``, the count and the span; a unit
    mix-up (``units``) is one too, with the fix, or a console warning when the unit was ``declared``; values outside
    ``PLAUSIBLE_C`` in a plausible map become missing (NaN), their count a console warning. Returns that count."""
    r = classify(temp, units=units)
    if r.kind in ("garbage", "byteswapped"):
        tail = "" if r.kind == "byteswapped" else "; it is not temperatures in C: check its unit or scale"
        raise DataError(f"{name}: {what} gives {r.message}{tail}")
    if r.kind in UNIT_KINDS:
        if not declared:
            raise DataError(f"{name}: {what}: {r.message}")
        log.warning("%s: %s (the unit was stated, so it is kept): %s", name, what, r.detail)
    if not r.outside:
        return 0
    with np.errstate(all="ignore"):
        bad = np.isfinite(temp) & _not_temperature(temp)
    temp[bad] = np.nan
    log.warning(
        "%s: %d of %d values from %s lie outside the plausible %g..%g C (from %.6g to %.6g): made missing",
        name,
        r.outside,
        r.finite,
        what,
        PLAUSIBLE_C[0],
        PLAUSIBLE_C[1],
        r.lo,
        r.hi,
    )
    return r.outside


def implausible_to_missing(temp: np.ndarray, name: str, what: str) -> int:
    """``check(temp, name, what, units=False)``: garbage refused, a few values outside ``PLAUSIBLE_C`` made missing
    (NaN, counted on the console); returns how many."""
    return check(temp, name, what, units=False)


def sample_problem(thermal: np.ndarray, meta: dict | None = None) -> str | None:
    """What is wrong with a dataset plugin's ``AlignedSample.thermal`` for the sample contract, or None: 8-bit
    counts, byte-swapped floats, Fahrenheit (unless ``meta["thermal_unit"]`` states ``celsius``). Values mostly
    outside the range and Kelvin are judged over the whole dataset by the input guard (``temperature-range``)."""
    r = classify(thermal)
    if r.kind == "byteswapped" or r.kind == "counts8":
        return r.message
    if r.kind == "fahrenheit" and str((meta or {}).get("thermal_unit", "")).lower() not in ("celsius", "c"):
        return f"{r.message} (meta['thermal_unit'] = 'celsius')"
    return None
