"""Training and evaluation throughput of the engine, and peak memory, on CPU (default: 640 px, batch 2).

First, the train step of ``ours`` against its anchors (``--step-threads``, default 1 thread; YOLOv8s, 4 channels,
8 classes, ``--imgsz`` x ``--imgsz``, batch ``--batch``, 20 boxes per image), CPU time per step:

* ``step-ours``: the engine's step as ``harness.engine.trainer.Trainer`` runs it: forward, the YOLOv8 loss (task-
  aligned assigner, BCE, CIoU, DFL), backward, gradient clipping, SGD (Nesterov) over the three parameter groups,
  zeroing and the EMA update, with the trainer's CPU set-up (flat buffers, ``keep_freed_memory``);
* ``step-ours-cl``: the same with ``train.channels_last`` (channels-last tensors, 1x1 convolutions on oneDNN: see
  ``harness.engine.trainer.pointwise_convs_on_onednn``), which changes float rounding and is not the default;
* ``step-ultralytics``: Ultralytics' YOLOv8s (``DetectionModel("yolov8s.yaml", ch=4, nc=8)``, its ``v8DetectionLoss``
  on the same boxes, the same SGD groups, torch's clipping, its ``ModelEMA``), when the ``ultralytics`` package
  imports in this environment. It is AGPL-3.0 and never a dependency of this project: install it into a
  measurement environment only (``pip install ultralytics --no-deps``; it reads torchvision's version at import);
* ``step-frozen``: the step as the engine ran it before the flat-buffer optimiser (torch's per-tensor SGD and
  clipping, the per-tensor EMA over ``state_dict()``, glibc's default allocator), on the project's model and loss,
  the anchor when Ultralytics is missing. If the model or loss files changed since the anchor was frozen, the
  benchmark says so: the anchor then includes those changes.

Each is measured in its own process, ``--rounds`` times in turn (the median of the rounds' medians), so a busy
machine slows all of them alike. The target is ``ours <= 0.85 x Ultralytics``, printed for both of ours, after the
machine lines (CPU, the instruction set torch dispatches to, any ISA restriction, the load). With ``--breakdown``,
one step of ours and one of Ultralytics are then timed op by op (thread time of every ATen op, grouped: convolution
forward, convolution backward, BatchNorm, SiLU, pooling/upsampling/concatenation/addition, other ops, and the time
outside ops), with the convolutions' GFLOP/s and how much of the target the convolutions of ours alone take.

Then four measurements of the whole engine, each in its own process (so that each peak-memory figure is its own):

* ``anchor-train``: the model alone, one step = ``forward_raw`` on random input + ``sum(mean(out^2))`` + backward +
  SGD step (the model-compute cost that nothing can remove);
* ``engine-train``: ``harness.engine.trainer.Trainer`` on prepared samples: mosaic + affine + HSV + flips,
  letterbox, the detector's real loss (assigner included), gradient accumulation, EMA;
* ``anchor-eval``: ``forward_raw`` under ``torch.inference_mode``;
* ``engine-eval``: ``harness.engine.predict.predict``: letterbox, forward, decoding, NMS at conf 0.001, COCO output.

Ratios are engine / anchor measured in the same run on the same machine, so they stay meaningful on a busy or a
different CPU; absolute images/s are printed for the record. Example::

    .venv/bin/python benchmarks/bench_train.py                       # ours, 640, batch 2, 2 threads
    .venv/bin/python benchmarks/bench_train.py --detector tinydet --imgsz 320 --no-step
    .venv/bin/python benchmarks/bench_train.py --step-only --rounds 5
    .venv/bin/python benchmarks/bench_train.py --step-only --breakdown
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
TARGET = 0.85  # ours / Ultralytics, train step
#: sha1 of the model and loss files the frozen step runs (adapters/detectors/yolo/...), when it was frozen
FROZEN_SOURCES = {
    "adapters/detectors/yolo/v8.py": "14790e484f79b2162bb50b453c802f78cf772a5b",
    "adapters/detectors/yolo/blocks.py": "0f4a9b89845e7411e54ba05d2483338f0471919a",
    "adapters/detectors/yolo/loss_v8.py": "aacf1e257382f1333b260ddcfc416c44f205afb7",
    "adapters/detectors/yolo/tal.py": "b4e837a9bae1281a783ad8dd7a7bffa145bd08a1",
    "harness/boxes.py": "6fe7a1d0d507ea0a807744002d8c80aedcdca2c5",
}


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
                rgb[y : y + bh, x : x + bw] = rng.integers(0, 256, 3)
                temp[y : y + bh, x : x + bw] += 3
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
                settings = TrainSettings(
                    imgsz=s,
                    epochs=2,
                    batch=b,
                    nominal_batch=64,
                    warmup_epochs=1.0,
                    warmup_min_iters=0,
                    close_mosaic=0,
                    threads=args.threads,
                    device="cpu",
                    patience=10,
                )
                res = Trainer(
                    model,
                    TrainDataset(src, s, AugmentSettings()),
                    settings,
                    spec.input_kind,
                    spec.thermal_channels,
                    progress=False,
                ).fit()
                last = res.history[-1]  # the second epoch: no first-iteration overheads
                out.update(s_per_step=last["time_s"] / args.steps, images_per_s=last["images_per_s"])
            else:
                options = dict(
                    batch=b,
                    input_kind=spec.input_kind,
                    thermal_channels=spec.thermal_channels,
                    conf=0.001,
                    iou=0.7,
                    max_det=300,
                )
                predict(model, SampleSource(prepared, [0], enc), s, **options)  # warm-up
                t0 = time.perf_counter()
                dets = predict(model, src, s, **options)
                dt = time.perf_counter() - t0
                out.update(s_per_step=dt / args.steps, images_per_s=n / dt, detections_per_image=len(dets) / n)
    out.update(
        peak_rss_mb=round(peak_mb(), 1),
        rss_before_mb=round(base, 1),
        peak_over_start_mb=round(peak_mb() - base, 1),
        model_params=int(sum(p.numel() for p in model.parameters())),
    )
    del np
    return out


# ---------------------------------------------------------------------------------------------- the train step
def step_targets(batch: int, size: int, classes: int, boxes: int = 20, seed: int = 0):
    import torch

    g = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, 4, size, size, generator=g)
    out = []
    for _ in range(batch):
        wh = (torch.rand(boxes, 2, generator=g) * 0.25 + 0.02) * size
        c = torch.rand(boxes, 2, generator=g) * (size - wh) + wh / 2
        out.append(
            {
                "boxes": torch.cat((c - wh / 2, c + wh / 2), 1),
                "labels": torch.randint(0, classes, (boxes,), generator=g),
            }
        )
    return x, out


class FrozenEMA:
    """The EMA update as the engine ran it when the step was frozen: two kernels per state-dict entry."""

    def __init__(self, model):
        import copy

        from harness.engine.ema import ema_decay

        self.module, self.updates, self.decay = copy.deepcopy(model).eval(), 0, ema_decay
        for p in self.module.parameters():
            p.requires_grad_(False)

    def update(self, model) -> None:
        import torch

        with torch.no_grad():
            self.updates += 1
            d = self.decay(self.updates)
            current = model.state_dict()
            for k, v in self.module.state_dict().items():
                if v.dtype.is_floating_point:
                    v.mul_(d).add_(current[k].detach(), alpha=1 - d)
                else:
                    v.copy_(current[k])


def build_step(kind: str, size: int, batch: int, classes: int):
    """``(step function, description)`` of one train step of ``kind`` (see the module docstring)."""
    import torch

    from harness.engine import optim

    x, targets = step_targets(batch, size, classes)
    torch.manual_seed(0)
    if kind == "ultralytics":
        os.environ.setdefault("YOLO_CONFIG_DIR", tempfile.mkdtemp(prefix="bench-yolo-"))
        os.environ.setdefault("YOLO_OFFLINE", "1")
        import ultralytics
        from ultralytics.nn.tasks import DetectionModel
        from ultralytics.utils import IterableSimpleNamespace
        from ultralytics.utils.torch_utils import ModelEMA as UltralyticsEMA

        model = DetectionModel("yolov8s.yaml", ch=4, nc=classes, verbose=False).train()
        model.args = IterableSimpleNamespace(box=7.5, cls=0.5, dfl=1.5)
        opt = optim.build_optimizer(model, "SGD", 0.01, 0.937, 5e-4)
        ema = UltralyticsEMA(model)
        idx, cls, xywh = [], [], []
        for i, t in enumerate(targets):
            b = t["boxes"]
            idx.append(torch.full((len(b),), float(i)))
            cls.append(t["labels"].float().view(-1, 1))
            xywh.append(torch.cat(((b[:, :2] + b[:, 2:]) / 2, b[:, 2:] - b[:, :2]), 1) / size)
        data = {"img": x, "batch_idx": torch.cat(idx), "cls": torch.cat(cls), "bboxes": torch.cat(xywh)}

        def step() -> None:
            loss, _ = model.loss(data)
            loss.sum().backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm=10.0)
            opt.step()
            opt.zero_grad(set_to_none=True)
            ema.update(model)

        return step, f"Ultralytics {ultralytics.__version__} YOLOv8s (v8DetectionLoss)"

    from harness.plugins import get_host
    from harness.runner import build_model

    model = build_model(get_host().detector("ours"), classes, 4, {"scale": "s"}).train()
    if kind == "ours-cl":
        from harness.engine.trainer import pointwise_convs_on_onednn

        model = model.to(memory_format=torch.channels_last)
        pointwise_convs_on_onednn(model, True)
        x = x.contiguous(memory_format=torch.channels_last)
    opt = optim.build_optimizer(model, "SGD", 0.01, 0.937, 5e-4)
    if kind in ("ours", "ours-cl"):
        from harness.engine.ema import ModelEMA
        from harness.engine.runtime import keep_freed_memory
        from harness.engine.trainer import flat_buffers

        keep_freed_memory()
        flat = flat_buffers(model, opt, torch.device("cpu"))
        if flat is not None:
            from harness.engine.flat import FlatOptimizer

            opt = FlatOptimizer(opt, flat)
        ema = ModelEMA(model, flat=flat)

        def clip() -> None:
            if flat is not None:
                flat.clip_grad_norm_(10.0)
            else:
                torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm=10.0)

        what = (
            "ours (the engine's step"
            + (", flat buffers" if flat is not None else "")
            + (", train.channels_last)" if kind == "ours-cl" else ")")
        )
    else:
        ema = FrozenEMA(model)

        def clip() -> None:
            torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm=10.0)

        what = "today's step, frozen (per-tensor optimiser, clipping and EMA)"

    def step() -> None:
        losses = model(x, targets)
        sum(v.sum() for v in losses.values()).backward()
        clip()
        opt.step()
        opt.zero_grad(set_to_none=True)
        ema.update(model)

    return step, what


def warm_step(args: argparse.Namespace) -> tuple[Callable[[], None], str] | dict:
    """The step that ``args.measure`` names, on ``--step-threads`` threads, after one warm-up call (first-call
    allocations, lazy criterion and anchor caches); or the "missing" record when its package does not import."""
    import torch

    torch.set_num_threads(args.step_threads)
    try:
        step, what = build_step(args.measure.split("-", 1)[1], args.imgsz, args.batch, args.classes)
    except ImportError as exc:
        return {"what": args.measure, "missing": f"{type(exc).__name__}: {exc}"}
    step()
    return step, what


def measure_step(args: argparse.Namespace) -> dict:
    built = warm_step(args)
    if isinstance(built, dict):
        return built
    step, what = built
    times = []
    for _ in range(args.steps):
        t0 = time.thread_time()  # CPU time of this (the only torch) thread: robust to other processes' load
        step()
        times.append(time.thread_time() - t0)
    return {
        "what": args.measure,
        "description": what,
        "s_per_step": statistics.median(times),
        "times": times,
        "peak_rss_mb": round(peak_mb(), 1),
    }


#: how ``--breakdown`` groups ATen ops: (label, op names; "pool/cat/add" includes the upsampling); the rest (loss,
#: optimiser, EMA, views) is "other ops"
OP_GROUPS = (
    ("conv fwd", ("convolution",)),
    ("conv bwd", ("convolution_backward",)),
    ("BN", ("native_batch_norm", "native_batch_norm_backward")),
    ("SiLU", ("silu", "silu_backward")),
    (
        "pool/cat/add",
        (
            "max_pool2d_with_indices",
            "max_pool2d_with_indices_backward",
            "upsample_nearest2d",
            "upsample_nearest2d_backward",
            "cat",
            "add",
            "add_",
        ),
    ),
)


def conv_flops(func_name: str, args: tuple) -> float:
    """Multiply-adds x 2 of one ``convolution`` or ``convolution_backward`` call (each computed gradient counts as
    much as the forward pass; ``w[0].numel()`` is in-channels / groups x kernel taps)."""
    if func_name == "convolution":
        x, w, stride, pad, dil = args[0], args[1], args[3], args[4], args[5]
        passes = 1
    else:
        x, w, stride, pad, dil = args[1], args[2], args[4], args[5], args[6]
        passes = sum(bool(m) for m in args[10][:2])
    out = [(x.shape[2 + i] + 2 * pad[i] - dil[i] * (w.shape[2 + i] - 1) - 1) // stride[i] + 1 for i in range(2)]
    return 2.0 * passes * x.shape[0] * w.shape[0] * out[0] * out[1] * w[0].numel()


def measure_breakdown(args: argparse.Namespace) -> dict:
    """CPU (thread) time of every ATen op in one train step after a warm-up, grouped by ``OP_GROUPS``, and the
    convolutions' GFLOP/s. The dispatch hook costs a few microseconds per op: it lands in "outside ops" (the Python
    and autograd work between ops), not in the op groups."""
    from torch.utils._python_dispatch import TorchDispatchMode

    built = warm_step(args)
    if isinstance(built, dict):
        return built
    step, what = built
    times: dict[str, float] = {}
    flops = [0.0]

    class Timed(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, a=(), kw=None):
            t0 = time.thread_time()
            out = func(*a, **(kw or {}))
            name = func.overloadpacket.__name__
            times[name] = times.get(name, 0.0) + time.thread_time() - t0
            if name in ("convolution", "convolution_backward"):
                flops[0] += conv_flops(name, a)
            return out

    t0 = time.thread_time()
    with Timed():
        step()
    total = time.thread_time() - t0
    groups = {label: sum(times.pop(n, 0.0) for n in names) for label, names in OP_GROUPS}
    groups["other ops"] = sum(times.values())
    groups["outside ops"] = total - sum(groups.values())
    conv = groups["conv fwd"] + groups["conv bwd"]
    return {
        "what": args.measure,
        "description": what,
        "total_s": total,
        "groups_s": groups,
        "conv_gflops_per_s": flops[0] / conv / 1e9 if conv else float("nan"),
    }


def print_breakdown(args: argparse.Namespace, step_medians: dict[str, float]) -> None:
    rows = [run_measure(k, args) for k in ("breakdown-ours", "breakdown-ultralytics")]
    rows = [r for r in rows if "missing" not in r]
    labels = list(rows[0]["groups_s"])
    print("where one step's CPU time goes, ms (thread time per ATen op, one step after a warm-up):")
    print(f"  {'':<12}" + "".join(f"{lb[:12]:>13}" for lb in labels) + f"{'step':>8}{'conv GFLOP/s':>14}")
    for r in rows:
        print(
            f"  {r['what'][10:]:<12}"
            + "".join(f"{1e3 * r['groups_s'][lb]:>13.0f}" for lb in labels)
            + f"{1e3 * r['total_s']:>8.0f}{r['conv_gflops_per_s']:>14.0f}"
        )
    if "step-ultralytics" in step_medians:
        ours = rows[0]["groups_s"]
        conv = ours["conv fwd"] + ours["conv bwd"]
        goal = TARGET * step_medians["step-ultralytics"]
        print(
            f"  the convolutions of ours alone: {conv:.3f} s = {conv / step_medians['step-ultralytics']:.3f} x "
            f"Ultralytics' step; the target ({TARGET:.2f} x) leaves {goal - conv:+.3f} s for everything else"
        )


def frozen_sources_changed() -> list[str]:
    out = []
    for rel, digest in FROZEN_SOURCES.items():
        text = (ROOT / rel).read_text(encoding="utf-8").replace("\r\n", "\n")
        if hashlib.sha1(text.encode()).hexdigest() != digest:
            out.append(rel)
    return out


def run_measure(what: str, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, __file__, "--measure", what] + [
        f"--{k.replace('_', '-')}={v}"
        for k, v in vars(args).items()
        if k not in ("measure", "step", "step_only", "breakdown")
    ]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode:
        sys.exit(f"{what} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def compare_steps(args: argparse.Namespace) -> dict[str, float]:
    kinds = ["step-ours", "step-ours-cl", "step-ultralytics", "step-frozen"]
    rounds: dict[str, list[dict]] = {k: [] for k in kinds}
    for _ in range(args.rounds):
        for k in kinds:
            if rounds[k] and "missing" in rounds[k][0]:
                continue
            rounds[k].append(run_measure(k, args))
    med = {k: statistics.median(r["s_per_step"] for r in v) for k, v in rounds.items() if v and "missing" not in v[0]}
    import torch  # noqa: F401  (loaded, so that the machine lines name the ISA torch dispatches to)

    from _machine import machine_lines

    for line in machine_lines():
        print(line)
    print(
        f"train step: YOLOv8s 4-channel, {args.classes} classes, {args.imgsz} px, batch {args.batch}, "
        f"{args.step_threads} thread(s), CPU time per step (median of {args.rounds} rounds x {args.steps} steps)"
    )
    for k in kinds:
        r = rounds[k][0]
        if "missing" in r:
            print(f"  {k:<17} not measured: {r['missing'].splitlines()[0][:70]}")
            continue
        print(f"  {k:<17} {med[k]:7.3f} s  {r['description']}")
    anchor = "step-ultralytics" if "step-ultralytics" in med else "step-frozen"
    for ours in ("step-ours", "step-ours-cl"):
        ratio = med[ours] / med[anchor]
        verdict = ("met" if ratio <= TARGET else "NOT met") if anchor == "step-ultralytics" else "no Ultralytics here"
        print(
            f"{ours[5:]} / {anchor[5:]}: {ratio:.3f}   target <= {TARGET:.2f} x Ultralytics: {verdict}"
            + (f"   ({ours[5:]} / frozen: {med[ours] / med['step-frozen']:.3f})" if anchor != "step-frozen" else "")
        )
    changed = frozen_sources_changed()
    if changed:
        print(f"note: the frozen step runs the current {', '.join(changed)}, changed since it was frozen")
    return med


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
    p.add_argument("--step-threads", type=int, default=1, help="torch threads of the train-step comparison")
    p.add_argument("--rounds", type=int, default=3, help="rounds of the train-step comparison")
    p.add_argument("--no-step", dest="step", action="store_false", help="skip the train-step comparison")
    p.add_argument("--step-only", action="store_true", help="only the train-step comparison")
    p.add_argument(
        "--breakdown",
        action="store_true",
        help="also time every ATen op of one step of ours and of Ultralytics, grouped (convolutions, ...)",
    )
    p.add_argument("--measure", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.measure:
        how = {"step": measure_step, "breakdown": measure_breakdown}.get(args.measure.split("-")[0], measure)
        print(json.dumps(how(args)))
        return
    # the same OpenMP wait policy as `harness run` (see harness/commands/run.py), inherited by every measurement
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if args.step or args.step_only:
        medians = compare_steps(args)
        if args.breakdown:
            print_breakdown(args, medians)
        if args.step_only:
            return
        print()
    rows = {}
    for what in ("anchor-train", "engine-train", "anchor-eval", "engine-eval"):
        rows[what] = run_measure(what, args)
    r0 = rows["anchor-train"]
    print(
        f"detector {args.detector} ({r0['model_params']:,} params), {args.imgsz} px, batch {args.batch}, "
        f"{args.threads} threads, CPU"
    )
    print(
        f"{'measurement':<14} {'images/s':>9} {'s/step':>8} {'peak RSS MB':>12} {'+MB over start':>15} "
        f"{'vs anchor':>10}"
    )
    for what, r in rows.items():
        anchor = rows["anchor-train" if "train" in what else "anchor-eval"]
        ratio = r["images_per_s"] / anchor["images_per_s"]
        print(
            f"{what:<14} {r['images_per_s']:>9.2f} {r['s_per_step']:>8.3f} {r['peak_rss_mb']:>12.0f} "
            f"{r['peak_over_start_mb']:>15.0f} {ratio:>10.2f}"
        )
    print("vs anchor: engine images/s divided by the model-only images/s of the same phase (1.00 = no overhead)")


if __name__ == "__main__":
    main()
