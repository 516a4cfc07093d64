"""Tiny copies of the RGBT-Tiny and M3FD releases, written by the tests in the exact official layouts.

Objects are bright blobs in the thermal image and coloured blocks in the visible one, at the annotated places, so a
detector trained on a few epochs has something to find. Everything is deterministic (seeded).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import pytest

from harness.api import PrepareReport
from harness.errors import ConfigError, DataError

RGBT_CLASSES = ("ship", "car", "cyclist", "pedestrian", "bus", "drone", "plane")
M3FD_NAMES = ("People", "Car", "Bus", "Motorcycle", "Lamp", "Truck")


def _draw(
    h: int, w: int, boxes: list[tuple[float, float, float, float]], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(visible BGR, thermal grey) with a blob per xywh box."""
    vis = np.full((h, w, 3), 70, np.uint8) + rng.integers(0, 20, (h, w, 3), dtype=np.uint8)
    th = np.full((h, w), 40, np.uint8) + rng.integers(0, 15, (h, w), dtype=np.uint8)
    for x, y, bw, bh in boxes:
        x0, y0, x1, y1 = int(x), int(y), int(x + bw), int(y + bh)
        vis[y0:y1, x0:x1] = (30, 200, 220)
        th[y0:y1, x0:x1] = 230
    return vis, th


def _frame_boxes(rng: np.random.Generator, w: int, h: int, n: int) -> list[tuple[int, int, int, int, int]]:
    """n boxes (x, y, bw, bh, class index) inside the frame."""
    out = []
    for _ in range(n):
        bw, bh = int(rng.integers(8, 16)), int(rng.integers(8, 16))
        x, y = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
        out.append((x, y, bw, bh, int(rng.integers(0, 3))))
    return out


def write_rgbt_tiny(
    root: Path,
    train_seqs=("DJI_0001_1", "DJI_0002_1"),
    test_seqs=("DJI_0101_1",),
    frames: int = 3,
    size: tuple[int, int] = (64, 48),
    split_files: bool = True,
    seed: int = 0,
    flat: bool = False,
) -> dict:
    """Write ``images/``, ``annotations_coco/`` and ``data_split/`` under ``root``; return what was written.

    ``flat=True`` writes what unzipping the three release archives into ``root`` gives: the sequence folders, the
    JSON files and the split lists side by side (the archives have no top-level folder).

    The visible and thermal JSONs number images differently (thermal 1, 2, ...; visible 5000 + reversed order),
    list the categories in a shuffled order with the official 0-based ids, and their boxes differ: the visible boxes
    are the thermal ones shifted by +1 px, and the first frame of every sequence has one extra visible-only box.
    """
    rng = np.random.default_rng(seed)
    w, h = size
    root = Path(root)
    images, annotations, splits = (
        (root, root, root) if flat else (root / "images", root / "annotations_coco", root / "data_split")
    )
    cats = [{"id": i, "name": n} for i, n in enumerate(RGBT_CLASSES)]
    cats = [cats[i] for i in (3, 0, 6, 1, 5, 2, 4)]
    expected: dict = {"frames": {}, "thermal_boxes": {}, "visible_boxes": {}}
    for split, seqs in (("train", train_seqs), ("test", test_seqs)):
        docs = {m: {"images": [], "annotations": [], "categories": cats} for m in ("00", "01")}
        keys = []
        for seq in seqs:
            for f in range(frames):
                frame = f"{f:05d}"
                keys.append((seq, frame))
                objs = _frame_boxes(rng, w, h, 2)
                vis, th = _draw(h, w, [o[:4] for o in objs], rng)
                for m, img in (("00", vis), ("01", th)):
                    p = images / seq / m / f"{frame}.jpg"
                    p.parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(
                        str(p), img if m == "00" else cv2.merge([img, img, img]), [cv2.IMWRITE_JPEG_QUALITY, 95]
                    )
                t_boxes = [(float(x), float(y), float(bw), float(bh), c) for x, y, bw, bh, c in objs]
                v_boxes = [(x + 1, y + 1, bw, bh, c) for x, y, bw, bh, c in t_boxes]
                if f == 0:
                    v_boxes.append((2.0, 2.0, 6.0, 5.0, 0))  # only annotated in the visible image (class ship, id 0)
                expected["thermal_boxes"][(seq, frame)] = t_boxes
                expected["visible_boxes"][(seq, frame)] = v_boxes
                expected["frames"][(seq, frame)] = split
        n = len(keys)
        for idx, (seq, frame) in enumerate(keys):
            ids = {"01": idx + 1, "00": 5000 + (n - 1 - idx)}
            for m, boxes in (
                ("01", expected["thermal_boxes"][seq, frame]),
                ("00", expected["visible_boxes"][seq, frame]),
            ):
                docs[m]["images"].append({"id": ids[m], "file_name": f"{seq}/{m}/{frame}.jpg", "width": w, "height": h})
                for x, y, bw, bh, c in boxes:
                    docs[m]["annotations"].append(
                        {
                            "id": len(docs[m]["annotations"]) + 1,
                            "image_id": ids[m],
                            "category_id": c,
                            "bbox": [x, y, bw, bh],
                            "area": bw * bh,
                            "iscrowd": 0,
                        }
                    )
        # visible images listed in reverse order, as another tool might write them
        docs["00"]["images"].reverse()
        for m in ("00", "01"):
            p = annotations / f"instances_{m}_{split}2017.json"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(json.dumps(docs[m], indent=1))
        if split_files:
            d = splits
            d.mkdir(parents=True, exist_ok=True)
            (d / f"{split}.txt").write_text("".join(f"{s}/00/{fr}\n" for s, fr in keys))
            for m in ("00", "01"):
                (d / f"{m}_{split}.txt").write_text("".join(f"{s}/{m}/{fr}\n" for s, fr in keys))
    return expected


