"""What a tracker plugin implements and registers: ``RunLogger``, ``TrackingOptions`` and ``LoggerSpec``.

Kept apart from ``harness.tracking`` (which finds trackers through the plugin host) so that the host and the hook
specifications can name ``LoggerSpec`` without importing the host back. ``harness.tracking`` re-exports all three.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol


class RunLogger(Protocol):
    """What a tracker implements (see the module docstring for the order of calls)."""

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

    ``requires``: the import name of the package it needs and ``extra`` the harness extra that installs it, so a
    missing package is reported as ``pip install 'rgbt-harness[extra]'`` before any run starts.
    """

    name: str
    create: Callable[[TrackingOptions], RunLogger]
    description: str = ""
    requires: tuple[str, ...] = ()
    extra: str | None = None

    def __post_init__(self) -> None:
        if not self.name or not isinstance(self.name, str) or "," in self.name:
            raise ValueError(f"LoggerSpec.name must be a non-empty name without commas, got {self.name!r}")
        if not callable(self.create):
            raise ValueError(f"logger {self.name!r}: create must be callable")

    def missing(self) -> list[str]:
        import importlib.util

        return [m for m in self.requires if importlib.util.find_spec(m) is None]
