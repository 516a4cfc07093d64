"""Time and peak memory of ``harness weights import`` on genuine-size stand-in checkpoints, as multiples of the file.

    .venv/bin/python benchmarks/bench_weights_import.py [--scales n s m l] [--icafusion-width 0.5] [--keep DIR]

Writes Ultralytics trainer checkpoints (``ours`` at each YOLOv8 scale, half precision, as ``tests/weights_standins``
writes them) and an ICAFusion-style checkpoint, then imports each in a forked worker of ``tests/hostile_runner.py``
(peak resident memory above the start, through ``/proc/self/clear_refs``). Prints the file size, the import time,
the peak and the peak as a multiple of the file: the stated bound is 64 MiB + 8 x the file's size
(``harness.weights.unpickle.PEAK_FLOOR``, ``PEAK_MULTIPLE``). Run it with ``PYTHONPATH`` at another checkout to
compare the same files through that checkout's importer.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scales", nargs="*", default=["n", "s", "m"])
    ap.add_argument("--icafusion-width", type=float, default=0.5)
    ap.add_argument("--keep", type=Path, default=None, help="write the checkpoints here (default: a temp folder)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    from adapters.detectors import icafusion, ours
    from weights_standins import save_ultralytics, save_yolov5_style

    folder = args.keep or Path(tempfile.mkdtemp(prefix="bench-weights-"))
    folder.mkdir(parents=True, exist_ok=True)
    runs = []
    for scale in args.scales:
        torch.manual_seed(0)
        path = save_ultralytics(
            ours.build(80, in_channels=3, scale=scale), folder / f"yolov8{scale}.pt", {i: f"c{i}" for i in range(80)}
        )
        runs.append({"name": f"ultralytics yolov8{scale}", "path": str(path), "mode": "import"})
    if args.icafusion_width:
        torch.manual_seed(0)
        model = icafusion.build(3, width=args.icafusion_width, depth=0.33)
        path = save_yolov5_style(model, folder / "icafusion.pt")
        runs.append({"name": f"icafusion width {args.icafusion_width}", "path": str(path), "mode": "import"})
    spec = folder / "runs.json"
    spec.write_text(json.dumps(runs))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.environ.get("PYTHONPATH", str(REPO)), str(REPO / "tests")])}
    out = subprocess.run(
        [
            sys.executable,
            str(REPO / "tests" / "hostile_runner.py"),
            str(spec),
            "--allowance",
            str(64 << 30),
            "--timeout",
            "600",
        ],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    print(f"{'checkpoint':<26} {'file MiB':>9} {'seconds':>8} {'peak MiB':>9} {'peak/file':>9}  outcome")
    for r in json.loads(out.stdout):
        size = Path(r["path"]).stat().st_size
        print(
            f"{r['name']:<26} {size / 2**20:>9.1f} {r['seconds']:>8.2f} {r['peak_bytes'] / 2**20:>9.1f} "
            f"{r['peak_bytes'] / size:>9.2f}  {r['outcome']} {r.get('message', '')[:60]}"
        )


if __name__ == "__main__":
    main()