def rgbt_json(root: Path, modality: str, split: str) -> Path:
    return Path(root) / "annotations_coco" / f"instances_{modality}_{split}2017.json"


def write_m3fd(
    root: Path, numbers=(0, 1, 2, 3, 120, 401, 402, 950), seed: int = 0, sizes: dict[int, tuple[int, int]] | None = None
) -> dict:
    """Write ``M3FD_Detection/{Annotation,Ir,Vis}`` under ``root``; return the boxes per frame number.

    Frame 120 is 72x40 (per-image sizes); class names are written with the dataset's capitals and, once, with a
    trailing space and lower case. The XMLs hold 1-based inclusive pixel indices, as labelImg writes them; the
    returned boxes are the 0-based corners of the drawn blobs.
    """
    rng = np.random.default_rng(seed)
    sizes = {120: (72, 40), **(sizes or {})}
    base = Path(root) / "M3FD_Detection"
    for d in ("Annotation", "Ir", "Vis"):
        (base / d).mkdir(parents=True, exist_ok=True)
    expected = {}
    for k, n in enumerate(numbers):
        w, h = sizes.get(n, (64, 48))
        objs = _frame_boxes(rng, w, h, 2)
        vis, th = _draw(h, w, [o[:4] for o in objs], rng)
        stem = f"{n:05d}"
        cv2.imwrite(str(base / "Vis" / f"{stem}.png"), vis)
        cv2.imwrite(str(base / "Ir" / f"{stem}.png"), cv2.merge([th, th, th]))
        names = [
            M3FD_NAMES[c] if not (k == 1 and j == 0) else f"{M3FD_NAMES[c].lower()} " for j, (*_, c) in enumerate(objs)
        ]
        # labelImg's convention: 1-based inclusive pixel indices (pixels x .. x+bw-1 are written x+1 .. x+bw)
        write_voc(
            base / "Annotation" / f"{stem}.xml",
            f"{stem}.png",
            w,
            h,
            [(nm, x + 1, y + 1, x + bw, y + bh) for nm, (x, y, bw, bh, _) in zip(names, objs)],
        )
        expected[n] = [(x, y, x + bw, y + bh, c) for x, y, bw, bh, c in objs]
    return expected


def write_voc(path: Path, filename: str, w: int, h: int, objects, folder: str = "M3FD") -> None:
    """A labelImg-style VOC XML; ``objects`` are ``(name, xmin, ymin, xmax, ymax[, difficult])`` as written."""
    obj_xml = "".join(
        f"  <object>\n    <name>{name}</name>\n    <pose>Unspecified</pose>\n    <truncated>0</truncated>\n"
        f"    <difficult>{int(bool(rest[0])) if rest else 0}</difficult>\n    <bndbox>\n      <xmin>{x0}</xmin>\n"
        f"      <ymin>{y0}</ymin>\n      <xmax>{x1}</xmax>\n      <ymax>{y1}</ymax>\n    </bndbox>\n  </object>\n"
        for name, x0, y0, x1, y1, *rest in objects
    )
    path.write_text(
        f"<annotation>\n  <folder>{folder}</folder>\n  <filename>{filename}</filename>\n"
        f"  <size>\n    <width>{w}</width>\n    <height>{h}</height>\n    <depth>3</depth>\n  </size>\n"
        f"{obj_xml}</annotation>\n"
    )


# ---------------------------------------------------------------------------------------------- real tiny runs
#: Settings that make a run take a couple of seconds on a CPU: 64 px, one epoch, the smallest YOLOv8 scale.
TINY_RUN = [
    "--set",
    "protocol.imgsz=64",
    "--set",
    "protocol.epochs=1",
    "--set",
    "protocol.patience=1",
    "--set",
    "train.batch=4",
    "--set",
    "train.nominal_batch=4",
    "--set",
    "train.threads=1",
    "--set",
    "model.scale=n",
    "--no-progress",
]


