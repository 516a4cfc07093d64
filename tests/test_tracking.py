"""Experiment tracking: the logger hook, the tracker fan-out, and real MLflow / TensorBoard read-back of a 1-epoch
run."""

from __future__ import annotations

import importlib.util
import json
import math

import pytest

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from engine_helpers import fast_overrides, shapes_and_tinydet
from harness import hookimpl
from harness.errors import ConfigError
from harness.testing import temporary_plugin
from harness.tracking import LoggerSpec, Tracker, epoch_metrics, final_metrics, flatten_params, log_to_overrides

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ONE_EPOCH = fast_overrides(epochs=1, warmup_epochs=0)


def _has(*modules: str) -> bool:
    return all(importlib.util.find_spec(m) is not None for m in modules)


needs_mlflow = pytest.mark.skipif(
    not _has("mlflow", "sqlalchemy", "alembic"), reason="MLflow is not installed (pip install 'rgbt-harness[mlflow]')"
)
needs_tensorboard = pytest.mark.skipif(
    not _has("tensorboard"), reason="TensorBoard is not installed (pip install 'rgbt-harness[tensorboard]')"
)


@pytest.fixture
def plugins(host, tmp_path, monkeypatch):
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    with shapes_and_tinydet("test"):
        yield host


def one_run(tmp_path, loggers: str, **kw):
    from harness.runner import RunRequest, run

    req = RunRequest(
        detector="tinydet",
        dataset="shapes",
        folds="A",
        store=tmp_path / "store",
        progress=False,
        overrides=[*ONE_EPOCH, *log_to_overrides(loggers)],
        **kw,
    )
    summary = run(req)
    (result,) = summary.results
    log = [json.loads(line) for line in (result.path / "log.jsonl").read_text().splitlines()]
    return result, log


# ------------------------------------------------------------------------------------------------- real libraries
@needs_mlflow
def test_mlflow_client_reads_back_a_real_run_and_a_report(plugins, tmp_path):
    from mlflow.tracking import MlflowClient

    from harness.tracking import log_report

    result, log = one_run(tmp_path, "mlflow")
    store = tmp_path / "store"
    client = MlflowClient(tracking_uri=f"sqlite:///{store / 'mlflow.db'}")
    exp = client.get_experiment_by_name("rgbt-harness")
    (run,) = client.search_runs([exp.experiment_id])
    assert run.info.run_name == str(result.key) and run.info.status == "FINISHED"
    assert run.data.params["train.batch"] == "8" and run.data.params["protocol.epochs"] == "1"
    assert run.data.tags["detector"] == "tinydet" and run.data.tags["fold"] == "A"
    history = client.get_metric_history(run.info.run_id, "loss/total")
    assert [m.step for m in history] == [1]
    assert history[0].value == pytest.approx(sum(log[0]["loss"].values()), rel=1e-6)
    stored = result.metrics["metrics"]
    for k in ("mAP50", "mAP50_95"):
        if stored.get(k) is not None:
            assert run.data.metrics[f"test/{k}"] == pytest.approx(stored[k])
    if log[0]["metrics"] and log[0]["metrics"].get("mAP50") is not None:
        assert run.data.metrics["val/mAP50"] == pytest.approx(log[0]["metrics"]["mAP50"])
    assert {"config.yaml", "metrics.json", "log.jsonl"} <= {a.path for a in client.list_artifacts(run.info.run_id)}

    page = tmp_path / "report.html"
    page.write_text("<html>report</html>")
    assert log_report(["mlflow"], store, [page], "Benchmark report") == []
    reports = client.search_runs([exp.experiment_id], filter_string="tags.`harness.kind` = 'report'")
    assert len(reports) == 1 and [a.path for a in client.list_artifacts(reports[0].info.run_id)] == ["report.html"]


