"""The labelled approximate route: temperatures for DJI files whose exact correction needs data only DJI's SDK holds.

It is opt-in (``--approximate`` on ``harness sensing decode``, ``sensing.radiometry.approximate: true`` for a
dataset); without it such files are refused, naming the camera, the format and both ways on (this route, or
DJI's own SDK through the converter route, ``dji_converter``). Each approximation is named and carries the bound
measured against DJI Thermal SDK on public sample files (``benchmarks/dji_approximate.py``). The bound is a
function of the temperature: it is measured per band, and temperatures above the hottest one measured come out
missing (NaN) rather than with an unknown error. Emissivities outside the measured range are refused.

========================== =============================================== ============================================
approximation              files                                           what is left out
========================== =============================================== ============================================
``emissivity-remap-        iirp, APP5 asks for DJI's emissivity re-mapping DJI's emissivity re-mapping tables; the
skipped``                  tables (Matrice 4T, H30T: APP4 format 0x300)    file's own transmission table is used
``builtin-tau-unity``      iirp, APP5 says "the camera's built-in default  the transmission: τ = 1; emissivity and the
                           table" (Mavic 2 Enterprise Advanced)            reflected temperature are applied
========================== =============================================== ============================================

``hirp`` files (Matrice 3TD / 4T, newer firmware) have no approximation: their temperatures come from DJI's integer
measurement core, which re-derives the camera's response from internal sensor readings; no smooth function of the
raw counts reproduces them (``benchmarks/hirp_curve_floor.py``), and the file does not state the offset such a
function would need. They decode through the converter route only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from harness.errors import DataError

LABEL = "approximate temperatures"


@dataclass(frozen=True)
class Approximation:
    """One approximate correction and its measured agreement with DJI Thermal SDK.

    ``bands``: ``(upper temperature C, max |approximate - SDK| C)`` in increasing order: the bound for a temperature
    is that of the first band whose upper temperature it does not exceed; temperatures above the last band were
    not measured. ``bands_high_emissivity``: tighter bands for emissivities at or above ``high_emissivity``.
    ``emissivity``: the range the bands were measured over (inclusive).
    """

    name: str
    left_out: str
    measured_on: str
    emissivity: tuple[float, float]
    bands: tuple[tuple[float, float], ...]
    bands_high_emissivity: tuple[tuple[float, float], ...] = ()
    high_emissivity: float = 1.1

    def bands_for(self, emissivity: float) -> tuple[tuple[float, float], ...]:
        return (
            self.bands_high_emissivity
            if emissivity >= self.high_emissivity and self.bands_high_emissivity
            else self.bands
        )

    @property
    def measured_up_to_c(self) -> float:
        return self.bands[-1][0]


# Measured with benchmarks/dji_approximate.py against DJI Thermal SDK 1.7 (dirp_measure_ex) on the public sample
# files named in ``measured_on``, at each file's own parameters and with emissivity set to 0.6, 0.8, 0.95 and
# 0.98 (builtin-tau-unity: 0.6, 0.8, 0.95; distance 1-25 m; humidity 20-90 %). docs/sensing.md has the table.
APPROXIMATIONS: dict[str, Approximation] = {
    "emissivity-remap-skipped": Approximation(
        name="emissivity-remap-skipped",
        left_out="DJI's emissivity re-mapping tables (the file's own transmission table is used)",
        measured_on="5 H30T and 2 Matrice 4T files",
        emissivity=(0.6, 0.98),
        bands=((30.0, 0.08), (60.0, 0.13), (100.0, 0.72), (180.0, 3.2)),
        bands_high_emissivity=((30.0, 0.009), (60.0, 0.038), (100.0, 0.2), (180.0, 0.87)),
        high_emissivity=0.95,
    ),
    "builtin-tau-unity": Approximation(
        name="builtin-tau-unity",
        left_out="the camera's built-in transmission table (transmission taken as 1)",
        measured_on="4 Mavic 2 Enterprise Advanced files",
        emissivity=(0.6, 0.95),
        bands=((30.0, 0.8), (63.0, 4.4)),
    ),
}
#: UnsupportedCorrection.kind -> the approximation that stands in for it
FOR_KIND = {"emissivity-remap": "emissivity-remap-skipped", "builtin-tau": "builtin-tau-unity"}


def for_kind(kind: str) -> Approximation | None:
    """The approximation for an ``UnsupportedCorrection.kind``, or ``None`` when there is none."""
    name = FOR_KIND.get(kind)
    return APPROXIMATIONS[name] if name else None


def unity_table() -> Any:
    """A transmission table of 1 everywhere (no humidity correction, a separate reflected term): the balance
    ``W(T0) = e W(T) + (1 - e) W(T_refl)`` for files whose table is built into DJI's SDK."""
    from harness.sensing import dji_correction as dc

    temps, dists = dc.tau_axes(0)
    tau = np.full((len(temps), len(dists)), dc.Q14, dtype=np.uint16)
    tau.flags.writeable = False
    return dc.TauTable(
        tau=tau,
        temps_k=temps,
        distances_m=dists,
        version=0,
        humidity=0,
        reflection=True,
        max_distance=25.0,
        approximation="builtin-tau-unity",
    )


def check_emissivity(approx: Approximation, emissivity: float, name: object) -> None:
    """A ``DataError`` naming ``name`` when ``emissivity`` lies outside the range the bound was measured over."""
    lo, hi = approx.emissivity
    if not lo <= emissivity <= hi:
        raise DataError(
            f"{name}: the approximate route ({approx.name}) was measured for emissivity {lo:g}-{hi:g} "
            f"only; emissivity {emissivity:g} has no measured bound (decode the file with DJI's SDK: "
            "--converter dji_irp)"
        )


def apply(temperature_c: np.ndarray, approx: Approximation, emissivity: float) -> tuple[np.ndarray, dict[str, Any]]:
    """(temperatures with those above the measured range set missing, the record of the route): ``bound_c`` is the
    largest band bound the frame's temperatures fall in."""
    t = np.asarray(temperature_c, dtype=np.float32)
    top = approx.measured_up_to_c
    above = np.isfinite(t) & (t > top)
    if above.any():
        t = t.copy()
        t[above] = np.nan
    finite = t[np.isfinite(t)]
    hottest = float(finite.max()) if finite.size else -math.inf
    bound = 0.0
    for upper, b in approx.bands_for(emissivity):
        bound = max(bound, b)
        if hottest <= upper:
            break
    record = {
        "label": LABEL,
        "approximation": approx.name,
        "left_out": approx.left_out,
        "bound_c": bound,
        "measured_on": approx.measured_on + " against DJI Thermal SDK",
        "measured_up_to_c": top,
        "missing_above_range": int(above.sum()),
    }
    return t, record


def describe(record: dict[str, Any]) -> str:
    """``approximate temperatures (within 0.034 C of DJI's SDK; emissivity-remap-skipped)`` for tables and logs."""
    return f"{LABEL} (within {record['bound_c']:g} C of DJI's SDK; {record['approximation']})"
