"""The plugin contracts of the harness, in one module: every record a plugin registers or is handed.

A plugin implements the hooks of ``harness.hookspecs``; each hook hands it a ``register`` callback (or, for
commands, the CLI group), and the records below are what it passes:

======================  =====================================  ===================================================
hook                    record                                 what comes back to the host
======================  =====================================  ===================================================
``register_detectors``  ``DetectorSpec`` (``Reference``)       ``build(...)`` -> a model (the detector contract)
``register_datasets``   ``DatasetSpec`` (``Fold``)             ``open(...)`` -> ``DatasetSource`` -> ``AlignedSample``
                                                               records, skips in a ``PrepareReport``
``register_encodings``  ``EncodingSpec``                       ``fn(sample)`` -> a uint8 H x W channel
``register_loggers``    ``LoggerSpec`` (``TrackingOptions``)   ``create(options)`` -> a ``RunLogger``
``register_commands``   ``CommandGroup`` (a ``click.Group``)   commands added to the ``harness`` command line
======================  =====================================  ===================================================

These are plain records: this module imports nothing of the harness. Every check of them, and of what a plugin's
code returns (a source, a sample, an encoded channel, a model's output), lives in ``harness.contracts``; the host
(``harness.plugins``) runs the record's check when a plugin registers it, and the other checks where a plugin's
output crosses into the harness. Names are unique per kind across all loaded plugins; a name two plugins
register (a command included) is an error naming both (``harness.plugins``). The walk-through with examples is
docs/plugins.md; everything here is exported from ``harness``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from os import PathLike, fspath
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Literal, Mapping, Protocol, Sequence, runtime_checkable

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np
    import torch

#: How a detector takes its input: one stacked tensor ("single") or an (RGB, thermal) pair ("dual").
InputKind = Literal["single", "dual"]
INPUT_KINDS: tuple[str, ...] = ("single", "dual")


# ------------------------------------------------------------------------------------------------ detectors
@dataclass(frozen=True)
class Reference:
    """A published figure to print beside the harness's own measurement (e.g. the seed paper's table).

    It applies to the configuration it was published for: the detector's default model options, ``num_classes``
    classes (None: any) and ``imgsz`` x ``imgsz`` input; beside any other model the profile shows no reference."""

    params_m: float | None = None
    gflops: float | None = None
    source: str = ""
    num_classes: int | None = None
    imgsz: int = 640

    def applies(self, num_classes: int, imgsz: int, model_options: dict[str, Any] | None = None) -> bool:
        """Whether the figures describe a model built with these classes, input size and model options."""
        return (
            not model_options and imgsz == self.imgsz and (self.num_classes is None or num_classes == self.num_classes)
        )


@dataclass(frozen=True)
class DetectorSpec:
    """A detector the harness can build, train, evaluate, profile and export.

    ``build(num_classes, in_channels=..., **model_cfg)`` returns a ``torch.nn.Module`` with this contract:

    * ``model(inputs, targets)`` in train mode returns a dict of scalar loss tensors (summed by the engine);
      ``inputs`` is a float tensor ``[B, C, H, W]`` in 0..1 for ``input_kind="single"`` or a tuple
      ``(rgb [B,3,H,W], thermal [B,Ct,H,W])`` for ``"dual"``; ``targets`` is a list of per-image dicts with
      ``boxes`` (float ``[N,4]`` xyxy pixels of the input tensor) and ``labels`` (int64 ``[N]``, 0-based).
    * ``model(inputs)`` in eval mode returns one dict per image with ``boxes`` (xyxy pixels), ``scores`` and
      ``labels``, after the model's own NMS (``model.conf``, ``model.iou`` and ``model.max_det`` attributes, which
      the host sets from ``eval.conf``, ``eval.iou`` and ``eval.max_det`` before predicting).
    * ``model.forward_raw(inputs)`` returns the raw head outputs (tensor or tuple of tensors) without decoding
      or NMS: what profiling counts and what ONNX export captures.
    * optional: ``harness_fuse()`` (or a ``fuse()`` method of the model's class) folds BatchNorm for profiling.

    ``in_channels`` is ``model_channels(...)``: for ``"single"`` the stacked input's ``3 + encoding channels``;
    for ``"dual"`` the thermal stream's ``thermal_channels`` (the encoding replicated, 3 by default), the RGB
    stream having 3. The host checks the outputs (``harness.contracts.check_detections`` and ``check_losses``).
    """

    name: str
    build: Callable[..., "torch.nn.Module"]
    input_kind: InputKind = "single"
    description: str = ""
    #: Shown wherever the detector is listed or reported, e.g. "reconstructed from the paper".
    label: str = ""
    #: Published complexity to print beside the measured one.
    reference: Reference | None = None
    #: Encoding of the thermal stream of a dual-stream detector when the run names none.
    default_thermal_encoding: str = "ir8"
    #: Channels of the thermal stream of a dual-stream detector (the encoding replicated).
    thermal_channels: int = 3
    #: Config overrides this detector wants by default (same schema as configs/default.yaml, e.g.
    #: ``{"eval": {"iou": 0.5}}``).
    defaults: Mapping[str, Any] = field(default_factory=dict)
    #: ``load_official(model, state_dict) -> dict`` imports weights in the detector's official checkpoint layout.
    load_official: Callable[["torch.nn.Module", Mapping[str, Any]], dict] | None = None

    def model_channels(self, stacked_channels: int) -> int:
        """The ``in_channels`` ``build`` receives when the stacked input has ``stacked_channels`` channels
        (``[R, G, B] + encoding``): those for a single-stream detector, ``thermal_channels`` for a dual-stream one."""
        return self.thermal_channels if self.input_kind == "dual" else int(stacked_channels)


# ------------------------------------------------------------------------------------------------ datasets
@dataclass(frozen=True)
class Fold:
    """One evaluation fold: train on ``train_groups``, evaluate on the held-out ``val_groups``."""

    name: str
    train_groups: tuple[str, ...]
    val_groups: tuple[str, ...]


@dataclass
class AlignedSample:
    """One image pair in the **thermal frame** after registration, warp and common-support crop.

    ==========  ======================  =============================================================
    field       type                    meaning
    ==========  ======================  =============================================================
    image_id    int                     unique within the dataset (COCO ``image_id``)
    rgb         uint8 HxWx3             RGB warped into the thermal frame (R, G, B order)
    thermal     float32 HxW or None     temperature in degrees C (None for 8-bit-only datasets); NaN = missing
    ir8         uint8 HxW               8-bit thermal preview (or the dataset's 8-bit thermal frame)
    boxes       float32 Nx4             xyxy pixels in the thermal frame, inside [0, W] x [0, H]
    labels      int64 N                 0-based category indices
    group       str                     project (M3T) or sequence (RGBT-Tiny); folds hold groups out
    meta        dict                    file names, capture time, homography, anything provenance-related
    ==========  ======================  =============================================================

    ``harness.contracts.validate_sample`` enforces the table and names the sample and the field in every error.
    Missing temperatures (NaN or inf: masked or dead pixels) are allowed up to
    ``harness.sensing.c2.MAX_INVALID_FRACTION`` of the map; the encodings leave them out (C2 gives them the neutral
    value) and ``prepare`` counts them per sample.
    """

    image_id: int
    rgb: np.ndarray
    thermal: np.ndarray | None
    ir8: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    group: str
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def height(self) -> int:
        return int(self.ir8.shape[0])

    @property
    def width(self) -> int:
        return int(self.ir8.shape[1])

    @property
    def name(self) -> str:
        """How errors refer to this sample: its id and, when known, its file name."""
        fname = self.meta.get("file_name") if isinstance(self.meta, dict) else None
        return f"sample {self.image_id}" + (f" ({fname})" if fname else "")


@dataclass
class PrepareReport:
    """Collects what happened while a dataset's samples were produced: counted skips and notes."""

    skipped: list[tuple[str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def skip(self, path: str | Path, reason: str) -> None:
        """Leave one pair (or annotation) out: ``reason`` is ``"short label: details"``, counted by its label."""
        self.skipped.append((str(path), reason))

    def note(self, text: str) -> None:
        self.notes.append(text)

    def summary(self) -> dict[str, Any]:
        reasons: dict[str, int] = {}
        for _, reason in self.skipped:
            key = reason_label(reason)
            reasons[key] = reasons.get(key, 0) + 1
        return {"skipped": len(self.skipped), "skip_reasons": reasons, "notes": list(self.notes)}


_BOX_DETAIL = re.compile(r"box \d+ \[[^\]]*\]")
_FRAME_SIZE = re.compile(r"the \d+x\d+ frame")


def reason_label(reason: str) -> str:
    """What a skip is counted by: the label before the first colon; for an invalid sample, the field and what was
    wrong, without the sample's name or the offending values (one count for every box outside its frame)."""
    key = reason.split(":")[0]
    if "field '" in reason:
        detail = _FRAME_SIZE.sub("its frame", _BOX_DETAIL.sub("a box", reason[reason.index("field '") :]))
        key += ", " + detail
    return key


@runtime_checkable
class DatasetSource(Protocol):
    """An opened dataset: what ``DatasetSpec.open`` returns (checked by ``harness.contracts.check_source``).

    * ``name`` and ``categories``: the categories in label order (label ``k`` is ``categories[k]``, COCO
      ``category_id`` ``k + 1``); they may differ from ``DatasetSpec.categories`` when they come from the data.
    * ``groups()``: every group (project, sequence, site) present, as strings; folds hold whole groups out.
    * ``folds()``: the dataset's own folds (``Fold`` records); an empty list means leave-one-group-out, and the
      config key ``protocol.folds`` overrides both.
    * ``fingerprint()``: a non-empty string that changes whenever anything that changes the samples changes.
    * ``samples(report)`` yields ``AlignedSample`` records in the thermal frame, one per usable image pair, in a
      stable order; a pair that cannot be used is not raised but recorded with ``report.skip(path, reason)`` so
      that a bad file is a counted skip and the rest of the dataset is still prepared.
    * optional: ``__len__`` (a progress bar with a total), ``write_artifacts(folder)`` (extra files written into the
      prepared folder before it is published) and ``pixel_files(sample)`` (the (RGB, thermal) files an 8-bit
      sample decodes from, so the compact cache can reference them instead of copying).
    """

    name: str
    categories: Sequence[str]

    def groups(self) -> list[str]: ...

    def folds(self) -> list[Fold]: ...

    def fingerprint(self) -> str:
        """A string that changes whenever the inputs change (file names, sizes, mtimes or hashes, options)."""
        ...

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]: ...


@dataclass(frozen=True)
class DatasetSpec:
    """A dataset the harness can prepare and evaluate on.

    ``open(root, **options) -> DatasetSource``; ``root`` is the dataset folder (``None`` lets the plugin use its
    default, e.g. an environment variable or a generated location). ``options`` are the other keys of the
    config's ``dataset`` section, passed by name: a key ``open`` does not accept is a ``ConfigError`` naming it.
    When ``open`` has a ``sensing`` parameter (or ``**kwargs``) it also receives ``sensing=`` the config's
    ``sensing`` section (radiometric decoder, undistortion, registration, warp settings) as a dict; a dataset
    with no sensing stage simply leaves the parameter out. See docs/plugins.md, "The dataset contract".

    ``protocol`` takes one of three forms (``harness.protocols`` finds the file):

    * a plain name, ``"m3t-4fold"``: ``configs/protocols/m3t-4fold.yaml`` of the harness;
    * a package resource, ``"my_dataset_pkg:protocol.yaml"``: a file the plugin ships inside its own package
      (listed as package data);
    * an absolute path (``str`` or ``pathlib.Path``), e.g. ``Path(__file__).with_name("protocol.yaml")``.
    """

    name: str
    open: Callable[..., DatasetSource]
    categories: tuple[str, ...]
    description: str = ""
    #: "radiometric" (thermal in degrees C available) or "8bit" (only an 8-bit thermal image).
    thermal: Literal["radiometric", "8bit"] = "radiometric"
    #: Encoding used when a run names none.
    default_encoding: str = "c2"
    #: The evaluation protocol (folds, image size, epochs): a name, ``"package:path/in/package.yaml"`` or an absolute
    #: path (see the class docstring).
    protocol: str = "default"
    #: Environment variable that points at the data, named in error messages.
    root_env: str | None = None
    #: True when preparation runs a sensing stage (radiometric decoding, registration, warp): the report then shows
    #: the sensor-level sections (registration error, C2 under displacement) with the commands that fill them.
    sensing_stage: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.protocol, PathLike):
            object.__setattr__(self, "protocol", fspath(self.protocol))


# ------------------------------------------------------------------------------------------------ encodings
@dataclass(frozen=True)
class EncodingSpec:
    """A way to make the detector's extra input channel from an aligned sample.

    ``fn(sample, **params) -> uint8 HxW`` in the sample's frame (or ``None`` when ``channels == 0``, e.g. RGB-only
    ``none``). ``params`` are the defaults, overridable from the ``encoding`` section of the config. ``needs`` says
    which field of the sample it reads (``"thermal"`` for radiometric encodings such as ``c2``, ``"ir8"`` for 8-bit
    ones), so the host refuses, with a clear message, an encoding a dataset cannot feed. The harness runs ``fn``
    through ``harness.contracts.encode(spec, sample, **overrides)``, which checks both sides of the call
    (``check_encoding_input`` and ``check_encoding_output``).
    """

    name: str
    fn: Callable[..., "np.ndarray | None"]
    channels: int = 1
    needs: Literal["thermal", "ir8", None] = "thermal"
    description: str = ""
    params: Mapping[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------ loggers
class RunLogger(Protocol):
    """What a tracker implements. The runner calls ``start(name, params, tags)`` once, ``log_epoch(step, metrics)``
    after every epoch, ``log_final(metrics)`` once the held-out fold is scored, ``log_artifact(path)`` for files worth
    keeping and ``finish(status)`` at the end (``"FINISHED"`` or ``"FAILED"``). Metric names are flat
    (``loss/box``, ``val/mAP50``); values are finite floats. A logger that raises is reported by name and switched
    off for the rest of the run (``harness.tracking``)."""

    def start(self, name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> None: ...

    def log_epoch(self, step: int, metrics: Mapping[str, float]) -> None: ...

    def log_final(self, metrics: Mapping[str, float]) -> None: ...

    def log_artifact(self, path: Path) -> None: ...

    def finish(self, status: str) -> None: ...


@dataclass(frozen=True)
class TrackingOptions:
    """Where trackers write: the results store's root and the ``tracking`` section of the configuration."""

    store: Path
    mlflow_uri: str | None = None
    mlflow_experiment: str | None = None
    tensorboard_dir: str | None = None
    group: str = "runs"  # what this logger records: "runs" (one per fold and seed) or "report"

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], store: str | Path, group: str = "runs") -> "TrackingOptions":
        t = dict(cfg.get("tracking") or {})
        return cls(Path(store), t.get("mlflow_uri"), t.get("mlflow_experiment"), t.get("tensorboard_dir"), group)


@dataclass(frozen=True)
class LoggerSpec:
    """A tracker, as a plugin registers it: ``create(options) -> RunLogger``.

    ``requires``: the import names of the packages it needs and ``extra`` the harness extra that installs them, so a
    missing package is reported as ``pip install 'rgbt-harness[extra]'`` before any run starts.
    """

    name: str
    create: Callable[[TrackingOptions], RunLogger]
    description: str = ""
    requires: tuple[str, ...] = ()
    extra: str | None = None

    def missing(self) -> list[str]:
        """The required packages that cannot be imported here."""
        import importlib.util

        return [m for m in self.requires if importlib.util.find_spec(m) is None]


# ------------------------------------------------------------------------------------------------ commands
@runtime_checkable
class CommandGroup(Protocol):
    """What ``register_commands(cli)`` is handed: the top-level ``click.Group`` of the ``harness`` command line.

    Add commands with ``@cli.command(name=...)``, groups with ``@cli.group()``, or ``cli.add_command(command)``;
    ``cli.commands`` maps the names taken so far to their commands. A name another plugin (or the harness) already
    added is a conflict naming both plugins: the first command stays listed and running it is a ``PluginError``
    until one of them is removed. Keep commands thin: parse, call one library function, print.
    """

    commands: dict[str, Any]

    def command(self, *args: Any, **kwargs: Any) -> Callable[..., Any]: ...

    def group(self, *args: Any, **kwargs: Any) -> Callable[..., Any]: ...

    def add_command(self, cmd: Any, name: str | None = None) -> None: ...


#: The record each registration hook takes: hook name -> (the kind users see, the record class).
REGISTRATIONS: dict[str, tuple[str, type]] = {
    "register_detectors": ("detector", DetectorSpec),
    "register_datasets": ("dataset", DatasetSpec),
    "register_encodings": ("encoding", EncodingSpec),
    "register_loggers": ("logger", LoggerSpec),
}
