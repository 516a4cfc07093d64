"""Frames per second of ``harness screen`` on real M3T-size captures, and the front end's share beside the model's.

The flight: the three real M3T R-JPEGs of ``../shared/data/dji-m3t-rjpeg/`` (640x512, DJI's corrected route), each
with a 4000x3000 wide JPEG made for it (the thermal frame's own picture seen through the factory prior, 3 % off
in scale, 1 deg and (14, -9) px, with sensor-like texture; quality 92, about DJI's file size), DJI EXIF (35-mm focal
lengths 24 and 40 mm) and XMP positions, and a wide-lens calibration (k1 -0.05), repeated ``--copies`` times
under new capture names (inspection groups of three). Every frame takes the default route: the wide JPEG decoded
at a reduced scale through its DCT, undistortion, automatic registration once per group (checked), warp, crop, C2.

For ours at scale s and n (random weights: timing only), in PyTorch and in ONNX Runtime, model on ``--threads``
threads (default 2, the two cores), one frame per model call, each screened twice: with the front end before the
model (sequential) and with the front end of the next frame in a thread beside the model (overlapped, the default),
alternated ``--rounds`` times so that both see the same load.
The first frame, with its one-time costs, is left out. Printed against the target (the front end adds at most 30 %
to the model's own time):

* CPU time: per frame, the front end's stages (CPU time of the thread that ran them) beside the model's (the
  process's CPU time over its call, less the front-end thread's), means with the registrations and the median frame
  (one that reuses its group's registration; each frame's front end over its own model call, back to back);
* wall clock: the whole screen's time per frame (1 / frames per second) against the model's own time (its calls in
  the sequential run, where nothing else of the screen runs beside it): the share the front end adds, sequential and
  overlapped.

Then one thread's split of the front end into its steps, and what the reduced decode changes in the model input
(against a full decode, on the bench's wide images and on a natural-statistics image with far more fine detail).
The machine line says the CPU and the load average: on a shared machine every wall-clock figure moves with the
others' work.

    .venv/bin/python benchmarks/bench_screen.py [--copies 5] [--threads 2] [--scales s,n] [--backends torch,onnx]
                                                [--rounds 3] [--workers 2]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_lines  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "data" / "dji-m3t-rjpeg"
TARGET = 0.30
RGB_SIZE = (4000, 3000)
STAGES = ("decode", "align", "encode")


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
    from harness.sensing.radiometry import read_rjpeg
    from harness.sensing.registration import focal_prior, homography_from_similarity, image_center

    folder.mkdir(parents=True, exist_ok=True)
    cam = wide_camera()
    cam_path = cam.save(folder.parent / "wide_camera.yaml")
    from harness.sensing.calibration import undistort_points, undistorted_camera

    new_cam, _ = undistorted_camera(cam, 0.0)
    prior = focal_prior(new_cam.image_size, (640, 512), (24.0, 40.0), f_rgb_px=new_cam.fx)
    true = homography_from_similarity(
        14.0, -9.0, 1.0, prior[0, 0] * 1.03, image_center(new_cam.image_size), image_center((640, 512))
    )
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
            gx, gy = np.meshgrid(
                np.arange(0, w + step, step, dtype=np.float64), np.arange(0, h + step, step, dtype=np.float64)
            )
            und = undistort_points(np.stack([gx.ravel(), gy.ravel()], 1), cam, new_cam)
            hom = np.hstack([und, np.ones((len(und), 1))]) @ true.T
            uv = (hom[:, :2] / hom[:, 2:3]).reshape(gx.shape + (2,)).astype(np.float32)
            mx = cv2.resize(uv[..., 0], (w, h), interpolation=cv2.INTER_LINEAR)
            my = cv2.resize(uv[..., 1], (w, h), interpolation=cv2.INTER_LINEAR)
            img = cv2.remap(
                np.ascontiguousarray(preview[:, :, ::-1]), mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101
            )
            tint = np.array([40, 25, 10], np.int16) * (rep + 1) % 60
            img = np.clip(
                img.astype(np.int16) // 2 + 60 + tint + rng.normal(0, 7, img.shape).astype(np.int16), 0, 255
            ).astype(np.uint8)
            ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 92])
            exif = jpeg.build_exif(
                {"Make": "DJI", "Model": "M3T", "FocalLengthIn35mmFilm": 24, "ExifImageWidth": w, "ExifImageHeight": h}
            )
            data = b"\xff\xd8" + jpeg.segment(jpeg.APP1, exif) + enc.tobytes()[2:]
            pos = {
                "lat": 48.137 + 1e-5 * k,
                "lon": 11.575 + 2e-5 * k,
                "alt_abs": 540.0,
                "alt_rel": 25.0,
                "gimbal_yaw": 90.0,
                "gimbal_pitch": 0.0,
            }
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


def run_screen(
    flight: Path,
    out: Path,
    weights: Path,
    scale: str,
    backend: str,
    threads: int,
    cam: Path,
    rgb_decode: str = "auto",
    workers: int = 1,
    overlap: bool = True,
) -> dict:
    """One screen of the flight; per-frame timings of the frames after the first (its one-time costs left out):
    means (``mean``: the automatic registrations, one per group of three, included), medians (``median``: a frame
    that reuses its group's registration), frames per second, and the registration's own cost."""
    from harness.screen import ScreenRequest, screen

    stamps: list[float] = []
    records: list[dict] = []

    def on_frame(rec: dict) -> None:
        stamps.append(time.perf_counter())
        records.append(rec)

    req = ScreenRequest(
        flight=flight,
        out=out,
        weights=weights,
        detector="ours",
        dataset="m3t",
        profile="paper",
        overrides=[f"model.scale={scale}", "eval.batch=1"],
        backend=backend,
        threads=threads,
        rgb_camera=cam,
        rgb_decode=rgb_decode,
        progress=False,
        overlays=False,
        force=True,
        conf=0.5,
        workers=workers,
        overlap=overlap,
    )
    c0 = time.process_time()
    screen(req, on_frame=on_frame)
    steady = records[1:]
    keys = [*STAGES, "model"]
    t = {k: [r["timings"][k] for r in steady] for k in keys}
    c = {k: [r["timings"][f"{k}_cpu"] for r in steady] for k in keys}
    front = [sum(r["timings"][k] for k in STAGES) for r in steady]
    front_cpu = [sum(r["timings"][f"{k}_cpu"] for k in STAGES) for r in steady]
    registering = [r["timings"]["align_cpu"] for r in steady if r["route"] == "auto"]
    reusing = [r["timings"]["align_cpu"] for r in steady if r["route"] != "auto"]
    return {
        "fps": (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else float("nan"),
        "mean": {k: statistics.fmean(v) for k, v in t.items()},
        "mean_cpu": {k: statistics.fmean(v) for k, v in c.items()},
        "median": {k: statistics.median(v) for k, v in t.items()},
        "median_cpu": {k: statistics.median(v) for k, v in c.items()},
        "front": statistics.fmean(front),
        "front_cpu": statistics.fmean(front_cpu),
        "front_median_cpu": statistics.median(front_cpu),
        # each frame's front end over its own model call, back to back (sequential runs): a load that changes
        # during the run weighs on both alike
        "cpu_ratio": statistics.median(f / r["timings"]["model_cpu"] for f, r in zip(front_cpu, steady)),
        "register_cpu": (statistics.median(registering) - statistics.median(reusing))
        if registering and reusing
        else float("nan"),
        "process_cpu": (time.process_time() - c0) / max(1, len(records)),
        "routes": {r["route"] for r in records},
        "reduction": {r["reduction"] for r in records},
    }


def stage_split(flight: Path, cam: Path, r: int | None = None, repeats: int = 3) -> tuple[dict[str, float], int]:
    """One thread: each step of one frame's front end timed on its own, CPU time (medians over frames and
    repeats), with the wide image decoded at ``1 / r`` (None: the default decode's reduction); and that ``r``."""
    import cv2

    from harness.encodings import encode_c2
    from harness.sample import AlignedSample
    from harness.screen.flight import find_captures
    from harness.screen.frontend import decode_rgb, read_header, reduction_for, sha1_bytes, source_scale
    from harness.sensing import jpeg
    from harness.sensing.calibration import CameraModel
    from harness.sensing.options import SensingOptions
    from harness.sensing.pipeline import SensingContext, read_capture_thermal
    from harness.sensing.registration import estimate_homography_auto
    from harness.sensing.registration.dataset import DatasetRegistration
    from harness.sensing.warp import align_pair

    cv2.setNumThreads(1)
    caps = find_captures(flight).captures[:3]
    opts = SensingOptions()
    cam_full = CameraModel.load(cam)
    if r is None:
        reg_f = DatasetRegistration(SensingContext(opts, cam_full), None, None, "undistorted", {}, (24.0, 40.0))
        r = reduction_for(source_scale(reg_f.prior(RGB_SIZE, (640, 512)), (640, 512)), RGB_SIZE)
    ctx = SensingContext(opts, cam_full.scaled((RGB_SIZE[0] // r, RGB_SIZE[1] // r)) if r > 1 else cam_full)
    reg = DatasetRegistration(ctx, None, None, "undistorted", {}, (24.0, 40.0))
    names = (
        "files + headers + SHA-1",
        "thermal R-JPEG",
        "wide decode",
        "undistort",
        "warp + crop",
        "C2",
        "registration",
    )
    times: dict[str, list[float]] = {k: [] for k in names}
    clock = time.thread_time
    for _ in range(repeats):
        for cap in caps:
            t0 = clock()
            data, tdata = cap.rgb.read_bytes(), cap.thermal.read_bytes()
            read_header(data, cap.rgb)
            jpeg.read_segments(tdata, cap.thermal, require_eoi=False)
            sha1_bytes(data), sha1_bytes(tdata)
            t1 = clock()
            temp, ir8, _ = read_capture_thermal(cap.thermal, opts)
            t2 = clock()
            rgb = decode_rgb(data, cap.rgb, r)
            t3 = clock()
            rgb_u, _ = ctx.undistort_rgb(rgb)
            t4 = clock()
            prior = reg.prior((rgb.shape[1], rgb.shape[0]), (640, 512))
            res = estimate_homography_auto(rgb_u, temp, init=prior)
            t5 = clock()
            pair = align_pair(rgb_u, temp, ir8, np.zeros((0, 4)), np.zeros(0), res.H)
            t6 = clock()
            encode_c2(AlignedSample(0, pair.rgb, pair.thermal, pair.ir8, np.zeros((0, 4)), np.zeros(0), "g"))
            t7 = clock()
            for key, dt in zip(names, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t6 - t5, t7 - t6, t5 - t4)):
                times[key].append(dt)
    return {k: statistics.median(v) for k, v in times.items()}, r


def detailed_flight(flight: Path, folder: Path) -> Path:
    """The first capture of ``flight`` with a wide image of natural-image statistics (amplitude falling as 1 /
    frequency, contrast 40 grey levels, sharp-edged rectangles: far more fine detail than a facade at the M3T's
    distance), the same EXIF: the reduced decode's harder case."""
    import cv2

    from harness.screen.flight import find_captures
    from harness.sensing import jpeg

    cap = find_captures(flight).captures[0]
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    h, w = RGB_SIZE[1], RGB_SIZE[0]
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.rfftfreq(w)[None, :]
    amp = 1.0 / np.maximum(np.hypot(fx, fy), 1.0 / w)
    img = np.stack([np.fft.irfft2(amp * np.exp(2j * np.pi * rng.random(amp.shape)), (h, w)) for _ in range(3)], -1)
    img = np.clip((img - img.mean()) / img.std() * 40 + 128, 0, 255).astype(np.uint8)
    for _ in range(200):
        x, y = rng.integers(0, w - 60), rng.integers(0, h - 80)
        img[y : y + rng.integers(10, 80), x : x + rng.integers(10, 60)] = rng.integers(0, 255, 3)
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 92])
    assert ok
    data = cap.rgb.read_bytes()
    app1 = b"".join(
        jpeg.segment(seg.marker, seg.payload)
        for seg in jpeg.read_segments(data, cap.rgb).segments
        if seg.marker == jpeg.APP1
    )
    (folder / cap.rgb.name).write_bytes(b"\xff\xd8" + app1 + enc.tobytes()[2:])
    shutil.copy(cap.thermal, folder / cap.thermal.name)
    return folder


def input_difference(flight: Path, cam: Path, reductions: tuple[int, ...] = (2, 4)) -> dict[int, tuple[float, float]]:
    """Per reduction: mean |difference| of the model input's RGB against a full decode's (grey levels), and the
    PSNR (dB), the registration being the same (the prior); the fourth channel never changes (the temperature map
    is not touched), which is checked."""
    from unittest import mock

    from harness.encodings import ENCODINGS
    from harness.screen import frontend
    from harness.screen.flight import find_captures
    from harness.sensing.calibration import CameraModel

    c2 = next(e for e in ENCODINGS if e.name == "c2")
    cap = find_captures(flight).captures[0]
    st = frontend.FrontEndSettings(
        sensing={"registration": {"method": "focal"}}, encoding="c2", rgb_camera=CameraModel.load(cam).to_dict()
    )
    images = {}
    for r in (1, *reductions):
        with mock.patch.object(frontend, "reduction_for", lambda f, size, r=r: r):
            images[r] = frontend.FrontEnd(st, c2).process(cap).image.astype(np.int16)
    out = {}
    for r in reductions:
        a, b = images[1], images[r]
        assert a.shape == b.shape and np.array_equal(a[..., 3], b[..., 3])
        d = np.abs(a[..., :3] - b[..., :3]).astype(np.float64)
        out[r] = (float(d.mean()), 10 * math.log10(255**2 / max(float((d**2).mean()), 1e-12)))
    return out


def _pct(x: float) -> str:
    return f"{x:+.0%}" if math.isfinite(x) else "n/a"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=5, help="times the three captures are repeated")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--scales", default="s,n")
    ap.add_argument("--backends", default="torch,onnx")
    ap.add_argument(
        "--workers", type=int, default=2, help="also time the first scale with this many front-end processes (1: skip)"
    )
    ap.add_argument("--rounds", type=int, default=3, help="sequential and overlapped screens, alternated")
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
        cam = (
            make_flight(flight, args.copies)
            if not (flight.is_dir() and any(flight.iterdir()))
            else work / "wide_camera.yaml"
        )
        n = len(list(flight.glob("*_W.JPG")))
        size = statistics.median(p.stat().st_size for p in flight.glob("*_W.JPG")) / 1e6
        print(
            f"flight: {n} captures (640x512 real M3T R-JPEGs, 4000x3000 wide JPEGs of {size:.1f} MB), built in "
            f"{time.perf_counter() - t0:.0f} s"
        )
        for line in machine_lines():
            print(line)
        print(
            f"model on {args.threads} threads, torch {torch.__version__}; front end on one OpenCV thread, in the "
            "main process: sequential (before the model) or overlapped (a thread, one frame ahead)"
        )
        rows = []
        for scale in [s.strip() for s in args.scales.split(",") if s.strip()]:
            w = weights_file(work, scale)
            for backend in [b.strip() for b in args.backends.split(",") if b.strip()]:
                seqs, ovls = [], []
                for _ in range(args.rounds):  # alternated, so both see the same load on a shared machine
                    seqs.append(
                        run_screen(
                            flight, work / f"out-{scale}-{backend}", w, scale, backend, args.threads, cam, overlap=False
                        )
                    )
                    ovls.append(
                        run_screen(flight, work / f"out-{scale}-{backend}", w, scale, backend, args.threads, cam)
                    )
                rows.append((f"ours-{scale}", backend, seqs, ovls))
                print(f"  ours-{scale} {backend}: done", file=sys.stderr)
        med = statistics.median
        print(
            f"\nper frame, ms (means over the frames after the first, an automatic registration every 3rd frame; "
            f"medians of {args.rounds} rounds)"
        )
        head = (
            f"{'model':<7} {'backend':<7} | {'decode':>6} {'reg+warp':>8} {'C2':>3} {'front':>5} | "
            f"{'model':>5} | {'front/model':>11} | {'median frame':>12}"
        )
        print("CPU time (sequential runs; front end: its thread's)\n" + head + "\n" + "-" * len(head))
        for name, backend, seqs, _ in rows:
            c = {k: med(q["mean_cpu"][k] for q in seqs) for k in (*STAGES, "model")}
            front = med(q["front_cpu"] for q in seqs)
            share = med(q["front_cpu"] / q["mean_cpu"]["model"] for q in seqs)
            print(
                f"{name:<7} {backend:<7} | {1e3 * c['decode']:>6.0f} {1e3 * c['align']:>8.0f} "
                f"{1e3 * c['encode']:>3.0f} {1e3 * front:>5.0f} | {1e3 * c['model']:>5.0f} | "
                f"{share:>11.0%} | {med(q['cpu_ratio'] for q in seqs):>12.0%}"
            )
        head = f"{'model':<7} {'backend':<7} | {'model':>5} | {'sequential':>16} | {'overlapped':>30} | <= {TARGET:.0%}"
        units = f"{'':<7} {'':<7} | {'ms':>5} | {'fr/s  ms added':>16} | {'fr/s  ms added (range)':>30} |"
        print(
            "\nwall clock: the whole screen's time per frame (1 / frames per second) against the model's own "
            "(its\ncalls in the sequential run of the same round); added: medians (and range) over the rounds\n"
            + head
            + "\n"
            + units
            + "\n"
            + "-" * len(head)
        )
        for name, backend, seqs, ovls in rows:
            m = [q["mean"]["model"] for q in seqs]
            add_s = [(1 / q["fps"] - mi) / mi for q, mi in zip(seqs, m)]
            add_o = [(1 / q["fps"] - mi) / mi for q, mi in zip(ovls, m)]
            fs, fo = med(q["fps"] for q in seqs), med(q["fps"] for q in ovls)
            rng = f"({_pct(min(add_o))}..{_pct(max(add_o))})"
            verdict = "met" if med(add_o) <= TARGET else "not met"
            print(
                f"{name:<7} {backend:<7} | {1e3 * med(m):>5.0f} | {fs:>4.2f} {1e3 / fs:>4.0f} "
                f"{_pct(med(add_s)):>6} | {fo:>4.2f} {1e3 / fo:>4.0f} {_pct(med(add_o)):>6} {rng:>13} | {verdict}"
            )
        seq = rows[0][2][0]
        print(
            f"\nroutes: {', '.join(sorted(seq['routes']))}; wide JPEG decoded at 1/{max(seq['reduction'])}; an "
            f"automatic registration costs {1e3 * seq['register_cpu']:.0f} ms CPU once per inspection group"
        )
        if args.workers > 1:
            scale = args.scales.split(",")[0].strip()
            r = run_screen(
                flight,
                work / f"out-{scale}-workers",
                work / f"ours-{scale}.pt",
                scale,
                "torch",
                args.threads,
                cam,
                workers=args.workers,
            )
            print(
                f"ours-{scale} torch with the front end in --workers {args.workers} processes beside the model: "
                f"{r['fps']:.2f} frames/s"
            )
        print(
            "\nfront-end steps on one thread by the wide decode's scale, CPU ms per frame (medians; the "
            "registration once per group):"
        )
        red = stage_split(flight, cam)[1]
        for r in dict.fromkeys((red, 2, 1)):
            split, _ = stage_split(flight, cam, r)
            frame = sum(v for k, v in split.items() if k != "registration")
            print(
                f"  1/{r}{' (default)' if r == red else ''}: "
                + ", ".join(f"{k} {1e3 * v:.0f}" for k, v in split.items() if k != "registration")
                + f" = {1e3 * frame:.0f}; registration {1e3 * split['registration']:.0f}"
            )
        print("\nreduced decode vs full, model input's RGB (same homography; C2 unchanged): mean |d| grey levels, PSNR")
        for label, fl in (
            ("bench wide images", flight),
            ("natural-statistics image", detailed_flight(flight, work / "detailed")),
        ):
            diff = input_difference(fl, cam)
            print(f"  {label}: " + ", ".join(f"1/{r} {d:.2f} ({p:.1f} dB)" for r, (d, p) in diff.items()))
        print(f"load average at the end {os.getloadavg()[0]:.1f} (other work on the machine slows every figure)")
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
