"""``harness show``: one prepared sample of any dataset, its channels side by side with its boxes.

``sample_picture(prepared, index, ...)`` draws sample ``index`` of a prepared dataset (RGB, thermal, the fourth
channel of an encoding) with its ground truth and any prediction sets (``harness.report.pictures.draw_sample``).
``run_predictions(store, dataset, detector, image_id)`` reads the predictions of a detector's finished runs on one
image from the results store, cut at each run's operating point (``metrics.conf_threshold``).
``show(...)`` finds the sample, draws it and writes it to a file, or into the terminal when it draws images.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from harness.errors import ConfigError, DataError, StoreError
from harness.report.pictures import (
    BoxSet,
    coco_boxes,
    draw_sample,
    encode_image,
    inline_image,
    save_image,
    terminal_protocol,
)

log = logging.getLogger(__name__)


def find_sample(prepared: Any, image_id: int | None = None, index: int | None = None, name: str | None = None) -> int:
    """The index of the sample chosen by image id, position or file name (exactly one of them; position 0 when
    none is given). An unknown one is an error that says what exists."""
    given = [x is not None for x in (image_id, index, name)]
    if sum(given) > 1:
        raise ConfigError("choose the sample by one of --image-id, --index or --name")
    n = len(prepared)
    if n == 0:
        raise DataError(f"{prepared.folder}: the prepared dataset has no samples")
    if image_id is not None:
        try:
            return prepared.index_of(int(image_id))
        except KeyError:
            ids = prepared.image_ids
            raise ConfigError(
                f"--image-id {image_id}: not a sample of {prepared.name} ({n} samples, ids {min(ids)}..{max(ids)})"
            ) from None
    if name is not None:
        hits = [i for i, r in enumerate(prepared.records) if _names_match(r.get("meta") or {}, name)]
        if len(hits) != 1:
            raise ConfigError(
                f"--name {name!r}: {len(hits)} samples of {prepared.name} match; give a longer name or --image-id"
            )
        return hits[0]
    index = 0 if index is None else int(index)
    if not 0 <= index < n:
        raise ConfigError(f"--index {index}: {prepared.name} has samples 0..{n - 1}")
    return index


def _names_match(meta: Mapping[str, Any], name: str) -> bool:
    """Whether a sample's file name (RGB or thermal), its base name or its stem is ``name``."""
    for key in ("file_name", "thermal_file", "rgb_file"):
        value = meta.get(key)
        if value:
            p = Path(str(value).replace("\\", "/"))
            if name in (str(p), p.name, p.stem):
                return True
    return False


def fourth_channel(
    prepared: Any, index: int, encoding: Any, params: Mapping[str, Any] | None = None
) -> np.ndarray | None:
    """The encoding's channel of sample ``index`` (None for an encoding that adds no channel)."""
    if encoding is None or getattr(encoding, "channels", 0) == 0:
        return None
    if getattr(encoding, "needs", None) == "thermal" and not prepared.radiometric:
        raise ConfigError(
            f"encoding {encoding.name!r} needs radiometric thermal, but {prepared.name} has only 8-bit "
            f"thermal; use an 8-bit encoding such as 'proxy8' or 'ir8'"
        )
    return prepared.channel(index, encoding, dict(params or {}))


def sample_picture(
    prepared: Any,
    index: int,
    *,
    encoding: Any = None,
    encoding_params: Mapping[str, Any] | None = None,
    predictions: Sequence[BoxSet] = (),
    height: int = 400,
    title: str | None = None,
) -> np.ndarray:
    """Sample ``index`` of ``prepared`` drawn with its ground truth and ``predictions`` (RGB uint8)."""
    s = prepared[index]
    fourth = fourth_channel(prepared, index, encoding, encoding_params)
    if title is None:
        fname = (s.meta or {}).get("file_name")
        title = f"{prepared.name} {s.image_id}" + (f" ({fname})" if fname else "") + f" group {s.group}"
    return draw_sample(
        s,
        fourth=fourth,
        fourth_name=getattr(encoding, "name", "fourth channel"),
        categories=list(prepared.categories),
        gt=True,
        predictions=predictions,
        height=height,
        title=title,
    )


def run_predictions(store: str | Path, dataset: str, detector: str, image_id: int) -> list[BoxSet]:
    """Predictions of ``detector``'s finished runs on ``image_id`` at each run's operating point, one set per run
    whose held-out images include it. None found is an error naming what the store holds."""
    from harness.io import read_json
    from harness.report.reader import StoreView

    view = StoreView(store)
    st = view.store
    runs = [r for r in view.finished_runs(dataset) if r.key.detector == detector]
    if not runs:
        raise StoreError(f"no finished run of {detector} on {dataset} in {st.root}")
    out = []
    for run in runs:
        gt = read_json(run.gt_path) if run.gt_path.is_file() else {}
        if int(image_id) not in {int(im["id"]) for im in gt.get("images") or []}:
            continue
        conf = (run.metrics.get("metrics") or {}).get("conf_threshold")
        boxes = coco_boxes(
            read_json(run.predictions_path),
            int(image_id),
            name=f"{run.key.detector}/{run.key.encoding}/{run.key.fold}/seed{run.key.seed}",
        ).above(conf)
        if conf is not None:
            boxes.name += f" >= {conf:.2f}"
        out.append(boxes)
    if not out:
        raise StoreError(
            f"image {image_id} is in no held-out fold of {detector}'s finished runs on {dataset} "
            f"({len(runs)} run(s) in {st.root})"
        )
    return out


@dataclass
class Shown:
    """Where a picture went: drawn in the terminal (``protocol``) or written to ``path``."""

    path: Path | None
    protocol: str | None = None
    image_id: int | None = None


def show(
    dataset: str,
    cfg: Mapping[str, Any],
    *,
    image_id: int | None = None,
    index: int | None = None,
    name: str | None = None,
    encoding: str | None = None,
    store: str | Path | None = None,
    detectors: Sequence[str] = (),
    height: int = 400,
    out: str | Path | None = None,
    cache_root: str | Path | None = None,
    inline: bool | None = None,
) -> Shown:
    """Draw one prepared sample (module docstring). Without ``out``, a terminal that draws images gets it inline
    (``inline=None``: when stdout is such a terminal); otherwise it is written to ``show_<dataset>_<id>.png``."""
    from harness.cache import prepare
    from harness.plugins import get_host

    host = get_host()
    spec = host.dataset(dataset)
    enc_name = encoding or spec.default_encoding
    enc = host.encoding(enc_name) if enc_name else None
    prepared = prepare(spec.name, dict(cfg), cache_root=cache_root)
    i = find_sample(prepared, image_id, index, name)
    iid = int(prepared.records[i]["image_id"])
    preds: list[BoxSet] = []
    for det in detectors:
        if store is None:
            raise ConfigError("--detectors needs --store: the predictions are read from finished runs")
        preds += run_predictions(store, spec.name, det, iid)
    params = dict(((cfg.get("encoding") or {}).get(enc_name) or {})) if enc_name else {}
    img = sample_picture(prepared, i, encoding=enc, encoding_params=params, predictions=preds, height=height)
    protocol = terminal_protocol() if out is None else None
    if inline is None:
        inline = protocol is not None and sys.stdout.isatty()
    if out is None and inline and protocol:
        sys.stdout.write(inline_image(encode_image(img, "png"), protocol))
        sys.stdout.flush()
        return Shown(None, protocol, iid)
    path = Path(out) if out is not None else Path(f"show_{spec.name}_{iid}.png")
    save_image(img, path)
    return Shown(path, None, iid)
