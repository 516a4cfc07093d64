"""Memory of one training step against image size x batch: the figures behind ``harness.config``'s memory bound.

Each (detector, size, batch) runs in a fresh process: the model is built, one forward + backward in train mode on a
random batch is run (``--mode eval``: a prediction without gradients), and the growth of the peak resident memory
over the process's peak after the build is printed, with that growth per pixel per batch item. ``marginal`` is the
growth from the previous size per added pixel per item (the fixed part left out): ``config.TRAIN_BYTES_PER_PIXEL``
and ``EVAL_BYTES_PER_PIXEL`` are the lightest built-in detector's marginal figures.

    .venv/bin/python benchmarks/imgsz_memory.py --detectors ours eme icafusion cmadet --sizes 256 384
    .venv/bin/python benchmarks/imgsz_memory.py --detectors ours icafusion --sizes 256 384 --mode eval
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys
import torch
torch.set_num_threads(1)
from harness.plugins import load_plugins
name, size, batch, mode = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
spec = load_plugins().detector(name)
in_ch = spec.model_channels(4)
model = spec.build(3, in_channels=in_ch).train(mode == "train")
x = torch.rand(batch, 4, size, size)
inputs = x if spec.input_kind == "single" else (x[:, :3], x[:, 3:].expand(-1, in_ch, -1, -1).contiguous())
boxes = torch.tensor([[size * 0.2, size * 0.2, size * 0.5, size * 0.6]])
targets = [{"boxes": boxes.clone(), "labels": torch.tensor([1])} for _ in range(batch)]
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
if mode == "train":
    losses = model(inputs, targets)
    sum(losses.values()).backward()
else:
    with torch.no_grad():
        model(inputs)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"before": before, "after": after}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--detectors", nargs="+", default=["ours"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[128, 256])
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--mode", choices=("train", "eval"), default="train", help="a training step or a prediction")
    args = ap.parse_args()
    print(f"{'detector':<10} {'size':>5} {'batch':>5} {'step MB':>8} {'bytes/px/item':>14} {'marginal':>9}")
    for det in args.detectors:
        last: tuple[int, int] | None = None
        for size in args.sizes:
            argv = [sys.executable, "-c", CHILD, det, str(size), str(args.batch), args.mode]
            out = subprocess.run(argv, capture_output=True, text=True)
            if out.returncode:
                print(f"{det:<10} {size:>5} failed: {out.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
                continue
            rec = json.loads(out.stdout.strip().splitlines()[-1])
            grown = rec["after"] - rec["before"]
            items = size * size * args.batch
            marginal = f"{(grown - last[1]) / (items - last[0]):>9.0f}" if last else f"{'-':>9}"
            print(f"{det:<10} {size:>5} {args.batch:>5} {grown / 2**20:>8.1f} {grown / items:>14.0f} {marginal}")
            last = (items, grown)


if __name__ == "__main__":
    main()