def invoke(args: list[str], cache: Path | None = None):
    """Run the ``harness`` CLI in-process (prepared data under ``cache``, never the working directory); a non-zero
    exit is returned, not raised (tests check it)."""
    import os

    from click.testing import CliRunner

    from harness.cli import get_cli

    env = {"HARNESS_CACHE": str(cache)} if cache is not None else {}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        return CliRunner().invoke(get_cli(), args, catch_exceptions=False)
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


_BUILT: dict = {}


def trained_store(tmp_path_factory) -> dict:
    """``build_trained_store`` once per test session (the runs are shared by the RGBT-Tiny, M3FD and compare tests).

    Skipped, saying why, only in a checkout that does not have the training engine (``harness run``) yet."""
    import pytest

    pytest.importorskip("harness.runner", reason="needs the training engine (`harness run`), absent from this checkout")
    if "store" not in _BUILT:
        _BUILT.update(build_trained_store(tmp_path_factory.mktemp("trained")))
    return _BUILT


def build_trained_store(base: Path) -> dict:
    """Write both fixture releases under ``base`` and fill a results store with real tiny runs:

    1. ``harness pretrain --detector ours --dataset m3fd``                 (m3fd/ours/ir8/val)
    2. ``harness run --detector ours --dataset rgbt-tiny --init <ckpt>``   (rgbt-tiny/ours/proxy8/test-T)
    3. the same with ``--encoding ir8``                                     (rgbt-tiny/ours/ir8/test-T)
    4. the same with ``--set dataset.gt=visible``                           (rgbt-tiny/ours/proxy8/test-RGB)
    """
    base = Path(base)
    rgbt_root, m3fd_root, store, cache = base / "RGBT-Tiny", base / "m3fd", base / "store", base / "cache"
    expected = write_rgbt_tiny(rgbt_root)
    write_m3fd(m3fd_root)
    common = [*TINY_RUN, "--store", str(store)]
    out = {
        "base": base,
        "store": store,
        "cache": cache,
        "rgbt_root": rgbt_root,
        "m3fd_root": m3fd_root,
        "expected": expected,
    }
    res = invoke(
        ["pretrain", "--detector", "ours", "--dataset", "m3fd", "--set", f"dataset.root={m3fd_root}", *common], cache
    )
    assert res.exit_code == 0, res.output
    out["pretrain_output"] = res.output
    out["checkpoint"] = Path(
        next(line.split(maxsplit=1)[1] for line in res.output.splitlines() if line.startswith("checkpoint:"))
    )
    rgbt = ["run", "--detector", "ours", "--dataset", "rgbt-tiny", "--set", f"dataset.root={rgbt_root}", *common]
    for name, extra in (
        ("run_init", ["--init", str(out["checkpoint"])]),
        ("run_ir8", ["--encoding", "ir8"]),
        ("run_visible", ["--set", "dataset.gt=visible"]),
    ):
        res = invoke(rgbt + extra, cache)
        assert res.exit_code == 0, res.output
        out[name] = res.output
    return out


def collect(source: Any) -> tuple[list[Any], PrepareReport]:
    """Every sample of an opened dataset source, and its prepare report."""
    report = PrepareReport()
    return list(source.samples(report)), report


def collect_with_drops(
    open_source: Callable[..., Any], root: Path, kept: int, reasons: dict[str, int], strict_error: str = "strict"
) -> tuple[list[Any], PrepareReport]:
    """Collect the samples of ``open_source(root)``: ``kept`` of them, the skips counted by ``reasons``; opened with
    ``strict=True`` the same release is an error matching ``strict_error``. Returns the samples and the report."""
    samples, report = collect(open_source(root))
    assert len(samples) == kept
    assert report.summary()["skip_reasons"] == reasons
    with pytest.raises(DataError, match=strict_error):
        open_source(root, strict=True)
    return samples, report


def check_layout_errors(
    open_source: Callable[..., Any], env: str, folder: Path, made: str, missing: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No root and no ``env`` is an error naming the variable; a ``folder`` holding only ``made`` is one naming what
    is ``missing``; ``strict="yes"`` is a ``ConfigError``."""
    monkeypatch.delenv(env, raising=False)
    with pytest.raises(DataError, match=env):
        open_source()
    (folder / made).mkdir()
    with pytest.raises(DataError, match=f"missing {missing}"):
        open_source(folder)
    with pytest.raises(ConfigError, match="'strict' must be true or false"):
        open_source(folder, strict="yes")
