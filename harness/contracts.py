"""Every boundary check of the plugin contracts (``harness.api``): where a plugin's record or output enters the
harness, it is checked here, and every error names the plugin, the field and what was expected.

The records themselves are plain data (``harness.api`` imports nothing of the harness); they are checked where they
enter:

* ``check_registered(spec, record_class)``: what a plugin hands a ``register`` callback is an instance of the hook's
  record class, and ``check_record`` passes it (the host calls it for every registration);
* ``check_record(record)``: ``check_detector_spec``, ``check_dataset_spec`` (with its ``protocol`` file),
  ``check_encoding_spec``, ``check_logger_spec`` or ``check_fold``, by the record's class;
* ``check_name(kind, name)``: names are lower-case identifiers, safe as folders of the results store;
* a ``Fold`` is checked by ``check_folds`` (a dataset's own folds) and where the configuration's folds are built.

What a plugin's code returns:

* ``check_source(source, label)``: what ``DatasetSpec.open`` returned has the ``DatasetSource`` methods, and
  ``check_groups``, ``check_folds``, ``check_fingerprint`` what they return;
* ``validate_sample(sample, num_classes)``: an ``AlignedSample`` against its table (a failing sample is a counted
  skip when a dataset is prepared);
* ``encode(spec, sample, **overrides)``: an encoding run with both sides checked, ``check_encoding_input`` (it gets
  the field it needs) and ``check_encoding_output`` (it returns a uint8 array of the sample's size);
* ``check_detections(det, detector, num_classes, image_size)``: one image's eval-mode output ``{"boxes" [K, 4]
  float, "scores" [K] float, finite, "labels" [K] int in 0..num_classes-1}``, and its boxes as ``harness run``
  judges them: none malformed (NaN or inf, inverted as x, y, w, h boxes often are, zero width or height), and not
  most of them normalised to 0..1 or (given the input's ``image_size``) mostly outside it (the box guard,
  ``harness.scoring.plausibility``). The host itself passes ``counted=True``: it counts and drops malformed boxes
  over the whole held-out fold (``harness.engine.predict``) and applies the guard there;
* ``check_losses(losses, detector)``: the train-mode output, a non-empty dict of scalar (one-element) tensors,
  finite (the host checks finiteness itself, ``finite=False``, to say at which epoch and what to try);
* ``fold_batchnorm(model)``: the host's call of a detector's BatchNorm fold. The host looks for the namespaced
  ``harness_fuse()`` first, then a ``fuse()`` *method defined on the model's class*; an attribute, a sub-module or
  anything else a plugin happens to call ``fuse`` is never called.

``plugin_call(label, what, func, ...)`` runs a plugin's function and turns an exception its code raises (not a
``HarnessError`` it raises on purpose) into a ``PluginError`` naming the plugin, the call and where it was raised
(``where``). ``plugin_label`` names a record's plugin through the host's lookup, which ``harness.plugins`` (the host,
above this module) installs with ``set_owner_lookup`` when it loads; this module never imports the host.
"""

from __future__ import annotations

import inspect
import numbers
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

from harness.errors import HarnessError, PluginError, SampleError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from harness.api import AlignedSample, DatasetSpec, DetectorSpec, EncodingSpec, Fold, LoggerSpec

#: The namespaced name of the BatchNorm fold the host calls on a model (``fuse`` is accepted as a class method).
FUSE_HOOK = "harness_fuse"
#: What an opened dataset must answer (``harness.api.DatasetSource``).
SOURCE_METHODS = ("groups", "folds", "fingerprint", "samples")
_NAME = re.compile(r"^[a-z0-9][a-z0-9_.+-]*$")
#: ``(kind, name) -> plugin``: the host's lookup of who registered a record (``set_owner_lookup``).
_owner_lookup: Callable[[str, str], str | None] | None = None


# ------------------------------------------------------------------------------------------------ who is speaking
def set_owner_lookup(lookup: Callable[[str, str], str | None]) -> None:
    """Install the host's ``(kind, name) -> plugin`` lookup; ``harness.plugins`` calls this when it is imported."""
    global _owner_lookup
    _owner_lookup = lookup


