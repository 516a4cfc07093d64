"""DJI Thermal SDK temperature correction for iirp-family R-JPEGs (M3T, M30T, M3TD, H20N, H30T, M4T, M2EA).

An iirp raw count is a blackbody temperature, ``T0 = raw14 / 16 - 273.15``. DJI's SDK (``dirp_measure_ex``)
corrects it per pixel for the object's emissivity, the reflected and atmospheric temperatures and the
atmospheric transmission ``tau`` between camera and object. ``tau`` is a Q14 fixed-point number (16384 = 1.0)
read from a table the camera writes into APP5, over target temperature and distance, then reduced for humidity.
This module implements those semantics, vectorised over numpy arrays; see ``docs/sensing.md`` for the measured
agreement with the SDK on real M3T files.

APP5 payload layout (little-endian uint16 words)::

    0x000  header, 0x100 bytes (128 words)
             w[0]      0
             w[1]      table version (0x14 in M3T files)           only when w[2] == w[3] == 0xFFFF,
             w[4..5]   emissivity-table flag, version              otherwise the header carries no fields
             w[6..7]   humidity-correction flag, version           (version 0, all flags off) and the
             w[10..11] separate-reflection flag, version           table starts at byte 0 (header included)
    0x100  tau[i_T, i_d] as Q14 words, temperature-major (row = temperature, column = distance):
             0x1C00 bytes (56 x 64 used) when the APP4 format version is 0x100 or 0x200 (M3T), else 0x1F00 bytes.

Axes (K and m), chosen by the table version ``v``:

    v < 0x40      T = 248.15, 273.15, ..., 1623.15 (56)        d = D (64)
    v < 0x101     T = 248.15, 273.15, ..., 1273.15 (42)        d = D + D_far (88)
    otherwise     T = 248.15 .. 823.15 step 25, 873.15 .. 1873.15 step 50 (45)    d = D + D_far (88)

    D     = 0.25..1.2 step 0.05, 1.3..2.0 step 0.1, 2.2..4.0 step 0.2, 4.5..8 step 0.5, 9..14 step 1,
            16..30 step 2, 35..50 step 5
    D_far = 60..100 step 10, 120..300 step 20, 350..500 step 50, 600..1000 step 100

Correction of one pixel (``W(T) = (T + 273.15)^4``, temperatures in C, ``e`` emissivity, ``t = tau / 16384``)::

    tau(T, d)  bilinear in (T + 273.15, d) between the four surrounding table cells, + 0.5, truncated;
               beyond the last distance: linear along temperature, truncated; beyond the last temperature: the
               last row's cell; below the first axis values the first cell's weights extrapolate linearly
    balance    W(T0) = t e W(T) + (1 - t e) W(T_atm)                               (no separate reflection)
               W(T0) = t e W(T) + t (1 - e) W(T_refl) + (1 - t) W(T_atm)          (table flag "reflection")
               =>  T = [(W(T0) - (1 - t e) W(T_atm)) / (t e)]^(1/4) - 273.15    (negative radiance -> 0)
    pass 1     T1 = balance(T0, tau(T0, d))
    pass 2     T  = balance(T0, tau_h(T1, tau(T1, d)))

Humidity (``RH`` fraction, ``T_a = T_atm`` in C, ``Tk = T1 + 273.15``)::

    p_w     = RH * 611.2 * exp(17.67 T_a / (243.5 + T_a))  Pa (Magnus), clamped to 800..3000 (v1) or 800..4000
              (v2, v3), truncated to whole Pa
    k(Tk)   = ((410.15 / Tk)^4 - 1) * 0.01 - 0.04          273.15 <= Tk < 410.15
            = ((Tk / 410.15)^4 - 1) * (-0.003) - 0.04      410.15 <= Tk < 1273.15
            = 0                                            otherwise;   x 0.6 in v2, x 0.3 in v3
    d_h     = d clamped to 1..1000 m (v2, v3: at most 10 m)
    tau_h   = trunc(tau * (p_w / 1425) ^ (k * ln(d_h) * 1.4427))       (1.4427 ~ 1 / ln 2: a log2 of distance)

Humidity version: table version < 0x102 -> v1; 0x110 -> v2; 0x104, 0x113, 0x116, 0x119 -> v3; otherwise the
header's flag and version. The atmospheric temperature is the file's ambient temperature; once measurement
parameters are set (here: any override), files with a pre-v0300 APP4 header (M3T: version 0x200) use the
reflected temperature in its place, as the SDK does.

Tables the SDK does not take from the file are not reproduced: an APP5 header starting ``FF FF FF FF`` (the SDK
substitutes built-in default tau tables) and the emissivity re-mapping tables (flag set or table version 0x101)
raise ``UnsupportedCorrection`` (its ``kind`` says which: ``builtin-tau`` or ``emissivity-remap``). Such files are
decoded exactly by DJI's own SDK through the converter route, or, on request, by the labelled approximate route
(``harness.sensing.dji_approximate``: ``parse_app5(..., skip_emissivity_remap=True)`` and ``unity_table()``).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass
from decimal import Decimal
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import ConfigError, DataError

log = logging.getLogger(__name__)

KELVIN = 273.15
Q14 = 16384
HEADER_BYTES = 0x100
OLD_TABLE_BYTES = 0x1C00
TABLE_BYTES = 0x1F00

#: what ``set_measurement_params`` accepts (distance up to 300 m for tables that say so).
OVERRIDE_RANGES: dict[str, tuple[float, float]] = {
    "distance": (1.0, 25.0),
    "humidity": (1.0, 100.0),
    "emissivity": (0.1, 1.0),
    "reflected": (-40.0, 100.0),
    "ambient": (-40.0, 80.0),
}
OVERRIDE_UNITS = {"distance": "m", "humidity": "%", "emissivity": "0-1", "reflected": "C", "ambient": "C"}


class UnsupportedCorrection(DataError):
    """The file's correction needs tables DJI's SDK carries itself (not in the file). ``kind``: ``builtin-tau``
    (the camera's default transmission table), ``emissivity-remap`` (DJI's emissivity re-mapping tables) or
    ``unknown`` (a table version this module does not know)."""

    def __init__(self, message: str, kind: str = "unknown"):
        super().__init__(message)
        self.kind = kind


# ---------------------------------------------------------------------------------------------- axes
def _ladder(*runs: tuple[str, str, str]) -> np.ndarray:
    """Evenly stepped runs ``(start, step, last)`` concatenated, as float64 (decimal steps, no drift)."""
    out: list[float] = []
    for start, step, last in runs:
        v, s, e = Decimal(start), Decimal(step), Decimal(last)
        while v <= e:
            out.append(float(v))
            v += s
    return np.asarray(out, dtype=np.float64)


_NEAR = (
    ("0.25", "0.05", "1.2"),
    ("1.3", "0.1", "2.0"),
    ("2.2", "0.2", "4.0"),
    ("4.5", "0.5", "8.0"),
    ("9", "1", "14"),
    ("16", "2", "30"),
    ("35", "5", "50"),
)
_FAR = (("60", "10", "100"), ("120", "20", "300"), ("350", "50", "500"), ("600", "100", "1000"))


@lru_cache(maxsize=None)
def tau_axes(table_version: int) -> tuple[np.ndarray, np.ndarray]:
    """(target temperatures in K, distances in m) of the tau table for ``table_version`` (module docstring)."""
    if table_version < 0x40:
        temps, dists = _ladder(("248.15", "25", "1623.15")), _ladder(*_NEAR)
    elif table_version < 0x101:
        temps, dists = _ladder(("248.15", "25", "1273.15")), _ladder(*_NEAR, *_FAR)
    else:
        temps = _ladder(("248.15", "25", "823.15"), ("873.15", "50", "1873.15"))
        dists = _ladder(*_NEAR, *_FAR)
    temps.flags.writeable = False
    dists.flags.writeable = False
    return temps, dists


def humidity_version(table_version: int, flag: int, version: int) -> int:
    """Humidity-correction version (0 = off) from the table version and the header's flag/version words."""
    if table_version < 0x102:
        return 1
    if table_version == 0x110:
        return 2
    if table_version in (0x104, 0x113, 0x116, 0x119):
        return 3
    return version if flag == 1 else 0


