"""The ``mlflow`` tracker: one MLflow run per harness run (``pip install 'rgbt-harness[mlflow]'``).

Store: ``tracking.mlflow_uri`` when given (any MLflow tracking URI: a server, a database), else the environment's
``MLFLOW_TRACKING_URI``, else a local SQLite store ``sqlite:///<store>/mlflow.db`` with artefacts under
``<store>/mlartifacts`` (browse it with ``mlflow ui --backend-store-uri sqlite:///<store>/mlflow.db``). Experiment:
``tracking.mlflow_experiment`` (default ``rgbt-harness``). Each run logs its flattened configuration as parameters,
the run's identity as tags, one metric per epoch and metric (``loss/box``, ``val/mAP50`` ... at step = epoch), the
held-out metrics (``test/mAP50`` ...), and artefacts such as the report. Written through ``MlflowClient``, so several
runs in one process never share MLflow's global "active run".
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Mapping

from harness.hookspecs import hookimpl
from harness.tracking import TrackingOptions, builtin_spec

DEFAULT_EXPERIMENT = "rgbt-harness"
#: MLflow's limits: entries per log_batch call, characters per parameter value
BATCH = 100
MAX_PARAM_CHARS = 500


def tracking_uri(options: TrackingOptions) -> str:
    if options.mlflow_uri:
        return options.mlflow_uri
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if env:
        return env
    return f"sqlite:///{options.store.resolve() / 'mlflow.db'}"


#: the description of this tracker in its ``LoggerSpec``
DESCRIPTION = "MLflow runs (local sqlite:///<store>/mlflow.db unless tracking.mlflow_uri / MLFLOW_TRACKING_URI)"


class MLflowLogger:
    def __init__(self, options: TrackingOptions):
        self.options = options
        self.uri = tracking_uri(options)
        if self.uri.startswith("sqlite:"):
            import importlib.util

            missing = [m for m in ("sqlalchemy", "alembic") if importlib.util.find_spec(m) is None]
            if missing:
                raise RuntimeError(
                    f"the SQLite store {self.uri} needs {', '.join(missing)}; pip install "
                    f"'rgbt-harness[mlflow]', or give a server as tracking.mlflow_uri"
                )
        self.client: Any = None
        self.run_id: str | None = None
        self.step = 0

    def _experiment(self) -> str:
        name = self.options.mlflow_experiment or DEFAULT_EXPERIMENT
        exp = self.client.get_experiment_by_name(name)
        if exp is not None:
            return exp.experiment_id
        local = (
            self.uri.startswith("sqlite:") and not self.options.mlflow_uri and "MLFLOW_TRACKING_URI" not in os.environ
        )
        where = (self.options.store.resolve() / "mlartifacts").as_uri() if local else None
        try:
            return self.client.create_experiment(name, artifact_location=where)
        except Exception:  # created by another process meanwhile
            exp = self.client.get_experiment_by_name(name)
            if exp is None:
                raise
            return exp.experiment_id

    def start(self, name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> None:
        from mlflow.entities import Param, RunTag
        from mlflow.tracking import MlflowClient

        if self.uri.startswith("sqlite:"):
            self.options.store.mkdir(parents=True, exist_ok=True)
        self.client = MlflowClient(tracking_uri=self.uri)
        run = self.client.create_run(
            self._experiment(),
            run_name=name,
            tags={"harness.kind": self.options.group, **{k: str(v) for k, v in tags.items()}},
        )
        self.run_id = run.info.run_id
        items = [Param(k, str(v)[:MAX_PARAM_CHARS]) for k, v in params.items()]
        for i in range(0, len(items), BATCH):
            self.client.log_batch(self.run_id, params=items[i : i + BATCH])
        self.client.log_batch(self.run_id, tags=[RunTag("harness.uri", self.uri)])

    def _metrics(self, metrics: Mapping[str, float], step: int) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v in metrics.items()]
        for i in range(0, len(items), BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + BATCH])

    def log_epoch(self, step: int, metrics: Mapping[str, float]) -> None:
        self.step = int(step)
        self._metrics(metrics, self.step)

    def log_final(self, metrics: Mapping[str, float]) -> None:
        self._metrics(metrics, self.step)

    def log_artifact(self, path: Path) -> None:
        self.client.log_artifact(self.run_id, str(path))

    def finish(self, status: str) -> None:
        if self.client is not None and self.run_id is not None:
            self.client.set_terminated(self.run_id, status=status)
            self.run_id = None


@hookimpl
def register_loggers(register):
    register(builtin_spec("mlflow", MLflowLogger, DESCRIPTION))
