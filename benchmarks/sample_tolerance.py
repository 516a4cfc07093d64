"""How far apart two preparations of the same dataset are: what chose the tolerance of matching across library
releases (``harness.cache.fingerprint.TOLERANCE``, docs/benchmark.md "Matching across library releases").

Give it two prepared-data folders (``<cache>/<dataset>/<key>``) of the same samples made under different package
versions or options, e.g. the default synthetic set prepared with OpenCV 5.0.0 and with 5.1.0 installed into a
folder of its own and put first on the path::

    harness prepare --dataset m3t-synth --cache /tmp/cache50
    pip install --no-deps --target /tmp/cv51 opencv-python-headless==5.1.0.95
    PYTHONPATH=/tmp/cv51 harness prepare --dataset m3t-synth --cache /tmp/cache51
    python benchmarks/sample_tolerance.py /tmp/cache50/m3t-synth/<key> /tmp/cache51/m3t-synth/<key>

It prints, exactly, how many box coordinates and pixel values differ and by how much (every picture: RGB, the aligned
temperatures, the 8-bit thermal picture, each encoding's channel), then what the shipped fingerprint measures of the
same difference and whether it lies within the tolerance.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reference", help="prepared-data folder taken as the reference")
    ap.add_argument("other", help="prepared-data folder compared with it")
    ap.add_argument("--encodings", default="c2,ir8,linear16", help="encodings whose channels are compared")
    args = ap.parse_args(argv)

    from harness.cache import fingerprint as FP
    from harness.cache.reader import PreparedDataset
    from harness.plugins import get_host

    a, b = PreparedDataset(args.reference), PreparedDataset(args.other)
    if [r["image_id"] for r in a.records] != [r["image_id"] for r in b.records]:
        print("the two folders hold other images: not the same samples", file=sys.stderr)
        return 2
    host = get_host()
    encs = [host.encoding(n) for n in args.encodings.split(",") if n]
    stats: dict[str, list[float]] = {}

    def add(name: str, x: np.ndarray | None, y: np.ndarray | None) -> None:
        if x is None or y is None:
            return
        d = np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))
        d = d[np.isfinite(d)]
        s = stats.setdefault(name, [0, 0, 0.0])
        s[0] += int((d > 0).sum())
        s[1] += int(d.size)
        s[2] = max(s[2], float(d.max()) if d.size else 0.0)

    box_changed = box_total = 0
    box_max = 0.0
    for i in range(len(a.records)):
        (ba, la), (bb, lb) = a.targets(i), b.targets(i)
        if len(la) != len(lb) or (la != lb).any():
            print(f"sample {a.records[i]['image_id']}: other labels: not the same samples", file=sys.stderr)
            return 2
        d = np.abs(ba.astype(np.float64) - bb.astype(np.float64))
        box_changed, box_total = box_changed + int((d > 0).sum()), box_total + int(d.size)
        box_max = max(box_max, float(d.max()) if d.size else 0.0)
        sa, sb = a[i], b[i]
        add("rgb", a.rgb(i), b.rgb(i))
        add("temperatures", sa.thermal, sb.thermal)
        add("ir8", sa.ir8, sb.ir8)
        for e in encs:
            add(f"enc:{e.name}", a.channel(i, e), b.channel(i, e))
    print(f"{len(a.records)} samples")
    print(f"boxes         {box_changed:>10,} of {box_total:>11,} coordinates differ, largest {box_max:.3g} px")
    for name, (changed, total, largest) in stats.items():
        share = 100 * changed / total if total else 0.0
        print(f"{name:13s} {changed:>10,} of {total:>11,} values differ ({share:.3f} %), largest {largest:g}")
    pairs = [(e, {}) for e in encs]
    planes = ["rgb", "aligned"] + [f"enc:{e.name}" for e in encs]
    diff = FP.compare(FP.compute(b, pairs), FP.compute(a, pairs), planes)
    print(f"fingerprint: {diff.describe()}")
    print(f"within the tolerance ({FP.TOLERANCE.describe()}): {'yes' if diff.within() else 'no'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