@needs_tensorboard
def test_tensorboard_event_file_reads_back_and_tracking_leaves_the_run_identity_alone(plugins, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    result, log = one_run(tmp_path, "tensorboard")
    folder = tmp_path / "store" / "tensorboard" / str(result.key)
    assert list(folder.glob("events.out.tfevents.*")), f"no event file in {folder}"
    acc = EventAccumulator(str(folder))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    assert {"loss/total", "lr", "fitness"} <= set(tags)
    for comp, value in log[0]["loss"].items():
        (event,) = acc.Scalars(f"loss/{comp}")
        assert event.step == 1 and event.value == pytest.approx(value, rel=1e-5)
    mAP = result.metrics["metrics"].get("mAP50")
    if mAP is not None:
        assert acc.Scalars("test/mAP50")[-1].value == pytest.approx(mAP, rel=1e-5)

    again, _ = one_run(tmp_path, "")  # the same run without a tracker: finished, same identity, skipped
    assert again.state == "skipped"


# ------------------------------------------------------------------------------------------------- the hook
class _Recorder:
    calls: list = []

    def __init__(self, options):
        self.options = options

    def start(self, name, params, tags):
        _Recorder.calls.append(("start", name))

    def log_epoch(self, step, metrics):
        _Recorder.calls.append(("epoch", step, sorted(metrics)))

    def log_final(self, metrics):
        _Recorder.calls.append(("final", sorted(metrics)))

    def log_artifact(self, path):
        _Recorder.calls.append(("artifact", path.name))

    def finish(self, status):
        _Recorder.calls.append(("finish", status))


class _Broken(_Recorder):
    def log_epoch(self, step, metrics):
        raise RuntimeError("disk full")


class _TrackerPlugin:
    @hookimpl
    def register_loggers(self, register):
        register(LoggerSpec(name="recorder", create=_Recorder))
        register(LoggerSpec(name="broken", create=_Broken))
        register(LoggerSpec(name="needs-pkg", create=_Recorder, requires=("no_such_package_here",), extra="nothing"))


def test_a_plugin_logger_sees_the_run_and_a_broken_one_never_stops_it(plugins, tmp_path, caplog):
    _Recorder.calls = []
    with temporary_plugin(_TrackerPlugin(), name="tracker-test"):
        result, _ = one_run(tmp_path, "recorder,broken")
    assert result.state == "trained" and (result.path / "metrics.json").exists()
    kinds = [c[0] for c in _Recorder.calls]
    # the recorder saw everything; the broken logger started, failed at its first epoch and was finished as FAILED
    assert kinds.count("start") == 2 and ("finish", "FAILED") in _Recorder.calls
    assert ("finish", "FINISHED") in _Recorder.calls and kinds.count("epoch") == 1
    epoch = next(c for c in _Recorder.calls if c[0] == "epoch")
    assert epoch[1] == 1 and "loss/total" in epoch[2]
    assert any("broken" in r.message and "disk full" in r.message for r in caplog.records)


def test_unknown_or_uninstalled_loggers_stop_the_run_before_training(plugins, tmp_path):
    with pytest.raises(Exception, match="logger.*'nope'"):
        one_run(tmp_path, "nope")
    with temporary_plugin(_TrackerPlugin(), name="tracker-test"):
        with pytest.raises(ConfigError, match=r"no_such_package_here.*rgbt-harness\[nothing\]"):
            one_run(tmp_path, "needs-pkg")
    assert not list((tmp_path / "store").rglob("metrics.json"))


# ------------------------------------------------------------------------------------------------- pieces
def test_metrics_are_flat_and_missing_values_are_left_out():
    rec = {
        "epoch": 2,
        "loss": {"box": 1.0, "cls": 0.5},
        "lr": {"bias": 0.01, "weight": 0.002},
        "metrics": {"mAP50": 0.25, "mAP50_95": float("nan"), "AP50_per_category": {"a": 0.1}},
        "fitness": None,
        "time_s": 3.0,
    }
    out = epoch_metrics(rec)
    assert out == {"loss/box": 1.0, "loss/cls": 0.5, "loss/total": 1.5, "val/mAP50": 0.25, "lr": 0.01, "time_s": 3.0}
    fin = final_metrics(
        {
            "metrics": {"mAP50": 0.5, "recall": None},
            "per_category": {"crack": {"AP50": 0.4}},
            "support": {"images": 8, "instances": 20},
            "model": {"params": 1234},
        }
    )
    assert fin == {
        "test/mAP50": 0.5,
        "test/AP50/crack": 0.4,
        "support/images": 8.0,
        "support/instances": 20.0,
        "model/params": 1234.0,
    }
    assert all(math.isfinite(v) for v in fin.values())
    assert flatten_params({"train": {"lr0": 0.01, "init": None}, "protocol": {"folds": None, "seeds": [0]}}) == {
        "train.lr0": "0.01",
        "train.init": "",
        "protocol.folds": "",
        "protocol.seeds": "[0]",
    }
    assert log_to_overrides(" mlflow, tensorboard ,mlflow") == ("tracking.loggers=[mlflow,tensorboard]",)
    assert log_to_overrides("") == () and not Tracker()
