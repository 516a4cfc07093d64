"""Loader throughput per worker for each prepared-cache form at 640x512, against the raw memory-mapped cache and
against one training step of "ours".

Data (written once under --data, default /tmp/bench-cache-forms):
  * radiometric: m3t-synth at thermal 640x512 (16 pairs of a benchmark-only profile, R-JPEG thermal), prepared
    ``raw`` (anchor) and ``compact`` (PNG RGB/8-bit thermal, exact temperature tables); encoding ``c2``;
  * 8-bit: an RGBT-Tiny-layout folder of 640x512 JPEG pairs (the test fixture's writer), prepared ``raw`` and
    ``compact`` (which references the JPEG files: decode + digest check the first time a process loads a sample);
    encoding ``proxy8``.

Per worker = one process, one OpenCV and one torch thread, as a DataLoader worker runs. Figures per form:
``read`` = what ``SampleSource.image`` + ``targets`` hand over (RGB + the encoding's channel); ``item 160`` and
``item 640`` = ``TrainDataset[k]`` at the smoke and paper image sizes with the default augmentation (a mosaic reads
four samples). Anchor: the raw form's figure measured in the same run. Then one CPU training step of "ours"
(YOLOv8s, 4 channels, forward + loss + backward + SGD) at the smoke (160 px) and paper (640 px) image sizes, as
seconds per image, and the ratio
"images one loader worker delivers while the CPU trains on one image".

    .venv/bin/python benchmarks/bench_cache_forms.py                  # the README figures
    .venv/bin/python benchmarks/bench_cache_forms.py --repeat 5 --no-train-step
"""

from __future__ import annotations

import argparse
import contextlib
import os
from pathlib import Path

from _common import median_time, on_path

on_path("tests", "benchmarks")

from harness.cache import forms as CF  # noqa: E402

#: The run profiles' image sizes (configs/profiles/*.yaml: protocol.imgsz).
SIZES = {"smoke": 160, "paper": 640}
#: A compact form's rate of paper-size (640) training items against the raw form's (0.41x-0.87x when introduced).
TARGET_VS_RAW = 0.4


