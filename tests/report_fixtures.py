"""Small results stores for the report tests, written the way ``harness run`` writes them: synthetic ground truth,
detections of a chosen quality, scored by ``harness.evaluation.evaluate`` (no hand-written metrics)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import pytest

from engine_helpers import run_args, set_args
from harness.io import atomic_write_json
from harness.store import RunKey, Store

CATEGORIES = ("window", "crack", "delamination", "water_seepage")
#: The example plugin's TinyDet, for tests that train real runs with a detector outside the built-ins.
TINYDET_SRC = Path(__file__).resolve().parent.parent / "plugins" / "harness-tinydet" / "src"
#: The smallest real run (``--set`` values): one epoch at 64 px, batch 8, one torch thread on the CPU.
TINY_RUN = [
    "protocol.imgsz=64",
    "protocol.epochs=1",
    "protocol.patience=5",
    "train.batch=8",
    "train.nominal_batch=8",
    "train.warmup_epochs=0.5",
    "train.close_mosaic=0",
    "train.threads=1",
    "train.device=cpu",
    "eval.batch=16",
]


def cli(args: list[str], code: int = 0) -> str:
    """``harness ARGS`` run in this process: its output, once its exit code is checked against ``code``."""
    from click.testing import CliRunner

    from harness.cli import get_cli

    res = CliRunner().invoke(get_cli(), args, catch_exceptions=False)
    assert res.exit_code == code, f"harness {' '.join(args)} exited {res.exit_code}:\n{res.output}"
    return res.output


@contextlib.contextmanager
def tinydet_on_path(root: Path, **env: str) -> Iterator[None]:
    """For a fixture that trains real runs: the example TinyDet importable (the test is skipped where it is not in
    this checkout), a prepared-data cache of its own in ``root / "cache"`` and the environment variables ``env``, all
    undone when the block ends."""
    if not TINYDET_SRC.is_dir():
        pytest.skip("the example TinyDet plugin is not in this checkout")
    mp = pytest.MonkeyPatch()
    mp.setenv("HARNESS_CACHE", str(root / "cache"))
    for name, value in env.items():
        mp.setenv(name, value)
    mp.syspath_prepend(str(TINYDET_SRC))
    try:
        yield
    finally:
        mp.undo()


@contextlib.contextmanager
def tiny_run(tiny_source: Path, root: Path, fold: str, tag: str) -> Iterator[Path]:
    """TinyDet trained by ``harness run`` (``TINY_RUN``) on the tiny synthetic M3T set at ``tiny_source`` with
    ``fold`` held out, stored in ``root / "store"``: its run folder, with the plugin registered (as ``tinydet-<tag>``,
    see ``tinydet_on_path``) until the block ends."""
    with tinydet_on_path(root):
        import harness_tinydet.plugin as tinydet

        from harness.testing import temporary_plugin

        with temporary_plugin(tinydet, name=f"tinydet-{tag}"):
            store = root / "store"
            cli(run_args("tinydet", "m3t-synth", fold, store, *set_args([*TINY_RUN, f"dataset.root={tiny_source}"])))
            yield store / "m3t-synth" / "tinydet" / "c2" / fold / "seed0"


CHROMIUM = Path("/usr/bin/chromium")
#: A test that opens a report in Debian's headless Chromium: skipped where it is not installed.
needs_chromium = pytest.mark.skipif(
    not CHROMIUM.exists() or not sys.platform.startswith("linux"),
    reason="Debian's chromium is not installed (apt-get install chromium; .ci/run installs it)",
)


def chromium_screenshot(
    page: Path, shot: Path, profile_dir: Path, size: str = "1400,5200"
) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Open ``page`` headless, screenshot it into ``shot``; the finished process and the page's console messages."""
    cmd = [
        str(CHROMIUM),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={profile_dir}",
        "--enable-logging=stderr",
        "--v=0",
        "--hide-scrollbars",
        f"--window-size={size}",
        f"--screenshot={shot}",
        page.resolve().as_uri(),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
    return proc, [ln for ln in proc.stderr.splitlines() if ":CONSOLE" in ln]


def make_gt(
    n_images: int,
    rng: np.random.Generator,
    first_id: int = 1,
    categories: Sequence[str] = CATEGORIES,
    objects: tuple[int, int] = (1, 4),
    size: tuple[int, int] = (160, 128),
    skip_category: str | None = None,
) -> dict[str, Any]:
    """COCO ground truth in the harness's convention (category_id = label + 1)."""
    w, h = size
    images, anns = [], []
    for k in range(n_images):
        iid = first_id + k
        images.append({"id": iid, "width": w, "height": h, "file_name": f"img{iid:04d}.jpg"})
        for _ in range(int(rng.integers(objects[0], objects[1] + 1))):
            label = int(rng.integers(0, len(categories)))
            if skip_category is not None and categories[label] == skip_category:
                label = (label + 1) % len(categories)
            bw, bh = float(rng.uniform(12, 40)), float(rng.uniform(12, 40))
            x, y = float(rng.uniform(0, w - bw)), float(rng.uniform(0, h - bh))
            anns.append(
                {
                    "id": len(anns) + 1,
                    "image_id": iid,
                    "category_id": label + 1,
                    "bbox": [x, y, bw, bh],
                    "area": bw * bh,
                    "iscrowd": 0,
                }
            )
    return {
        "info": {"dataset": "synthetic", "frame": "thermal"},
        "images": images,
        "annotations": anns,
        "categories": [{"id": i + 1, "name": n} for i, n in enumerate(categories)],
    }


def make_detections(
    gt: dict[str, Any],
    rng: np.random.Generator,
    recall: float = 0.9,
    jitter: float = 1.0,
    false_positives: float = 1.0,
    label_noise: float = 0.0,
) -> list[dict[str, Any]]:
    """Detections of a given quality: each GT found with probability ``recall`` (box jittered by ``jitter`` px,
    score 0.5..1), plus on average ``false_positives`` random boxes per image (score 0..0.6)."""
    ncat = len(gt["categories"])
    dets = []
    for a in gt["annotations"]:
        if rng.random() < recall:
            x, y, w, h = a["bbox"]
            cat = a["category_id"] if rng.random() >= label_noise else int(rng.integers(1, ncat + 1))
            dets.append(
                {
                    "image_id": a["image_id"],
                    "category_id": cat,
                    "bbox": [
                        x + rng.normal(0, jitter),
                        y + rng.normal(0, jitter),
                        max(1.0, w + rng.normal(0, jitter)),
                        max(1.0, h + rng.normal(0, jitter)),
                    ],
                    "score": float(rng.uniform(0.5, 1.0)),
                }
            )
    for im in gt["images"]:
        for _ in range(int(rng.poisson(false_positives))):
            w, h = float(rng.uniform(10, 40)), float(rng.uniform(10, 40))
            dets.append(
                {
                    "image_id": im["id"],
                    "category_id": int(rng.integers(1, ncat + 1)),
                    "bbox": [float(rng.uniform(0, im["width"] - w)), float(rng.uniform(0, im["height"] - h)), w, h],
                    "score": float(rng.uniform(0.0, 0.6)),
                }
            )
    return dets


def complexity_record(
    params: float, gflops: float, options: dict[str, Any] | None = None, imgsz: int = 64
) -> dict[str, Any]:
    """A ``metrics.json`` complexity record as ``harness run`` measures it (paper/exact GFLOPs at 640 and imgsz)."""
    return {
        "schema": 1,
        "model_options": dict(options or {}),
        "num_classes": len(CATEGORIES),
        "input_kind": "single",
        "in_channels": 4,
        "imgsz": imgsz,
        "params": int(params),
        "params_fused": int(params),
        "bn_folded": True,
        "trainable": int(params),
        "unused_params": 0,
        "gflops": {
            str(imgsz): {"paper": gflops / 100, "exact": gflops / 99},
            "640": {"paper": gflops, "exact": gflops * 1.01},
        },
    }


def write_run(
    store: Store,
    key: RunKey,
    gt: dict[str, Any],
    dets: list[dict[str, Any]],
    imgsz: int = 64,
    complexity: dict[str, Any] | None = None,
    analysis: bool = True,
) -> dict[str, Any]:
    """Score ``dets`` against ``gt`` and write the run's folder as the engine does (status last); ``analysis``:
    store its error analysis too (``analysis.json``), as every run since it existed does."""
    from harness.evaluation import evaluate
    from harness.evaluation.analysis import store_analysis

    run = store.run(key)
    run.path.mkdir(parents=True, exist_ok=True)
    run.set_status("running", config_hash="synthetic")
    ev = evaluate(gt, dets)
    atomic_write_json(run.predictions_path, dets, indent=None)
    atomic_write_json(run.gt_path, gt, indent=None)
    run.write_metrics(
        {
            **ev,
            "model": {"params": 1000},
            "train": {"epochs": 1, "imgsz": imgsz},
            **({"complexity": complexity} if complexity else {}),
            "environment": {"device": "cpu", "threads": 1, "torch": "test"},
        }
    )
    if analysis:
        store_analysis(run, gt, dets, {}, ev["metrics"]["conf_threshold"])
    run.set_status("finished", config_hash="synthetic")
    return run.read_metrics()


QUALITY = {
    "strong": {"recall": 0.95, "jitter": 0.5, "false_positives": 0.3},
    "medium": {"recall": 0.75, "jitter": 2.0, "false_positives": 1.0, "label_noise": 0.1},
    "weak": {"recall": 0.45, "jitter": 3.0, "false_positives": 2.0, "label_noise": 0.3},
}


def synthetic_store(
    root: Path,
    dataset: str = "synth",
    folds: Sequence[str] = ("P1", "P2"),
    per_fold: int = 6,
    detectors: dict[str, str] | None = None,
    encodings: dict[str, Sequence[str]] | None = None,
    seed: int = 0,
    profiles: dict[str, tuple[float, float]] | None = None,
    seeds: Sequence[int] = (0,),
    analysis: bool = True,
) -> Store:
    """A store with ``detectors`` ({name: quality}) on every fold and training seed (``seeds``: each seed's
    detections an independent draw of the same quality), optionally extra encodings of a detector on the last fold
    (``encodings``: {detector: [enc, ...]}), and profiles ({detector: (params, gflops)})."""
    store = Store(root)
    detectors = detectors or {"alpha": "strong", "beta": "weak"}
    rng = np.random.default_rng(seed)
    gts = {}
    first = 1
    for f in folds:
        gts[f] = make_gt(per_fold, rng, first_id=first, skip_category="water_seepage" if f == folds[0] else None)
        first += per_fold
    for i, (det, quality) in enumerate(detectors.items()):
        for f in folds:
            for s in seeds:
                drng = np.random.default_rng([seed, i, folds.index(f)] + ([s] if s else []))
                comp = complexity_record(*profiles[det]) if det in (profiles or {}) else None
                write_run(
                    store,
                    RunKey(dataset, det, "c2", f, s),
                    gts[f],
                    make_detections(gts[f], drng, **QUALITY[quality]),
                    complexity=comp,
                    analysis=analysis,
                )
    for det, encs in (encodings or {}).items():
        for j, enc in enumerate(encs):
            drng = np.random.default_rng([seed, 100 + j])
            q = QUALITY["weak"] if j % 2 else QUALITY["strong"]
            comp = complexity_record(*profiles[det]) if det in (profiles or {}) else None
            write_run(
                store,
                RunKey(dataset, det, enc, folds[-1], 0),
                gts[folds[-1]],
                make_detections(gts[folds[-1]], drng, **q),
                complexity=comp,
                analysis=analysis,
            )
    return store
