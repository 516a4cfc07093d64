"""How well ``harness.box_fit`` separates boxes as given from boxes read as centres or moved to the next image.

For each prepared dataset named (cache folders, ``--prepared``) and for ``make_coco_rgbt`` folders of the tests
(``--coco N``, N pairs; prepared into a temporary cache), it measures ``box_fit.fit`` on the boxes as given and on the
same samples with two mistakes made in memory: every box written as centre x, centre y, w, h and read as x1, y1, w, h
(moved by half its size, clipped to the frame), and every image's boxes moved to the next image in image-id order
(image ids shifted by +1). One row per set and reading: the mean in-box contrast of the given boxes and of the other
reading, their ratio, on how many of the compared boxes or images the other reading is higher, whether it counts as
clearly better, and the reading ``misplaced`` reports (the finding). The last column is the median time of
``box_fit.misplaced`` on the correct set.

Usage: ``nice -n 15 python benchmarks/box_fit.py [--prepared FOLDER ...] [--coco N ...] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from _common import add_set_arguments, measured_sets, median_time, on_path

on_path("tests")


class Mistaken:
    """``prepared`` with its boxes misread in memory: ``centre`` (x1, y1 were a centre) or ``ids`` (each image holds
    the boxes of the one before it in image-id order; the first holds the last's)."""

    def __init__(self, prepared: Any, mistake: str):
        self.prepared, self.mistake, self.records = prepared, mistake, prepared.records
        order = sorted(range(len(self.records)), key=lambda i: int(self.records[i]["image_id"]))
        self.before = {order[k]: order[k - 1] for k in range(len(order))}

    def __getitem__(self, i: int) -> Any:
        return self.prepared[i]

    def targets(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        if self.mistake == "ids":
            return self.prepared.targets(self.before[i])
        boxes, labels = self.prepared.targets(i)
        b = np.asarray(boxes, np.float64).reshape(-1, 4)
        b = b + np.concatenate([b[:, 2:] - b[:, :2]] * 2, axis=1) / 2
        rec = self.records[i]
        return np.minimum(b, [rec["width"], rec["height"], rec["width"], rec["height"]]), labels


def _rows(name: str, boxes: str, data: Any, seconds: float | None) -> list[str]:
    from harness import box_fit

    found = box_fit.misplaced(data)
    ms = f"{seconds * 1000:6.0f}" if seconds is not None else ""
    out = []
    for r in box_fit.fit(data):
        out.append(
            f"{name[:22]:22s} {boxes:7s} {r.name:8s} {r.given:6.2f} {r.contrast:6.2f} "
            f"{r.contrast / max(r.given, 1e-9):5.2f} {r.higher:4d}/{r.compared:<4d} {r.share:4.0%} "
            f"{'yes' if r.better else 'no':>3s} {found.name if found else '-':>8s} {ms:>6s}"
        )
        ms = ""
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_set_arguments(ap)
    args = ap.parse_args(argv)

    from harness import box_fit

    print(
        f"{'dataset':22s} {'boxes':7s} {'reading':8s} {'given':>6s} {'other':>6s} {'ratio':>5s} {'higher':>9s} "
        f"{'shr':>4s} {'clr':>3s} {'finding':>8s} {'ms':>6s}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        sets = measured_sets(args.coco, args.prepared, Path(tmp))
        for name, data in sets:
            seconds = median_time(lambda d=data: box_fit.misplaced(d), args.repeat)
            for boxes, view in (
                ("given", data),
                ("centre", Mistaken(data, "centre")),
                ("ids+1", Mistaken(data, "ids")),
            ):
                print("\n".join(_rows(name, boxes, view, seconds if boxes == "given" else None)), flush=True)
    print(
        "given/other: mean in-box contrast of the boxes as given and as the other reading reads them; higher: boxes "
        "(centre) or images (previous, next) where the other reading's is higher; clr: clearly better (box_fit.FACTOR, "
        "MIN_GAIN, SHARE, MIN_COMPARED); finding: what box_fit.misplaced reports",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