def _size(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


@contextlib.contextmanager
def _codec(codec: str):
    """Prepare with the given 8-bit codec (the default is zstd when installed, else png)."""
    saved = CF.default_u8_codec
    CF.default_u8_codec = lambda: codec  # type: ignore[assignment]
    try:
        yield
    finally:
        CF.default_u8_codec = saved  # type: ignore[assignment]


def _datasets(data: Path, cache: Path):
    from adapters.datasets import synthetic as S
    from eightbit_fixtures import write_rgbt_tiny
    from harness.cache import prepare
    from harness.config import load_config

    S.PROFILES.setdefault(
        "bench640",
        S.Profile(
            "bench640",
            (4, 4, 4, 2, 2),
            (640, 512),
            (2000, 1500),
            (1, 1, 1, 1, 1),
            description="loader benchmark: 16 pairs",
        ),
    )
    m3t_root = data / "m3t-synth-bench640"
    if not m3t_root.exists():
        S.generate(m3t_root, profile="bench640", seed=0, workers=1, progress=False)
    rgbt_root = data / "rgbt-tiny-640"
    if not rgbt_root.exists():
        write_rgbt_tiny(
            rgbt_root, train_seqs=("DJI_0001_1", "DJI_0002_1"), test_seqs=("DJI_0101_1",), frames=4, size=(640, 512)
        )
    cfg = load_config(protocol="m3t-4fold")
    cfg["dataset"] = {"root": str(m3t_root), "profile": "bench640"}
    rcfg = load_config(protocol="rgbt-tiny", overrides=[f"dataset.root={rgbt_root}"])
    out = []
    for name, dataset, c, enc, src in (
        ("m3t-synth 640x512", "m3t-synth", cfg, "c2", m3t_root),
        ("RGBT-Tiny layout 640x512", "rgbt-tiny", rcfg, "proxy8", rgbt_root / "images"),
    ):
        forms = {"raw": prepare(dataset, c, cache_root=cache / "raw", progress=False, form="raw")}
        for codec in CF.U8_CODECS:
            if codec == "png" or CF.default_u8_codec() == "zstd":
                with _codec(codec):
                    forms[f"compact/{codec}"] = prepare(dataset, c, cache_root=cache / codec, progress=False)
        out.append((name, enc, forms, src))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/bench-cache-forms"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--step-batch", type=int, default=2, help="images per timed CPU train step (per-image figure)")
    ap.add_argument("--no-train-step", action="store_true")
    args = ap.parse_args()

    import cv2
    import torch

    from harness.encodings import ENCODINGS
    from harness.engine.data import AugmentSettings, SampleSource, TrainDataset

    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    encs = {e.name: e for e in ENCODINGS}
    sets = _datasets(args.data, args.data / "cache")
    print(f"{os.cpu_count()} CPU(s); per worker = 1 process, 1 thread; median of {args.repeat} passes")
    print(
        f"{'':<25} {'':<12} {'':>8} {'':>6} {'read':>9} {'':>6}"
        + "".join(f" {f'item {s}':>9} {'':>6}" for s in SIZES.values())
    )
    print(
        f"{'data':<25} {'form':<12} {'size MB':>8} {'x src':>6} {'/s':>9} {'x raw':>6}"
        + "".join(f" {'/s':>9} {'x raw':>6}" for _ in SIZES)
    )
    worst: dict[str, tuple[float, str]] = {}
    worst_ratio: dict[str, float] = {}  # per compact set: its paper-size training-item rate as a share of raw's
    for name, enc_name, forms, src in sets:
        enc = encs[enc_name]
        src_bytes = sum(p.stat().st_size for p in src.rglob("*") if p.is_file())
        anchor = {}
        for form in forms:
            ds = forms[form]
            source = SampleSource(ds, encoding=enc)
            source.warm()
            n = len(source)

            def read() -> None:
                for k in range(n):
                    source.image(k)
                    source.targets(k)

            t = {"read": median_time(read, args.repeat)}
            for size in SIZES.values():
                train = TrainDataset(source, size, AugmentSettings(), seed=0)

                def items() -> None:
                    for k in range(n):
                        train[k]

                t[size] = median_time(items, args.repeat)
            if form == "raw":
                anchor = t
            nbytes = _size(ds.folder)
            cells = "".join(f" {n / t[k]:>9.1f} {anchor[k] / t[k]:>6.2f}" for k in t)
            print(f"{name:<25} {form:<12} {nbytes / 1e6:>8.1f} {nbytes / src_bytes:>6.2f}{cells}", flush=True)
            if form != "raw":
                worst_ratio[f"{name}, {form}"] = anchor[SIZES["paper"]] / t[SIZES["paper"]]
            for profile, size in SIZES.items():
                if form != "raw" and (profile not in worst or n / t[size] < worst[profile][0]):
                    worst[profile] = (n / t[size], f"{name}, {form}")
    print("x src: cache bytes / source bytes (m3t: every file of the dataset folder; RGBT-Tiny: images/)")
    slowest = min(worst_ratio, key=worst_ratio.get, default="")
    ratio = worst_ratio.get(slowest, float("nan"))
    print(
        f"target: every compact form >= {TARGET_VS_RAW:g}x the raw form's rate of paper-size training items -> "
        f"{'met' if ratio >= TARGET_VS_RAW else 'NOT met'} (slowest {ratio:.2f}x: {slowest})"
    )
    if args.no_train_step:
        return
    from ours_train_step import measure

    print(f"\nCPU train step of ours (YOLOv8s, 4 ch, {args.step_batch} images/step, 20 boxes/image, 1 thread)")
    for profile, size in SIZES.items():
        r = measure(size, args.step_batch, 1, 20, max(1, args.repeat - 1), "s")
        per_img = r["full"] / args.step_batch
        rate, which = worst[profile]
        print(
            f"{profile} (imgsz {size}): {per_img:.3f} s/image on this CPU; meanwhile one loader worker delivers "
            f"{rate * per_img:,.1f} items\n  (slowest compact set: {which}; 8 workers: {8 * rate * per_img:,.0f})",
            flush=True,
        )


if __name__ == "__main__":
    main()
