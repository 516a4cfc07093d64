"""Results integrity of runs: the complexity of the model that was trained, transactional replacement, statuses."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from engine_helpers import CATEGORIES, fast_overrides, set_args, shapes_run_args  # noqa: E402
from harness.errors import ConfigError  # noqa: E402

FAST = fast_overrides(epochs=1, close_mosaic=0)


def request(tmp_path, extra=(), **kw):
    from harness.runner import RunRequest

    base = dict(
        detector="tinydet",
        dataset="shapes",
        folds="A",
        store=tmp_path / "store",
        overrides=[*FAST, *extra],
        progress=False,
    )
    base.update(kw)
    return RunRequest(**base)


def _files(path):
    return {
        p.relative_to(path).as_posix(): p.read_bytes()
        for p in sorted(path.rglob("*"))
        if p.is_file() and p.name not in (".lock", "status.json")
    }


def test_run_stores_the_complexity_of_the_model_it_trained_and_reports_read_only_that(shapes_run_plugins, tmp_path):
    from harness_tinydet.model import TinyDet

    from harness.report.reader import StoreView
    from harness.report.tables import project_table
    from harness.runner import run

    summary = run(request(tmp_path, ["model.width=8"]))
    comp = summary.results[0].metrics["complexity"]
    built = TinyDet(3, in_channels=4, width=8)
    assert comp["model_options"] == {"width": 8} and comp["num_classes"] == len(CATEGORIES) == 3
    assert comp["params"] == sum(p.numel() for p in built.parameters())
    assert comp["bn_folded"] is True and comp["params_fused"] < comp["params"]
    assert set(comp["gflops"]) == {"64", "640"}
    assert comp["gflops"]["640"]["paper"] > 50 * comp["gflops"]["64"]["paper"] > 0
    # a profile of another model (the old source of the report's numbers) is ignored
    store = summary.store
    (store / "_profiles").mkdir()
    (store / "_profiles" / "tinydet.json").write_text(
        json.dumps(
            {
                "detector": "tinydet",
                "imgsz": 640,
                "num_classes": 8,
                "params": {"fused": 11_100_000},
                "flops": {"paper": {"gflops": 28.5}, "exact": {"gflops": 28.6}},
            }
        )
    )
    table = project_table(StoreView(store), "shapes")
    row = table.rows[0]
    assert row["detector"] == "tinydet [width=8]"
    assert row["params"] == pytest.approx(comp["params_fused"] / 1e6)
    assert row["gflops"] == comp["gflops"]["640"]["paper"]
    note = next(n for n in table.notes if n.startswith("Params (M)"))
    assert "3 class(es)" in note and "8 classes" not in note
    from harness.compare import build_table

    compared = build_table(store, ["shapes"])
    assert compared.rows[0].options == "width=8" and "tinydet [width=8]" in compared.to_text()


def test_profile_takes_the_run_options_and_writes_the_run_store(shapes_run_plugins, tmp_path, monkeypatch, cli_runner):
    monkeypatch.chdir(tmp_path)
    res = cli_runner(
        [
            "profile",
            "--detector",
            "tinydet",
            "--set",
            "model.width=8",
            "--imgsz",
            "64",
            "--no-latency",
            "--no-onnx",
            "--no-fvcore",
            "--format",
            "json",
        ]
    )
    assert res.exit_code == 0, res.output
    stored = json.loads((tmp_path / "results" / "smoke" / "_profiles" / "tinydet.json").read_text())
    from harness_tinydet.model import TinyDet

    assert stored["model_options"] == {"width": 8}
    assert stored["params"]["total"] == sum(p.numel() for p in TinyDet(8, in_channels=4, width=8).parameters())


def test_force_with_a_bad_option_keeps_the_finished_run_and_fails_the_new_attempt(
    shapes_run_plugins, tmp_path, monkeypatch
):
    from harness.engine.trainer import Trainer
    from harness.runner import run

    first = run(request(tmp_path)).results[0]
    before = _files(first.path)
    assert {"metrics.json", "log.jsonl", "checkpoints/best.pt", "checkpoints/last.pt"} <= set(before)
    with pytest.raises(ConfigError, match="widht"):  # refused while planning: nothing is touched
        run(request(tmp_path, ["model.widht=32"], force=True))
    assert _files(first.path) == before and not (first.path.parent / ".seed0.new").exists()

    def boom(self, resume=True):
        raise RuntimeError("out of memory in epoch 1")

    monkeypatch.setattr(Trainer, "fit", boom)
    with pytest.raises(RuntimeError, match="out of memory"):
        run(request(tmp_path, ["model.width=8"], force=True))
    assert _files(first.path) == before
    status = json.loads((first.path / "status.json").read_text())
    assert status["state"] == "finished"
    assert status["replacement"]["state"] == "failed" and "out of memory" in status["replacement"]["error"]
    staged = json.loads((first.path.parent / ".seed0.new" / "status.json").read_text())
    assert staged["state"] == "failed" and "out of memory" in staged["error"]


def test_force_replaces_a_finished_run_in_one_swap(shapes_run_plugins, tmp_path):
    from harness.runner import run

    first = run(request(tmp_path)).results[0]
    old_started = json.loads((first.path / "status.json").read_text())["started"]
    (first.path / "marker").write_text("old")
    again = run(request(tmp_path, force=True)).results[0]
    assert again.state == "trained" and again.path == first.path
    assert not (first.path / "marker").exists()  # the folder is the new one, not the old one patched
    assert not (first.path.parent / ".seed0.new").exists() and not (first.path.parent / ".seed0.old").exists()
    m = json.loads((first.path / "metrics.json").read_text())
    assert m["train"]["best_path"] == str(first.path / "checkpoints" / "best.pt")
    assert json.loads((first.path / "status.json").read_text())["state"] == "finished"
    assert old_started  # the old status existed


@pytest.mark.parametrize("bad", ["model.widht=32", "protocol.imgsz=100"])
def test_bad_settings_are_refused_before_a_run_is_started(shapes_run_plugins, tmp_path, bad):
    from harness.runner import run
    from harness.store import RunKey, Store

    with pytest.raises(ConfigError):
        run(request(tmp_path, [bad]))
    assert Store(tmp_path / "store").run(RunKey("shapes", "tinydet", "test-ir8", "A", 0)).status() is None


def test_an_error_while_building_the_model_in_a_run_is_recorded_as_failed(shapes_run_plugins, tmp_path, monkeypatch):
    import harness.runner as runner
    from harness.store import RunKey, Store

    calls = []
    real = runner.build_model

    def flaky(*a, **kw):  # passes the planning check, fails when the run builds its model
        calls.append(1)
        if len(calls) > 1:
            raise RuntimeError("cannot allocate the head")
        return real(*a, **kw)

    monkeypatch.setattr(runner, "build_model", flaky)
    with pytest.raises(RuntimeError, match="allocate"):
        runner.run(request(tmp_path))
    status = Store(tmp_path / "store").run(RunKey("shapes", "tinydet", "test-ir8", "A", 0)).status()
    assert status["state"] == "failed" and "cannot allocate the head" in status["error"]


def test_report_lists_a_dead_running_run_as_interrupted(tmp_path):
    from harness.report.reader import StoreView
    from harness.store import RunKey, Store

    store = Store(tmp_path / "s")
    run = store.run(RunKey("synth", "alpha", "c2", "P1", 0))
    run.path.mkdir(parents=True)
    run.set_status("running", config_hash="x")
    assert StoreView(store).unfinished("synth") == [(str(run.key), "interrupted")]
    with run.exclusive():  # a live process holds it: running
        assert StoreView(store).unfinished("synth") == [(str(run.key), "running")]


def test_an_interrupted_swap_is_recovered(tmp_path):
    from harness.store import RunKey, Store

    run = Store(tmp_path / "s").run(RunKey("synth", "alpha", "c2", "P1", 0))
    run.path.mkdir(parents=True)
    run.set_status("finished", config_hash="x")
    run.path.rename(run.retired_path)  # a crash between the two renames of a swap
    with run.exclusive():
        assert run.status()["state"] == "finished"
    assert not run.retired_path.exists()


def test_a_dataset_given_from_another_folder_is_the_same_run(shapes_run_plugins, tmp_path, cli_runner):
    from harness.runner import run

    run(request(tmp_path, [f"dataset.root={tmp_path / 'here'}"]))
    res = cli_runner(shapes_run_args(tmp_path / "store", "--root", str(tmp_path / "moved"), *set_args(FAST)))
    assert res.exit_code == 0, res.output
    assert "skipped" in res.output


def test_a_changed_configuration_is_refused_with_the_keys_that_differ(shapes_run_plugins, tmp_path):
    from harness.errors import StoreError
    from harness.runner import run

    run(request(tmp_path))
    with pytest.raises(StoreError) as err:
        run(request(tmp_path, ["train.lr0=0.02", "augment.fliplr=0.0"]))
    text = str(err.value)
    assert "train.lr0: 0.002 -> 0.02" in text and "augment.fliplr: 0.5 -> 0.0" in text and "--force" in text
