"""What plugins register: detector, dataset and encoding specifications, and the contracts behind them.

These are plain records. A plugin builds one and hands it to the ``register`` callback of the matching hook
(``harness.hookspecs``); the host checks it, keys it by name and builds objects from it when a run asks.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from os import PathLike, fspath
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Literal, Mapping, Protocol, Sequence, runtime_checkable

from harness.errors import HarnessError, PluginError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np
    import torch

    from harness.sample import AlignedSample

InputKind = Literal["single", "dual"]
INPUT_KINDS = ("single", "dual")
_NAME = re.compile(r"^[a-z0-9][a-z0-9_.+-]*$")


def check_name(kind: str, name: str) -> None:
    """Names are lower-case identifiers that are safe as directory names in the results store."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise PluginError(
            f"invalid {kind} name {name!r}: use lower-case letters, digits and '._+-', starting with a letter or digit"
        )


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
        return (not model_options and imgsz == self.imgsz
                and (self.num_classes is None or num_classes == self.num_classes))


@dataclass(frozen=True)
class DetectorSpec:
    """A detector the harness can build, train, evaluate, profile and export.

    ``build(num_classes, in_channels=..., **model_cfg)`` returns a ``torch.nn.Module`` with this contract:

    * ``model(inputs, targets)`` in train mode returns a dict of scalar loss tensors (summed by the engine);
      ``inputs`` is a float tensor ``[B, C, H, W]`` in 0..1 for ``input_kind="single"`` or a tuple
      ``(rgb [B,3,H,W], thermal [B,Ct,H,W])`` for ``"dual"``; ``targets`` is a list of per-image dicts with
      ``boxes`` (float ``[N,4]`` xyxy pixels of the input tensor) and ``labels`` (int64 ``[N]``, 0-based).
    * ``model(inputs)`` in eval mode returns one dict per image with ``boxes`` (xyxy pixels), ``scores`` and
      ``labels``, after the model's own NMS (``model.conf``, ``model.iou`` and ``model.max_det`` attributes).
    * ``model.forward_raw(inputs)`` returns the raw head outputs (tensor or tuple of tensors) without decoding
      or NMS: what profiling counts and what ONNX export captures.

    For ``"single"`` the host passes ``in_channels = 3 + encoding channels``; for ``"dual"`` the RGB stream has
    3 channels and ``in_channels`` is the thermal stream's (the encoding replicated to 3 by default).
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
    #: Config overrides this detector wants by default (same schema as configs/default.yaml, e.g. {"eval": {"iou": 0.5}}).
    defaults: Mapping[str, Any] = field(default_factory=dict)
    #: ``load_official(model, state_dict) -> dict`` imports weights in the detector's official checkpoint layout.
    load_official: Callable[["torch.nn.Module", Mapping[str, Any]], dict] | None = None

    def __post_init__(self) -> None:
        check_name("detector", self.name)
        if self.input_kind not in INPUT_KINDS:
            raise PluginError(f"detector {self.name!r}: input_kind must be one of {INPUT_KINDS}, got {self.input_kind!r}")
        if not callable(self.build):
            raise PluginError(f"detector {self.name!r}: build must be callable")


@dataclass(frozen=True)
class Fold:
    """One evaluation fold: train on ``train_groups``, evaluate on the held-out ``val_groups``."""

    name: str
    train_groups: tuple[str, ...]
    val_groups: tuple[str, ...]

    def __post_init__(self) -> None:
        overlap = set(self.train_groups) & set(self.val_groups)
        if overlap:
            raise PluginError(f"fold {self.name!r}: groups {sorted(overlap)} are both trained on and held out")


@runtime_checkable
class DatasetSource(Protocol):
    """An opened dataset: what ``DatasetSpec.open`` returns (the full contract is in docs/plugins.md).

    * ``name`` and ``categories``: the categories in label order (label ``k`` is ``categories[k]``, COCO
      ``category_id`` ``k + 1``); they may differ from ``DatasetSpec.categories`` when they come from the data.
    * ``groups()``: every group (project, sequence, site) present; folds hold whole groups out.
    * ``folds()``: the dataset's own folds (``Fold`` records); an empty list means leave-one-group-out, and the
      config key ``protocol.folds`` overrides both.
    * ``fingerprint()``: a string that changes whenever anything that changes the samples changes.
    * ``samples(report)`` yields ``AlignedSample`` records in the thermal frame, one per usable image pair, in a
      stable order; a pair that cannot be used is not raised but recorded with ``report.skip(path, reason)`` so
      that a bad file is a counted skip and the rest of the dataset is still prepared.
    * optional: ``__len__`` (a progress bar with a total) and ``write_artifacts(folder)`` (extra files written
      into the prepared folder before it is published).
    """

    name: str
    categories: Sequence[str]

    def groups(self) -> list[str]: ...

    def folds(self) -> list[Fold]: ...

    def fingerprint(self) -> str:
        """A string that changes whenever the inputs change (file names, sizes, mtimes or hashes, options)."""
        ...

    def samples(self, report: "PrepareReport") -> Iterator["AlignedSample"]: ...


@dataclass
class PrepareReport:
    """Collects what happened while a dataset's samples were produced: counted skips and notes."""

    skipped: list[tuple[str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def skip(self, path: str | Path, reason: str) -> None:
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
        detail = _FRAME_SIZE.sub("its frame", _BOX_DETAIL.sub("a box", reason[reason.index("field '"):]))
        key += ", " + detail
    return key


@dataclass(frozen=True)
class DatasetSpec:
    """A dataset the harness can prepare and evaluate on.

    ``open(root, **options) -> DatasetSource``; ``root`` is the dataset folder (``None`` lets the plugin use its
    default, e.g. an environment variable or a generated location). ``options`` are the other keys of the
    config's ``dataset`` section, passed by name: a key ``open`` does not accept is a ``ConfigError`` naming it.
    When ``open`` has a ``sensing`` parameter (or ``**kwargs``) it also receives ``sensing=`` the config's
    ``sensing`` section (radiometric decoder, undistortion, registration, warp settings) as a dict; a dataset
    with no sensing stage simply leaves the parameter out. See docs/plugins.md, "The dataset contract".
    """

    name: str
    open: Callable[..., DatasetSource]
    categories: tuple[str, ...]
    description: str = ""
    #: "radiometric" (thermal in degrees C available) or "8bit" (only an 8-bit thermal image).
    thermal: Literal["radiometric", "8bit"] = "radiometric"
    #: Encoding used when a run names none.
    default_encoding: str = "c2"
    #: The evaluation protocol (folds, image size, epochs): a name under configs/protocols/, a YAML file shipped in
    #: the plugin's package as ``"package:path/in/package.yaml"``, or an absolute path (``harness.protocols``).
    protocol: str = "default"
    #: Environment variable that points at the data, named in error messages.
    root_env: str | None = None
    #: True when preparation runs a sensing stage (radiometric decoding, registration, warp): the report then shows
    #: the sensor-level sections (registration error, C2 under displacement) with the commands that fill them.
    sensing_stage: bool = False

    def __post_init__(self) -> None:
        check_name("dataset", self.name)
        if not callable(self.open):
            raise PluginError(f"dataset {self.name!r}: open must be callable")
        if isinstance(self.protocol, PathLike):
            object.__setattr__(self, "protocol", fspath(self.protocol))
        if not isinstance(self.protocol, str) or not self.protocol:
            raise PluginError(f"dataset {self.name!r}: protocol must be a name, 'package:file.yaml' or an absolute "
                              f"path, got {self.protocol!r}")
        from harness.protocols import protocol_form, shipped_protocol

        if protocol_form(self.protocol) != "name":
            try:
                shipped_protocol(self.protocol)
            except HarnessError as exc:
                raise PluginError(f"dataset {self.name!r}: {exc}") from None
        elif "/" in self.protocol or "\\" in self.protocol:
            raise PluginError(f"dataset {self.name!r}: protocol {self.protocol!r} is a relative path; give a name "
                              "under configs/protocols/, 'package:file.yaml' or an absolute path")
        if self.thermal not in ("radiometric", "8bit"):
            raise PluginError(f"dataset {self.name!r}: thermal must be 'radiometric' or '8bit'")


@dataclass(frozen=True)
class EncodingSpec:
    """A way to make the detector's extra input channel from an aligned sample.

    ``fn(sample, **params) -> uint8 HxW`` (or ``None`` when ``channels == 0``). ``params`` are the defaults,
    overridable from the ``encoding`` section of the config.
    """

    name: str
    fn: Callable[..., "np.ndarray | None"]
    channels: int = 1
    needs: Literal["thermal", "ir8", None] = "thermal"
    description: str = ""
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_name("encoding", self.name)
        if self.channels not in (0, 1):
            raise PluginError(f"encoding {self.name!r}: channels must be 0 or 1")
        if self.needs not in ("thermal", "ir8", None):
            raise PluginError(f"encoding {self.name!r}: needs must be 'thermal', 'ir8' or None")

    def encode(self, sample: "AlignedSample", **overrides: Any) -> "np.ndarray | None":
        if self.needs == "thermal" and sample.thermal is None:
            raise PluginError(
                f"encoding {self.name!r} needs radiometric thermal, but sample {sample.image_id} has only 8-bit "
                f"thermal; use an 8-bit encoding such as 'proxy8' or 'ir8'"
            )
        return self.fn(sample, **{**self.params, **overrides})
