"""Why the ``hirp`` temperatures stay refused: how close any smooth function of raw14 can get to DJI's values.

Anchor: DJI Thermal SDK ``temp_c`` of the Matrice 3TD ``hirp`` files (``m3td_hirp_*_reference.npz`` beside the
files). For each file it prints

* the layout the file carries: the APP5 ``HIDR`` block directory (type, size, offset), the APP4 measurement
  parameters (emissivity and distance in Q13, ambient in milli-C, humidity in thousandths, the lens slot, the gain
  mode byte, two sensor readings) and the calibration block's response constants ``R, B, O, F`` of that slot and
  gain (the camera response ``gray = O + R / (exp(B / T) - F)``, B in 1/16384 K);
* the shape of the reference curve: distinct raw values, the largest spread of ``temp_c`` within one raw value
  (0 means temp_c is a function of raw14 alone), and whether ``temp_dc`` is ``round(10 temp_c)``;
* the floor of every smooth model: the smallest possible max ``|p(raw) - temp_c|`` over polynomials ``p`` of
  degree 1..8 (a linear program), and the same for a model whose output is truncated to 0.1 C like the SDK's;
  a Planck inversion is as smooth as these polynomials over a file's raw range, so no float model (whatever its
  constants) can be nearer than this floor;
* a Planck inversion with the file's own B and F, R scaled by the slot's gain word, the grey-body balance with
  the file's emissivity and ambient, and a fitted raw offset and gain (which the file does not state directly).

A decoder meets the target (``|d| <= 0.05`` C on every pixel) only where the floor is below 0.05 C. On the three
M3TD files it is 0.105-0.156 C: the reference curves step irregularly (0.1 C values skipped, others held two to
three times as long), and files a and b give equal temperatures at raw values 60 counts apart on 148 of 164
shared values, so the steps belong to DJI's fixed-point temperature arithmetic, not to the scene.

    .venv/bin/python benchmarks/hirp_curve_floor.py [--data ../shared/data/dji-rjpeg-cameras]
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np

from _common import SHARED_DATA, reference_arrays

DATA = SHARED_DATA / "dji-rjpeg-cameras"
APP4_PARAMS = 0x48  # measurement-parameter block inside the hirp APP4 payload
CALIB_TYPE = 7  # HIDR block holding the 0x3800-byte calibration (payload 0x1C bytes into the block)


def layout(path: Path) -> dict:
    """The fields of a hirp file that this benchmark reads (see the module docstring)."""
    from harness.sensing import jpeg

    segs = jpeg.read_segments(path.read_bytes(), path, require_eoi=False)
    app4 = segs.payloads(jpeg.APP4)[0]
    app5 = b"".join(segs.payloads(jpeg.APP5))
    if app5[:4] != b"HIDR":
        raise ValueError(f"{path}: APP5 does not start with the HIDR container")
    blocks = [struct.unpack_from("<III", app5, 12 + 12 * i) for i in range(9)]
    blocks = [b for b in blocks if b[1]]
    calib_at = next(off for typ, _, off in blocks if typ == CALIB_TYPE) + 0x1C
    calib = app5[calib_at : calib_at + 0x3800]
    tp = app4[APP4_PARAMS : APP4_PARAMS + 0x48]
    slot, gain = struct.unpack_from("<H", tp, 0x32)[0], tp[0x34]
    r, b, o, f = struct.unpack_from("<iiii", calib, 0x654 + 0x44 * slot + 0x154 * gain)
    _, gain_word = struct.unpack_from("<ii", calib, 0xCF8 + 0x24 * slot + 0xB4 * gain)
    return {
        "blocks": [(typ, size, off, app5[off : off + 4].decode("latin-1")) for typ, size, off in blocks],
        "emissivity": struct.unpack_from("<H", tp, 0x10)[0] / 8192,
        "distance": struct.unpack_from("<i", tp, 0x14)[0] / 8192,
        "ambient": struct.unpack_from("<i", tp, 0x28)[0] / 1000,
        "humidity": struct.unpack_from("<i", tp, 0x2C)[0] / 1000,
        "slot": slot,
        "gain": gain,
        "readings": struct.unpack_from("<HH", tp, 0x30)[:1] + struct.unpack_from("<H", tp, 0x36),
        "response": (r, b, o, f),
        "gain_word": gain_word,
    }


def smooth_floor(raw: np.ndarray, lo: np.ndarray, hi: np.ndarray, degree: int) -> float:
    """Smallest ``s`` such that a polynomial ``p`` of ``degree`` has ``lo - s <= p(raw) <= hi + s`` everywhere."""
    from scipy.optimize import linprog

    x = (raw - raw.mean()) / max(float(np.ptp(raw)), 1.0)
    v = np.vander(x, degree + 1)
    ones = np.ones((len(raw), 1))
    a_ub = np.vstack([np.hstack([v, -ones]), np.hstack([-v, -ones])])
    res = linprog(
        np.r_[np.zeros(degree + 1), 1.0],
        A_ub=a_ub,
        b_ub=np.r_[hi, -lo],
        bounds=[(None, None)] * (degree + 1) + [(0, None)],
        method="highs",
    )
    return float(res.fun)


def planck_fit(raw: np.ndarray, temp: np.ndarray, weight: np.ndarray, info: dict) -> np.ndarray:
    """Residuals (model - temp_c) of the Planck inversion with the file's B, F, R and a fitted offset and gain."""
    from scipy.optimize import least_squares

    r, b, _, f = info["response"]
    r_eff, b_k, f_eff = r * info["gain_word"] / 2**28, b / 16384, f / 256
    e, w_amb = info["emissivity"], (info["ambient"] + 273.15) ** 4

    def model(x: np.ndarray) -> np.ndarray:
        signal = np.maximum((raw - x[0]) / x[1], 1e-6)
        t_bb = b_k / np.log(r_eff / signal + f_eff)
        return ((t_bb**4 - (1 - e) * w_amb) / e) ** 0.25 - 273.15

    t_mid = float(np.median(temp)) + 273.15
    x0 = [float(np.median(raw)) - r_eff / (np.exp(b_k / t_mid) - f_eff), 1.0]
    fit = least_squares(lambda x: (model(x) - temp) * np.sqrt(weight), x0=x0)
    return model(fit.x) - temp


