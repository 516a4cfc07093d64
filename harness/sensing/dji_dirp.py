"""DJI "dirp" R-JPEGs (Zenmuse H20T, "class D"): raw counts through the camera's temperature curve.

The older DJI thermal cameras do not store blackbody counts. An H20T file carries (see ``docs/sensing.md``)::

    APP3  640 x 512 little-endian uint16 raw counts (kept as they are: ``raw14`` is the stored word)
    APP4  a 0xA00-byte calibration block starting AA 55 12 (offsets below, little-endian)
    APP5  the temperature curve: 16384 int16 values in 0.1 C, increasing with the curve index

Calibration block fields used by the measurement::

    0x24..0x3C  float32 K1, K2, K3, K4, KF, B1, B2       gains and offsets of the raw -> curve-index map
    0x44        uint16 distance (m)                      0x46 uint16 relative humidity (%)
    0x48        uint16 emissivity (%)                    0x4A int16 reflected temperature (0.1 C)
    0x4C, 0x50  int32 distance coefficients D1, D2
    0x54        uint16 KJ (percent scale of the result)  0x56 int16 DB (0.1 C offset of the result)
    0x58        int16 reference temperature (0.1 C)      0x64, 0x84, 0x88, 0xA4, 0xA8 float32 internal temps (C)
    0x146       uint16 raw offset                        0x148 uint32 header version

DJI's SDK ignores the four measurement parameters stored in the block: it measures at its own defaults
(``DEFAULTS``: 5 m, 70 %, emissivity 1.00, reflected 23.0 C) unless parameters are set, and so does ``measure``.
One raw count ``v`` becomes a temperature in float32 arithmetic, step by step::

    Tref  = 0x58 / 10 C, or the float at 0x64 when 0x58 holds less than -273.5 C
    p0    = (T_A4 - Tref) K1 + B1
    p1    = (K3 f6 + K2 f6 f6 + K4) - (K3 f7 + K2 f7 f7 + K4)      f6 = T_88 - Tref, f7 = T_A8 - Tref
    s     = 4 (k + 1) for the first k with curve[k] < round(10 T_A4) <= curve[k + 1]   (65532 when above the curve)
    p4    = (RH' / 70) ((D1 dd^2 / 1e5 + 1) - D2 dd / 1e5),  dd = distance - 50,  RH' = (RH - 70) / 6.4 + 70
    g     = ((((v - raw_offset) KF / 79 + s) + B2) - p0 - p1) / p4
    index = 0 when g < 0, 16383 when round(g) >= 65534, else floor(round(g) / 4 + 0.5)
    Tc    = curve[index] / 10                                     (the blackbody temperature, 0.1 C steps)
    T     = DB / 10 + KJ / 100 ((100 ((Tc + 273)^4 - Tr^4) / E + Tr^4)^(1/4) - 273),  Tr = refl / 10 + 273

(``E`` the emissivity in percent; the kelvin offset is 273, not 273.15, as the camera's firmware has it.)
The map is evaluated once per possible raw value (a 65536-entry table) and indexed by the frame.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import ConfigError, DataError

F = np.float32
BLOCK_MAGIC = b"\xaa\x55\x12"
BLOCK_BYTES = 0xA00
CURVE_BYTES = 0x8000
#: EXIF models whose R-JPEGs are dirp class D (calibration block in APP4, curve in APP5).
DIRP_MODELS = ("ZH20T",)
#: the SDK's measurement parameters for these files: distance m, humidity %, emissivity %, reflected 0.1 C
DEFAULTS = {"distance": 5.0, "humidity": 70.0, "emissivity": 1.0, "reflected": 23.0}
#: what the SDK accepts when parameters are set
RANGES = {"distance": (1.0, 25.0), "humidity": (20.0, 100.0), "emissivity": (0.1, 1.0), "reflected": (-40.0, 500.0)}
UNITS = {"distance": "m", "humidity": "%", "emissivity": "0-1", "reflected": "C"}


def is_dirp_block(app4: bytes) -> bool:
    """Whether an APP4 payload is a dirp class-D calibration block."""
    return len(app4) >= BLOCK_BYTES and app4[:3] == BLOCK_MAGIC


def _roundf(x: np.ndarray | np.floating) -> np.ndarray:
    """C ``roundf``: float32 rounded half away from zero (exact: ``x - trunc(x)`` is representable)."""
    x = np.asarray(x, dtype=F)
    whole = np.trunc(x)
    return (whole + np.where(np.abs(x - whole) >= F(0.5), np.sign(x), F(0.0))).astype(F)


def _first_step(curve: np.ndarray, value: int) -> int | None:
    """First ``k`` with ``curve[k] < value <= curve[k + 1]`` (the curve is scanned from the cold end)."""
    hits = np.flatnonzero((curve[:-1] < value) & (curve[1:] >= value))
    return int(hits[0]) if hits.size else None


@dataclass(frozen=True)
class DirpCalibration:
    """The calibration block and curve of one class-D file (module docstring)."""

    block: bytes
    curve: np.ndarray  # int16 [16384], 0.1 C
    header_version: int
    stored_params: dict[str, float] = field(default_factory=dict)

    def f32(self, off: int) -> np.float32:
        return F(struct.unpack_from("<f", self.block, off)[0])

    def i16(self, off: int) -> int:
        return struct.unpack_from("<h", self.block, off)[0]

    def u16(self, off: int) -> int:
        return struct.unpack_from("<H", self.block, off)[0]

    def summary(self) -> dict[str, Any]:
        return {
            "format": "dirp",
            "header_version": self.header_version,
            "curve_c": [int(self.curve[0]) / 10.0, int(self.curve[-1]) / 10.0],
        }


def parse(app4: bytes, app5: bytes | None, name: str | Path = "<R-JPEG>") -> DirpCalibration:
    """The calibration block (APP4) and curve (APP5) of a class-D file; a short segment is a ``DataError``."""
    if not is_dirp_block(app4):
        raise DataError(
            f"{name}: APP4 is not a dirp calibration block (expected {BLOCK_BYTES:#x} bytes starting "
            f"aa 55 12, got {len(app4)} bytes starting {app4[:3].hex(' ')})"
        )
    if app5 is None or len(app5) < CURVE_BYTES:
        got = "no APP5 segment" if app5 is None else f"{len(app5)} bytes"
        raise DataError(
            f"{name}: the dirp temperature curve (APP5, {CURVE_BYTES:#x} bytes) is missing or cut "
            f"short ({got}); the file is damaged"
        )
    block = bytes(app4[:BLOCK_BYTES])
    curve = np.frombuffer(app5[:CURVE_BYTES], dtype="<i2").astype(np.int16)
    curve.flags.writeable = False
    d, h, e, r = struct.unpack_from("<HHHh", block, 0x44)
    stored = {"distance": float(d), "humidity": float(h), "emissivity": e / 100.0, "reflected": r / 10.0}
    return DirpCalibration(
        block=block, curve=curve, header_version=struct.unpack_from("<I", block, 0x148)[0], stored_params=stored
    )


def measurement_params(overrides: Mapping[str, float | None] | None = None) -> dict[str, float]:
    """The SDK defaults with the given (non-None) overrides, each checked against ``RANGES`` (``ConfigError``)."""
    p = dict(DEFAULTS)
    for key, value in dict(overrides or {}).items():
        if value is None:
            continue
        if key not in RANGES:
            raise ConfigError(
                f"measurement parameter {key!r} does not apply to dirp (H20T) files; known: {', '.join(RANGES)}"
            )
        v = float(value)
        lo, hi = RANGES[key]
        if not lo <= v <= hi:
            raise ConfigError(
                f"measurement parameter {key}={v:g} {UNITS[key]} is outside the range the dirp "
                f"correction accepts ({lo:g}..{hi:g} {UNITS[key]})"
            )
        p[key] = v
    return p


def temperature_table(cal: DirpCalibration, params: Mapping[str, float], name: str | Path = "<R-JPEG>") -> np.ndarray:
    """Temperature (C, float32) of every raw value 0..65535 at ``params`` (module docstring)."""
    # the parameters as the SDK stores them: whole metres and percent, emissivity in percent, reflection in 0.1 C
    dist = int(np.int16(int(F(params["distance"]))))
    hum = int(np.int16(int(F(params["humidity"]))))
    ems_pct = int(np.int16(int(F(F(params["emissivity"]) * F(100.0)))))
    refl10 = int(np.int16(int(F(F(params["reflected"]) * F(10.0)))))
    for off in (0x64, 0xA4, 0x88, 0xA8, 0x84):
        if cal.f32(off) < F(-273.5):
            raise DataError(
                f"{name}: dirp calibration block holds an invalid internal temperature at {off:#x} "
                f"({float(cal.f32(off)):g} C); the file is damaged"
            )
    curve = cal.curve
    t_a4 = cal.f32(0xA4)
    s9 = int(np.int16(int(_roundf(t_a4 * F(10.0)))))
    if curve[-1] <= s9:
        shift = F(65532.0)
    else:
        k = _first_step(curve, s9) if curve[0] < s9 else None
        if k is None:
            raise DataError(
                f"{name}: the camera's internal temperature {float(t_a4):.2f} C lies outside its "
                "temperature curve; the file cannot be measured"
            )
        shift = F(int(_roundf(F((k + 1) * 4))) & 0xFFFF)
    k1, k2, k3, k4, kf, b1, b2 = (cal.f32(o) for o in (0x24, 0x28, 0x2C, 0x30, 0x34, 0x38, 0x3C))
    ref = cal.i16(0x58)
    t_ref = cal.f32(0x64) if ref < -2735 else F(F(ref) / F(10.0))
    p0 = F(F(F(t_a4 - t_ref) * k1) + b1)
    f6, f7 = F(cal.f32(0x88) - t_ref), F(cal.f32(0xA8) - t_ref)
    p1 = F(F(F(F(f6 * k3) + F(F(f6 * k2) * f6)) + k4) - F(F(F(k3 * f7) + F(F(k2 * f7) * f7)) + k4))
    p3 = F(kf / F(79.0))
    dd = dist - 50
    d1, d2 = struct.unpack_from("<ii", cal.block, 0x4C)
    rh = F(F(F(hum - 70) / F(6.4)) + F(70.0))
    p4 = F(F(rh / F(70.0)) * F(F(F(F(d1 * dd * dd) / F(100000.0)) + F(1.0)) - F(F(dd * d2) / F(100000.0))))
    raw = np.arange(65536, dtype=np.int64) - cal.u16(0x146)
    with np.errstate(all="ignore"):
        g = (raw.astype(F) * p3).astype(F)
        g = (((((g + shift).astype(F) + b2).astype(F) - p0).astype(F) - p1).astype(F) / p4).astype(F)
        u = _roundf(g).astype(np.float64)
        index = np.where(g < 0, 0, np.where(u >= 0xFFFE, 0x3FFF, np.floor(u * 0.25 + 0.5))).astype(np.int64)
        index = np.clip(index, 0, 0x3FFF)
        tc = (curve[index].astype(F) / F(10.0)).astype(F)
        # powf as the SDK's libm gives it: the power in double, rounded once to float32. NumPy's float32 power
        # takes a SIMD path whose last bits depend on the CPU (AVX-512 or not), which broke bit-exactness.
        r4 = F(np.power(np.float64(F(F(F(refl10) / F(10.0)) + F(273.0))), 4.0))
        t4 = np.power((tc + F(273.0)).astype(F).astype(np.float64), 4.0).astype(F)
        q = ((((t4 - r4).astype(F) * F(100.0)).astype(F) / F(ems_pct)).astype(F) + r4).astype(F)
        tt = np.power(np.maximum(q, F(0.0)).astype(np.float64), 0.25).astype(F)
        kj, db = F(cal.u16(0x54)), F(F(cal.i16(0x56)) / F(10.0))
        out = (db + ((tt - F(273.0)).astype(F) * kj).astype(F) / F(100.0)).astype(F)
    return out


def measure(
    raw: np.ndarray, cal: DirpCalibration, params: Mapping[str, float], name: str | Path = "<R-JPEG>"
) -> np.ndarray:
    """Temperature (C, float32, shaped like ``raw``) of a class-D frame at ``params`` (see ``DEFAULTS``)."""
    return temperature_table(cal, params, name)[np.asarray(raw, dtype=np.uint16)]
