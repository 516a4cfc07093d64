"""Bit-for-bit training across instruction sets and BLAS code paths, and what each kernel setting costs.

One machine cannot show two CPU models; what it can show is whether results change when the instruction set the
kernels may use (``ONEDNN_MAX_CPU_ISA``, ``ATEN_CPU_CAPABILITY``) or the BLAS's code path (``MKL_CBWR``) is changed,
which is how one CPU model differs from another to the kernels. Each setting below trains the same short run through
the real engine (``harness run``: a detector at the benchmark profile, one fold, one seed, one thread) in a fresh
process, and a probe process hashes one training step's gradients (a fixed model and batch) and the trained
weights' raw eval-mode outputs on a fixed batch. Two settings are identical when every hash is equal: the final
weights (last.pt), the held-out predictions, the metrics, the per-epoch losses, the gradients and the raw outputs.

Cost: the CPU seconds per epoch of the training loop (``Trainer.fit``: the epochs and their validation; CPU time,
since the machine is shared) of each setting against today's AVX2 profile (``avx2``), measured in the same run with
the settings alternated, ``--repeat`` times, median.

    .venv/bin/python benchmarks/reproducibility.py                        # ours, P1, 3 epochs, 3 repeats
    .venv/bin/python benchmarks/reproducibility.py --epochs 2 --repeat 1 --settings avx2,native

The data are prepared on first use (``harness prepare --dataset m3t-synth``, into ./data and ./cache).

Measured on the 2-core AMD EPYC (AVX-512) of the development machines, torch 2.13.0 (oneDNN 3.12, oneMKL 2024.2),
ours, P1, 3 epochs, 3 repeats: every setting repeats itself bit for bit, and no two settings are identical. Changing
the instruction-set cap changes whole runs under every kernel policy, oneDNN off and ``MKL_CBWR=AVX2`` included:
there one step's gradients are identical under ATen's AVX2 and AVX-512 kernels, but the trained weights are not
(ATen's vectorised kernels differ by width, e.g. a softmax over rows of 8 or 256). Cost against ``avx2``: native
1.00x, ``MKL_CBWR=AVX2`` 1.04x (0.96x native), oneDNN off 1.19-1.26x, oneDNN off with ``MKL_CBWR=COMPATIBLE`` (the
one MKL branch it keeps on every x86 CPU; its AVX2 branch is kept on Intel CPUs only) 2.09x.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import REPO
from _machine import machine_lines

AVX2 = {"ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"}
CBWR = {"MKL_CBWR": "AVX2"}
OFF = {"HARNESS_ONEDNN": "0"}
#: name -> (environment, what it is); ``avx2`` is today's benchmark profile and the anchor of the cost ratios
SETTINGS: dict[str, tuple[dict[str, str], str]] = {
    "avx2": (AVX2, "today's profile: oneDNN and ATen capped at AVX2"),
    "native": ({}, "no cap (AVX-512 where the CPU has it)"),
    "avx2+cbwr": ({**AVX2, **CBWR}, "today's profile, MKL_CBWR=AVX2"),
    "native+cbwr": (CBWR, "no cap, MKL_CBWR=AVX2"),
    "off+cbwr/avx2": ({**OFF, **CBWR, "ATEN_CPU_CAPABILITY": "avx2"}, "oneDNN off, MKL_CBWR=AVX2, ATen AVX2"),
    "off+cbwr/avx512": ({**OFF, **CBWR, "ATEN_CPU_CAPABILITY": "avx512"}, "oneDNN off, MKL_CBWR=AVX2, ATen AVX-512"),
    "off/avx2": ({**OFF, "ATEN_CPU_CAPABILITY": "avx2"}, "oneDNN off, MKL's own path, ATen AVX2"),
    # MKL promises its AVX2 branch only on Intel CPUs (elsewhere MKL_CBWR=AVX2 falls back to its AUTO branch);
    # COMPATIBLE (SSE2) is the branch it keeps on every x86 CPU
    "off+compat/avx2": (
        {**OFF, "MKL_CBWR": "COMPATIBLE", "ATEN_CPU_CAPABILITY": "avx2"},
        "oneDNN off, MKL_CBWR=COMPATIBLE, ATen AVX2",
    ),
    "off/avx512": ({**OFF, "ATEN_CPU_CAPABILITY": "avx512"}, "oneDNN off, MKL's own path, ATen AVX-512"),
}
#: the variables a setting sets; each run starts from the environment without any of them
CONTROLLED = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "MKL_CBWR", "HARNESS_ONEDNN")
#: the pairs the decision rests on: the same kernel policy under another instruction-set cap
PAIRS = (
    ("avx2", "native"),
    ("avx2", "avx2+cbwr"),
    ("avx2+cbwr", "native+cbwr"),
    ("off+cbwr/avx2", "off+cbwr/avx512"),
    ("off/avx2", "off/avx512"),
    ("off/avx2", "off+cbwr/avx2"),
    ("off+cbwr/avx2", "off+compat/avx2"),
)
#: the most a reproducible setting may cost against today's profile to become the benchmark's default
MAX_COST = 1.5


def digest(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p)
    return h.hexdigest()[:12]


def tensors_digest(tensors: dict[str, Any]) -> str:
    """A digest of named tensors (names sorted; dtype, shape and bytes of each)."""
    h = hashlib.sha256()
    for k in sorted(tensors):
        t = tensors[k].detach().contiguous().cpu()
        h.update(f"{k}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()[:12]


def probe(weights: str, scale: str, size: int) -> None:
    """In a fresh process under the setting: one training step's gradients (fixed seed, model and batch) and the
    raw eval-mode outputs of ``weights`` on a fixed batch, printed as JSON digests."""
    import torch

    from adapters.detectors.yolo.v8 import build_yolov8
    from harness.engine.runtime import apply_onednn_setting

    torch.set_num_threads(1)
    onednn = apply_onednn_setting()
    torch.manual_seed(0)
    model = build_yolov8(8, in_channels=4, scale=scale).train()
    g = torch.Generator().manual_seed(1)
    x = torch.rand(4, 4, size, size, generator=g)
    targets = []
    for _ in range(4):
        wh = (torch.rand(6, 2, generator=g) * 0.25 + 0.05) * size
        c = torch.rand(6, 2, generator=g) * (size - wh) + wh / 2
        targets.append(
            {"boxes": torch.cat((c - wh / 2, c + wh / 2), 1), "labels": torch.randint(0, 8, (6,), generator=g)}
        )
    losses = model(x, targets)
    sum(losses.values()).backward()
    grads = {k: p.grad for k, p in model.named_parameters() if p.grad is not None}
    state = torch.load(weights, map_location="cpu", weights_only=True)["model"]
    model.load_state_dict(state)
    with torch.inference_mode():
        raw = model.eval().forward_raw(x)
    outputs = {str(i): t for i, t in enumerate(raw)}
    print(
        json.dumps(
            {
                "onednn": onednn,
                "aten": torch.backends.cpu.get_cpu_capability(),
                "grad": tensors_digest(grads),
                "outputs": tensors_digest(outputs),
            }
        )
    )


def timed_run(timing: str, argv: list[str]) -> None:
    """``harness`` with ``argv``, writing the CPU and wall seconds of the training loop (``Trainer.fit``) to
    ``timing`` (JSON)."""
    from harness.cli import main as harness_main
    from harness.engine import trainer

    fit = trainer.Trainer.fit

    def timed_fit(self: Any, *a: Any, **k: Any) -> Any:
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            return fit(self, *a, **k)
        finally:
            Path(timing).write_text(json.dumps({"cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - w0}))

    trainer.Trainer.fit = timed_fit  # type: ignore[method-assign]
    harness_main(argv)


def environ(setting: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    env.update(SETTINGS[setting][0])
    env.update({"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})
    return env


def train(setting: str, store: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One training run under ``setting`` (a fresh ``harness run``) and the digests of what it left."""
    timing = store.parent / f"{store.name}.timing.json"
    cmd = [
        sys.executable,
        __file__,
        "--timed-run",
        str(timing),
        "run",
        "--detector",
        args.detector,
        "--dataset",
        "m3t-synth",
        "--folds",
        args.fold,
        "--profile",
        "benchmark",
        "--config",
        f"configs/benchmark/{args.detector}.yaml",
        "--set",
        f"protocol.epochs={args.epochs}",
        "--set",
        f"protocol.patience={args.epochs}",
        "--seeds",
        "0",
        "--store",
        str(store),
        "--force",
        "--no-progress",
    ]
    done = subprocess.run(cmd, cwd=REPO, env=environ(setting), capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"{setting}: harness run failed ({done.returncode}):\n{done.stderr[-3000:]}")
    run = next(store.glob(f"m3t-synth/{args.detector}/*/{args.fold}/seed0"))
    import torch

    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    metrics = json.loads((run / "metrics.json").read_text())
    state = torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["model"]
    preds = (run / "predictions.json").read_bytes()
    m = metrics.get("metrics", metrics)
    fit = json.loads(timing.read_text())
    result = {
        "epoch_s": fit["cpu_s"] / len(log),
        "epoch_wall_s": fit["wall_s"] / len(log),
        "weights": tensors_digest(state),
        "predictions": digest(preds),
        "n_predictions": len(json.loads(preds)),
        "metrics": digest(json.dumps([m.get("mAP50"), m.get("mAP50_95")]).encode()),
        "mAP": (m.get("mAP50"), m.get("mAP50_95")),
        "losses": digest(json.dumps([r["loss"] for r in log]).encode()),
        "box_loss_1": log[0]["loss"]["box"],
    }
    if args.detector == "ours":
        pr = subprocess.run(
            [sys.executable, __file__, "--probe", str(run / "checkpoints" / "last.pt"), "--imgsz", str(args.imgsz)],
            cwd=REPO,
            env=environ(setting),
            capture_output=True,
            text=True,
        )
        if pr.returncode:
            sys.exit(f"{setting}: probe failed:\n{pr.stderr[-3000:]}")
        result.update(json.loads(pr.stdout.strip().splitlines()[-1]))
    return result


