"""Cost of one training step of "ours" on CPU, split into the network and the loss (task-aligned assigner, BCE,
CIoU, DFL).

Anchor: the network's forward + backward + SGD step on the same batch, measured in the same run. The loss and the
assigner are timed forward + backward on the detached head maps (so none of the network is in their figure), and
printed as a ratio to the anchor.

    .venv/bin/python benchmarks/ours_train_step.py                       # 640x2 and 256x8, 1 and 2 threads
    .venv/bin/python benchmarks/ours_train_step.py --configs 320x4 --threads 2 --boxes 50
"""

from __future__ import annotations

import argparse

import torch

from _common import median_time
from adapters.detectors.yolo.v8 import build_yolov8

#: The loss with its assigner, forward + backward, as a share of the network's step (1-2 % when measured).
TARGET_LOSS = 0.05


def random_targets(batch: int, size: int, boxes: int, nc: int, seed: int = 0) -> list[dict[str, torch.Tensor]]:
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(batch):
        wh = (torch.rand(boxes, 2, generator=g) * 0.25 + 0.02) * size
        c = torch.rand(boxes, 2, generator=g) * (size - wh) + wh / 2
        out.append(
            {"boxes": torch.cat((c - wh / 2, c + wh / 2), 1), "labels": torch.randint(0, nc, (boxes,), generator=g)}
        )
    return out


def measure(size: int, batch: int, threads: int, boxes: int, iters: int, scale: str, nc: int = 8) -> dict[str, float]:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = build_yolov8(nc, in_channels=4, scale=scale).train()
    opt = torch.optim.SGD(model.parameters(), lr=1e-4, momentum=0.9)
    x = torch.rand(batch, 4, size, size)
    targets = random_targets(batch, size, boxes, nc)
    grads = [torch.randn_like(m) for m in model.forward_raw(x)]

    def network() -> None:  # forward + backward (with a fixed upstream gradient) + optimiser step
        maps = model.forward_raw(x)
        torch.autograd.backward(maps, grads)
        opt.step()
        opt.zero_grad(set_to_none=True)

    with torch.no_grad():
        frozen = [m.detach() for m in model.forward_raw(x)]

    def loss_only() -> None:  # assigner + BCE + CIoU + DFL, forward and backward, on detached maps
        maps = [m.clone().requires_grad_(True) for m in frozen]
        sum(model.criterion(maps, targets).values()).backward()

    def full_step() -> None:
        losses = model(x, targets)
        sum(losses.values()).backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    net = median_time(network, iters)
    loss = median_time(loss_only, iters)
    full = median_time(full_step, iters)
    return {"network": net, "loss": loss, "full": full}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", default="640x2,256x8", help="comma-separated SIZExBATCH")
    p.add_argument("--threads", default="1,2", help="comma-separated torch thread counts")
    p.add_argument("--boxes", type=int, default=20, help="ground-truth boxes per image")
    p.add_argument("--iters", type=int, default=3)
    p.add_argument("--scale", default="s")
    args = p.parse_args()
    print(f"YOLOv8{args.scale} 4-channel, nc=8, {args.boxes} boxes/image, median of {args.iters} after 1 warm-up")
    print("anchor = network forward + backward + SGD step; loss = assigner + BCE + CIoU + DFL, forward + backward")
    header = (
        f"{'input':>9} {'thr':>3} {'network s':>10} {'loss s':>8} {'loss/anchor':>12} {'full step s':>12} "
        f"{'full/anchor':>12}"
    )
    print(header)
    print("-" * len(header))
    worst = 0.0
    for cfg in args.configs.split(","):
        size, batch = (int(v) for v in cfg.lower().split("x"))
        for threads in (int(t) for t in args.threads.split(",")):
            r = measure(size, batch, threads, args.boxes, args.iters, args.scale)
            worst = max(worst, r["loss"] / r["network"])
            print(
                f"{size:>5}x{batch:<3} {threads:>3} {r['network']:>10.3f} {r['loss']:>8.3f} "
                f"{r['loss'] / r['network']:>12.3f} {r['full']:>12.3f} {r['full'] / r['network']:>12.3f}",
                flush=True,
            )
    print(
        f"target: loss/anchor <= {TARGET_LOSS:g} (the loss and assigner a small part of a step) -> "
        f"{'met' if worst <= TARGET_LOSS else 'NOT met'}"
    )


if __name__ == "__main__":
    main()
