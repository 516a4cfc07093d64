"""Export held-out samples and every detector's predictions to FiftyOne (an optional extra).

``build_records(store, dataset, out)`` reads the finished runs of ``dataset`` in the results store, writes each
held-out sample's slices as image files under ``out`` (``rgb`` JPEG; ``thermal`` colour-mapped PNG, or grey levels
for 8-bit thermal; ``fourth``: the encoding's channel as a grey PNG) and returns one ``GroupRecord`` per sample with
its ground truth and each run's predictions in FiftyOne's box convention (``[x, y, w, h]`` relative to the image,
``label`` the category name, ``confidence`` the score). It needs no FiftyOne; ``records.json`` beside the images
holds the same records.

``to_fiftyone(export)`` imports FiftyOne lazily and builds a grouped dataset: one group per held-out sample, one
slice per modality (default slice ``rgb``), a ``ground_truth`` field and one ``Detections`` field per run
(``<detector>_<encoding>_s<seed>``, with ``_<fold>`` added only where one image is held out in several folds).
Each run's operating point is in ``dataset.info["operating_points"]``.
"""

from __future__ import annotations

import logging
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from harness.errors import HarnessError, StoreError

log = logging.getLogger(__name__)

SLICES = ("rgb", "thermal", "fourth")
INSTALL_HINT = "pip install 'rgbt-harness[fiftyone]'"


class FiftyOneMissing(HarnessError):
    """FiftyOne is not installed (the export is an optional extra)."""


@dataclass
class GroupRecord:
    """One held-out sample: its slice files and its box fields (FiftyOne's relative ``[x, y, w, h]``)."""

    image_id: int
    group: str
    width: int
    height: int
    slices: dict[str, str]
    fields: dict[str, list[dict[str, Any]]] = field(default_factory=dict)


@dataclass
class FiftyOneExport:
    dataset: str
    out: Path
    records: list[GroupRecord]
    #: field name -> {"run", "conf_threshold"}
    fields: dict[str, dict[str, Any]]
    records_path: Path | None = None
    name: str | None = None
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"{len(self.records)} held-out sample(s) of {self.dataset}, {len(self.fields)} prediction field(s): "
               f"{', '.join(self.fields) or '-'}; images in {self.out}"]
        out += self.notes
        if self.name:
            out.append(f"FiftyOne dataset {self.name!r}: open it with fiftyone.launch_app(fiftyone.load_dataset("
                       f"{self.name!r}))")
        return out


