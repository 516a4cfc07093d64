"""Training and evaluation throughput of the engine, and peak memory, on CPU (default: 640 px, batch 2).

Four measurements, each in its own process (so that each peak-memory figure is its own):

* ``anchor-train``: the model alone, one step = ``forward_raw`` on random input + ``sum(mean(out^2))`` + backward +
  SGD step (the model-compute cost that nothing can remove);
* ``engine-train``: ``harness.engine.trainer.Trainer`` on prepared samples: mosaic + affine + HSV + flips,
  letterbox, the detector's real loss (assigner included), gradient accumulation, EMA;
* ``anchor-eval``: ``forward_raw`` under ``torch.inference_mode``;
* ``engine-eval``: ``harness.engine.predict.predict``: letterbox, forward, decoding, NMS at conf 0.001, COCO output.

Ratios are engine / anchor measured in the same run on the same machine, so they stay meaningful on a busy or a
different CPU; absolute images/s are printed for the record. Example::

    .venv/bin/python benchmarks/bench_train.py                       # ours, 640, batch 2, 2 threads
    .venv/bin/python benchmarks/bench_train.py --detector tinydet --imgsz 320
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def write_samples(folder: Path, n: int, size: tuple[int, int], categories: int, seed: int = 0):
    """Noise frames with random rectangles (thermal-frame size ``size``), written with PreparedWriter."""
    import numpy as np

    from harness import AlignedSample
    from harness.cache import PreparedDataset, PreparedWriter

    rng = np.random.default_rng(seed)
    h, w = size
    with PreparedWriter(folder, "bench", [f"c{k}" for k in range(categories)]) as wr:
        for i in range(n):
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            temp = (20 + rng.normal(0, 1, (h, w))).astype(np.float32)
            boxes, labels = [], []
            for _ in range(int(rng.integers(3, 9))):
                bw, bh = int(rng.integers(16, w // 4)), int(rng.integers(16, h // 4))
                x, y = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
                rgb[y:y + bh, x:x + bw] = rng.integers(0, 256, 3)
                temp[y:y + bh, x:x + bw] += 3
                boxes.append([x, y, x + bw, y + bh])
                labels.append(int(rng.integers(0, categories)))
            ir8 = np.clip((temp - 15) * 20, 0, 255).astype(np.uint8)
            wr.add(AlignedSample(i + 1, rgb, temp, ir8, np.array(boxes, np.float32), np.array(labels, np.int64), "g"))
    return PreparedDataset(folder)


def measure(args: argparse.Namespace) -> dict:
    import numpy as np
    import torch

    from harness.engine.runtime import seed_everything
    from harness.plugins import get_host
    from harness.runner import build_model

    torch.set_num_threads(args.threads)
    seed_everything(0)
    spec = get_host().detector(args.detector)
    in_ch = spec.thermal_channels if spec.input_kind == "dual" else 4
    model = build_model(spec, args.classes, in_ch, {})
    b, s = args.batch, args.imgsz
    base = rss_mb()
    out: dict = {"what": args.measure, "detector": args.detector, "imgsz": s, "batch": b, "threads": args.threads}

    def inputs():
        x = torch.rand(b, 4, s, s)
        if spec.input_kind == "dual":
            return x[:, :3], x[:, 3:4].repeat(1, spec.thermal_channels, 1, 1)
        return x

    if args.measure in ("anchor-train", "anchor-eval"):
        train = args.measure == "anchor-train"
        model.train(train)
        opt = torch.optim.SGD(model.parameters(), lr=1e-4, momentum=0.9)
        times = []
        for _ in range(args.steps):
            x = inputs()
            t0 = time.perf_counter()
            if train:
                raw = model.forward_raw(x)
                raw = raw if isinstance(raw, (list, tuple)) else [raw]
                loss = sum(r.float().pow(2).mean() for r in raw)
                loss.backward()
                opt.step()
                opt.zero_grad(set_to_none=True)
            else:
                with torch.inference_mode():
                    model.forward_raw(x)
            times.append(time.perf_counter() - t0)
        step = statistics.median(times[1:])
        out.update(s_per_step=step, images_per_s=b / step)
    else:
        from harness.engine.data import AugmentSettings, SampleSource, TrainDataset
        from harness.engine.predict import predict
        from harness.engine.trainer import Trainer, TrainSettings

        with tempfile.TemporaryDirectory() as tmp:
            n = b * args.steps
            prepared = write_samples(Path(tmp) / "ds", n, (512, 640), args.classes)
            enc = _ir8()
            src = SampleSource(prepared, None, enc)
            base = rss_mb()
            if args.measure == "engine-train":
                settings = TrainSettings(imgsz=s, epochs=2, batch=b, nominal_batch=64, warmup_epochs=1.0,
                                         warmup_min_iters=0, close_mosaic=0, threads=args.threads, device="cpu",
                                         patience=10)
                res = Trainer(model, TrainDataset(src, s, AugmentSettings()), settings, spec.input_kind,
                              spec.thermal_channels, progress=False).fit()
                last = res.history[-1]  # the second epoch: no first-iteration overheads
                out.update(s_per_step=last["time_s"] / args.steps, images_per_s=last["images_per_s"])
            else:
                predict(model, SampleSource(prepared, [0], enc), s, batch=b, input_kind=spec.input_kind,
                        thermal_channels=spec.thermal_channels, conf=0.001, iou=0.7, max_det=300)  # warm-up
                t0 = time.perf_counter()
                dets = predict(model, src, s, batch=b, input_kind=spec.input_kind,
                               thermal_channels=spec.thermal_channels, conf=0.001, iou=0.7, max_det=300)
                dt = time.perf_counter() - t0
                out.update(s_per_step=dt / args.steps, images_per_s=n / dt, detections_per_image=len(dets) / n)
    out.update(peak_rss_mb=round(peak_mb(), 1), rss_before_mb=round(base, 1), peak_over_start_mb=round(peak_mb() - base, 1),
               model_params=int(sum(p.numel() for p in model.parameters())))
    del np
    return out


def _ir8():
    import numpy as np

    from harness import EncodingSpec

    return EncodingSpec(name="bench-ir8", fn=lambda smp, **_: np.ascontiguousarray(smp.ir8), channels=1, needs="ir8")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--detector", default="ours")
    p.add_argument("--imgsz", type=int, default=640)
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--steps", type=int, default=6, help="timed steps (the first is dropped)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--classes", type=int, default=8)
    p.add_argument("--measure", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.measure:
        print(json.dumps(measure(args)))
        return
    # the same OpenMP wait policy as `harness run` (see harness/commands/run.py), inherited by every measurement
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    rows = {}
    for what in ("anchor-train", "engine-train", "anchor-eval", "engine-eval"):
        cmd = [sys.executable, __file__, "--measure", what] + [f"--{k}={v}" for k, v in vars(args).items()
                                                                if k != "measure"]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode:
            sys.exit(f"{what} failed:\n{res.stderr[-3000:]}")
        rows[what] = json.loads(res.stdout.strip().splitlines()[-1])
    r0 = rows["anchor-train"]
    print(f"detector {args.detector} ({r0['model_params']:,} params), {args.imgsz} px, batch {args.batch}, "
          f"{args.threads} threads, CPU")
    print(f"{'measurement':<14} {'images/s':>9} {'s/step':>8} {'peak RSS MB':>12} {'+MB over start':>15} {'vs anchor':>10}")
    for what, r in rows.items():
        anchor = rows["anchor-train" if "train" in what else "anchor-eval"]
        ratio = r["images_per_s"] / anchor["images_per_s"]
        print(f"{what:<14} {r['images_per_s']:>9.2f} {r['s_per_step']:>8.3f} {r['peak_rss_mb']:>12.0f} "
              f"{r['peak_over_start_mb']:>15.0f} {ratio:>10.2f}")
    print("vs anchor: engine images/s divided by the model-only images/s of the same phase (1.00 = no overhead)")


if __name__ == "__main__":
    main()
