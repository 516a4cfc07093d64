"""Does a change keep every output? The before/after check of a refactor, over the whole user path.

``run CHECKOUT OUT`` runs, with the code of CHECKOUT, what a new user runs: the synthetic set (small, seed 0), its
preparation, a demo-profile run of each built-in detector with P4+P5 held out, a report of those runs and a screen of
one flight (project P4) with ours; every output lands in OUT (one run at a time: it works in one fixed temporary
folder). ``compare A B`` then compares two such folders file by file: bytes first; a file that differs is compared
again with what records when, where or how fast it ran masked (time stamps, timings, the checkout and output paths,
keys and digests over file times); checkpoints by their tensors; command logs on stderr are skipped. Prints a summary
and each file that still differs; exits 1 if any::

    git worktree add ../before HEAD~3
    .venv/bin/python benchmarks/parity_outputs.py run ../before /tmp/parity/before     # about 80 s on 2 cores
    .venv/bin/python benchmarks/parity_outputs.py run . /tmp/parity/after
    .venv/bin/python benchmarks/parity_outputs.py compare /tmp/parity/before /tmp/parity/after

Run it twice on one checkout to see that the masks leave nothing that changes between two runs of the same code.
``benchmarks/parity_stores.py`` compares the results stores alone, number by number.
"""

from __future__ import annotations

import argparse
import difflib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

DETECTORS = ("ours", "eme", "icafusion", "cmadet")
FOLD = "P4+P5"
#: keys whose values are timings (seconds, rates, ratios of times)
TIMING_KEYS = "seconds|frames_per_s|frontend_over_model|frontend_over_model_cpu|compute|decode|align|encode|model"
MASKS = [
    (re.compile(r"\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d(\.\d+)?"), "<time>"),
    (re.compile(r"\b[0-9a-f]{16}\b|\b[0-9a-f]{40}\b"), "<digest>"),  # keys over file times, hashes of checkpoints
    (re.compile(rf'("(?:\w*_s|\w*_cpu|{TIMING_KEYS})"\s*:\s*)-?[0-9.e+-]+'), r"\1<t>"),
    (re.compile(r"\(\d+(\.\d+)? s\)"), "(<t> s)"),
    (re.compile(r"^per frame:.*$", re.M), "<per-frame timings>"),
]
#: the prepared data's folder is named by a key over the raw files' times
KEY_FOLDER = re.compile(r"^(cache/[^/]+/)[0-9a-f]{16}(/|$)")


def harness(checkout: Path, out: Path, name: str, *args: str) -> bool:
    env = {
        **os.environ,
        "PYTHONPATH": str(checkout),
        "HARNESS_DATA": str(out / "data"),
        "HARNESS_CACHE": str(out / "cache"),
        "OMP_NUM_THREADS": "1",
    }
    with open(out / f"{name}.out", "wb") as stdout, open(out / f"{name}.err", "wb") as stderr:
        rc = subprocess.call(
            [sys.executable, "-m", "harness", *args], cwd=checkout, env=env, stdout=stdout, stderr=stderr
        )
    print(f"{name}: exit {rc}", file=sys.stderr)
    return rc == 0


