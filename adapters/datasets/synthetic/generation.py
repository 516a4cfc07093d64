"""Writing a generated dataset: the plan of inspection groups and chunks, parallel rendering, the raw M3T layout
(JPEGs, R-JPEGs or temperature files, annotations, landmarks, calibration, manifest) and the ground truth."""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from adapters.datasets.synthetic.geometry import (
    Rig,
    Session,
    canvas_for_session,
    make_session,
    project_box_to_rgb,
    rgb_render_maps,
    undistort_points_dense,
)
from adapters.datasets.synthetic.profiles import LOOKS, PROFILES, PROJECTS, Profile, get_profile
from adapters.datasets.synthetic.rendering import pick_landmarks, render_frame
from harness.errors import DataError
from harness.progress import bar as progress_bar

log = logging.getLogger(__name__)

#: Bumped whenever the generator's output changes for the same profile and seed.
GENERATOR_VERSION = 2
#: File at the root of a generated dataset: generator version, profile, seed, counts (the adapter ignores it).
MARKER = "synth.json"
ENV_DATA = "HARNESS_DATA"


def default_root(profile: str = "small", seed: int = 0, thermal_format: str = "rjpeg") -> Path:
    """Where ``m3t-synth`` lives when no root is given: ``$HARNESS_DATA`` or ``./data``."""
    base = Path(os.environ.get(ENV_DATA) or "data")
    suffix = "" if thermal_format == "rjpeg" else f"-{thermal_format}"
    return base / f"m3t-synth-{profile}-seed{seed}{suffix}"


@dataclass
class SynthSummary:
    root: Path
    profile: str
    seed: int
    images: dict[str, int]
    annotations: dict[str, int]  # RGB-frame annotations per category
    thermal_instances: dict[str, int]  # true objects inside the thermal frame per category
    groups: list[str]
    seconds: float

    def table(self) -> str:
        from harness.textable import text_table

        cats = list(self.annotations)
        rows = [[c, f"{self.annotations[c]:,}", f"{self.thermal_instances.get(c, 0):,}"] for c in cats]
        rows.append(["total", f"{sum(self.annotations.values()):,}", f"{sum(self.thermal_instances.values()):,}"])
        return text_table(["category", "RGB annotations", "in thermal frame"], rows, "lrr")


THERMAL_FORMATS = ("rjpeg", "centikelvin")


def _sawtooth(index: int, period: int, phase: int, lo: float, hi: float) -> float:
    """Offset drift of an uncooled core between shutter calibrations: a ramp from ``lo`` to ``hi``, then a reset."""
    return lo + (hi - lo) * ((index + phase) % period) / max(period - 1, 1)


def _rgb_jpeg_bytes(rgb: np.ndarray, when: datetime, rig: Rig, quality: int) -> bytes:
    """The wide camera's JPEG with the EXIF a DJI capture carries (make, model, capture time, focal length)."""
    import cv2

    from harness.sensing import jpeg

    ok, enc = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover
        raise DataError("could not encode a synthetic RGB frame")
    tags = {
        "Make": "DJI",
        "Model": "M3T",
        "DateTimeOriginal": when,
        "FocalLength": 6.72,
        "FocalLengthIn35mmFilm": 24,
        "ExifImageWidth": rig.rgb_size[0],
        "ExifImageHeight": rig.rgb_size[1],
    }
    return b"\xff\xd8" + jpeg.segment(jpeg.APP1, jpeg.build_exif(tags)) + enc.tobytes()[2:]


def _coco_categories() -> list[dict[str, Any]]:
    from adapters.datasets.m3t import M3T_CATEGORIES, SUPERCATEGORY

    return [{"id": i + 1, "name": n, "supercategory": SUPERCATEGORY[n]} for i, n in enumerate(M3T_CATEGORIES)]


def _round_box(box: Iterable[float]) -> list[float]:
    x0, y0, x1, y1 = (float(b) for b in box)
    return [round(x0, 2), round(y0, 2), round(x1 - x0, 2), round(y1 - y0, 2)]


