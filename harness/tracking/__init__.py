"""Experiment tracking: loggers that mirror a run into a tracking tool, beside the built-in ``log.jsonl``.

The results store stays the record (``log.jsonl``, ``metrics.json``); trackers are copies for the tools people
browse runs with. A tracker is a plugin: ``register_loggers(register)`` (``harness.hookspecs``) declares a
``LoggerSpec`` whose ``create(options)`` returns a ``RunLogger``. The built-in ones are ``tensorboard``
(``harness.tracking.tensorboard_logger``, event files) and ``mlflow`` (``harness.tracking.mlflow_logger``, a local
SQLite store by default); each needs its optional extra (``pip install 'rgbt-harness[tensorboard,mlflow]'``).

Which trackers a run uses is configuration (``tracking.loggers``, or ``--log-to mlflow,tensorboard`` on ``run``,
``ablate``, ``sweep`` and ``report``); the ``tracking`` section is not part of a run's identity, so turning a
tracker on never makes a finished run look different.

A ``RunLogger`` is called in this order by the runner: ``start(name, params, tags)`` once, ``log_epoch(step,
metrics)`` after every epoch, ``log_final(metrics)`` once the held-out fold is scored, ``log_artifact(path)`` for
files worth keeping, ``finish(status)`` at the end (``"FINISHED"`` or ``"FAILED"``). Metric names are flat
(``loss/box``, ``val/mAP50``, ``test/mAP50_95``); values are finite floats (a missing or NaN value is left out,
never sent as zero). A logger that raises is reported by name and switched off for the rest of the run: tracking
never loses a run's results.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from harness.api import LoggerSpec, RunLogger, TrackingOptions  # re-exported for plugins
from harness.errors import ConfigError

log = logging.getLogger(__name__)


def builtin_spec(name: str, create: Callable[[TrackingOptions], RunLogger], description: str) -> LoggerSpec:
    """A built-in tracker's ``LoggerSpec``: it needs the package of its name, installed by the extra of its name."""
    return LoggerSpec(name=name, create=create, requires=(name,), extra=name, description=description)


def parse_names(text: str | Sequence[str] | None) -> list[str]:
    """``"mlflow, tensorboard"`` or a list -> names, in order, without duplicates or blanks."""
    if not text:
        return []
    items = text.split(",") if isinstance(text, str) else list(text)
    return list(dict.fromkeys(str(s).strip() for s in items if str(s).strip()))


def log_to_overrides(text: str | None) -> tuple[str, ...]:
    """``--log-to mlflow,tensorboard`` as the ``--set`` override it stands for."""
    names = parse_names(text)
    return (f"tracking.loggers=[{','.join(names)}]",) if names else ()


def resolve(names: Iterable[str]) -> list[LoggerSpec]:
    """The specs of ``names``; an unknown name or a missing optional package is a ``ConfigError`` that says what to
    install, raised before anything is trained."""
    from harness.plugins import get_host

    host = get_host()
    specs = []
    for name in parse_names(list(names)):
        spec = host.logger(name)
        missing = spec.missing()
        if missing:
            how = f"pip install 'rgbt-harness[{spec.extra}]'" if spec.extra else f"pip install {' '.join(missing)}"
            raise ConfigError(
                f"tracking.loggers: logger {name!r} needs {', '.join(missing)}, which is not installed; {how}"
            )
        specs.append(spec)
    return specs