def run(checkout: Path, final: Path) -> int:
    """The user path with ``checkout``'s code. It runs in one fixed folder, moved to ``final`` at the end: outputs
    that carry their own path where no mask reaches (the text of a plot) then read the same for every checkout."""
    checkout, final = checkout.resolve(), final.resolve()
    if final.exists():
        raise SystemExit(f"{final} exists: give a new folder")
    out = Path(tempfile.gettempdir()) / "harness-parity-outputs"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    (out / "where.txt").write_text(f"{checkout}\n{out}\n")
    t0 = time.perf_counter()
    store = str(out / "store")
    ok = harness(checkout, out, "synth", "synth", "--size", "small", "--workers", "2", "--no-progress")
    ok &= harness(checkout, out, "prepare", "prepare", "--dataset", "m3t-synth")
    for d in DETECTORS:
        args = ["--detector", d, "--folds", FOLD, "--dataset", "m3t-synth", "--profile", "demo", "--store", store]
        ok &= harness(checkout, out, f"run-{d}", "run", *args, "--config", f"configs/demo/{d}.yaml", "--no-progress")
    ok &= harness(
        checkout, out, "report", "report", "--store", store, "--out", str(out / "report"), "--resamples", "50"
    )
    flight = out / "data" / "m3t-synth-small-seed0" / "images" / "P4"
    run_dir = out / "store" / "m3t-synth" / "ours" / "c2" / FOLD / "seed0"
    screen = ["screen", str(flight), "--run", str(run_dir), "--out", str(out / "screen"), "--no-progress"]
    ok &= harness(checkout, out, "screen", *screen)
    final.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(out, final)
    print(f"{final}: {time.perf_counter() - t0:.0f} s{'' if ok else ', with failures (see the .err files)'}")
    return 0 if ok else 1


def _mask(text: str, where: list[str]) -> str:
    for i, path in sorted(enumerate(where), key=lambda p: -len(p[1])):  # the longer first: OUT may lie in CHECKOUT
        text = text.replace(path, f"<path{i}>")
    for rx, rep in MASKS:
        text = rx.sub(rep, text)
    return text


def _tensors(obj: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    import torch

    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _tensors(v, f"{prefix}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}[{i}]")


def _same_tensors(a: Path, b: Path) -> bool:
    import torch

    ta = dict(_tensors(torch.load(a, map_location="cpu", weights_only=True)))
    tb = dict(_tensors(torch.load(b, map_location="cpu", weights_only=True)))
    return ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)


def _listing(root: Path) -> dict[str, Path]:
    return {
        KEY_FOLDER.sub(r"\1<key>\2", p.relative_to(root).as_posix()): p
        for p in root.rglob("*")
        if p.is_file() and p.suffix != ".err" and p.name not in (".last-used", "where.txt")
    }


def compare(a_root: Path, b_root: Path) -> int:
    for root in (a_root, b_root):
        if not (root / "where.txt").is_file():
            raise SystemExit(f"{root}: not a folder made by `parity_outputs.py run` (no where.txt)")
    where = [(r / "where.txt").read_text().splitlines() for r in (a_root, b_root)]
    la, lb = _listing(a_root), _listing(b_root)
    if not la or not lb:
        raise SystemExit(f"{a_root if not la else b_root}: no outputs to compare")
    bad = [f"only in {a_root if n in la else b_root}: {n}" for n in sorted(set(la) ^ set(lb))]
    same = masked = 0
    for name in sorted(set(la) & set(lb)):
        a, b = la[name].read_bytes(), lb[name].read_bytes()
        if a == b:
            same += 1
        elif name.endswith(".pt"):
            if _same_tensors(la[name], lb[name]):
                masked += 1
            else:
                bad.append(f"tensors differ: {name}")
        else:
            try:
                ma, mb = _mask(a.decode(), where[0]), _mask(b.decode(), where[1])
            except UnicodeDecodeError:
                bad.append(f"binary file differs: {name}")
                continue
            if ma == mb:
                masked += 1
            else:
                diff = list(difflib.unified_diff(ma.splitlines(), mb.splitlines(), lineterm="", n=0))[2:6]
                bad.append(f"differs: {name}: " + " | ".join(diff)[:300])
    print(f"{same} files byte-identical, {masked} identical with times, paths and keys masked, {len(bad)} differ")
    for line in bad:
        print("  " + line)
    return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("run", help="run the user path with CHECKOUT's code into OUT (a new folder)")
    r.add_argument("checkout", type=Path)
    r.add_argument("out", type=Path)
    c = sub.add_parser("compare", help="compare two folders made by run")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = ap.parse_args()
    return run(args.checkout, args.out) if args.what == "run" else compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