# ---------------------------------------------------------------------------------------------- APP5
@dataclass(frozen=True)
class TauTable:
    """The atmospheric-transmission table of an iirp APP5 segment.

    ``tau`` uint16 ``[len(temps_k), len(distances_m)]`` Q14 transmissions; ``version`` the table version (0 for a
    header without fields); ``humidity`` the humidity-correction version (0 = off, 1..3); ``reflection``: the
    balance has a separate reflected term; ``max_distance`` the largest distance the SDK accepts as a setting.
    """

    tau: np.ndarray
    temps_k: np.ndarray
    distances_m: np.ndarray
    version: int
    humidity: int
    reflection: bool
    max_distance: float
    valid_rows: int = 0  # leading temperature rows holding Q14 values (0: all rows)
    #: what the table leaves out of DJI's correction (``dji_approximate``): "" exact, else the approximation's name
    approximation: str = ""

    @property
    def valid_below_k(self) -> float:
        """Target temperatures (K) at or above this need rows past ``valid_rows`` (inf when all rows are valid)."""
        if not self.valid_rows or self.valid_rows >= len(self.temps_k):
            return math.inf
        return float(self.temps_k[self.valid_rows - 1])

    def summary(self) -> dict[str, Any]:
        """What a sidecar records of the table (``valid_up_to_c`` is ``None`` when every row is valid: JSON has no
        infinity)."""
        rows = self.valid_rows or len(self.temps_k)
        return {
            "table_version": self.version,
            "shape": list(self.tau.shape),
            "humidity_version": self.humidity,
            "separate_reflection": self.reflection,
            "tau_range": [int(self.tau[:rows].min()), int(self.tau[:rows].max())],
            "max_distance_m": self.max_distance,
            "valid_up_to_c": (None if math.isinf(self.valid_below_k) else round(self.valid_below_k - KELVIN, 2)),
            **({"approximation": self.approximation} if self.approximation else {}),
        }