class Tracker:
    """The loggers of one run, called together; each call to a logger that raises switches that logger off with a
    warning naming it, so the run and its stored results go on."""

    def __init__(self, loggers: Sequence[tuple[str, RunLogger]] = ()):
        self.loggers = list(loggers)
        self.problems: list[str] = []

    def __bool__(self) -> bool:
        return bool(self.loggers)

    def _call(self, method: str, *args: Any) -> None:
        for name, lg in list(self.loggers):
            try:
                getattr(lg, method)(*args)
            except Exception as exc:  # a broken tracker must not take the run down
                msg = f"logger {name!r} failed in {method}: {type(exc).__name__}: {exc}; switched off for this run"
                log.warning(msg)
                self.problems.append(msg)
                self.loggers.remove((name, lg))
                if method != "finish":
                    try:
                        lg.finish("FAILED")
                    except Exception:  # noqa: BLE001  already reported
                        pass

    def start(self, name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> None:
        self._call("start", name, params, tags)

    def log_epoch(self, step: int, metrics: Mapping[str, float]) -> None:
        self._call("log_epoch", step, metrics)

    def log_final(self, metrics: Mapping[str, float]) -> None:
        self._call("log_final", metrics)

    def log_artifact(self, path: Path) -> None:
        self._call("log_artifact", Path(path))

    def finish(self, status: str) -> None:
        self._call("finish", status)


def open_tracker(names: Iterable[str], options: TrackingOptions) -> Tracker:
    """A ``Tracker`` over the named loggers (none: an empty tracker whose calls do nothing)."""
    loggers = []
    for spec in resolve(names):
        try:
            loggers.append((spec.name, spec.create(options)))
        except Exception as exc:
            raise ConfigError(f"logger {spec.name!r} could not be created: {type(exc).__name__}: {exc}") from exc
    return Tracker(loggers)


# ------------------------------------------------------------------------------------------------- the runner's
def for_run(cfg: Mapping[str, Any], store: str | Path) -> Tracker:
    """The tracker of one run from its configuration (``tracking.loggers``); empty when none is asked for."""
    return open_tracker((cfg.get("tracking") or {}).get("loggers") or [], TrackingOptions.from_config(cfg, store))


def flatten_params(cfg: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """``{"train": {"lr0": 0.01}}`` -> ``{"train.lr0": "0.01"}``; lists and ``None`` as text."""
    out: dict[str, str] = {}
    for k, v in cfg.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(flatten_params(v, key + "."))
        else:
            out[key] = "" if v is None else str(v)
    return out


def _finite(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _put(out: dict[str, float], key: str, value: Any) -> None:
    f = _finite(value)
    if f is not None:
        out[key] = f


def epoch_metrics(record: Mapping[str, Any]) -> dict[str, float]:
    """The flat metrics of one ``log.jsonl`` record: ``loss/<component>``, ``loss/total``, ``val/<metric>``,
    ``lr``, ``fitness``, ``time_s``, ``images_per_s``."""
    out: dict[str, float] = {}
    losses = record.get("loss") or {}
    for k, v in losses.items():
        _put(out, f"loss/{k}", v)
    parts = [_finite(v) for v in losses.values()]
    if parts and all(p is not None for p in parts):
        out["loss/total"] = float(sum(p for p in parts if p is not None))
    for k, v in (record.get("metrics") or {}).items():
        if k != "AP50_per_category":
            _put(out, f"val/{k}", v)
    lrs = [f for f in (_finite(v) for v in (record.get("lr") or {}).values()) if f is not None]
    if lrs:
        out["lr"] = max(lrs)
    for k in ("fitness", "time_s", "images_per_s"):
        _put(out, k, record.get(k))
    return out


def final_metrics(metrics: Mapping[str, Any]) -> dict[str, float]:
    """The flat metrics of a run's ``metrics.json``: ``test/<metric>``, ``test/AP50/<category>``, ``support/*``,
    ``model/params``."""
    out: dict[str, float] = {}
    for k, v in (metrics.get("metrics") or {}).items():
        _put(out, f"test/{k}", v)
    for cat, v in (metrics.get("per_category") or {}).items():
        if isinstance(v, Mapping):
            _put(out, f"test/AP50/{cat}", v.get("AP50"))
    for k in ("images", "instances"):
        _put(out, f"support/{k}", (metrics.get("support") or {}).get(k))
    _put(out, "model/params", (metrics.get("model") or {}).get("params"))
    return out


# ------------------------------------------------------------------------------------------------- the report's
def log_report(
    names: Iterable[str], store: str | Path, files: Sequence[Path], title: str, cfg: Mapping[str, Any] | None = None
) -> list[str]:
    """Log a report's files as artefacts of one tracking run named after it; returns the problems (empty: all
    loggers took it)."""
    tracker = open_tracker(names, TrackingOptions.from_config(cfg or {}, store, group="report"))
    if not tracker:
        return []
    tracker.start(title, {"store": str(store)}, {"kind": "report"})
    for f in files:
        tracker.log_artifact(Path(f))
    tracker.finish("FINISHED")
    return tracker.problems


__all__ = [
    "LoggerSpec",
    "RunLogger",
    "Tracker",
    "TrackingOptions",
    "epoch_metrics",
    "final_metrics",
    "flatten_params",
    "for_run",
    "log_report",
    "log_to_overrides",
    "open_tracker",
    "parse_names",
    "resolve",
]
