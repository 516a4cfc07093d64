"""How well the input guard's ``mismatched-pairs`` check separates correct RGB-thermal pairs from pairs shifted by one.

For each prepared dataset named (cache folders, ``--prepared``) and for ``make_coco_rgbt`` folders of the tests
(``--coco N``, N pairs; prepared into a temporary cache), it measures ``harness.input_guard.pair_summary`` on the
pairs as given and on the same samples with every thermal frame replaced by the next sample's of the same size
(in memory, the ``pairs-shifted-by-one`` mistake), by the one 2 and 5 on, and by a random one, and prints a row
each: the samples compared, the median edge agreement of the given pairs, of the other pairings and of each RGB
frame's best other thermal frame, the share of samples beaten (the finding needs more than ``MAX_BEATEN``), whether
the guard finds ``mismatched-pairs``, and the median time of the check on the correct set.

Usage: ``nice -n 15 python benchmarks/pair_agreement.py [--prepared FOLDER ...] [--coco N ...] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from _common import add_set_arguments, measured_sets, median_time, on_path

on_path("tests")


class Shifted:
    """``prepared`` with every sample's thermal frame (temperatures and 8-bit) taken from another sample of the same
    frame size: the sample ``shift`` places on in record order (wrapping round), or with ``shift=0`` one of a random
    permutation (seed 0)."""

    def __init__(self, prepared: Any, shift: int = 1):
        import numpy as np

        self.prepared, self.records = prepared, prepared.records
        sizes: dict[tuple[int, int], list[int]] = {}
        for i, rec in enumerate(self.records):
            sizes.setdefault((rec["height"], rec["width"]), []).append(i)
        rng = np.random.default_rng(0)
        self.next: dict[int, int] = {}
        for idx in sizes.values():
            k = shift % len(idx)
            other = idx[k:] + idx[:k] if shift else [idx[k] for k in rng.permutation(len(idx))]
            self.next.update(zip(idx, other))

    def __getitem__(self, i: int) -> Any:
        own, other = self.prepared[i], self.prepared[self.next[i]]
        return dataclasses.replace(own, thermal=other.thermal, ir8=other.ir8)


def _row(name: str, pairing: str, data: Any, seconds: float | None) -> str:
    from harness.input_guard import _pair_findings, pair_summary

    s = pair_summary(data)
    found = "yes" if _pair_findings(data) else "no"
    med = {k: statistics.median(s[k]) if s[k] else float("nan") for k in ("own", "shuffled", "best_other")}
    share = len(s["beaten"]) / s["compared"] if s["compared"] else float("nan")
    ms = f"{seconds * 1000:7.0f}" if seconds is not None else "       "
    return (
        f"{name[:24]:24s} {pairing:7s} {s['compared']:4d} {med['own']:6.2f} {med['shuffled']:6.2f} "
        f"{med['best_other']:6.2f} {share:6.0%} {found:>5s} {ms}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_set_arguments(ap)
    args = ap.parse_args(argv)

    from harness.input_guard import _pair_findings

    print(
        f"{'dataset':24s} {'pairs':7s} {'cmp':>4s} {'own':>6s} {'other':>6s} {'best':>6s} {'beaten':>6s} "
        f"{'found':>5s} {'ms':>7s}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        sets = measured_sets(args.coco, args.prepared, Path(tmp))
        for name, data in sets:
            seconds = median_time(lambda d=data: _pair_findings(d), args.repeat)
            print(_row(name, "given", data, seconds), flush=True)
            for pairing, shift in (("shift 1", 1), ("shift 2", 2), ("shift 5", 5), ("random", 0)):
                print(_row(name, pairing, Shifted(data, shift), None), flush=True)
    for line in (
        "cmp: samples compared; own, other, best: median edge agreement r of the given pairs, of the other",
        "pairings and of each RGB frame's best other thermal frame; beaten: share of the compared samples",
        "beaten by another pairing (harness.input_guard.pair_statistics); found: mismatched-pairs found",
    ):
        print(line, file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