def generate(
    out: str | Path | None = None,
    profile: str = "small",
    seed: int = 0,
    thermal_format: str = "rjpeg",
    force: bool = False,
    progress: bool = True,
    workers: int | None = None,
) -> SynthSummary:
    """Write the synthetic M3T-like dataset to ``out`` (atomically: a temporary folder renamed into place).

    ``workers``: processes rendering in parallel (default: up to 4, at most the CPU count; 1 renders in this
    process). The output does not depend on it: every image draws from its own seed.
    """
    from harness.io import atomic_folder, atomic_write_json, atomic_write_text

    prof = get_profile(profile)
    if thermal_format not in THERMAL_FORMATS:
        raise DataError(f"unknown thermal format {thermal_format!r}; use one of {', '.join(THERMAL_FORMATS)}")
    out = Path(out) if out is not None else default_root(profile, seed, thermal_format)
    if out.exists() and any(out.iterdir()) and not force:
        raise DataError(f"{out} already exists and is not empty; pass --force to replace it, or choose --out")
    if workers is None:
        workers = 1 if prof.total <= 16 else min(4, os.cpu_count() or 1)
    t_start = time.perf_counter()
    with atomic_folder(out) as tmp:
        summary = _generate_into(
            tmp, prof, seed, thermal_format, progress, max(1, int(workers)), atomic_write_json, atomic_write_text
        )
    summary.root = out
    summary.seconds = time.perf_counter() - t_start
    log.info("generated %d synthetic pairs in %s (%.1f s)", sum(summary.images.values()), out, summary.seconds)
    return summary


@dataclass(frozen=True)
class _Chunk:
    """Consecutive images of one inspection group, rendered and written by one worker."""

    root: str
    profile: str
    seed: int
    thermal_format: str
    project: str
    session: int
    items: tuple[tuple[int, int], ...]  # (index in the session, index in the project)