def plugin_label(kind: str, name: str, fallback: Any = None) -> str:
    """``dataset 'NAME' (plugin P)``: how an error names a registered record and the plugin that registered it.
    ``fallback``: a function of the plugin, whose module is named when no loaded plugin registered ``name``."""
    try:
        if _owner_lookup is None:  # no host loaded, so no plugin registered anything
            raise LookupError(name)
        owner: str | None = _owner_lookup(kind, name)
    except Exception:  # noqa: BLE001 - a record no plugin registered (tests, the API) has no owner to name
        owner = getattr(fallback, "__module__", None)
    return f"{kind} {name!r}" + (f" (plugin {owner})" if owner else "")


def where(exc: BaseException) -> str:
    """`` (at file:line)``: the innermost frame outside the harness (the plugin's code) where ``exc`` was raised."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    own = str(Path(__file__).resolve().parent)
    outside = [
        f
        for f in frames
        if not f.filename.startswith("<")
        and "pluggy" not in Path(f.filename).parts
        and not str(Path(f.filename).resolve()).startswith(own)
    ] or frames
    if isinstance(exc, SyntaxError) and exc.filename:
        return f" (at {exc.filename}:{exc.lineno})"
    return f" (at {outside[-1].filename}:{outside[-1].lineno})" if outside else ""


def plugin_call(label: str | Callable[[], str], what: str, func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``func(*args, **kwargs)`` of a plugin; an exception its code raises becomes a ``PluginError`` naming ``label``
    (or what ``label()`` returns, worked out only then), the call (``what``) and where it was raised. A
    ``HarnessError`` passes unchanged."""
    try:
        return func(*args, **kwargs)
    except (HarnessError, KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:
        text = label() if callable(label) else label
        raise PluginError(f"{text}: {what} raised {type(exc).__name__}: {exc}{where(exc)}") from exc


# ------------------------------------------------------------------------------------------------ records
def check_name(kind: str, name: str) -> None:
    """Names are lower-case identifiers that are safe as directory names in the results store."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise PluginError(
            f"invalid {kind} name {name!r}: use lower-case letters, digits and '._+-', starting with a letter or digit"
        )


def check_registered(spec: Any, record: type) -> Any:
    """What a plugin passed to a ``register`` callback: an instance of the hook's record class, which passes
    ``check_record``."""
    if not isinstance(spec, record):
        raise PluginError(f"register() expects a {record.__name__}, got {type(spec).__name__}")
    return check_record(spec)


def check_record(record: Any) -> Any:
    """Check one contract record (``DetectorSpec``, ``DatasetSpec``, ``EncodingSpec``, ``LoggerSpec`` or ``Fold``)
    with its class's check and return it unchanged; a ``PluginError`` names the record and the field."""
    from harness.api import DatasetSpec, DetectorSpec, EncodingSpec, Fold, LoggerSpec

    checks: dict[type, Callable[[Any], None]] = {
        DetectorSpec: check_detector_spec,
        DatasetSpec: check_dataset_spec,
        EncodingSpec: check_encoding_spec,
        LoggerSpec: check_logger_spec,
        Fold: check_fold,
    }
    for cls, check in checks.items():
        if isinstance(record, cls):
            check(record)
            return record
    kinds = ", ".join(c.__name__ for c in checks)
    raise PluginError(f"expected a contract record ({kinds}), got {type(record).__name__}")


def check_detector_spec(spec: DetectorSpec) -> None:
    from harness.api import INPUT_KINDS

    check_name("detector", spec.name)
    if spec.input_kind not in INPUT_KINDS:
        raise PluginError(f"detector {spec.name!r}: input_kind must be one of {INPUT_KINDS}, got {spec.input_kind!r}")
    if not callable(spec.build):
        raise PluginError(f"detector {spec.name!r}: build must be callable")


def check_fold(fold: Fold) -> None:
    overlap = set(fold.train_groups) & set(fold.val_groups)
    if overlap:
        raise PluginError(f"fold {fold.name!r}: groups {sorted(overlap)} are both trained on and held out")


def check_dataset_spec(spec: DatasetSpec) -> None:
    """Name, ``open``, ``thermal`` and ``protocol``: a shipped protocol file must exist when the plugin registers."""
    check_name("dataset", spec.name)
    if not callable(spec.open):
        raise PluginError(f"dataset {spec.name!r}: open must be callable")
    if not isinstance(spec.protocol, str) or not spec.protocol:
        raise PluginError(
            f"dataset {spec.name!r}: protocol must be a name, 'package:file.yaml' or an absolute "
            f"path, got {spec.protocol!r}"
        )
    from harness.protocols import protocol_form, shipped_protocol

    if protocol_form(spec.protocol) != "name":
        try:
            shipped_protocol(spec.protocol)
        except HarnessError as exc:
            raise PluginError(f"dataset {spec.name!r}: {exc}") from None
    elif "/" in spec.protocol or "\\" in spec.protocol:
        raise PluginError(
            f"dataset {spec.name!r}: protocol {spec.protocol!r} is a relative path; give a name "
            "under configs/protocols/, 'package:file.yaml' or an absolute path"
        )
    if spec.thermal not in ("radiometric", "8bit"):
        raise PluginError(f"dataset {spec.name!r}: thermal must be 'radiometric' or '8bit'")


def check_encoding_spec(spec: EncodingSpec) -> None:
    check_name("encoding", spec.name)
    if spec.channels not in (0, 1):
        raise PluginError(f"encoding {spec.name!r}: channels must be 0 or 1")
    if spec.needs not in ("thermal", "ir8", None):
        raise PluginError(f"encoding {spec.name!r}: needs must be 'thermal', 'ir8' or None")
    if not callable(spec.fn):
        raise PluginError(f"encoding {spec.name!r}: fn must be callable")


def check_logger_spec(spec: LoggerSpec) -> None:
    check_name("logger", spec.name)
    if not callable(spec.create):
        raise PluginError(f"logger {spec.name!r}: create must be callable")


# ------------------------------------------------------------------------------------------------ datasets
def check_source(source: Any, label: str) -> Any:
    """What ``DatasetSpec.open`` returned: an object with ``groups()``, ``folds()``, ``fingerprint()`` and
    ``samples(report)``, and ``categories`` (when it has them) a sequence of strings; else a ``PluginError``."""
    missing = [m for m in SOURCE_METHODS if not callable(getattr(source, m, None))]
    if missing:
        raise PluginError(
            f"{label}: open() returned {type(source).__name__}, which has no "
            f"{', '.join(m + '()' for m in missing)}; it must return a DatasetSource (groups(), folds(), "
            f"fingerprint(), samples(report); docs/plugins.md, 'The dataset contract')"
        )
    categories = getattr(source, "categories", None)
    if categories is not None and (
        isinstance(categories, (str, bytes))
        or not isinstance(categories, Sequence)
        or not all(isinstance(c, str) and c for c in categories)
    ):
        raise PluginError(
            f"{label}: the opened source's categories must be a sequence of non-empty strings in label "
            f"order, got {categories!r}"
        )
    return source


def check_groups(groups: Any, label: str) -> list[str]:
    """``groups()``: a list (or tuple) of non-empty strings."""
    if (
        isinstance(groups, (str, bytes))
        or not isinstance(groups, Sequence)
        or not all(isinstance(g, str) and g for g in groups)
    ):
        raise PluginError(f"{label}: groups() must return a list of non-empty strings, got {groups!r}")
    return list(groups)


def check_folds(folds: Any, label: str) -> list[Fold]:
    """``folds()``: a list (or tuple) of ``harness.api.Fold`` records (empty: leave one group out)."""
    from harness.api import Fold

    if isinstance(folds, (str, bytes)) or not isinstance(folds, Sequence):
        raise PluginError(f"{label}: folds() must return a list of Fold records, got {type(folds).__name__}")
    bad = [f for f in folds if not isinstance(f, Fold)]
    if bad:
        raise PluginError(
            f"{label}: folds() must return Fold records (harness.Fold(name, train_groups, "
            f"val_groups)), got {type(bad[0]).__name__} {bad[0]!r}"
        )
    for fold in folds:
        try:
            check_fold(fold)
        except PluginError as exc:
            raise PluginError(f"{label}: folds(): {exc}") from None
    return list(folds)


def check_fingerprint(fingerprint: Any, label: str) -> str:
    """``fingerprint()``: a non-empty string (it keys the prepared cache: anything else would key it on nothing)."""
    if not isinstance(fingerprint, str) or not fingerprint:
        raise PluginError(
            f"{label}: fingerprint() must return a non-empty string that changes whenever the samples "
            f"would, got {fingerprint!r}"
        )
    return fingerprint


def _fail(sample: Any, field_name: str, message: str) -> SampleError:
    from harness.api import AlignedSample

    name = sample.name if isinstance(sample, AlignedSample) else f"sample {getattr(sample, 'image_id', '?')}"
    return SampleError(f"{name}: field {field_name!r}: {message}")


def _check_array(sample: AlignedSample, name: str, value: Any, dtype: Any, ndim: int) -> np.ndarray:
    import numpy as np

    if not isinstance(value, np.ndarray):
        raise _fail(sample, name, f"expected a numpy array, got {type(value).__name__}")
    if value.dtype != dtype:
        raise _fail(sample, name, f"expected dtype {np.dtype(dtype).name}, got {value.dtype.name}")
    if value.ndim != ndim:
        raise _fail(sample, name, f"expected {ndim} dimensions, got shape {tuple(value.shape)}")
    return value


def validate_sample(
    sample: AlignedSample, num_classes: int | None = None, box_tolerance: float = 1e-3
) -> AlignedSample:
    """Check ``sample`` against the contract; return it unchanged or raise ``SampleError`` naming the field."""
    import numpy as np

    from harness.api import AlignedSample

    if not isinstance(sample, AlignedSample):
        raise SampleError(f"expected an AlignedSample, got {type(sample).__name__}")
    if isinstance(sample.image_id, (bool, np.bool_)) or not isinstance(sample.image_id, (int, np.integer)):
        raise _fail(sample, "image_id", f"expected an int, got {type(sample.image_id).__name__}")
    if not isinstance(sample.group, str) or not sample.group:
        raise _fail(sample, "group", "expected a non-empty string (project or sequence)")
    if not isinstance(sample.meta, dict):
        raise _fail(sample, "meta", f"expected a dict, got {type(sample.meta).__name__}")

    ir8 = _check_array(sample, "ir8", sample.ir8, np.uint8, 2)
    h, w = ir8.shape
    if h < 1 or w < 1:
        raise _fail(sample, "ir8", f"empty image of shape {ir8.shape}")
    rgb = _check_array(sample, "rgb", sample.rgb, np.uint8, 3)
    if rgb.shape != (h, w, 3):
        raise _fail(sample, "rgb", f"expected shape {(h, w, 3)} (thermal frame, 3 channels), got {rgb.shape}")
    if sample.thermal is not None:
        th = _check_array(sample, "thermal", sample.thermal, np.float32, 2)
        if th.shape != (h, w):
            raise _fail(sample, "thermal", f"expected shape {(h, w)} like ir8, got {th.shape}")
        if not np.isfinite(th).all():
            from harness.sensing.c2 import MAX_INVALID_FRACTION

            bad = int((~np.isfinite(th)).sum())
            if bad > MAX_INVALID_FRACTION * th.size:
                raise _fail(
                    sample,
                    "thermal",
                    f"{bad} of {th.size} pixels are non-finite temperature values (NaN or "
                    f"inf), more than the {100 * MAX_INVALID_FRACTION:g} % a map may miss",
                )
        from harness.sensing.plausible import sample_problem  # the check every thermal input passes

        problem = sample_problem(th, sample.meta)  # 8-bit counts, byte-swapped floats, Fahrenheit declared as C
        if problem:
            raise _fail(sample, "thermal", problem)

    boxes = _check_array(sample, "boxes", sample.boxes, np.float32, 2)
    if boxes.shape[1] != 4:
        raise _fail(sample, "boxes", f"expected shape (N, 4) xyxy, got {boxes.shape}")
    labels = _check_array(sample, "labels", sample.labels, np.int64, 1)
    if labels.shape[0] != boxes.shape[0]:
        raise _fail(sample, "labels", f"{labels.shape[0]} labels for {boxes.shape[0]} boxes")
    if len(boxes):
        if not np.isfinite(boxes).all():
            raise _fail(sample, "boxes", "non-finite coordinates")
        x1, y1, x2, y2 = boxes.T
        if (x2 <= x1).any() or (y2 <= y1).any():
            i = int(np.nonzero((x2 <= x1) | (y2 <= y1))[0][0])
            raise _fail(sample, "boxes", f"box {i} {boxes[i].tolist()} has zero or negative width/height")
        tol = box_tolerance
        outside = (x1 < -tol) | (y1 < -tol) | (x2 > w + tol) | (y2 > h + tol)
        if outside.any():
            i = int(np.nonzero(outside)[0][0])
            raise _fail(sample, "boxes", f"box {i} {boxes[i].tolist()} lies outside the {w}x{h} frame")
        if (labels < 0).any() or (num_classes is not None and (labels >= num_classes).any()):
            wrong = labels[(labels < 0) | ((labels >= num_classes) if num_classes is not None else False)]
            raise _fail(sample, "labels", f"label {int(wrong[0])} outside 0..{(num_classes or 0) - 1}")
    return sample


def check_unique_id(seen: dict[int, str], sample: Any, where: str, label: str) -> None:
    """Two samples with one ``image_id`` are a ``DataError`` (not a skip: keeping the first would publish a cache
    without the others and every result on it would be wrong). ``seen`` maps the ids so far to where they came from."""
    from harness.errors import DataError

    iid = getattr(sample, "image_id", None)
    if isinstance(iid, numbers.Integral) and not isinstance(iid, bool):
        iid = int(iid)
        if iid in seen:
            raise DataError(
                f"{label}: image_id {iid!r} is given to two samples ({seen[iid]} and {where}); every "
                f"sample needs its own image_id. Nothing was cached"
            )
        seen[iid] = where


# ------------------------------------------------------------------------------------------------ encodings
def encode(spec: EncodingSpec, sample: AlignedSample, **overrides: Any) -> Any:
    """``spec.fn(sample, **spec.params, **overrides)``, checked: what the encoding needs is there, an exception its
    code raises names the encoding and its plugin, and what it returns is a uint8 array of the sample's height and
    width (``None`` for a zero-channel encoding, whose callers know it has none: hence ``Any``)."""
    check_encoding_input(spec, sample)
    out = plugin_call(
        lambda: f"{plugin_label('encoding', spec.name, spec.fn)}: {sample.name}",
        "fn()",
        spec.fn,
        sample,
        **{**spec.params, **overrides},
    )
    return check_encoding_output(spec, sample, out)


def check_encoding_input(spec: EncodingSpec, sample: AlignedSample) -> None:
    """A radiometric encoding asked of a sample that has only 8-bit thermal is a ``PluginError`` saying what to use."""
    if spec.needs == "thermal" and sample.thermal is None:
        raise PluginError(
            f"encoding {spec.name!r} needs radiometric thermal, but sample {sample.image_id} has only 8-bit "
            f"thermal; use an 8-bit encoding such as 'proxy8' or 'ir8'"
        )


def check_encoding_output(spec: EncodingSpec, sample: AlignedSample, out: Any) -> np.ndarray | None:
    """What ``fn`` returned: ``None`` for a zero-channel encoding, else a uint8 numpy array of the sample's height and
    width; anything else is a ``PluginError`` naming the encoding, its plugin, the sample and what came back."""
    import numpy as np

    if spec.channels == 0 and out is None:
        return None
    want = (sample.height, sample.width)
    if isinstance(out, np.ndarray) and out.dtype == np.uint8 and out.shape == want:
        return out
    got = f"a {out.dtype} array of shape {tuple(out.shape)}" if isinstance(out, np.ndarray) else type(out).__name__
    raise PluginError(
        f"{plugin_label('encoding', spec.name, spec.fn)}: {sample.name}: fn returned {got}, expected a "
        f"uint8 numpy array of shape {want}" + (" or None" if spec.channels == 0 else "")
    )


# ------------------------------------------------------------------------------------------------ detectors
def _shape(t: Any) -> str:
    return str(list(t.shape)) if hasattr(t, "shape") else type(t).__name__


def check_detections(
    det: Any,
    detector: str,
    num_classes: int | None = None,
    image_size: tuple[int, int] | None = None,
    counted: bool = False,
) -> tuple[Any, Any, Any]:
    """(boxes [K, 4], scores [K], labels [K]) as numpy arrays, or a ``PluginError`` naming the field (module
    docstring). ``image_size``: the input's (width, height) in pixels, for the test of boxes outside it."""
    import numpy as np
    import torch

    where = f"detector {detector!r}: eval-mode output"
    if not isinstance(det, Mapping):
        raise PluginError(
            f"{where} must be one dict per image with 'boxes', 'scores' and 'labels', got {type(det).__name__}"
        )
    missing = [k for k in ("boxes", "scores", "labels") if k not in det]
    if missing:
        raise PluginError(f"{where} has no {', '.join(repr(k) for k in missing)} (keys: {sorted(map(str, det))})")
    for k in ("boxes", "scores", "labels"):
        if not isinstance(det[k], torch.Tensor):
            raise PluginError(f"{where} field {k!r} must be a tensor, got {type(det[k]).__name__}")
    boxes, scores, labels = det["boxes"], det["scores"], det["labels"]
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise PluginError(f"{where} field 'boxes' must have shape [K, 4] (x1, y1, x2, y2), got {_shape(boxes)}")
    k = boxes.shape[0]
    if scores.ndim != 1 or scores.shape[0] != k:
        raise PluginError(f"{where} field 'scores' must have shape [K] = [{k}], got {_shape(scores)}")
    if labels.ndim != 1 or labels.shape[0] != k:
        raise PluginError(f"{where} field 'labels' must have shape [K] = [{k}], got {_shape(labels)}")
    if labels.dtype.is_floating_point or labels.dtype.is_complex or labels.dtype == torch.bool:
        raise PluginError(f"{where} field 'labels' must be an integer tensor, got {labels.dtype}")
    b = boxes.detach().float().cpu().numpy()
    s = scores.detach().float().cpu().numpy()
    lab = labels.detach().cpu().numpy().astype(np.int64)
    if not np.isfinite(s).all():  # a NaN or inf box is a degenerate box: the caller counts and drops it
        raise PluginError(f"{where} field 'scores' must be finite, got {int((~np.isfinite(s)).sum())} NaN/inf value(s)")
    if num_classes is not None and k and (lab.min() < 0 or lab.max() >= num_classes):
        bad = int(lab.min()) if lab.min() < 0 else int(lab.max())
        hint = f": a model built for {bad + 1} or more classes?" if bad >= num_classes else ": 0-based labels expected"
        raise PluginError(
            f"{where} field 'labels' must lie in 0..{num_classes - 1}, got {bad} (the dataset has {num_classes} "
            f"categories{hint})"
        )
    if not counted and k:
        _check_boxes(b, where, image_size)
    return b, s, lab


def _check_boxes(b: Any, where: str, image_size: tuple[int, int] | None) -> None:
    """What ``harness run`` says of one image's boxes: malformed ones (a warning there, counted over the fold),
    and the box guard's findings (a stop there)."""
    from harness.boxes import DEGENERATE, degenerate_kinds
    from harness.scoring import plausibility as guard

    kind = degenerate_kinds(b)
    bad = kind >= 0
    if bad.any():
        seen = ", ".join(
            f"{int((kind == i).sum())} {DEGENERATE[i].replace('_', ' ')}" for i in range(3) if (kind == i).any()
        )
        raise PluginError(
            f"{where}: {int(bad.sum())} of {len(b)} boxes are malformed ({seen}; e.g. {guard.examples(b, bad)}); "
            f"boxes must be finite x1, y1, x2, y2 with x2 > x1 and y2 > y1 (not x, y, w, h)"
        )
    w, h = image_size if image_size is not None else (float("inf"), float("inf"))
    only = ("normalised", "outside") if image_size is not None else ("normalised",)
    found = guard.box_findings(
        b,
        w,
        h,
        "boxes",
        "input",
        fix_outside="boxes must be in pixels of the input",
        fix_normalised="boxes must be in input pixels",
        only=only,
    )
    if found:
        raise PluginError(f"{where}: {found[0].message}")


def check_built_model(model: Any, detector: str) -> None:
    """What a detector's ``build`` returned must be a ``torch.nn.Module`` (it is trained, put in eval mode, saved):
    anything else (``None`` from a builder that forgot its ``return``, a tuple, a config) is a ``PluginError`` naming
    the detector and the type it got."""
    import torch

    if not isinstance(model, torch.nn.Module):
        raise PluginError(
            f"detector {detector!r}: build(num_classes, ...) returned {type(model).__name__}, not a torch.nn.Module; "
            "the builder must return the model (a missing `return`?)"
        )


def check_class_count(model: Any, detector: str, num_classes: int) -> None:
    """A model that declares fewer classes (``nc`` or ``num_classes``, as an int) than the dataset has: a
    ``PluginError`` naming the detector and both counts, before training would fail on a label it has no output for.
    More is allowed (a background class)."""
    for attr in ("nc", "num_classes"):
        declared = getattr(model, attr, None)
        if isinstance(declared, int) and not isinstance(declared, bool) and declared < num_classes:
            raise PluginError(
                f"detector {detector!r}: the model was built for {declared} classes (model.{attr}), the dataset has "
                f"{num_classes}; build(num_classes, ...) must make a model with num_classes outputs"
            )


def check_losses(losses: Any, detector: str, finite: bool = True) -> Mapping[str, Any]:
    """The train-mode output: a non-empty dict of scalar tensors, finite unless ``finite=False``, else a
    ``PluginError`` naming the entry."""
    import torch

    where = f"detector {detector!r}: in train mode model(inputs, targets)"
    if not isinstance(losses, Mapping) or not losses:
        raise PluginError(
            f"{where} must return a non-empty dict of scalar loss tensors, got "
            f"{type(losses).__name__}{' (empty)' if isinstance(losses, Mapping) else ''}"
        )
    for k, v in losses.items():
        if not isinstance(v, torch.Tensor):
            raise PluginError(f"{where}: loss {k!r} must be a tensor, got {type(v).__name__}")
        if v.numel() != 1:
            raise PluginError(
                f"{where}: loss {k!r} must be a scalar (one element), got shape {_shape(v)}; "
                f"reduce it over the batch (sum or mean) inside the detector"
            )
        if finite and not bool(torch.isfinite(v.detach()).all()):
            raise PluginError(
                f"{where}: loss {k!r} is {float(v.detach().float().reshape(-1)[0])}; harness run stops "
                f"on a loss that is not finite"
            )
    return losses


def fold_batchnorm(model: Any) -> tuple[Any, bool]:
    """Call the model's declared BatchNorm fold (see the module docstring): (folded model, whether it was folded).

    A fold returning a module replaces the model; one returning ``None`` folded in place.
    """
    fn = None
    for name in (FUSE_HOOK, "fuse"):
        attr = inspect.getattr_static(type(model), name, None)
        if inspect.isfunction(attr):
            fn = getattr(model, name)
            break
    if fn is None:
        return model, False
    out = fn()
    if out is not None and hasattr(out, "parameters"):
        return out, True
    return model, True
