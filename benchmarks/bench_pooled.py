"""Pooled automatic registration on m3t-synth, against its true homographies: share registered, error, time.

Every inspection group of a generated m3t-synth set is registered the way ``harness screen`` registers a flight's
group (``harness.screen.frontend.FrontEnd.register_group``: the wide images undistorted with the set's calibration,
the factory prior from the EXIF focal lengths, ``register_pooled``), and the result is compared with the group's true
homography over a 9x9 grid of the thermal frame. Anchors: the factory prior's error, and the least-squares fit of
the group's landmarks (the route the benchmark's samples are registered by), both against the same truth.

    .venv/bin/python benchmarks/bench_pooled.py [--root data/m3t-synth-small-seed0] [--projects P1,P2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

#: Targets: share of frames registered, and the median error no larger than the landmark fit's median clicking
#: error (the landmarks' error as measured, 3.6 px on m3t-synth small).
TARGET_REGISTERED = 0.95


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path("data/m3t-synth-small-seed0"))
    ap.add_argument("--projects", default=None, help="comma-separated projects (default: all)")
    args = ap.parse_args(argv)

    import cv2

    cv2.setNumThreads(1)
    from harness.screen.flight import find_captures, inspection_groups
    from harness.screen.frontend import FrontEnd, FrontEndSettings
    from harness.sensing.calibration import CameraModel
    from harness.sensing.registration import apply_homography, fit_groups, load_homography_entries, read_landmarks
    from harness.sensing.registration.truth import frame_grid

    root = args.root
    true = {g: e.H for g, e in load_homography_entries(root / "ground_truth" / "homographies.yaml").items()}
    cam = CameraModel.load(root / "calibration" / "wide_camera.yaml")
    fitted = {g: f.H for g, f in fit_groups(read_landmarks(root / "registration" / "landmarks.json"), "lsq").items()}
    fe = FrontEnd(FrontEndSettings({}, "none", rgb_camera=cam.to_dict()))
    projects = args.projects.split(",") if args.projects else sorted(p.name for p in (root / "images").iterdir())
    rows, errors, registered, total = [], [], 0, 0
    print(
        f"{'group':>6} {'frames':>6} {'ok':>5} {'agree':>6} {'corr':>6} {'prior':>6} {'err px':>7} "
        f"{'prior px':>8} {'landmk px':>9} {'s':>6}"
    )
    for project in projects:
        caps = find_captures(root / "images" / project).captures
        groups = inspection_groups(caps, 300.0)
        for g in sorted(set(groups.values())):
            members = [c for c in caps if groups[c.name] == g]
            name = f"{project}-{g[1:]}"
            t0 = time.perf_counter()
            reg, thermal_size = fe.register_group(members)
            dt = time.perf_counter() - t0
            pts = frame_grid(thermal_size)
            rgb = apply_homography(np.linalg.inv(true[name]), pts)

            def err(H: np.ndarray, rgb: np.ndarray = rgb, pts: np.ndarray = pts) -> float:
                return float(np.median(np.linalg.norm(apply_homography(H, rgb) - pts, axis=1)))

            e, e_prior, e_lm = err(np.asarray(reg["H"])), err(np.asarray(reg["prior"])), err(fitted[name])
            q = reg["registration"]
            total += len(members)
            if q["ok"]:
                registered += len(members)
            errors += [e] * len(members)
            rows.append(
                (
                    name,
                    len(members),
                    q["ok"],
                    q["agreeing"],
                    q["correlation"],
                    q["prior_correlation"],
                    e,
                    e_prior,
                    e_lm,
                    dt,
                )
            )
            print(
                f"{name:>6} {len(members):>6} {str(q['ok']):>5} {q['agreeing']:>6} {q['correlation']:>6.3f} "
                f"{q['prior_correlation']:>6.3f} {e:>7.2f} {e_prior:>8.2f} {e_lm:>9.2f} {dt:>6.1f}",
                flush=True,
            )
    share = registered / total if total else 0.0
    med = float(np.median(errors)) if errors else float("nan")
    lm_med = float(np.median([r[8] for r in rows for _ in range(r[1])]))
    print(
        f"\nframes registered: {registered} / {total} ({share:.1%}); median error against the truth {med:.2f} px "
        f"(per frame, its group's homography); the landmark fit's {lm_med:.2f} px; the prior's "
        f"{float(np.median([r[7] for r in rows for _ in range(r[1])])):.2f} px"
    )
    met = share >= TARGET_REGISTERED and med <= max(lm_med, 3.6)
    print(
        f"target: >= {TARGET_REGISTERED:.0%} registered, median error <= the landmark fit's -> "
        f"{'met' if met else 'NOT met'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