def parse_app5(
    payload: bytes, format_version: int = 0x100, name: str | Path = "<APP5>", skip_emissivity_remap: bool = False
) -> TauTable:
    """Parse an iirp APP5 payload (header + tau table) into a ``TauTable``; layout in the module docstring.

    ``format_version`` is the APP4 format version (``header["version"]``, 0x200 in M3T files; 0x100 when the
    APP4 block has no magic): 0x100 and 0x200 carry a 0x1C00-byte table, others a 0x1F00-byte one. A payload too
    short for its header or table, a table too small for its axes, or Q14 values outside 1..16384 is a
    ``DataError`` naming ``name``; tables the SDK would replace by built-in data are ``UnsupportedCorrection``.
    ``skip_emissivity_remap``: read a table that asks for DJI's emissivity re-mapping anyway and use it without the
    re-mapping (the approximate route; the table's ``approximation`` says so).
    """
    if len(payload) < HEADER_BYTES:
        raise DataError(
            f"{name}: APP5 calibration segment is {len(payload)} bytes, shorter than its "
            f"{HEADER_BYTES}-byte header; the file is damaged (decode it with the blackbody decoder)"
        )
    head = payload[:HEADER_BYTES]
    if head[:4] == b"\xff\xff\xff\xff":
        raise UnsupportedCorrection(
            f"{name}: APP5 says the camera's built-in default transmission table applies, "
            "which the file does not carry",
            kind="builtin-tau",
        )
    old = ((format_version - 0x100) & 0xFFFFFEFF) == 0
    size = OLD_TABLE_BYTES if old else TABLE_BYTES
    max_distance = 25.0 if old or struct.unpack_from("<H", head, 2)[0] <= 0x3F else 300.0
    words = np.frombuffer(payload[: (min(len(payload), HEADER_BYTES + size) // 2) * 2], dtype="<u2")
    h = words[: HEADER_BYTES // 2]
    if h[2] == 0xFFFF and h[3] == 0xFFFF:
        version, ems_on, hum_on, hum_ver, refl_on, refl_ver = (int(h[k]) for k in (1, 4, 6, 7, 10, 11))
        table = words[HEADER_BYTES // 2 :]
    else:  # no header fields: the table is read from the start of the payload
        version, ems_on, hum_on, hum_ver, refl_on, refl_ver = 0, 0, 0, 0, 0, 0
        table = words
    remap = ems_on == 1 or version == 0x101
    if remap and not skip_emissivity_remap:
        raise UnsupportedCorrection(
            f"{name}: APP5 table version {version:#x} asks for DJI's emissivity re-mapping "
            "tables, which the file does not carry",
            kind="emissivity-remap",
        )
    if refl_on == 1 and refl_ver != 1:
        raise UnsupportedCorrection(f"{name}: APP5 reflected-temperature table version {refl_ver} is not known")
    hum = humidity_version(version, hum_on, hum_ver)
    if not 0 <= hum <= 3:
        raise UnsupportedCorrection(f"{name}: APP5 humidity-correction version {hum} is not known")
    temps, dists = tau_axes(version)
    n = len(temps) * len(dists)
    if table.size < n:
        raise DataError(
            f"{name}: APP5 holds {table.size} table words, table version {version:#x} needs "
            f"{len(temps)}x{len(dists)} = {n} (APP4 format version {format_version:#x}); the "
            "transmission table is cut short (decode the file with the blackbody decoder)"
        )
    tau = table[:n].reshape(len(temps), len(dists)).copy()
    # Some cameras (M2EA) fill only the rows up to their measuring range; the rest of the read holds other data.
    # Those rows are never used for temperatures below them; temperatures that would use them come out NaN.
    good = ((tau >= 1) & (tau <= Q14)).all(axis=1)
    valid_rows = len(temps) if good.all() else int(np.argmin(good))
    if valid_rows < 2:
        raise DataError(
            f"{name}: APP5 transmission values span {int(tau.min())}..{int(tau.max())}, outside the "
            f"Q14 range 1..{Q14} from the first rows on; the table is damaged (decode the file with "
            "the blackbody decoder)"
        )
    tau.flags.writeable = False
    return TauTable(
        tau=tau,
        temps_k=temps,
        distances_m=dists,
        version=version,
        humidity=hum,
        reflection=refl_on == 1,
        max_distance=max_distance,
        valid_rows=0 if valid_rows == len(temps) else valid_rows,
        approximation="emissivity-remap-skipped" if remap else "",
    )


# ---------------------------------------------------------------------------------------------- maths
# The SDK computes in a mix of float32 and float64; rounding to float32 where it does (``_f32``) makes the result
# bit-identical to its ``dirp_measure_ex`` on the reference files instead of ~1e-5 C away.
F32 = np.float32


def _f32(x: Any) -> np.ndarray:
    """``x`` rounded to float32 and returned as float64 (a C ``(float)`` cast inside double arithmetic)."""
    return np.asarray(x, dtype=np.float64).astype(F32).astype(np.float64)


def _kelvin(temperature_c: Any) -> np.ndarray:
    """``(float)(T + 273.15)``: the target temperature in K as the SDK's table look-ups see it."""
    return _f32(np.asarray(temperature_c, dtype=np.float64) + KELVIN)


def _cell_index(x: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Index of the grid cell holding ``x``: last ``k`` with ``grid[k] - 1e-4 < x``, clamped to the grid."""
    k = np.searchsorted(grid - 1e-4, x, side="left") - 1
    return np.clip(k, 0, len(grid) - 1)


def interpolate_tau(table: TauTable, temperature_c: Any, distance_m: float) -> np.ndarray:
    """Q14 transmission at ``(temperature_c + 273.15 K, distance_m)``: bilinear between the surrounding cells,
    + 0.5 and truncated; beyond the last distance column: linear along temperature, truncated; beyond the last
    temperature row: the row's cell. Below the first axis values the first cell's weights extrapolate linearly.
    Returns float64 whole numbers shaped like ``temperature_c``."""
    tg, dg, tau = table.temps_k, table.distances_m, table.tau.astype(np.float64)
    x = _kelvin(temperature_c)
    y = float(F32(distance_m))
    i = _cell_index(x, tg)
    j = int(_cell_index(np.asarray([y]), dg)[0])
    nt, nd = len(tg), len(dg)
    inner = i < nt - 1
    i0 = np.minimum(i, nt - 2)
    t_lo, t_hi = tg[i0], tg[i0 + 1]
    if j < nd - 1:
        d_lo, d_hi = dg[j], dg[j + 1]
        area = abs(d_hi - d_lo) * abs(t_hi - t_lo)
        v = (
            tau[i0, j] * (((d_hi - y) * (t_hi - x)) / area)
            + tau[i0, j + 1] * (((y - d_lo) * (t_hi - x)) / area)
            + tau[i0 + 1, j] * (((d_hi - y) * (x - t_lo)) / area)
            + tau[i0 + 1, j + 1] * (((y - d_lo) * (x - t_lo)) / area)
            + 0.5
        )
        return np.where(inner, np.trunc(v), tau[nt - 1, j])
    span = abs(t_hi - t_lo)
    v = tau[i0 + 1, j] * ((x - t_lo) / span) + tau[i0, j] * ((t_hi - x) / span)
    return np.where(inner, np.trunc(v), tau[nt - 1, j])


def vapour_pressure_pa(humidity_frac: float, air_c: float, version: int = 1) -> int:
    """Water vapour pressure ``RH * 611.2 exp(17.67 T / (243.5 + T))`` Pa (Magnus), clamped to 800..3000 (v1)
    or 800..4000 (v2, v3) and truncated to whole pascals."""
    p = float(F32(float(F32(humidity_frac)) * 611.2 * math.exp(17.67 * (air_c / (243.5 + air_c)))))
    return int(min(max(p, 800.0), 3000.0 if version == 1 else 4000.0))


def humidity_exponent_coefficient(temperature_c: Any, version: int = 1) -> np.ndarray:
    """``k(Tk)`` of the humidity correction (module docstring) per target temperature, float32 steps."""
    tk = _kelvin(temperature_c)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        k = np.where(
            tk < KELVIN,
            0.0,
            np.where(
                tk < 410.15,
                ((410.15 / tk) ** 4 - 1.0) * 0.01 - 0.04,
                np.where(tk < 1273.1501, ((tk / 410.15) ** 4 - 1.0) * -0.003 - 0.04, 0.0),
            ),
        )
    return _f32(_f32(k) * {1: 1.0, 2: 0.6, 3: 0.3}[version])


def humidity_adjusted_tau(
    tau_q14: Any, temperature_c: Any, humidity_frac: float, air_c: float, distance_m: float, version: int = 1
) -> np.ndarray:
    """``tau_h = trunc(tau * (p_w / 1425) ^ (k(T) * ln(d_h) * 1.4427))`` (version 0: ``tau`` unchanged)."""
    tau = np.asarray(tau_q14, dtype=np.float64)
    if version == 0:
        return tau
    d = min(max(float(F32(distance_m)), 1.0), 1000.0)
    if version in (2, 3):
        d = min(d, 10.0)
    base = float(F32(F32(vapour_pressure_pa(humidity_frac, air_c, version)) / F32(1425.0)))
    k = humidity_exponent_coefficient(temperature_c, version)
    factor = _f32(base ** (math.log(float(F32(d))) * 1.4427 * k))
    return np.trunc(_f32(_f32(tau) * factor))


def radiance_balance(
    t0_c: Any, tau_q14: Any, emissivity: float, atmosphere_c: float, reflected_c: float | None = None
) -> np.ndarray:
    """Object temperature (C, float32) from the apparent temperature ``t0_c``, ``W(T) = (T + 273.15)^4``:

    ``W0 = t e W + (1 - t e) W_atm`` (``reflected_c`` None: the atmosphere stands in for the reflection), or
    ``W0 = t e W + t (1 - e) W_refl + (1 - t) W_atm``; ``t = tau_q14 / 16384``, so
    ``T = [(W0 - (1 - t e) W_atm) / (t e)]^(1/4) - 273.15``. A negative object radiance is clamped to 0.
    """
    tau = np.asarray(tau_q14, dtype=np.float64)
    e = float(F32(emissivity))
    w0 = _kelvin(t0_c) ** 4
    w_atm = (float(F32(atmosphere_c)) + KELVIN) ** 4
    if reflected_c is None:
        w = w0 - w_atm * (1.0 - (tau * e) / Q14)
    else:
        w_refl = (float(F32(reflected_c)) + KELVIN) ** 4
        w = (w0 - (w_refl * (1.0 - e) * tau) / Q14) - w_atm * (1.0 - tau / Q14)
    te = _f32(_f32(tau * e) / Q14)  # (float)((float)tau * e / 16384.f)
    t_k = _f32(np.sqrt(np.sqrt(np.maximum(w, 0.0) / te)))
    return (t_k - KELVIN).astype(F32)


def correct_temperature(
    t0_c: Any,
    table: TauTable,
    emissivity: float,
    distance_m: float,
    humidity_pct: float,
    reflected_c: float,
    atmosphere_c: float,
) -> np.ndarray:
    """DJI's corrected temperature (C, float32) from blackbody temperatures ``t0_c`` (any shape), in two passes:

    ``T1 = balance(T0, tau(T0, d))``, then ``T = balance(T0, tau_h(T1, tau(T1, d)))`` (module docstring), with
    ``atmosphere_c`` as the air temperature (and, without the table's reflection flag, the reflected one).
    Evaluated once per distinct value of ``t0_c`` (a 640x512 frame has a few thousand).
    """
    m = _Measurement(emissivity, distance_m, humidity_pct, reflected_c, atmosphere_c)
    t0 = np.asarray(t0_c, dtype=F32)
    values, inverse = np.unique(t0, return_inverse=True)
    return _correct_values(values, table, m)[inverse.reshape(-1)].reshape(t0.shape)


@dataclass(frozen=True)
class _Measurement:
    """The measurement parameters of ``correct_temperature`` and ``correct_raw14``, checked once."""

    emissivity: float
    distance_m: float
    humidity_pct: float
    reflected_c: float
    atmosphere_c: float

    def __post_init__(self) -> None:
        if not self.emissivity >= 1e-4:
            raise ConfigError(f"emissivity {self.emissivity} is too small to correct for")


def _correct_values(values: np.ndarray, table: TauTable, m: _Measurement) -> np.ndarray:
    """The two-pass correction of the blackbody temperatures ``values`` (1-D float32), element by element."""
    refl = m.reflected_c if table.reflection else None
    t1 = radiance_balance(values, interpolate_tau(table, values, m.distance_m), m.emissivity, m.atmosphere_c, refl)
    tau1 = interpolate_tau(table, t1, m.distance_m)
    tau2 = humidity_adjusted_tau(tau1, t1, m.humidity_pct / 100.0, m.atmosphere_c, m.distance_m, table.humidity)
    tau2 = np.maximum(tau2, 1.0)  # a zero transmission leaves nothing to measure; keep the division defined
    out = radiance_balance(values, tau2, m.emissivity, m.atmosphere_c, refl)
    limit = table.valid_below_k
    if limit < math.inf:
        unusable = (_kelvin(values) >= limit) | (_kelvin(t1) >= limit)
        if unusable.any():
            out = np.where(unusable, np.float32(np.nan), out).astype(F32)
    return out


def correct_raw14(
    raw14: Any,
    table: TauTable,
    emissivity: float,
    distance_m: float,
    humidity_pct: float,
    reflected_c: float,
    atmosphere_c: float,
) -> np.ndarray:
    """``correct_temperature`` of the blackbody temperatures ``raw14 / 16 - 273.15`` by a lookup table.

    A raw count is an integer, so the correction is evaluated once for each count between the frame's smallest
    and largest (a few hundred for a facade scene) and the frame indexes that table: the same float32 values as
    ``correct_temperature``, without sorting the frame. Temperatures the table cannot correct are NaN.
    """
    m = _Measurement(emissivity, distance_m, humidity_pct, reflected_c, atmosphere_c)
    raw = np.asarray(raw14)
    if raw.size == 0:
        return np.zeros(raw.shape, dtype=F32)
    lo, hi = int(raw.min()), int(raw.max())
    counts = np.arange(lo, hi + 1, dtype=np.float64)
    t0 = (counts / 16.0 - KELVIN).astype(F32)  # the blackbody temperature, as ``radiometry.raw14_to_celsius``
    lut = _correct_values(t0, table, m)
    index = raw.astype(np.intp, copy=False) - lo if lo else raw
    return lut[index]


def deci_celsius(temperature_c: np.ndarray) -> np.ndarray:
    """``dirp_measure``'s int16 deci-Celsius: ``trunc(10 * T)`` (toward zero, not rounded)."""
    t = np.asarray(temperature_c, dtype=np.float32) * np.float32(10.0)
    return np.trunc(t).astype(np.int16)


# ---------------------------------------------------------------------------------------------- parameters
def check_overrides(overrides: Mapping[str, float | None], max_distance: float = 25.0) -> dict[str, float]:
    """The given (non-None) measurement overrides as floats, each checked against the range DJI's SDK accepts
    (``OVERRIDE_RANGES``; distance up to ``max_distance``); a value outside is a ``ConfigError`` naming it."""
    out: dict[str, float] = {}
    for key, value in overrides.items():
        if value is None:
            continue
        if key not in OVERRIDE_RANGES:
            raise ConfigError(f"unknown measurement parameter {key!r}; known: {', '.join(OVERRIDE_RANGES)}")
        v = float(value)
        lo, hi = OVERRIDE_RANGES[key]
        if key == "distance":
            hi = max_distance
        if not (lo <= v <= hi) or math.isnan(v):
            raise ConfigError(
                f"measurement parameter {key}={v:g} {OVERRIDE_UNITS[key]} is outside the range the "
                f"correction accepts ({lo:g}..{hi:g} {OVERRIDE_UNITS[key]})"
            )
        out[key] = v
    return out


#: the smallest emissivity the correction divides by; a file stating less (about 0) is physically impossible
MIN_EMISSIVITY = 1e-4


def check_file_params(params: Mapping[str, float], name: str | Path = "<APP4>") -> None:
    """The file's own parameters must be in the range the SDK measures with, else ``DataError`` naming ``name``
    (a property of that file: a batch lists it and decodes the others)."""
    limits = {
        "emissivity": (MIN_EMISSIVITY, 1.0, ""),
        "humidity": (0.0, 100.0, " %"),
        "distance": (0.0, 1000.0, " m"),
        "ambient": (-KELVIN, 100.0, " C"),
        "reflected": (-KELVIN, 100.0, " C"),
    }
    for key, (lo, hi, unit) in limits.items():
        v = params.get(key)
        if v is None or not (lo <= float(v) <= hi):
            what = (
                " (a surface that emits nothing cannot be measured)"
                if key == "emissivity" and v is not None and float(v) < lo
                else ""
            )
            raise DataError(
                f"{name}: APP4 measurement parameter {key}={v}{unit} is outside {lo:g}..{hi:g}{what}; "
                "give it explicitly or use the blackbody decoder"
            )
