"""Configuration: YAML files under ``configs/``, merged in a fixed order, checked against a schema.

Order of precedence (later wins):

1. ``configs/default.yaml``: every known key with its default; this file *is* the schema;
2. ``configs/protocols/<protocol>.yaml``: the evaluation protocol of the dataset (folds, image size, epochs), or
   the YAML a dataset plugin ships in its own package (``harness.protocols``);
3. the detector's own defaults (``DetectorSpec.defaults``) and ``configs/detectors/<detector>.yaml`` if present;
4. ``configs/profiles/<profile>.yaml``: ``smoke`` (small and fast, for CPU), ``demo`` (``make demo``), ``benchmark``
   (the reference results) or ``paper`` (the seed's protocol);
5. files given with ``--config FILE``;
6. ``--set section.key=value`` overrides (values parsed as YAML scalars).

A key that is not in the schema is an error naming the key and the file; so is a value of the wrong type. A
mapping written as ``{}`` in ``default.yaml`` is open (free-form options handed to a plugin, e.g. ``model``), and
a key whose default is ``null`` accepts any type.

``configs/`` is the checkout's folder, or the copy a regular install carries as ``harness.configs`` (``config_dir``);
a ``--config configs/...`` path that is not in the working folder is that copy's file (``config_file``).
"""

from __future__ import annotations

import copy
import difflib
import logging
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from harness.errors import ConfigError
from harness.io import read_text

log = logging.getLogger(__name__)

ENV_CONFIG_DIR = "HARNESS_CONFIG_DIR"
#: The package ``configs/`` is installed as (setup.py); a ``--config configs/...`` path falls back to it.
CONFIGS_PACKAGE = "harness.configs"
BUNDLED_PREFIX = "configs"


def data_package_dir(package: str, marker: str) -> Path | None:
    """The folder of a data package the harness installs (``harness.configs``, ``harness.shipped_references``) that
    holds ``marker``, or None when it is not installed.

    These packages have no ``__init__.py`` (they are namespace packages), so the folder is read from the package's
    search locations: ``importlib.resources.files`` gives a ``MultiplexedPath`` for them, whose ``str`` is not a path.
    A regular install finds ``site-packages/harness/configs``; an editable one the checkout's ``configs/``.
    """
    from importlib.util import find_spec

    try:
        spec = find_spec(package)
    except (ImportError, ValueError):
        return None
    for location in (spec.submodule_search_locations or []) if spec is not None else []:
        if (Path(location) / marker).exists():
            return Path(location)
    return None


def config_dir() -> Path:
    """The folder holding default.yaml, protocols/, profiles/ and detectors/: ``$HARNESS_CONFIG_DIR``, the installed
    ``harness.configs``, or ``configs/`` of the checkout the code runs from."""
    env = os.environ.get(ENV_CONFIG_DIR)
    if env:
        return Path(env)
    installed = data_package_dir(CONFIGS_PACKAGE, "default.yaml")
    if installed is not None:
        return installed
    return Path(__file__).resolve().parent.parent / "configs"


def config_file(path: str | Path) -> Path:
    """A ``--config`` file: the path as given when it exists; otherwise a relative ``configs/<rest>`` (the files the
    project ships, e.g. ``configs/demo/ours.yaml``) is the installed copy ``<config_dir()>/<rest>`` when that exists,
    so the commands of the documentation work from any folder. Anything else is returned unchanged (and reading it
    names the missing file)."""
    given = Path(path)
    if given.exists() or given.is_absolute() or not given.parts or given.parts[0] != BUNDLED_PREFIX:
        return given
    bundled = config_dir().joinpath(*given.parts[1:])
    if bundled.is_file():
        log.debug("%s: not in %s, using the installed copy %s", path, Path.cwd(), bundled)
        return bundled
    return given


class _Loader(yaml.SafeLoader):
    """Safe loader that refuses duplicate keys (a common silent mistake in hand-edited YAML)."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: set = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
        seen.add(key)
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping with ``safe_load`` semantics; errors name the file and the line."""
    path = Path(path)
    text = read_text(path, ConfigError, "config file")
    try:
        data = yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{path}: invalid YAML{where}: {problem}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def dump_yaml(data: Mapping[str, Any]) -> str:
    return yaml.safe_dump(_plain(data), sort_keys=False, default_flow_style=None, width=120)


