"""``harness export-predictions``: a run's held-out predictions as COCO results in an original image frame.

Each run stores its predictions in the prepared frame (``predictions.json``). Exported, every detection becomes
``{"image_id", "file_name", "category_id", "category_name", "bbox", "score"}`` with the box moved into the
original ``thermal`` or ``rgb`` image (``harness.scoring.frames``: the exact preimage of the way ``harness score``
moves it back) or left in the ``prepared`` frame; ``image_id`` and ``category_id`` stay the dataset's; boxes and
scores keep their full precision. Beside ``X.json``, ``X.images.json`` lists the images and categories in COCO
form, which ``harness score --images`` reads back: the round trip to other tools is closed, and scoring the export
gives the run's metrics to the last digit, in any order of the predictions and with the image and category ids
renumbered (given the renumbered image list).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from harness.errors import ConfigError, StoreError
from harness.io import atomic_write_json, read_json
from harness.scoring.frames import FRAMES, image_name, preimage

log = logging.getLogger(__name__)


@dataclass
class Exported:
    run: str
    path: Path
    images_path: Path
    detections: int
    images: int
    #: boxes too thin for the frame's homography or lens to have an exact preimage (``harness.scoring.frames``)
    inexact: int = 0


def _prepared_of(run: Any) -> Any:
    """The prepared dataset a finished run was trained and scored on (from its stored configuration)."""
    from harness.cache import prepare
    from harness.config import read_yaml

    cfg = read_yaml(run.config_path)
    ds = run.key.dataset
    prepared = prepare(ds, cfg, progress=False)
    stored = (read_yaml(run.config_path).get("meta") or {}).get("prepared_fingerprint")
    if stored and stored != prepared.manifest.get("fingerprint"):
        raise StoreError(
            f"{run.key}: the dataset's prepared samples changed since the run "
            f"(fingerprint {stored} then, {prepared.manifest.get('fingerprint')} now)"
        )
    return prepared


def export_run(run: Any, frame: str, out: Path, prepared: Any = None) -> Exported:
    if frame not in FRAMES:
        raise ConfigError(f"--frame {frame!r}: use one of {', '.join(FRAMES)}")
    prepared = prepared if prepared is not None else _prepared_of(run)
    preds = read_json(run.predictions_path)
    gt = read_json(run.gt_path)
    index = {int(r["image_id"]): r for r in prepared.records}
    cats = list(prepared.categories)
    by_image: dict[int, list[dict[str, Any]]] = {}
    for p in preds:
        by_image.setdefault(int(p["image_id"]), []).append(p)
    out_dets: list[dict[str, Any]] = []
    images: list[dict[str, Any]] = []
    inexact = 0
    for im in gt["images"]:
        iid = int(im["id"])
        r = index.get(iid)
        if r is None:
            raise StoreError(f"{run.key}: image {iid} of gt.json is not in the prepared dataset")
        meta = r.get("meta") or {}
        fname = image_name(meta, frame, iid)
        images.append({"id": iid, "file_name": fname})
        dets = by_image.get(iid, [])
        if not dets:
            continue
        b = np.array([[x, y, x + w, y + h] for x, y, w, h in (d["bbox"] for d in dets)], np.float64)
        moved = preimage(b, frame, meta, where=f"image {iid}")
        inexact += moved.inexact
        for d, (x1, y1, x2, y2) in zip(dets, moved.boxes.tolist()):
            cid = int(d["category_id"])
            out_dets.append(
                {
                    "image_id": iid,
                    "file_name": fname,
                    "category_id": cid,
                    "category_name": cats[cid - 1] if 1 <= cid <= len(cats) else None,
                    "bbox": [x1, y1, x2 - x1, y2 - y1],
                    "score": d["score"],
                }
            )
    atomic_write_json(out, out_dets, indent=None)
    images_path = companion_path(out)
    atomic_write_json(
        images_path,
        {
            "info": {"frame": frame, "run": str(run.key)},
            "images": images,
            "categories": [{"id": k + 1, "name": n} for k, n in enumerate(cats)],
        },
    )
    if inexact:
        log.warning(
            "%s: %d of %d box(es) are too thin for the %s frame's homography or lens to have an exact "
            "preimage; exported as the closest box, they score back slightly wider",
            run.key,
            inexact,
            len(out_dets),
            frame,
        )
    return Exported(str(run.key), out, images_path, len(out_dets), len(images), inexact)


def companion_path(out: Path) -> Path:
    """The image list written beside an export: ``X.images.json`` for ``X.json``."""
    return out.with_name(out.stem + ".images.json")


def export_predictions(
    store: str | Path,
    dataset: str | None = None,
    detector: str | None = None,
    encoding: str | None = None,
    folds: Sequence[str] | None = None,
    seed: int | Sequence[int] | None = None,
    frame: str = "thermal",
    out: str | Path = "predictions",
) -> list[Exported]:
    """Export every finished run that matches (``seed``: one training seed or several); ``out`` is the file for one
    run, a folder for several."""
    from harness.report.reader import read_run
    from harness.store import Store

    st = Store(store)
    seeds = None if seed is None else {int(seed)} if isinstance(seed, int) else {int(s) for s in seed}
    runs = [
        r
        for r in st.runs(dataset=dataset, detector=detector)
        if (encoding is None or r.key.encoding == encoding)
        and (not folds or r.key.fold in folds)
        and (seeds is None or r.key.seed in seeds)
    ]
    if not runs:
        raise StoreError(
            f"no finished run in {st.root} matches (dataset {dataset}, detector {detector}, encoding "
            f"{encoding}, folds {list(folds or []) or 'all'})"
        )
    out = Path(out)
    results: list[Any] = []
    cache: dict[Any, Any] = {}
    for r in runs:
        if len(runs) == 1 and out.suffix == ".json":
            target = out
        else:
            k = r.key
            target = out / f"{k.dataset}_{k.detector.replace('/', '.')}_{k.encoding}_{k.fold}_seed{k.seed}.json"
        fp = (r.key.dataset, (read_run(r).metrics.get("run") or {}).get("dataset"))
        prepared = cache.get(fp)
        if prepared is None:
            prepared = cache[fp] = _prepared_of(r)
        results.append(export_run(r, frame, target, prepared))
    return results
