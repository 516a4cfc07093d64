"""Files per second of ``harness sensing decode`` over a folder of real 640x512 M3T R-JPEGs, in one run.

The folder holds ``--files`` hard links (copies where links are refused) of one real M3T file. Timed, in the same
run and in an order rotating round by round: the previous sequential loop (read, correct, write the temperature
PNG and its sidecar, file after file, as the command did before batches; the anchor), ``decode_batch`` with one
worker (same work plus the temporary-name writes), and ``decode_batch`` with ``--workers`` processes. Each writes
into a fresh output folder. The sum of decoded files is checked.

    .venv/bin/python benchmarks/bench_decode_batch.py [--files 40] [--workers 2] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parent.parent
DEFAULT_FRAME = REPO.parent / "shared" / "data" / "dji-m3t-rjpeg" / "m3t_a.jpg"


def sequential_anchor(files: list[Path], out: Path) -> int:
    """The command's loop before batches: one file after another, no temporary names."""
    from harness.sensing.radiometry import read_rjpeg, rjpeg_temperature, write_thermal

    for path in files:
        rj = read_rjpeg(path)
        t, info = rjpeg_temperature(rj)
        write_thermal(
            out / f"{path.stem}.png",
            t,
            unit="centikelvin",
            params=rj.params,
            extra={"source": str(path), "decoder_route": rj.decoder},
        )
    return len(files)


#: 1 worker: the loop's work plus temporary-name writes; more workers must pay for their start-up.
TARGET_ONE, TARGET_MANY = 0.8, 1.2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frame", type=Path, default=DEFAULT_FRAME, help="a real M3T R-JPEG")
    args = ap.parse_args(argv)
    if not args.frame.exists():
        print(f"{args.frame} not found; give --frame", file=sys.stderr)
        return 2
    from harness.sensing.batch import decode_batch

    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        folder = tmp / "flight"
        folder.mkdir()
        for i in range(args.files):
            target = folder / f"DJI_{i:04d}_T.JPG"
            try:
                os.link(args.frame, target)
            except OSError:
                shutil.copyfile(args.frame, target)
        files = sorted(folder.iterdir())
        runs = {
            "anchor: sequential loop (before)": lambda out: sequential_anchor(files, out),
            "decode_batch, 1 worker": lambda out: len(decode_batch([folder], out, workers=1).decoded),
            f"decode_batch, {args.workers} workers": lambda out: len(
                decode_batch([folder], out, workers=args.workers).decoded
            ),
        }
        names = list(runs)
        times: dict[str, list[float]] = {n: [] for n in names}
        for k in range(args.rounds):
            for name in names[k % 3 :] + names[: k % 3]:
                out = tmp / f"out-{k}-{names.index(name)}"
                out.mkdir()
                t0 = time.perf_counter()
                done = runs[name](out)
                times[name].append(time.perf_counter() - t0)
                if done != args.files:
                    print(f"{name}: decoded {done} of {args.files}", file=sys.stderr)
                    return 1
                shutil.rmtree(out)
    anchor = statistics.median(times[names[0]])
    print(
        f"Decoding {args.files} real 640x512 M3T R-JPEGs ({args.frame.name}), {args.rounds} rounds, "
        f"{os.cpu_count()} CPU(s)"
    )
    print(f"  {'route':<36} {'median s':>9} {'files/s':>8} {'vs anchor':>10}")
    for name in names:
        med = statistics.median(times[name])
        print(f"  {name:<36} {med:>9.2f} {args.files / med:>8.1f} {anchor / med:>9.2f}x")
    one, many = (anchor / statistics.median(times[n]) for n in names[1:3])
    print(
        f"target: 1 worker >= {TARGET_ONE:g}x the loop (it pays for atomic writes), {args.workers} workers >= "
        f"{TARGET_MANY:g}x -> {'met' if one >= TARGET_ONE and many >= TARGET_MANY else 'NOT met'} "
        f"(needs {args.workers} idle cores)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