def _plain(obj: Any) -> Any:
    """Turn tuples, paths and numpy scalars into YAML-safe builtins."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "item") and callable(obj.item):
        return obj.item()
    return obj


def schema() -> dict[str, Any]:
    return read_yaml(config_dir() / "default.yaml")


def _type_ok(default: Any, value: Any) -> bool:
    if default is None or value is None:
        return True
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, int):
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(default, float):
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if isinstance(default, str):
        return isinstance(value, str)
    if isinstance(default, list):
        return isinstance(value, (list, tuple))
    if isinstance(default, dict):
        return isinstance(value, dict)
    return True


def merge(
    base: dict[str, Any], update: Mapping[str, Any], schema_node: Mapping[str, Any] | None, source: str, path: str = ""
) -> dict[str, Any]:
    """Merge ``update`` into a copy of ``base``, checking keys and types against ``schema_node``."""
    out = copy.deepcopy(base)
    for key, value in update.items():
        dotted = f"{path}{key}"
        if schema_node is not None and key not in schema_node:
            known = sorted(map(str, schema_node))
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f"; did you mean '{path}{close[0]}'?" if close else ""
            raise ConfigError(f"{source}: unknown key {dotted!r}{hint} (known keys here: {', '.join(known) or 'none'})")
        default = schema_node.get(key) if schema_node is not None else None
        if schema_node is not None and not _type_ok(default, value):
            raise ConfigError(
                f"{source}: key {dotted!r} expects {type(default).__name__}, got {type(value).__name__} ({value!r})"
            )
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            open_map = isinstance(default, dict) and not default
            out[key] = merge(
                out[key], value, None if (open_map or schema_node is None) else default, source, dotted + "."
            )
        else:
            out[key] = copy.deepcopy(_plain(value))
    return out


def parse_override(item: str) -> dict[str, Any]:
    """``"train.epochs=3"`` -> ``{"train": {"epochs": 3}}`` (the value is parsed as a YAML scalar)."""
    if "=" not in item:
        raise ConfigError(f"override {item!r}: expected section.key=value")
    dotted, raw = item.split("=", 1)
    keys = [k for k in dotted.strip().split(".") if k]
    if not keys:
        raise ConfigError(f"override {item!r}: empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {item!r}: value is not valid YAML ({exc})") from None
    node: dict[str, Any] = {}
    cur = node
    for k in keys[:-1]:
        cur = cur.setdefault(k, {})
    cur[keys[-1]] = value
    return node


#: ``protocol.imgsz`` is a multiple of this (the detectors' largest stride; the trainer needs it)
IMGSZ_STRIDE = 32

#: Ranges of the numeric keys the harness reads itself: (low, high, low included, high included, integer); None is
#: unbounded. Checked once the layers are merged, so a bad value stops before anything is prepared or trained.
_RANGES: dict[tuple[str, str], tuple[float | None, float | None, bool, bool, bool]] = {
    **{("protocol", k): (1, None, True, True, True) for k in ("imgsz", "epochs")},
    ("protocol", "patience"): (0, None, True, True, True),
    **{
        ("train", k): (1, None, True, True, True)
        for k in ("batch", "nominal_batch", "val_period", "threads", "max_images")
    },
    **{("train", k): (0, None, False, True, False) for k in ("lr0", "lrf", "ema_tau")},
    **{
        ("train", k): (0, None, True, True, False)
        for k in ("weight_decay", "warmup_epochs", "warmup_bias_lr", "clip_grad")
    },
    **{("train", k): (0, None, True, True, True) for k in ("warmup_min_iters", "close_mosaic", "workers")},
    **{("train", k): (0, 1, True, False, False) for k in ("momentum", "ema_decay")},
    ("train", "warmup_momentum"): (0, 1, True, True, False),
    **{("augment", k): (0, 1, True, True, False) for k in ("mosaic", "hsv_h", "hsv_s", "hsv_v", "fliplr", "flipud")},
    **{("augment", k): (0, 1, True, False, False) for k in ("translate", "scale")},
    **{("augment", k): (0, None, True, True, False) for k in ("degrees", "shear", "perspective")},
    ("eval", "conf"): (0, 1, True, True, False),
    ("eval", "iou"): (0, 1, False, True, False),
    **{("eval", k): (1, None, True, True, True) for k in ("max_det", "batch")},
}


def _range_text(low: float | None, high: float | None, low_in: bool, high_in: bool, integer: bool) -> str:
    kind = "an integer" if integer else "a number"
    if high is None:
        return f"{kind} {'>=' if low_in else '>'} {low:g}"
    return f"{kind} in {'[' if low_in else '('}{low:g}, {high:g}{']' if high_in else ')'}"


def check_values(cfg: Mapping[str, Any], layers: Iterable[tuple[str, Mapping[str, Any]]] = ()) -> None:
    """Every numeric key the harness reads is finite and in its range (``_RANGES``); a value out of range is a
    ``ConfigError`` naming the key, the value, the range and the layer that set it (``--set``, a file)."""
    import math

    for (section, key), (low, high, low_in, high_in, integer) in _RANGES.items():
        value = (cfg.get(section) or {}).get(key) if isinstance(cfg.get(section), Mapping) else None
        if value is None:
            continue
        bad = isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
        if not bad:
            below = low is not None and (value < low if low_in else value <= low)
            above = high is not None and (value > high if high_in else value >= high)
            bad = (integer and float(value) != int(value)) or below or above
        if bad:
            source = next(
                (
                    src
                    for src, layer in reversed(list(layers))
                    if isinstance(layer.get(section), Mapping) and key in layer[section]
                ),
                "the configuration",
            )
            raise ConfigError(
                f"{source}: {section}.{key}={value!r} must be {_range_text(low, high, low_in, high_in, integer)}"
            )
    size = (cfg.get("protocol") or {}).get("imgsz") if isinstance(cfg.get("protocol"), Mapping) else None
    if isinstance(size, int) and not isinstance(size, bool) and size % IMGSZ_STRIDE:
        source = next(
            (src for src, layer in reversed(list(layers)) if "imgsz" in (layer.get("protocol") or {})),
            "the configuration",
        )
        raise ConfigError(
            f"{source}: protocol.imgsz={size} must be a multiple of {IMGSZ_STRIDE} (the detectors' largest stride), "
            f"e.g. {max(IMGSZ_STRIDE, size // IMGSZ_STRIDE * IMGSZ_STRIDE)}"
        )


#: Memory of one image per input pixel (bytes, at ``protocol.imgsz`` squared) in a training step (forward + backward:
#: the letterboxed tensors and the detector's activations) and in a prediction (no gradients). Measured with
#: ``benchmarks/imgsz_memory.py`` (the growth of peak memory from 256 to 384 px, batch 2, on CPU): ours 1015, CMA-Det
#: 1480, EME 2773, ICAFusion 3800 for training; ours 166, ICAFusion 174 for prediction. The lightest is taken, so the
#: bound refuses only what no built-in detector could hold.
TRAIN_BYTES_PER_PIXEL = 1000
EVAL_BYTES_PER_PIXEL = 160
#: Data-loader worker processes (``train.workers``) and ``--workers`` per CPU core at most (each is a process with
#: its own copy of the loader); never fewer than ``MIN_WORKER_CAP``.
MAX_WORKERS_PER_CPU = 4
MIN_WORKER_CAP = 8
#: Most epochs a run may ask for: 10x the longest schedules of the field's detectors (YOLO's 300-500, the paper's
#: 150); a count past it is a slip of the keyboard that would hold the machine for years, not a training plan.
MAX_EPOCHS = 5000


def worker_cap() -> int:
    """The most worker processes a setting or ``--workers`` may ask for on this machine."""
    return max(MIN_WORKER_CAP, MAX_WORKERS_PER_CPU * (os.cpu_count() or 1))


def memory_needed(cfg: Mapping[str, Any]) -> dict[str, int]:
    """Bytes a training step (``train``: ``TRAIN_BYTES_PER_PIXEL x imgsz^2 x train.batch``) and a prediction
    (``eval``: ``EVAL_BYTES_PER_PIXEL x imgsz^2 x eval.batch``) of ``cfg`` need at least."""
    size = int((cfg.get("protocol") or {}).get("imgsz") or 0)
    out = {}
    for section, per_pixel in (("train", TRAIN_BYTES_PER_PIXEL), ("eval", EVAL_BYTES_PER_PIXEL)):
        batch = int((cfg.get(section) or {}).get("batch") or 1)
        out[section] = per_pixel * size * size * batch
    return out


def available_memory(device: str = "auto") -> tuple[int, str]:
    """(bytes, what they are) the activations of ``device`` (``train.device``) can use: a CUDA device's total memory
    where the device is CUDA (``auto`` with an NVIDIA driver present), else the host's ``MemAvailable``
    (``/proc/meminfo``), else 0 (unknown: no bound)."""
    dev = str(device or "auto")
    if dev.startswith("cuda") or (dev == "auto" and os.path.exists("/dev/nvidiactl")):
        try:
            import torch

            if torch.cuda.is_available():
                index = int(dev.split(":")[1]) if ":" in dev else 0
                total = int(torch.cuda.get_device_properties(index).total_memory)
                return total, f"the memory of {dev if dev != 'auto' else 'cuda:0'}"
        except Exception:  # noqa: BLE001 - no usable GPU: the host's memory is what a CPU run uses
            pass
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024, "the memory available on this machine (MemAvailable)"
    except OSError:
        pass
    return 0, "unknown"


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n < 2**40 else f"{n / 2**40:.1f} TiB"


def check_bounds(cfg: Mapping[str, Any], layers: Iterable[tuple[str, Mapping[str, Any]]] = ()) -> None:
    """Settings that would exhaust the machine stop before any work: ``train.workers`` above ``worker_cap()``,
    ``protocol.epochs`` above ``MAX_EPOCHS``, and an image size x batch whose memory (``memory_needed``, a lower
    estimate) exceeds ``available_memory``. The ``ConfigError`` names the keys, the layer that set them, the memory
    needed and the memory there is."""
    layers = list(layers)

    def source(*keys: tuple[str, str]) -> str:
        for src, layer in reversed(layers):
            if any(isinstance(layer.get(sec), Mapping) and k in layer[sec] for sec, k in keys):
                return src
        return "the configuration"

    workers = (cfg.get("train") or {}).get("workers")
    if isinstance(workers, int) and workers > worker_cap():
        raise ConfigError(
            f"{source(('train', 'workers'))}: train.workers={workers} asks for more worker processes than "
            f"{worker_cap()} ({MAX_WORKERS_PER_CPU} per CPU core, {os.cpu_count()} here); use at most {worker_cap()}"
        )
    epochs = (cfg.get("protocol") or {}).get("epochs")
    if isinstance(epochs, int) and not isinstance(epochs, bool) and epochs > MAX_EPOCHS:
        raise ConfigError(
            f"{source(('protocol', 'epochs'))}: protocol.epochs={epochs} is more than {MAX_EPOCHS} epochs (10x the "
            f"longest schedules of the field's detectors); use at most {MAX_EPOCHS}"
        )
    need = memory_needed(cfg)
    have, where = available_memory(str((cfg.get("train") or {}).get("device") or "auto"))
    if not have:
        return
    size = int((cfg.get("protocol") or {}).get("imgsz") or 0)
    for section, per_pixel in (("train", TRAIN_BYTES_PER_PIXEL), ("eval", EVAL_BYTES_PER_PIXEL)):
        if need[section] <= have:
            continue
        batch = int((cfg.get(section) or {}).get("batch") or 1)
        fits = int((have / (per_pixel * batch)) ** 0.5) // 32 * 32
        raise ConfigError(
            f"{source(('protocol', 'imgsz'), (section, 'batch'))}: protocol.imgsz={size} with {section}.batch={batch} "
            f"needs at least {_gib(need[section])} ({per_pixel} bytes per pixel per image, {size}x{size} x {batch}); "
            f"{where} is {_gib(have)}: lower protocol.imgsz (at most {fits} at this batch) or {section}.batch"
        )


def _named_file(root: Path, kind: str, name: str, option: str) -> Path:
    """``<root>/<kind>/<name>.yaml`` for a profile, protocol or detector name; a name that is a path (``../x``,
    ``a/b``, an absolute path) is refused, so a name can never read a file outside the config folder."""
    if not name or name in (".", "..") or any(c in name for c in ("/", "\\", "\x00")) or os.path.isabs(name):
        raise ConfigError(
            f"{option} {name!r}: expected a plain name such as those under {root / kind} "
            f"(available: {', '.join(available(kind)) or 'none'}); to use your own file, pass --config FILE"
        )
    return root / kind / f"{name}.yaml"


def available(kind: str) -> list[str]:
    folder = config_dir() / kind
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.exists() else []


def load_config(
    profile: str | None = None,
    protocol: str | None = None,
    detector: str | None = None,
    detector_defaults: Mapping[str, Any] | None = None,
    files: Iterable[str | Path] = (),
    overrides: Iterable[str] = (),
) -> dict[str, Any]:
    """Resolve a run's configuration (see the module docstring for the order)."""
    root = config_dir()
    sch = schema()
    cfg = copy.deepcopy(sch)
    layers: list[tuple[str, Mapping[str, Any]]] = []
    if protocol:
        from harness.protocols import shipped_protocol

        path = shipped_protocol(protocol) or _named_file(root, "protocols", protocol, "protocol")
        if not path.exists():
            raise ConfigError(
                f"unknown protocol {protocol!r}: no {path} (available: {', '.join(available('protocols'))})"
            )
        layers.append((str(path), read_yaml(path)))
    if detector_defaults:
        layers.append((f"defaults of detector {detector!r}", detector_defaults))
    if detector and _named_file(root, "detectors", detector, "detector").exists():
        path = _named_file(root, "detectors", detector, "detector")
        layers.append((str(path), read_yaml(path)))
    if profile:
        path = _named_file(root, "profiles", profile, "--profile")
        if not path.exists():
            raise ConfigError(f"unknown profile {profile!r}: no {path} (available: {', '.join(available('profiles'))})")
        layers.append((str(path), read_yaml(path)))
    for f in files:
        path = config_file(f)
        layers.append((str(f) if path == Path(f) else str(path), read_yaml(path)))
    for item in overrides:
        layers.append((f"--set {item}", parse_override(item)))
    for source, layer in layers:
        cfg = merge(cfg, layer, sch, source)
    check_values(cfg, layers)
    check_bounds(cfg, layers)
    cfg.setdefault("meta", {})
    cfg["meta"] = {**cfg.get("meta", {}), "profile": profile, "protocol": protocol, "sources": [s for s, _ in layers]}
    return cfg
