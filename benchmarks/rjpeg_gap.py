"""How far the harness's R-JPEG temperatures are from DJI's corrected ones, on the real M3T samples.

Anchor: DJI Thermal SDK ``temp_c`` (reference arrays beside the files). Compared: the harness's default route
(``dji``: DJI's correction with the file's APP5 transmission table, ``harness.sensing.dji_correction``), the
blackbody route (``raw14 / 16 - 273.15``), and two published corrections applied to the blackbody temperature in a
``T^4`` radiance balance with the file's parameters: grey body only (emissivity, reflected temperature), and grey
body + the FLIR/Thermimage atmospheric transmission model. Also checks that ``raw14`` is reproduced bit for bit,
how many pixels of the corrected route equal ``temp_c`` exactly, and the deci-C (``temp_dc``) mismatches.

    .venv/bin/python benchmarks/rjpeg_gap.py [--data ../shared/data/dji-m3t-rjpeg]
"""

from __future__ import annotations

import math
import sys

import numpy as np

from _common import SHARED_DATA, reference_arrays

DATA = SHARED_DATA / "dji-m3t-rjpeg"


def flir_tau(distance_m: float, humidity_pct: float, t_atm_c: float) -> float:
    """Atmospheric transmission of the FLIR model with Thermimage's default constants."""
    a1, a2, b1, b2, x = 0.006569, 0.01262, -0.002276, -0.00667, 1.9
    h2o = (
        humidity_pct / 100 * math.exp(1.5587 + 0.06939 * t_atm_c - 0.00027816 * t_atm_c**2 + 0.00000068455 * t_atm_c**3)
    )
    k = math.sqrt(distance_m / 2)
    return x * math.exp(-k * (a1 + b1 * math.sqrt(h2o))) + (1 - x) * math.exp(-k * (a2 + b2 * math.sqrt(h2o)))


def radiance_balance(t0_c: np.ndarray, emissivity: float, reflected_c: float, tau: float, t_atm_c: float) -> np.ndarray:
    """Object temperature from ``W = tau (e W_obj + (1 - e) W_refl) + (1 - tau) W_atm`` with ``W = T^4``."""
    w = (t0_c + 273.15) ** 4
    wr, wa = (reflected_c + 273.15) ** 4, (t_atm_c + 273.15) ** 4
    wo = (w - (1 - tau) * wa - tau * (1 - emissivity) * wr) / (tau * emissivity)
    return wo**0.25 - 273.15


def main(argv: list[str] | None = None) -> int:
    from harness.sensing.radiometry import read_rjpeg

    files = reference_arrays(argv, __doc__.splitlines()[0], DATA, "*_reference.npz")
    print(f"{'file':<8} {'raw14':>6} {'route':<28} {'mean d':>8} {'mean |d|':>9} {'P95 |d|':>8} {'max |d|':>8}")
    for ref_path in files:
        name = ref_path.name.replace("_reference.npz", "")
        rj = read_rjpeg(ref_path.with_name(f"{name}.jpg"))
        ref = np.load(ref_path)
        exact = bool(np.array_equal(rj.raw14, ref["raw14"]))
        p = rj.params
        t0 = rj.blackbody_c().astype(np.float64)
        corrected = rj.corrected_c()
        # DJI's iirp SDK uses the reflected temperature for the atmosphere as well (pre-v3 headers)
        routes = {
            "dji correction (harness)": corrected.astype(np.float64),
            "blackbody (harness)": t0,
            "grey body": radiance_balance(t0, p["emissivity"], p["reflected"], 1.0, p["reflected"]),
            "grey body + FLIR atmosphere": radiance_balance(
                t0,
                p["emissivity"],
                p["reflected"],
                flir_tau(p["distance"], p["humidity"], p["reflected"]),
                p["reflected"],
            ),
        }
        for route, est in routes.items():
            d = ref["temp_c"].astype(np.float64) - est
            print(
                f"{name:<8} {'exact' if exact else 'DIFF':>6} {route:<28} {d.mean():>+8.3f} {np.abs(d).mean():>9.3f} "
                f"{np.percentile(np.abs(d), 95):>8.3f} {np.abs(d).max():>8.3f}"
            )
        same = float(np.mean(corrected == ref["temp_c"]))
        dc_bad = int((rj.deci_celsius() != ref["temp_dc"]).sum())
        print(
            f"{name:<8} dji correction: {same:.2%} of pixels equal temp_c bit for bit; "
            f"deci-C mismatches vs temp_dc: {dc_bad}"
        )
    print("d = DJI temp_c - route, degrees C; target of a full correction: |d| <= 0.05")
    return 0


if __name__ == "__main__":
    sys.exit(main())