def _ident(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", text).strip("_")


def field_name(detector: str, encoding: str, seed: int) -> str:
    """A FiftyOne field name for a run: letters, digits and underscores, not starting with a digit."""
    name = _ident(f"{detector}_{encoding}_s{seed}")
    return name if name and not name[0].isdigit() else f"run_{name}"


def relative_detections(records: Sequence[dict[str, Any]], width: int, height: int, categories: Sequence[str],
                        scored: bool) -> list[dict[str, Any]]:
    """COCO records (``bbox`` xywh px, ``category_id`` = label + 1) as FiftyOne detection dicts."""
    out = []
    for r in records:
        x, y, w, h = (float(v) for v in r["bbox"])
        k = int(r["category_id"]) - 1
        det: dict[str, Any] = {"label": categories[k] if 0 <= k < len(categories) else str(r["category_id"]),
                               "bounding_box": [x / width, y / height, w / width, h / height]}
        if scored:
            det["confidence"] = float(r["score"])
        out.append(det)
    return out


def _run_fingerprint(run: Any) -> str | None:
    """The prepared-data fingerprint a run was scored on (``config.yaml``, or ``score.json`` for external runs)."""
    from harness.config import read_yaml
    from harness.io import read_json

    if run.config_path.is_file():
        return (read_yaml(run.config_path).get("meta") or {}).get("prepared_fingerprint")
    score = run.path / "score.json"
    if score.is_file():
        return (read_json(score).get("identity") or {}).get("prepared_fingerprint")
    return None


def _write_slices(prepared: Any, index: int, encoding: Any, params: dict[str, Any], out: Path) -> dict[str, str]:
    from PIL import Image

    from harness.report.pictures import thermal_panel
    from harness.report.show import fourth_channel

    s = prepared[index]
    base = out / f"{s.image_id}"
    paths = {"rgb": base.with_name(f"{s.image_id}_rgb.jpg"), "thermal": base.with_name(f"{s.image_id}_thermal.png")}
    Image.fromarray(np.ascontiguousarray(s.rgb)).save(paths["rgb"], format="JPEG", quality=90)
    thermal = thermal_panel(s.thermal)[0] if s.thermal is not None else np.asarray(s.ir8)
    Image.fromarray(np.ascontiguousarray(thermal)).save(paths["thermal"], format="PNG", optimize=True)
    fourth = fourth_channel(prepared, index, encoding, params)
    if fourth is not None:
        paths["fourth"] = base.with_name(f"{s.image_id}_fourth.png")
        Image.fromarray(np.ascontiguousarray(fourth)).save(paths["fourth"], format="PNG", optimize=True)
    return {k: str(v.resolve()) for k, v in paths.items()}


def build_records(store: str | Path, dataset: str, out: str | Path, folds: Sequence[str] | None = None,
                  seed: int | Sequence[int] | None = None, encoding: str | None = None) -> FiftyOneExport:
    """The group records of every held-out sample of ``dataset``'s finished runs (module docstring); ``seed``: only
    runs of this training seed, or of these seeds."""
    from harness.config import read_yaml
    from harness.io import atomic_write_json, read_json
    from harness.plugins import get_host
    from harness.report.reader import StoreView
    from harness.scoring.export import _prepared_of

    view = StoreView(store)
    st = view.store
    runs = [r for r in view.finished_runs(dataset) if not folds or r.key.fold in folds]
    seeds = None if seed is None else [seed] if isinstance(seed, int) else [int(x) for x in seed]
    runs = [r for r in runs if seeds is None or r.key.seed in seeds]
    if not runs:
        said = "all" if seeds is None else ",".join(map(str, seeds))
        raise StoreError(f"no finished run of {dataset} in {st.root} (folds {list(folds or []) or 'all'}, seed "
                         f"{said})")
    host = get_host()
    spec = host.dataset(dataset)
    configured = [r for r in runs if r.config_path.is_file()]  # runs of `harness score` store no config.yaml
    if configured:
        prepared = _prepared_of(configured[0])
        cfg = read_yaml(configured[0].config_path)
    else:
        from harness.cache import prepare
        from harness.config import load_config

        cfg = load_config(protocol=spec.protocol)
        prepared = prepare(spec.name, cfg, progress=False)
    fingerprint = prepared.manifest.get("fingerprint")
    enc_name = encoding or spec.default_encoding
    enc = host.encoding(enc_name) if enc_name and enc_name != "none" else None
    params = dict(((cfg.get("encoding") or {}).get(enc_name) or {})) if enc_name else {}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    categories = list(prepared.categories)
    notes: list[str] = []
    records: dict[int, GroupRecord] = {}
    fields: dict[str, dict[str, Any]] = {}
    for run in runs:
        stored = _run_fingerprint(run)
        if stored and fingerprint and stored != fingerprint:
            notes.append(f"{run.key}: left out (prepared on other samples: fingerprint {stored}, now {fingerprint})")
            continue
        gt = read_json(run.gt_path)
        conf = (run.metrics.get("metrics") or {}).get("conf_threshold")
        by_image: dict[int, list[dict[str, Any]]] = {}
        for p in read_json(run.predictions_path):
            by_image.setdefault(int(p["image_id"]), []).append(p)
        base = field_name(run.key.detector, run.key.encoding, run.key.seed)
        for im in gt.get("images") or []:
            iid = int(im["id"])
            rec = records.get(iid)
            if rec is None:
                i = prepared.index_of(iid)
                r = prepared.records[i]
                boxes, labels = prepared.targets(i)
                gt_recs = [{"bbox": [x1, y1, x2 - x1, y2 - y1], "category_id": int(k) + 1}
                           for (x1, y1, x2, y2), k in zip(boxes.tolist(), labels.tolist())]
                rec = GroupRecord(iid, str(r["group"]), int(r["width"]), int(r["height"]),
                                  _write_slices(prepared, i, enc, params, out))
                rec.fields["ground_truth"] = relative_detections(gt_recs, rec.width, rec.height, categories, False)
                records[iid] = rec
            name = base if base not in rec.fields else f"{base}_{_ident(run.key.fold)}"
            rec.fields[name] = relative_detections(by_image.get(iid, []), rec.width, rec.height, categories, True)
            fields.setdefault(name, {"run": str(run.key), "conf_threshold": conf})
    export = FiftyOneExport(dataset, out, [records[k] for k in sorted(records)], fields, notes=notes)
    export.records_path = atomic_write_json(out / "records.json", {
        "dataset": dataset, "slices": list(SLICES), "categories": categories, "fields": fields,
        "records": [asdict(r) for r in export.records]}, indent=None)
    return export


def import_fiftyone() -> Any:
    """``fiftyone``, or a clear error saying how to install it."""
    try:
        import fiftyone
    except ImportError as exc:
        raise FiftyOneMissing(f"FiftyOne is not installed ({exc}); install the optional extra: {INSTALL_HINT} "
                              f"(or use --records-only to write the images and records.json without it)") from None
    return fiftyone


def fiftyone_samples(export: FiftyOneExport, fo: Any) -> list[Any]:
    """The ``fiftyone.Sample``s of ``export``: one per slice, the slices of a held-out image in one ``Group``."""
    samples = []
    for rec in export.records:
        group = fo.Group()
        for slice_name, path in rec.slices.items():
            s = fo.Sample(filepath=path, group=group.element(slice_name))
            s["image_id"] = rec.image_id
            s["source_group"] = rec.group
            for fname, dets in rec.fields.items():
                s[fname] = fo.Detections(detections=[fo.Detection(**d) for d in dets])
            samples.append(s)
    return samples


def to_fiftyone(export: FiftyOneExport, name: str | None = None, overwrite: bool = False,
                persistent: bool = True) -> str:
    """Build the grouped FiftyOne dataset of ``export`` (module docstring); returns its name."""
    fo = import_fiftyone()
    name = name or f"harness-{export.dataset}"
    if fo.dataset_exists(name) and not overwrite:
        raise StoreError(f"FiftyOne dataset {name!r} exists; pass --overwrite to replace it, or --name")
    ds = fo.Dataset(name, overwrite=overwrite)
    ds.add_group_field("group", default="rgb")
    ds.add_samples(fiftyone_samples(export, fo))
    ds.info = {"harness_dataset": export.dataset, "operating_points": export.fields}
    ds.persistent = persistent
    ds.save()
    export.name = name
    return name


def export_fiftyone(store: str | Path, dataset: str, out: str | Path, folds: Sequence[str] | None = None,
                    seed: int | Sequence[int] | None = None, encoding: str | None = None, name: str | None = None,
                    overwrite: bool = False, records_only: bool = False) -> FiftyOneExport:
    """``build_records`` then, unless ``records_only``, ``to_fiftyone``. A missing FiftyOne stops before anything
    is written (``records_only`` needs none)."""
    if not records_only:
        import_fiftyone()  # fail before writing anything when the extra is missing
    export = build_records(store, dataset, out, folds, seed, encoding)
    if not records_only:
        to_fiftyone(export, name, overwrite)
    return export
