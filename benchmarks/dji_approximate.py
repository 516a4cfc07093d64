"""How far the labelled approximate route lands from DJI Thermal SDK: temperatures and the fourth channel (C2).

Anchor: DJI Thermal SDK's ``dirp_measure_ex`` temperatures of the same files. Each reference is an ``.npz`` with
``temp_c`` (float32 C); either it sits beside its R-JPEG as ``<name>_reference.npz`` (the layout of
``shared/data/dji-rjpeg-cameras``, the default), or it names its R-JPEG in ``source`` and, when the SDK was run
with measurement parameters set, holds ``set`` true and ``params`` = (distance m, humidity %, emissivity,
reflection C, ambient C), which the approximate route is then given as overrides.

Per file it prints the route the harness takes with ``approximate=True`` (or why there is none), the largest
``|approximate - SDK|`` in each temperature band, and the C2 maps (``harness.sensing.c2.c2_uint8``, 8-bit) of
the two temperature maps compared: the share of pixels within one grey level and the largest difference. Then,
per approximation, the band maxima over all files next to the bounds ``harness.sensing.dji_approximate`` states
(``EXCEEDED`` where a measurement is above them). For files without an approximate route (hirp) it shows what the
best smooth model could do at most: a cubic in the raw counts fitted to DJI's own values (in-sample), as
temperatures and as C2.

    .venv/bin/python benchmarks/dji_approximate.py                       # the shared reference files
    .venv/bin/python benchmarks/dji_approximate.py REFS_DIR [REFS_DIR ...]   # references made with DJI's SDK
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data" / "dji-rjpeg-cameras"
BANDS = (30.0, 60.0, 100.0, 180.0, math.inf)  # the bands the measurement groups by (the stated ones are coarser)


def references(paths: list[Path]) -> list[tuple[Path, Path, dict[str, float]]]:
    """(reference npz, R-JPEG, overrides) for every reference under ``paths``."""
    out = []
    for p in paths:
        files = sorted(p.glob("*.npz")) if p.is_dir() else [p]
        for f in files:
            with np.load(f) as z:
                if "source" in z:
                    src = Path(str(z["source"]))
                elif f.name.endswith("_reference.npz"):
                    src = f.with_name(f.name.replace("_reference.npz", ".jpg"))
                else:
                    continue
                over: dict[str, float] = {}
                if "set" in z and bool(z["set"]):
                    d, h, e, r, _ = (float(v) for v in z["params"])
                    over = {"distance": d, "humidity": h, "emissivity": round(e, 4), "reflected": r}
            out.append((f, src, over))
    return out


def band_maxima(
    approx: np.ndarray, ref: np.ndarray, stated: tuple[tuple[float, float], ...] = ()
) -> dict[float, float]:
    """The largest ``|approx - ref|`` per temperature band of the reference (``BANDS``, or the stated bands' upper
    temperatures and everything above them)."""
    d = np.abs(approx.astype(np.float64) - ref.astype(np.float64))
    out, lo = {}, -math.inf
    for hi in ([b for b, _ in stated] + [math.inf]) if stated else BANDS:
        m = (ref > lo) & (ref <= hi) & np.isfinite(d)
        if m.any():
            out[hi] = float(d[m].max())
        lo = hi
    return out


def c2_agreement(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """(% of pixels whose 8-bit C2 differ by at most one grey level, largest difference)."""
    from harness.sensing.c2 import c2_uint8

    d = np.abs(c2_uint8(a.astype(np.float32)).astype(np.int32) - c2_uint8(b.astype(np.float32)).astype(np.int32))
    return 100.0 * float((d <= 1).mean()), int(d.max())


def smooth_best(raw: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """A cubic in the raw counts least-squares fitted to the reference itself (in-sample)."""
    x = raw.astype(np.float64)
    x = (x - x.mean()) / max(float(x.std()), 1.0)
    coef = np.polyfit(x.ravel(), ref.astype(np.float64).ravel(), 3)
    return np.polyval(coef, x).astype(np.float32)


def _bands_text(b: dict[float, float]) -> str:
    return ", ".join(f"<={hi:g}: {v:.4f}" if hi != math.inf else f">180: {v:.4f}" for hi, v in b.items())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("refs", nargs="*", type=Path, default=[DATA])
    args = ap.parse_args(argv)
    from harness.errors import HarnessError
    from harness.sensing import dji_approximate, dji_formats
    from harness.sensing.radiometry import read_rjpeg, rjpeg_temperature

    rows = references(args.refs)
    if not rows:
        print(f"no reference arrays under {', '.join(map(str, args.refs))}", file=sys.stderr)
        return 1
    per_approx: dict[tuple[str, bool], dict[float, float]] = {}
    c2_rows: dict[str, list[tuple[float, int]]] = {}
    for ref_path, src, over in rows:
        with np.load(ref_path) as z:
            ref = z["temp_c"].astype(np.float32)
        name = f"{src.parent.name}/{src.name}" + (
            f" e={over['emissivity']:g} d={over['distance']:g} h={over['humidity']:g}" if over else ""
        )
        try:
            rj = read_rjpeg(src, approximate=True)
            if rj.decoder != "approximate":
                print(f"{name}: route {rj.decoder} (exact), not measured here")
                continue
            temp, info = rjpeg_temperature(rj, over)
        except HarnessError as exc:
            print(f"{name}: no approximate route ({str(exc).split(': ', 1)[-1][:90]}...)")
            try:
                _, _, raw = dji_formats.read_original_raw(src)
            except HarnessError:
                continue
            fit = smooth_best(raw, ref)
            pct, worst = c2_agreement(fit, ref)
            print(
                f"  best smooth model (cubic fitted to the SDK's own values): max |d| "
                f"{float(np.abs(fit - ref).max()):.3f} C; C2 within one grey level {pct:.2f} %, max {worst}"
            )
            continue
        rec = info["approximate"]
        bands = band_maxima(temp, ref)
        e = info["correction"]["emissivity"]
        high = e >= dji_approximate.APPROXIMATIONS[rec["approximation"]].high_emissivity
        agg = per_approx.setdefault((rec["approximation"], high), {})
        for hi, v in band_maxima(temp, ref, dji_approximate.APPROXIMATIONS[rec["approximation"]].bands_for(e)).items():
            agg[hi] = max(agg.get(hi, 0.0), v)
        agg["hottest"] = max(agg.get("hottest", -math.inf), float(ref.max()))
        pct, worst = c2_agreement(temp, ref)
        if not over:
            c2_rows.setdefault(rec["approximation"], []).append((pct, worst))
        missing = int(np.isnan(temp).sum())
        print(
            f"{name}: {rec['approximation']}, stated bound {rec['bound_c']:g} C; max |d| by band "
            f"({_bands_text(bands)}); C2 within one grey level {pct:.3f} %, max {worst}"
            + (f"; {missing} px above the measured range left missing" if missing else "")
        )
    print()
    for (name, high), agg in sorted(per_approx.items()):
        approx = dji_approximate.APPROXIMATIONS[name]
        stated = dict(approx.bands_for(approx.high_emissivity if high else approx.emissivity[0]))
        hottest = agg.pop("hottest")
        parts = []
        for hi, v in sorted(agg.items()):
            limit = stated.get(hi)
            flag = "" if limit is not None and v <= limit else " EXCEEDED" if limit is not None else " (left missing)"
            parts.append(f"<={hi:g} C: {v:.4f} (stated {limit if limit is not None else '-'}){flag}")
        group = (
            f"emissivity < {approx.high_emissivity:g}"
            if not high and approx.bands_high_emissivity
            else f"emissivity >= {approx.high_emissivity:g}"
            if high
            else "all emissivities"
        )
        print(f"{name} [{group}]: " + "; ".join(parts) + f"; hottest reference pixel {hottest:.1f} C")
    for name, vals in sorted(c2_rows.items()):
        print(
            f"{name} C2 at the files' own parameters: within one grey level {min(p for p, _ in vals):.3f} % "
            f"or more, max difference {max(w for _, w in vals)} ({len(vals)} files)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
