"""Frames per second of ``harness screen`` on real M3T-size captures, and the front end's share beside the model's.

The flight: the three real M3T R-JPEGs of ``../shared/data/dji-m3t-rjpeg/`` (640x512, DJI's corrected route), each
with a 4000x3000 wide JPEG made for it (the thermal frame's own picture seen through the factory prior, 3 % off
in scale, 1 deg and (14, -9) px, with sensor-like texture; quality 92, about DJI's file size), DJI EXIF (35-mm focal
lengths 24 and 40 mm) and XMP positions, and a wide-lens calibration (k1 -0.05), repeated ``--copies`` times
under new capture names. Every frame takes the default route: the wide JPEG decoded at 1/2 through its DCT,
undistortion, automatic registration (checked), warp, crop, C2.

For ours at scale s and n (random weights: timing only), in PyTorch and in ONNX Runtime, on ``--threads`` threads
(default 2, the two cores), one frame per model call: frames per second of the whole screen in steady state (the
first frame, with its one-time costs, left out), and per frame (medians) the front end's stages (decode; undistort
+ register + warp + crop; fourth channel) beside the model's own time (letterbox, network, NMS). Target: the front
end adds at most 30 % to the model's time; the ratio is the median over frames of each frame's front end over its
model time (measured back to back, so a machine shared with other work loads both alike), in wall clock and in CPU
time of the process. A second table splits the front end into its steps on one thread, and times ``--rgb-decode
full`` against the reduced decode (with the mean difference of the model inputs).

    .venv/bin/python benchmarks/bench_screen.py [--copies 5] [--threads 2] [--scales s,n] [--backends torch,onnx]
                                                [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "data" / "dji-m3t-rjpeg"
TARGET = 0.30
RGB_SIZE = (4000, 3000)


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def wide_camera() -> "object":
    from harness.sensing.calibration import CameraModel
    from harness.sensing.registration import focal_length_px

    f = focal_length_px(focal_35mm=24, image_size=RGB_SIZE)
    cam = CameraModel.ideal(f, RGB_SIZE, name="M3T wide (benchmark)")
    cam.dist[0] = -0.05
    return cam


def make_flight(folder: Path, copies: int) -> Path:
    """The benchmark flight (see the module docstring); returns the wide calibration file."""
    import cv2

    from harness.screen.position import add_xmp
    from harness.sensing import jpeg
    from harness.sensing.registration import focal_prior, homography_from_similarity, image_center
    from harness.sensing.radiometry import read_rjpeg

    folder.mkdir(parents=True, exist_ok=True)
    cam = wide_camera()
    cam_path = cam.save(folder.parent / "wide_camera.yaml")
    from harness.sensing.calibration import undistort_points, undistorted_camera

    new_cam, _ = undistorted_camera(cam, 0.0)
    prior = focal_prior(new_cam.image_size, (640, 512), (24.0, 40.0), f_rgb_px=new_cam.fx)
    true = homography_from_similarity(14.0, -9.0, 1.0, prior[0, 0] * 1.03, image_center(new_cam.image_size),
                                      image_center((640, 512)))
    rng = np.random.default_rng(0)
    k = 0
    for rep in range(copies):
        for src in sorted(REAL.glob("m3t_?.jpg")):
            k += 1
            name = f"DJI_20240603{10 + rep:02d}{k:04d}_{k:04d}"
            preview = read_rjpeg(src).preview()  # RGB palette picture, 640x512
            # the wide image as shot: each raw pixel -> undistorted pixel -> thermal pixel through the true H
            h, w = RGB_SIZE[1], RGB_SIZE[0]
            step = 8  # map on a coarse grid, then resize the maps (smooth)
            gx, gy = np.meshgrid(np.arange(0, w + step, step, dtype=np.float64),
                                 np.arange(0, h + step, step, dtype=np.float64))
            und = undistort_points(np.stack([gx.ravel(), gy.ravel()], 1), cam, new_cam)
            hom = np.hstack([und, np.ones((len(und), 1))]) @ true.T
            uv = (hom[:, :2] / hom[:, 2:3]).reshape(gx.shape + (2,)).astype(np.float32)
            mx = cv2.resize(uv[..., 0], (w, h), interpolation=cv2.INTER_LINEAR)
            my = cv2.resize(uv[..., 1], (w, h), interpolation=cv2.INTER_LINEAR)
            img = cv2.remap(np.ascontiguousarray(preview[:, :, ::-1]), mx, my, cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REFLECT_101)
            tint = np.array([40, 25, 10], np.int16) * (rep + 1) % 60
            img = np.clip(img.astype(np.int16) // 2 + 60 + tint + rng.normal(0, 7, img.shape).astype(np.int16),
                          0, 255).astype(np.uint8)
            ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 92])
            exif = jpeg.build_exif({"Make": "DJI", "Model": "M3T", "FocalLengthIn35mmFilm": 24,
                                    "ExifImageWidth": w, "ExifImageHeight": h})
            data = b"\xff\xd8" + jpeg.segment(jpeg.APP1, exif) + enc.tobytes()[2:]
            pos = {"lat": 48.137 + 1e-5 * k, "lon": 11.575 + 2e-5 * k, "alt_abs": 540.0, "alt_rel": 25.0,
                   "gimbal_yaw": 90.0, "gimbal_pitch": 0.0}
            (folder / f"{name}_W.JPG").write_bytes(add_xmp(data, pos))
            (folder / f"{name}_T.JPG").write_bytes(add_xmp(src.read_bytes(), pos))
    return cam_path


def weights_file(folder: Path, scale: str) -> Path:
    import torch

    from harness.plugins import get_host

    model = get_host().detector("ours").build(8, in_channels=4, scale=scale)
    path = folder / f"ours-{scale}.pt"
    torch.save(model.state_dict(), path)
    return path


def run_screen(flight: Path, out: Path, weights: Path, scale: str, backend: str, threads: int, cam: Path,
               rgb_decode: str = "auto", workers: int = 1) -> dict:
    from harness.screen import ScreenRequest, screen

    stamps: list[float] = []
    records: list[dict] = []

    def on_frame(rec: dict) -> None:
        stamps.append(time.perf_counter())
        records.append(rec)

    req = ScreenRequest(flight=flight, out=out, weights=weights, detector="ours", dataset="m3t", profile="paper",
                        overrides=[f"model.scale={scale}", "eval.batch=1"], backend=backend, threads=threads,
                        rgb_camera=cam, rgb_decode=rgb_decode, progress=False, overlays=False, force=True,
                        conf=0.5, workers=workers)
    screen(req, on_frame=on_frame)
    steady = records[1:]
    med = {k: statistics.median(r["timings"][k] for r in steady) for k in ("decode", "align", "encode", "model")}
    # each frame's front end and model ran back to back, under the same load: their ratio, per frame
    ratio = statistics.median((r["timings"]["decode"] + r["timings"]["align"] + r["timings"]["encode"])
                              / r["timings"]["model"] for r in steady)
    cpu = {k: statistics.median(r["timings"][f"{k}_cpu"] for r in steady) for k in ("decode", "align", "encode",
                                                                                      "model")}
    cpu_ratio = statistics.median((r["timings"]["decode_cpu"] + r["timings"]["align_cpu"]
                                   + r["timings"]["encode_cpu"]) / r["timings"]["model_cpu"] for r in steady)
    fps = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else float("nan")
    return {"fps": fps, "median": med, "ratio": ratio, "cpu": cpu, "cpu_ratio": cpu_ratio,
            "routes": {r["route"] for r in records}, "reduction": {r["reduction"] for r in records}}


def stage_split(flight: Path, cam: Path, repeats: int = 3) -> dict[str, float]:
    """One thread: each step of one frame's front end timed on its own (medians over frames and repeats)."""
    import cv2

    from harness.screen.flight import find_captures
    from harness.screen.frontend import decode_rgb, reduction_for, source_scale
    from harness.sensing.calibration import CameraModel
    from harness.sensing.options import SensingOptions
    from harness.sensing.pipeline import SensingContext, read_capture_thermal
    from harness.sensing.registration import estimate_homography_auto
    from harness.sensing.registration.dataset import DatasetRegistration
    from harness.sensing.warp import align_pair

    cv2.setNumThreads(1)
    caps = find_captures(flight).captures[:3]
    opts = SensingOptions()
    times: dict[str, list[float]] = {k: [] for k in ("thermal decode", "wide decode 1/2", "wide decode full",
                                                     "undistort", "register (auto)", "warp + crop", "C2")}
    from harness.encodings import encode_c2

    for _ in range(repeats):
        for cap in caps:
            data = cap.rgb.read_bytes()
            t0 = time.perf_counter()
            temp, ir8, _ = read_capture_thermal(cap.thermal, opts)
            t1 = time.perf_counter()
            cam_full = CameraModel.load(cam)
            ctx_f = SensingContext(opts, cam_full)
            reg_f = DatasetRegistration(ctx_f, None, None, "undistorted", {}, (24.0, 40.0))
            r = reduction_for(source_scale(reg_f.prior(RGB_SIZE, (640, 512)), (640, 512)), RGB_SIZE)
            rgb = decode_rgb(data, cap.rgb, r)
            t2 = time.perf_counter()
            decode_rgb(data, cap.rgb, 1)
            t3 = time.perf_counter()
            ctx = SensingContext(opts, cam_full.scaled((RGB_SIZE[0] // r, RGB_SIZE[1] // r)))
            reg = DatasetRegistration(ctx, None, None, "undistorted", {}, (24.0, 40.0))
            rgb_u, _ = ctx.undistort_rgb(rgb)
            t4 = time.perf_counter()
            prior = reg.prior((rgb.shape[1], rgb.shape[0]), (640, 512))
            res = estimate_homography_auto(rgb_u, temp, init=prior)
            t5 = time.perf_counter()
            pair = align_pair(rgb_u, temp, ir8, np.zeros((0, 4)), np.zeros(0), res.H)
            t6 = time.perf_counter()
            from harness.sample import AlignedSample

            encode_c2(AlignedSample(0, pair.rgb, pair.thermal, pair.ir8, np.zeros((0, 4)), np.zeros(0), "g"))
            t7 = time.perf_counter()
            for key, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6)):
                times[key].append(dt)
    return {k: statistics.median(v) for k, v in times.items()}


def input_difference(flight: Path, cam: Path) -> tuple[float, float, int]:
    """Mean |difference| of the RGB and of the fourth channel of the model input, reduced vs full decode (grey
    levels, file route with the prior so the registration is the same), and the reduction used."""
    from harness.encodings import ENCODINGS
    from harness.screen.flight import find_captures
    from harness.screen.frontend import FrontEnd, FrontEndSettings
    from harness.sensing.calibration import CameraModel

    c2 = next(e for e in ENCODINGS if e.name == "c2")
    cap = find_captures(flight).captures[0]
    out = []
    for mode in ("full", "auto"):
        st = FrontEndSettings(sensing={"registration": {"method": "focal"}}, encoding="c2",
                              rgb_camera=CameraModel.load(cam).to_dict(), rgb_decode=mode)
        out.append(FrontEnd(st, c2).process(cap))
    a, b = out[0].image.astype(np.int16), out[1].image.astype(np.int16)
    if a.shape != b.shape:
        return float("nan"), float("nan"), out[1].reduction
    return float(np.abs(a[..., :3] - b[..., :3]).mean()), float(np.abs(a[..., 3] - b[..., 3]).mean()), out[1].reduction


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=5, help="times the three captures are repeated")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--scales", default="s,n")
    ap.add_argument("--backends", default="torch,onnx")
    ap.add_argument("--workers", type=int, default=2, help="also time the first scale with this many front-end "
                    "processes (1: skip)")
    ap.add_argument("--keep", type=Path, default=None, help="build the flight here and keep it")
    args = ap.parse_args(argv)
    if not REAL.is_dir():
        print(f"the real M3T files are not at {REAL}", file=sys.stderr)
        return 2
    import torch

    from harness.cli import setup_logging

    setup_logging(30)
    torch.set_num_threads(args.threads)
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-screen-"))
    try:
        flight = work / "flight"
        t0 = time.perf_counter()
        cam = make_flight(flight, args.copies) if not (flight.is_dir() and any(flight.iterdir())) \
            else work / "wide_camera.yaml"
        n = len(list(flight.glob("*_W.JPG")))
        size = statistics.median(p.stat().st_size for p in flight.glob("*_W.JPG")) / 1e6
        print(f"flight: {n} captures (640x512 real M3T R-JPEGs, 4000x3000 wide JPEGs of {size:.1f} MB), built in "
              f"{time.perf_counter() - t0:.0f} s")
        print(f"CPU: {cpu_name()}, {os.cpu_count()} logical cores (load average {os.getloadavg()[0]:.1f} at the "
              f"start); model threads {args.threads}, front end in the main process; torch {torch.__version__}")
        header = (f"{'model':<7} {'backend':<7} {'fr/s':>5} | {'decode':>6} {'reg+warp':>8} {'C2':>4} {'front':>5} "
                  f"{'model':>5} {'ratio':>5} | {'front':>5} {'model':>5} {'ratio':>5} | <= {TARGET:.0%}")
        print("\nper frame, ms (medians over the frames after the first): wall clock | CPU time of the process\n"
              + header + "\n" + "-" * len(header))
        for scale in [s.strip() for s in args.scales.split(",") if s.strip()]:
            w = weights_file(work, scale)
            for backend in [b.strip() for b in args.backends.split(",") if b.strip()]:
                r = run_screen(flight, work / f"out-{scale}-{backend}", w, scale, backend, args.threads, cam)
                m, c = r["median"], r["cpu"]
                front, front_cpu = m["decode"] + m["align"] + m["encode"], c["decode"] + c["align"] + c["encode"]
                met = "wall " + ("met" if r["ratio"] <= TARGET else "no") + ", CPU " + \
                    ("met" if r["cpu_ratio"] <= TARGET else "no")
                wall = f"{1e3 * m['decode']:>6.0f} {1e3 * m['align']:>8.0f} {1e3 * m['encode']:>4.0f} " \
                    f"{1e3 * front:>5.0f} {1e3 * m['model']:>5.0f} {r['ratio']:>5.0%}"
                print(f"ours-{scale:<2} {backend:<7} {r['fps']:>5.2f} | {wall} | {1e3 * front_cpu:>5.0f} "
                      f"{1e3 * c['model']:>5.0f} {r['cpu_ratio']:>5.0%} | {met}")
                sys.stdout.flush()
        print(f"routes: {', '.join(sorted(r['routes']))}; wide JPEG decoded at 1/{max(r['reduction'])}")
        if args.workers > 1:
            scale = args.scales.split(",")[0].strip()
            r = run_screen(flight, work / f"out-{scale}-workers", work / f"ours-{scale}.pt", scale, "torch",
                           args.threads, cam, workers=args.workers)
            print(f"ours-{scale} torch with the front end in --workers {args.workers} processes beside the model: "
                  f"{r['fps']:.2f} frames/s")
        split = stage_split(flight, cam)
        print("\nfront-end steps on one thread, ms per frame (medians):")
        print("  " + ", ".join(f"{k} {1e3 * v:.0f}" for k, v in split.items()))
        d_rgb, d_c2, red = input_difference(flight, cam)
        print(f"reduced decode (1/{red}) vs full: model input differs by mean |d| {d_rgb:.2f} grey levels in RGB, "
              f"{d_c2:.2f} in C2 (same homography)")
        print(f"load average at the end {os.getloadavg()[0]:.1f} (other work on the machine slows every figure)")
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