def _plan(prof: Profile, root: Path, seed: int, thermal_format: str, chunk: int = 8) -> list[_Chunk]:
    out = []
    for p, (project, n_img) in enumerate(zip(PROJECTS, prof.images)):
        n_sess = prof.sessions[p]
        per = [n_img // n_sess + (1 if s < n_img % n_sess else 0) for s in range(n_sess)]
        k = 0
        for s, count in enumerate(per):
            items = [(i, k + i) for i in range(count)]
            k += count
            for c in range(0, count, chunk):
                out.append(_Chunk(str(root), prof.name, seed, thermal_format, project, s, tuple(items[c : c + chunk])))
    return out


def _session(rig: Rig, seed: int, project: str, s: int) -> tuple[Session, tuple[int, int]]:
    """The inspection group's geometry and the sawtooth of its sensor drift, from the group's own seed."""
    p = PROJECTS.index(project)
    look = LOOKS[project]
    srng = np.random.default_rng(np.random.SeedSequence((seed, p, 1000 + s)))
    start = datetime.fromisoformat(look.date) + timedelta(days=int(s // 2), hours=3 * (s % 2))
    session = make_session(rig, project, s, start, look, srng)
    return session, (int(srng.integers(6, 13)), int(srng.integers(0, 12)))


_WORKER: dict[Any, Any] = {}


def _render_chunk(task: _Chunk) -> list[dict[str, Any]]:
    """Render and write the chunk's images; return what the annotation files need, per image."""
    from harness.sensing.radiometry import write_rjpeg, write_thermal

    prof = PROFILES[task.profile]
    if ("rig", task.profile) not in _WORKER:
        rig = Rig.for_profile(prof)
        w, h = prof.rgb_size
        grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
        _WORKER.clear()
        _WORKER[("rig", task.profile)] = (rig, undistort_points_dense(grid, rig.k_rgb, rig.dist_rgb))
    rig, undist = _WORKER[("rig", task.profile)]
    session, saw = _session(rig, task.seed, task.project, task.session)
    canvas = canvas_for_session(rig, session)
    maps = rgb_render_maps(rig, session, canvas, undist)
    look = LOOKS[task.project]
    p = PROJECTS.index(task.project)
    root = Path(task.root)
    folder = root / "images" / task.project
    folder.mkdir(parents=True, exist_ok=True)
    w, h = prof.rgb_size
    hinv = np.linalg.inv(session.homography)
    out = []
    for i, k in task.items:
        rng = np.random.default_rng(np.random.SeedSequence((task.seed, p, k)))
        frame = render_frame(rig, session, canvas, maps, look, rng, _sawtooth(i, saw[0], saw[1], *look.drift_c))
        when = session.start + timedelta(seconds=float(i * 5 + rng.integers(0, 3)))
        stem = f"DJI_{when:%Y%m%d%H%M%S}_{k + 1:04d}"
        (folder / f"{stem}_W.JPG").write_bytes(_rgb_jpeg_bytes(frame.rgb, when, rig, prof.jpeg_quality))
        params = {
            "ambient": look.ambient_c,
            "distance": round(session.distance_m, 2),
            "emissivity": 0.95,
            "humidity": 50.0,
            "reflected": look.ambient_c,
        }
        if task.thermal_format == "rjpeg":
            thermal_rel = f"{task.project}/{stem}_T.JPG"
            write_rjpeg(folder / f"{stem}_T.JPG", frame.temperature, params=params, exif={"DateTimeOriginal": when})
        else:
            thermal_rel = f"{task.project}/{stem}_T.png"
            write_thermal(
                folder / f"{stem}_T.png",
                frame.temperature,
                unit="centikelvin",
                params=params,
                extra={"captured": when.isoformat(sep=" ")},
            )
        write_thermal(
            root / "ground_truth" / "temperature" / task.project / f"{stem}.png",
            frame.true_temperature,
            unit="centikelvin",
        )
        objects = []
        for obj in frame.objects:
            rgb_box = project_box_to_rgb(obj.box, hinv, rig)
            full = (rgb_box[2] - rgb_box[0]) * (rgb_box[3] - rgb_box[1])
            clip = np.clip(rgb_box, 0, [w, h, w, h])
            cw, ch = clip[2] - clip[0], clip[3] - clip[1]
            if cw < 2 or ch < 2 or cw * ch < 0.3 * full:
                continue  # not (enough) in the RGB picture: an annotator would not box it
            objects.append(
                {
                    "category": obj.category,
                    "rgb_box": [float(b) for b in clip],
                    "box": [float(b) for b in obj.box],
                    "attrs": {a: v for a, v in obj.attrs.items() if a != "storey_top"},
                }
            )
        out.append(
            {
                "k": k,
                "project": task.project,
                "group": session.name,
                "stem": stem,
                "when": when,
                "rgb_rel": f"{task.project}/{stem}_W.JPG",
                "thermal_rel": thermal_rel,
                "objects": objects,
                "drift_c": frame.drift_c,
                "vignette_c": frame.vignette_c,
                "landmarks": pick_landmarks(frame, session, rig, rng, limit=12, clicks=prof.clicks),
            }
        )
    return out


def _run_chunks(chunks: list[_Chunk], workers: int, progress: bool, label: str) -> list[list[dict[str, Any]]]:
    results: list[list[dict[str, Any]] | None] = [None] * len(chunks)
    with progress_bar(label, sum(len(c.items) for c in chunks), enabled=progress, eta=True, transient=False) as bar:
        if workers <= 1 or len(chunks) <= 1:
            for n, c in enumerate(chunks):
                results[n] = _render_chunk(c)
                bar.advance(len(c.items))
        else:
            import multiprocessing
            from concurrent.futures import as_completed

            from harness.workers import worker_pool  # workers ignore Ctrl-C: the parent stops them, no tracebacks

            ctx = multiprocessing.get_context("spawn")
            with worker_pool(min(workers, len(chunks)), mp_context=ctx) as pool:
                futures = {pool.submit(_render_chunk, c): n for n, c in enumerate(chunks)}
                try:
                    for fut in as_completed(futures):
                        results[futures[fut]] = fut.result()
                        bar.advance(len(chunks[futures[fut]].items))
                except BaseException:
                    for fut in futures:
                        fut.cancel()
                    raise
    return [r for r in results if r is not None]


def _generate_into(
    root: Path,
    prof: Profile,
    seed: int,
    thermal_format: str,
    progress: bool,
    workers: int,
    write_json: Callable[..., Any],
    write_text: Callable[..., Any],
) -> SynthSummary:
    from adapters.datasets.m3t import M3T_CATEGORIES
    from harness.sensing.registration import HomographyEntry, save_homographies

    rig = Rig.for_profile(prof)
    w, h = prof.rgb_size
    tw, th = prof.thermal_size
    chunks = _plan(prof, root, seed, thermal_format)
    rendered = _run_chunks(chunks, workers, progress, f"generating m3t-synth ({prof.name})")
    cat_id = {n: i + 1 for i, n in enumerate(M3T_CATEGORIES)}
    images, anns, gt_images, gt_anns, frames_meta, landmarks = [], [], [], [], [], []
    lm_count: dict[str, int] = {}
    sessions_out: dict[str, Any] = {}
    true_h: dict[str, np.ndarray] = {}
    ann_counts = {c: 0 for c in M3T_CATEGORIES}
    th_counts = {c: 0 for c in M3T_CATEGORIES}
    image_id, ann_id = 0, 0
    for chunk, results in zip(chunks, rendered):
        if chunk.items[0][0] == 0:
            session, _ = _session(rig, seed, chunk.project, chunk.session)
            sessions_out[session.name] = {
                "project": chunk.project,
                "distance_m": round(session.distance_m, 3),
                "start": session.start.isoformat(sep=" "),
                "normal": [round(float(x), 6) for x in session.normal],
            }
            true_h[session.name] = session.homography
            lm_count[session.name] = 0
        for r in results:
            image_id += 1
            when = r["when"].isoformat(sep=" ")
            images.append({"id": image_id, "file_name": r["rgb_rel"], "width": w, "height": h, "date_captured": when})
            gt_images.append(
                {
                    "id": image_id,
                    "file_name": r["thermal_rel"],
                    "rgb_file_name": r["rgb_rel"],
                    "width": tw,
                    "height": th,
                    "group": r["group"],
                    "project": r["project"],
                }
            )
            objects_meta = []
            for obj in r["objects"]:
                ann_id += 1
                cat = obj["category"]
                bbox = _round_box(obj["rgb_box"])
                anns.append(
                    {
                        "id": ann_id,
                        "image_id": image_id,
                        "category_id": cat_id[cat],
                        "bbox": bbox,
                        "area": round(bbox[2] * bbox[3], 2),
                        "iscrowd": 0,
                    }
                )
                ann_counts[cat] += 1
                box = np.array(obj["box"])
                tbox = np.clip(box, 0, [tw, th, tw, th])
                tarea = max(tbox[2] - tbox[0], 0) * max(tbox[3] - tbox[1], 0)
                area = (box[2] - box[0]) * (box[3] - box[1])
                objects_meta.append(
                    {"id": ann_id, "category": cat, "thermal_box": [round(float(b), 4) for b in box], **obj["attrs"]}
                )
                if tarea > 0:
                    tb = [float(b) for b in tbox]
                    gt_anns.append(
                        {
                            "id": ann_id,
                            "image_id": image_id,
                            "category_id": cat_id[cat],
                            "bbox": [tb[0], tb[1], tb[2] - tb[0], tb[3] - tb[1]],
                            "area": float(tarea),
                            "iscrowd": 0,
                            "unclipped_box": obj["box"],
                            "visible_fraction": round(float(tarea / area), 4),
                        }
                    )
                    th_counts[cat] += 1
            frames_meta.append(
                {
                    "image_id": image_id,
                    "file_name": r["rgb_rel"],
                    "thermal_file": r["thermal_rel"],
                    "group": r["group"],
                    "captured": when,
                    "drift_c": round(r["drift_c"], 4),
                    "vignette_c": round(r["vignette_c"], 4),
                    "objects": objects_meta,
                }
            )
            for lm in r["landmarks"]:  # the first 24 clicks of each inspection group
                if lm_count[r["group"]] < 24:
                    landmarks.append({"scene": r["rgb_rel"], "group": r["group"], **lm})
                    lm_count[r["group"]] += 1

    categories = _coco_categories()
    write_json(
        root / "annotations" / "instances_rgb.json",
        {
            "info": {
                "description": f"m3t-synth {prof.name}, seed {seed}: annotations in the RGB (wide) frame",
                "frame": "rgb",
            },
            "images": images,
            "annotations": anns,
            "categories": categories,
        },
        indent=None,
    )
    write_json(
        root / "registration" / "landmarks.json",
        {
            "description": "landmark pairs clicked on the undistorted wide-camera image (calibration K, full frame) "
            "and on the thermal image; scene = the RGB file, group = its inspection group",
            "rgb_frame": "undistorted",
            "convention": "OpenCV pixel coordinates (pixel centres at integers)",
            "landmarks": landmarks,
        },
    )
    _write_camera(root / "calibration" / "wide_camera.yaml", rig)
    gt = root / "ground_truth"
    save_homographies(
        gt / "homographies.yaml",
        {
            n: HomographyEntry(
                hm,
                method="true",
                rgb_size=prof.rgb_size,
                thermal_size=prof.thermal_size,
                note=f"distance {sessions_out[n]['distance_m']} m",
            )
            for n, hm in true_h.items()
        },
        meta={
            "frame": "undistorted wide-camera pixels (calibration K) -> thermal pixels",
            "generator": f"m3t-synth {prof.name} seed {seed}",
        },
    )
    write_json(gt / "sessions.json", sessions_out)
    write_json(
        gt / "instances_thermal.json",
        {
            "info": {
                "description": "true boxes in the thermal frame (clipped), ids = RGB annotation ids",
                "frame": "thermal",
            },
            "images": gt_images,
            "annotations": gt_anns,
            "categories": categories,
        },
        indent=None,
    )
    write_json(gt / "frames.json", frames_meta, indent=None)
    write_text(root / "m3t.yaml", _MANIFEST.format(profile=prof.name, seed=seed, tw=tw, th=th))
    write_text(root / "README.md", _README.format(profile=prof.name, seed=seed, n=len(images)))
    counts = {pr: n for pr, n in zip(PROJECTS, prof.images)}
    write_json(
        root / MARKER,
        {
            "generator": "m3t-synth",
            "generator_version": GENERATOR_VERSION,
            "profile": prof.name,
            "seed": seed,
            "thermal_format": thermal_format,
            "images": counts,
            "annotations": ann_counts,
            "thermal_instances": th_counts,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        },
    )
    return SynthSummary(root, prof.name, seed, counts, ann_counts, th_counts, list(sessions_out), 0.0)


def _write_camera(path: Path, rig: Rig) -> None:
    from harness.sensing.calibration import CameraModel

    CameraModel(K=rig.k_rgb, dist=np.array(rig.dist_rgb), image_size=rig.rgb_size, name="M3T wide").save(path)


_MANIFEST = """\
# M3T raw layout manifest (see docs/datasets.md). Written by the m3t-synth generator ({profile}, seed {seed});
# every key below is the default, spelled out as an example.
format: raw
images: images
annotations: annotations/instances_rgb.json
rgb_suffix: _W
thermal_suffix: _T
thermal_size: [{tw}, {th}]
rgb_camera: calibration/wide_camera.yaml
landmarks: registration/landmarks.json
landmarks_rgb: undistorted
"""

_README = """\
# m3t-synth ({profile}, seed {seed}): {n} synthetic M3T-like RGB-thermal pairs

Generated by `harness synth`; laid out exactly like the raw M3T release, so `--dataset m3t --set dataset.root=THIS`
reads it too. `ground_truth/` holds what a real release cannot (true homographies, true thermal-frame boxes, true
temperature maps, per-frame sensor offsets); the adapters never read it.
"""