KEYS = ("weights", "predictions", "metrics", "losses", "grad", "outputs")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated names of SETTINGS")
    ap.add_argument("--detector", default="ours")
    ap.add_argument("--fold", default="P1")
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--imgsz", type=int, default=192)
    ap.add_argument("--probe", metavar="LAST_PT", help=argparse.SUPPRESS)
    if sys.argv[1:2] == ["--timed-run"]:
        timed_run(sys.argv[2], sys.argv[3:])
        return
    args = ap.parse_args()
    if args.probe:
        probe(args.probe, "n", args.imgsz)
        return
    names = args.settings.split(",")
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        sys.exit(f"--settings: unknown {unknown}; known: {', '.join(SETTINGS)}")
    if not any((REPO / "cache").glob("m3t-synth*")):
        print("preparing m3t-synth (harness prepare)", file=sys.stderr)
        subprocess.run([str(REPO / ".venv/bin/harness"), "prepare", "--dataset", "m3t-synth"], cwd=REPO, check=True)
    runs: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    with tempfile.TemporaryDirectory(prefix="reproducibility-") as tmp:
        for rep in range(args.repeat):
            order = names if rep % 2 == 0 else names[::-1]  # alternated, so a drift in load spreads over all
            for name in order:
                r = train(name, Path(tmp) / f"{name.replace('/', '_')}-{rep}", args)
                runs[name].append(r)
                print(f"[{rep + 1}/{args.repeat}] {name}: {r['epoch_s']:.2f} s/epoch {r}", file=sys.stderr, flush=True)
    for line in machine_lines():
        print(line)
    print(
        f"{args.detector}, benchmark profile, fold {args.fold}, seed 0, {args.epochs} epochs, one thread\n"
        f"cost: CPU s/epoch of the training loop, median of {args.repeat}, against avx2's"
    )
    anchor = statistics.median(r["epoch_s"] for r in runs["avx2"]) if "avx2" in runs else None
    head = (
        f"{'setting':<17} {'CPU s/ep':>8} {'x avx2':>6} {'rep':>3} {'weights':>12} {'grad':>12} {'box loss 1':>11} "
        f"{'dets':>5} mAP50"
    )
    print(head)
    print("-" * len(head))
    for name in names:
        rs = runs[name]
        med = statistics.median(r["epoch_s"] for r in rs)
        same = all(all(r[k] == rs[0][k] for k in KEYS if k in r) for r in rs)
        ratio = f"{med / anchor:6.2f}" if anchor else "     -"
        print(
            f"{name:<17} {med:8.2f} {ratio} {'yes' if same else 'NO':>3} {rs[0]['weights']:>12} "
            f"{rs[0].get('grad', '-'):>12} {rs[0]['box_loss_1']:11.5f} {rs[0]['n_predictions']:>5} "
            f"{rs[0]['mAP'][0]:.4f}"
        )
    print("rep: every repeat identical to the first (weights, predictions, metrics, losses, probe);")
    print("dets: held-out detections of the first run; grad: one step of a fixed model and batch")
    print()
    print(f"{'pair':<36} identical? (what differs)")
    for a, b in PAIRS:
        if a in runs and b in runs:
            ra, rb = runs[a][0], runs[b][0]
            diff = [k for k in KEYS if k in ra and ra[k] != rb[k]]
            print(f"{a + ' vs ' + b:<36} {'yes' if not diff else 'no (' + ', '.join(diff) + ')'}")
    print()
    for name, (env, what) in SETTINGS.items():
        if name in runs:
            print(f"{name:<17} {what}")
            print(f"{'':<17} {' '.join(f'{k}={v}' for k, v in env.items()) or '(nothing set)'}")
    print(f"rule: a setting identical across its ISA caps at <= {MAX_COST}x avx2's cost can be the default")


if __name__ == "__main__":
    main()