def main(argv: list[str] | None = None) -> int:
    for ref_path in reference_arrays(argv, __doc__.splitlines()[0], DATA, "*hirp*_reference.npz"):
        name = ref_path.name.replace("_reference.npz", "")
        info = layout(ref_path.with_name(f"{name}.jpg"))
        ref = np.load(ref_path)
        raw = ref["raw14"].ravel().astype(np.int64)
        temp = ref["temp_c"].ravel().astype(np.float64)
        values, inverse, counts = np.unique(raw, return_inverse=True, return_counts=True)
        lo = np.full(len(values), np.inf)
        hi = np.full(len(values), -np.inf)
        np.minimum.at(lo, inverse, temp)
        np.maximum.at(hi, inverse, temp)
        dc_round = bool(np.array_equal(ref["temp_dc"].ravel(), np.round(temp * 10)))
        print(f"{name}: HIDR " + ", ".join(f"{t}:{tag}@{o:#x}+{s:#x}" for t, s, o, tag in info["blocks"]))
        print(
            f"  e={info['emissivity']:.4f} d={info['distance']:g} m ambient={info['ambient']:g} C "
            f"RH={info['humidity']:g} % slot={info['slot']} gain={info['gain']} readings={info['readings']}"
        )
        r, b, o, f = info["response"]
        print(f"  response R={r} B={b} ({b / 16384:.1f} K) O={o} F={f}; gain word {info['gain_word']}")
        print(
            f"  raw {values[0]}..{values[-1]} ({len(values)} values) -> {temp.min():.1f}..{temp.max():.1f} C; "
            f"spread per raw {float((hi - lo).max()):.4f} C"
        )
        print(f"  temp_dc = round(10 temp_c): {dc_round}")
        floors = [
            (d, smooth_floor(values, lo, hi, d), smooth_floor(values, lo, hi + 0.0999, d)) for d in (1, 2, 3, 5, 8)
        ]
        print("  smooth floor, max|d| C by degree (continuous / truncated to 0.1):")
        print("   " + ", ".join(f"{d}: {c:.3f}/{t:.3f}" for d, c, t in floors))
        res = planck_fit(values.astype(np.float64), lo, counts.astype(np.float64), info)
        rms = float(np.sqrt(np.average(res**2, weights=counts)))
        print(f"  Planck, file's R B F + fitted offset, gain: rms {rms:.3f} max {np.abs(res).max():.3f} C")
    print("target: max|d| <= 0.05 C on every pixel; a floor above it rules out every smooth model")
    return 0


if __name__ == "__main__":
    sys.exit(main())
