"""Writing an RGBT-Tiny-like set in the release's layout: sequences rendered in parallel, the four COCO files, the
split lists, the README and ``synth.json``; atomically (a temporary folder renamed into place)."""

from __future__ import annotations

import logging
import os
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from adapters.datasets.synthetic_tiny.model import CATEGORIES, Plan, coco_documents, get_profile, plan_dataset
from adapters.datasets.synthetic_tiny.rendering import COLUMN_C, make_backdrop, render_frame
from harness.errors import DataError
from harness.progress import bar as progress_bar

log = logging.getLogger(__name__)

GENERATOR = "rgbt-tiny-synth"
#: Bumped whenever the generator's output changes for the same profile and seed.
GENERATOR_VERSION = 1
MARKER = "synth.json"
ENV_DATA = "HARNESS_DATA"
JPEG_QUALITY = 92


def default_root(profile: str = "small", seed: int = 0) -> Path:
    """Where the set goes when no folder is given: ``$HARNESS_DATA`` or ``./data``."""
    return Path(os.environ.get(ENV_DATA) or "data") / f"{GENERATOR}-{profile}-seed{seed}"


@dataclass
class TinySynthSummary:
    root: Path
    profile: str
    seed: int
    sequences: dict[str, int]  # per split
    pairs: dict[str, int]  # per split
    annotations: dict[str, dict[str, int]]  # modality ("visible"/"thermal") -> category -> count
    seconds: float

    def table(self) -> str:
        from harness.textable import text_table

        rows = [[c, f"{self.annotations['thermal'][c]:,}", f"{self.annotations['visible'][c]:,}"] for c in CATEGORIES]
        rows.append(
            [
                "total",
                f"{sum(self.annotations['thermal'].values()):,}",
                f"{sum(self.annotations['visible'].values()):,}",
            ]
        )
        return text_table(["category", "thermal (01) boxes", "visible (00) boxes"], rows, "lrr")


def _encode(img: np.ndarray) -> bytes:
    import cv2

    if img.ndim == 3:
        img = np.ascontiguousarray(img[:, :, ::-1])
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:  # pragma: no cover
        raise DataError("could not encode a synthetic frame")
    return enc.tobytes()


@dataclass(frozen=True)
class _Task:
    root: str
    profile: str
    seed: int
    sequence: int


_PLANS: dict[str, Any] = {}


def _render_sequence(task: _Task) -> int:
    """Render and write one sequence's frames (both modalities); every draw comes from the sequence's own seeds."""
    if _PLANS.get("key") != (task.profile, task.seed):
        _PLANS.update(key=(task.profile, task.seed), plan=plan_dataset(task.profile, task.seed))
    plan = _PLANS["plan"]
    prof = plan.profile
    seq = plan.sequences[task.sequence]
    rng = np.random.default_rng(np.random.SeedSequence((task.seed, 1, seq.index)))
    backdrop = make_backdrop(seq, prof.size, prof.frames, rng)
    columns = rng.normal(0, COLUMN_C, prof.size[0]).astype(np.float32)
    folder = Path(task.root) / "images" / seq.name
    for mdir in ("00", "01"):
        (folder / mdir).mkdir(parents=True, exist_ok=True)
    for t in range(prof.frames):
        frng = np.random.default_rng(np.random.SeedSequence((task.seed, 2, seq.index, t)))
        rgb, ir8 = render_frame(seq, backdrop, t, prof.size, columns, frng)
        (folder / "00" / f"{t:05d}.jpg").write_bytes(_encode(rgb))
        (folder / "01" / f"{t:05d}.jpg").write_bytes(_encode(ir8))
    return prof.frames


def _run(tasks: list[_Task], workers: int, progress: bool, label: str, frames: int) -> None:
    with progress_bar(label, frames * len(tasks), enabled=progress, eta=True, transient=False) as bar:
        if workers <= 1 or len(tasks) <= 1:
            for task in tasks:
                bar.advance(_render_sequence(task))
            return
        import multiprocessing
        from concurrent.futures import as_completed

        from harness.workers import worker_pool  # workers ignore Ctrl-C: the parent stops them, no tracebacks

        ctx = multiprocessing.get_context("spawn")
        with worker_pool(min(workers, len(tasks)), mp_context=ctx) as pool:
            futures = [pool.submit(_render_sequence, t) for t in tasks]
            try:
                for fut in as_completed(futures):
                    bar.advance(fut.result())
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise


def generate(
    out: str | Path | None = None,
    profile: str = "small",
    seed: int = 0,
    force: bool = False,
    progress: bool = True,
    workers: int | None = None,
) -> TinySynthSummary:
    """Write the RGBT-Tiny-like set to ``out`` (default ``$HARNESS_DATA/rgbt-tiny-synth-<profile>-seed<seed>``).

    ``workers``: processes rendering sequences in parallel (default: up to 4, at most the CPU count; 1 renders
    in this process). The files do not depend on it.
    """
    from harness.io import atomic_folder

    prof = get_profile(profile)
    out = Path(out) if out is not None else default_root(profile, seed)
    if out.exists() and any(out.iterdir()) and not force:
        raise DataError(f"{out} already exists and is not empty; pass --force to replace it, or choose --out")
    if workers is None:
        workers = 1 if prof.total <= 32 else min(4, os.cpu_count() or 1)
    t_start = time.perf_counter()
    with atomic_folder(out) as tmp:
        plan = plan_dataset(prof, seed)
        tasks = [_Task(str(tmp), prof.name, seed, s.index) for s in plan.sequences]
        _run(tasks, max(1, int(workers)), progress, f"generating {GENERATOR} ({prof.name})", prof.frames)
        summary = _write_files(tmp, plan)
    summary.root = out
    summary.seconds = time.perf_counter() - t_start
    log.info("generated %d synthetic RGBT-Tiny-like pairs in %s (%.1f s)", prof.total, out, summary.seconds)
    return summary


def _write_files(root: Path, plan: Plan) -> TinySynthSummary:
    from harness.io import atomic_write_json, atomic_write_text

    prof, seed = plan.profile, plan.seed
    docs = coco_documents(plan)
    for (mdir, split), doc in docs.items():
        atomic_write_json(root / "annotations_coco" / f"instances_{mdir}_{split}2017.json", doc, indent=None)
    for split in ("train", "test"):
        for mdir in ("00", "01"):
            lines = [im["file_name"].rsplit(".", 1)[0] for im in docs[mdir, split]["images"]]
            atomic_write_text(root / "data_split" / f"{mdir}_{split}.txt", "\n".join(lines) + "\n")
        lines = [im["file_name"].rsplit(".", 1)[0] for im in docs["00", split]["images"]]
        atomic_write_text(root / "data_split" / f"{split}.txt", "\n".join(lines) + "\n")
    atomic_write_json(root / "ground_truth" / "sequences.json", sequences_record(plan))
    counts: dict[str, dict[str, int]] = {}
    for modality, mdir in (("visible", "00"), ("thermal", "01")):
        c = Counter(a["category_id"] for s in ("train", "test") for a in docs[mdir, s]["annotations"])
        counts[modality] = {name: int(c[i]) for i, name in enumerate(CATEGORIES)}
    sequences = {s: sum(1 for q in plan.sequences if q.spec.split == s) for s in ("train", "test")}
    pairs = {s: n * prof.frames for s, n in sequences.items()}
    atomic_write_text(
        root / "README.md",
        _README.format(
            profile=prof.name,
            seed=seed,
            n=prof.total,
            w=prof.size[0],
            h=prof.size[1],
            train=sequences["train"],
            test=sequences["test"],
        ),
    )
    atomic_write_json(
        root / MARKER,
        {
            "generator": GENERATOR,
            "generator_version": GENERATOR_VERSION,
            "profile": prof.name,
            "seed": seed,
            "size": list(prof.size),
            "sequences": sequences,
            "pairs": pairs,
            "annotations": counts,
        },
    )
    return TinySynthSummary(root, prof.name, seed, sequences, pairs, counts, 0.0)


def sequences_record(plan: Plan) -> list[dict[str, Any]]:
    """What a real release cannot contain (``ground_truth/sequences.json``; no adapter reads it): each sequence's
    scene, light, registration offset and camera motion, and each track's category, size bin, visibility in the
    two modalities and thermal signature."""
    out = []
    for seq in plan.sequences:
        out.append(
            {
                "name": seq.name,
                "split": seq.spec.split,
                "scene": seq.spec.scene,
                "light": seq.spec.light,
                "registration_offset_px": [round(v, 3) for v in seq.offset],
                "pan_px_per_frame": [round(v, 3) for v in seq.pan],
                "tracks": [
                    {
                        "track_id": tr.id,
                        "category": tr.category,
                        "size_bin": tr.size_bin,
                        "size_px": [round(v, 2) for v in tr.size],
                        "in_thermal": tr.thermal,
                        "in_visible": tr.visible,
                        "parallax_px": [round(v, 3) for v in tr.parallax],
                        "warmth_c": round(tr.warmth, 3),
                        "halo_sigma_per_size": round(tr.halo, 3),
                        "halo_share": round(tr.halo_share, 3),
                    }
                    for tr in seq.tracks
                ],
            }
        )
    return out


_README = """\
# rgbt-tiny-synth ({profile}, seed {seed}): {n} synthetic RGBT-Tiny-like visible-thermal pairs

Generated by `harness synth --family rgbt-tiny`; laid out like the unpacked RGBT-Tiny release ({w}x{h}, both
modalities; {train} train / {test} test sequences), so `harness prepare --dataset rgbt-tiny --root THIS` reads it
with the real release's adapter. `images/<SEQ>/00/` holds the visible frames and `01/` the 8-bit thermal frames;
`annotations_coco/instances_00_*` the visible annotations and `instances_01_*` the thermal ones, which differ as in
the release (a registration offset of a few pixels, objects seen in one modality only).
`ground_truth/sequences.json` holds what a real release cannot (each track's visibility, signature, offsets); the
adapter never reads it. It is a stand-in for checking the pipeline and comparing detectors, not the real data.
"""
