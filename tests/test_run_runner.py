"""The main job end to end on a tiny dataset: store layout, skip / refuse / force, resume, tables, errors."""

from __future__ import annotations

import json

import pytest

# the whole job needs the dataset cache and the evaluation (skipped cleanly on a checkout without them)
pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from engine_helpers import CATEGORIES, fast_overrides
from harness.config import read_yaml
from harness.errors import ConfigError, StoreError
from harness.testing import temporary_plugin

FAST = fast_overrides(epochs=3, close_mosaic=1)


def request(tmp_path, **kw):
    from harness.runner import RunRequest

    base = dict(detector="tinydet", dataset="shapes", store=tmp_path / "store", overrides=FAST, progress=False)
    base.update(kw)
    return RunRequest(**base)


@pytest.mark.slow
def test_run_trains_every_fold_and_fills_the_store(shapes_run_plugins, tmp_path, monkeypatch):
    import torch

    import harness.complexity
    from harness.engine.trainer import Trainer
    from harness.report.run_tables import category_table, fold_table
    from harness.runner import run
    from harness.store import METRICS_SCHEMA

    measured, at_fit = [], []
    measure, fit = harness.complexity.measure, Trainer.fit

    def measure_drawing(*a, **k):  # a fold that builds layers draws from torch's generator, as YOLO folds do
        measured.append(torch.rand(3))
        return measure(*a, **k)

    monkeypatch.setattr(harness.complexity, "measure", measure_drawing)
    monkeypatch.setattr(
        Trainer, "fit", lambda self, *a, **k: at_fit.append(torch.get_rng_state()) or fit(self, *a, **k)
    )
    summary = run(request(tmp_path))
    assert [r.key.fold for r in summary.results] == ["A", "B"] and {r.state for r in summary.results} == {"trained"}
    assert len(measured) == 1  # both folds train the same architecture: measured once, stored with each
    assert torch.equal(at_fit[0], at_fit[1])  # and fold B trains from the generator state measuring would leave
    records = [json.loads((r.path / "metrics.json").read_text())["complexity"] for r in summary.results]
    assert records[0] == records[1] and records[0]["params"] > 1000
    for r in summary.results:
        files = {p.name for p in r.path.iterdir()}
        assert {
            "config.yaml",
            "status.json",
            "metrics.json",
            "predictions.json",
            "gt.json",
            "log.jsonl",
            "checkpoints",
        } <= files
        assert {p.name for p in (r.path / "checkpoints").iterdir()} == {"last.pt", "best.pt"}
        status = json.loads((r.path / "status.json").read_text())
        assert status["state"] == "finished" and status["config_hash"]
        m = json.loads((r.path / "metrics.json").read_text())
        assert m["schema"] == METRICS_SCHEMA
        assert m["run"] == {
            "dataset": "shapes",
            "detector": "tinydet",
            "encoding": "test-ir8",
            "fold": r.key.fold,
            "seed": 0,
        }
        gt = json.loads((r.path / "gt.json").read_text())
        assert m["support"]["images"] == len(gt["images"]) == 8 == r.val_images
        assert m["support"]["instances"] == len(gt["annotations"])
        assert len(m["support"]["image_ids_sha1"]) == 40
        assert set(m["per_category"]) == set(CATEGORIES)
        assert m["model"]["params"] > 1000 and m["model"]["in_channels"] == 4
        assert m["train"]["epochs_run"] == 3 and m["train"]["images"] == 8 and m["train"]["imgsz"] == 64
        assert m["environment"]["torch"] and m["environment"]["device"] == "cpu"
        preds = json.loads((r.path / "predictions.json").read_text())
        gt_ids = {im["id"] for im in gt["images"]}
        assert all(p["image_id"] in gt_ids and 1 <= p["category_id"] <= 3 and len(p["bbox"]) == 4 for p in preds)
        log = [json.loads(line) for line in (r.path / "log.jsonl").read_text().splitlines()]
        assert [rec["epoch"] for rec in log] == [1, 2, 3] and all(rec["fold"] == r.key.fold for rec in log)
        analysis = json.loads((r.path / "analysis.json").read_text())  # stored once, beside the metrics
        assert analysis["run"] == m["run"] and analysis["tide"]["mAP50"] == m["metrics"]["mAP50"]
        assert analysis["conf_threshold"] == m["metrics"]["conf_threshold"]
        assert sum(map(sum, analysis["confusion"]["matrix"])) >= m["support"]["instances"]
        cfg = read_yaml(r.path / "config.yaml")
        assert cfg["train"]["batch"] == 8
        # the detector's defaults are a layer of the resolved config, below the profile (which sets lr0 itself)
        assert "defaults of detector 'tinydet'" in cfg["meta"]["sources"] and cfg["train"]["lr0"] == 0.002
        assert cfg["meta"]["fold"] == r.key.fold and cfg["meta"]["val_groups"] == [r.key.fold]
    assert json.loads((tmp_path / "store" / "shapes" / "_dataset.json").read_text()) == {
        "dataset": "shapes",
        "thermal": "radiometric",
        "sensing_stage": False,
    }  # what a report reads, not the plugin
    table = fold_table(summary)
    assert "mean ± SD" in table and table.count("trained") == 2
    lines = category_table(summary).splitlines()
    assert any(line.startswith("warm") for line in lines) and "AP50 A" in lines[1]


@pytest.mark.slow
def test_a_run_is_scored_with_every_setting_of_its_eval_section(shapes_run_plugins, tmp_path, monkeypatch):
    """Validation and the final evaluation call the one evaluation path with the run's ``eval`` section: the SAFit
    anchor and ``strict`` reach the evaluator (the runner used to pass engine and matching only)."""
    import harness.evaluation
    import harness.evaluation.coco as coco
    from harness.runner import run

    real, seen = coco.evaluate, []

    def spy(gt, dets, *args, **kwargs):
        seen.append(kwargs)
        return real(gt, dets, *args, **kwargs)

    monkeypatch.setattr(coco, "evaluate", spy)
    monkeypatch.setattr(harness.evaluation, "evaluate", spy)
    summary = run(
        request(
            tmp_path,
            folds="A",
            overrides=[
                *FAST,
                "protocol.epochs=1",
                "eval.matching=safit",
                "eval.safit_anchor=topleft",
                "eval.strict=true",
            ],
        )
    )
    assert len(seen) == 2  # one validation, the final evaluation
    assert all(
        (kw.get("matching"), kw.get("safit_anchor"), kw.get("strict")) == ("safit", "topleft", True) for kw in seen
    )
    r = summary.results[0]
    gt, preds = (json.loads((r.path / name).read_text()) for name in ("gt.json", "predictions.json"))
    expected = real(gt, preds, matching="safit", safit_anchor="topleft")["metrics"]["safit"]
    assert r.metrics["metrics"]["safit"] == expected


@pytest.mark.slow
def test_finished_runs_are_skipped_changed_ones_refused_and_forced(shapes_run_plugins, tmp_path):
    from harness.runner import run

    first = run(request(tmp_path, folds="A"))
    again = run(request(tmp_path, folds="A"))
    assert again.results[0].state == "skipped"
    assert again.results[0].metrics == first.results[0].metrics
    changed = request(tmp_path, folds="A", overrides=[*FAST, "train.lr0=0.02"])
    with pytest.raises(StoreError, match="different configuration.*--force"):
        run(changed)
    changed.force = True
    forced = run(changed)
    assert forced.results[0].state == "trained"
    assert forced.results[0].metrics["train"] != first.results[0].metrics["train"]
    # --init starts another run from the finished run's best weights, and records where they came from
    best = first.results[0].path / "checkpoints" / "best.pt"
    init = run(request(tmp_path, folds="B", store=tmp_path / "other", init=best))
    report = init.results[0].metrics["train"]["init"]
    assert report["loaded"] == report["total"] and report["path"] == str(best)
    assert read_yaml(init.results[0].path / "config.yaml")["train"]["init"] == str(best)


def test_a_run_another_process_is_training_is_refused_and_left_alone(shapes_run_plugins, tmp_path):
    from harness.runner import run
    from harness.store import RunBusyError, RunKey, Store

    busy = Store(tmp_path / "store").run(RunKey("shapes", "tinydet", "test-ir8", "A", 0))
    with busy.exclusive():
        with pytest.raises(RunBusyError, match="being trained by another process"):
            run(request(tmp_path, folds="A"))
        assert {p.name for p in busy.path.iterdir()} == {".lock"}  # nothing of the other process's run touched
    assert run(request(tmp_path, folds="A")).results[0].state == "trained"


@pytest.mark.slow
def test_an_interrupted_run_resumes_to_the_uninterrupted_result(shapes_run_plugins, tmp_path, monkeypatch):
    from harness.engine import trainer as trainer_mod
    from harness.runner import run

    reference = run(request(tmp_path, folds="B", store=tmp_path / "reference"))

    original = trainer_mod.Trainer._validate
    calls = {"n": 0}

    def crash_on_second(self):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(trainer_mod.Trainer, "_validate", crash_on_second)
    with pytest.raises(KeyboardInterrupt):
        run(request(tmp_path, folds="B"))
    monkeypatch.setattr(trainer_mod.Trainer, "_validate", original)
    run_dir = tmp_path / "store" / "shapes" / "tinydet" / "test-ir8" / "B" / "seed0"
    status = json.loads((run_dir / "status.json").read_text())
    assert status["state"] == "failed" and status["error"] == "interrupted"
    assert (run_dir / "checkpoints" / "last.pt").exists()

    resumed = run(request(tmp_path, folds="B"))
    assert resumed.results[0].state == "resumed"
    a, b = reference.results[0].metrics, resumed.results[0].metrics
    assert a["metrics"] == b["metrics"] and a["per_category"] == b["per_category"]
    assert a["train"]["best_epoch"] == b["train"]["best_epoch"] and b["train"]["resumed_from"] == 1
    log = [json.loads(line)["epoch"] for line in (run_dir / "log.jsonl").read_text().splitlines()]
    assert log == [1, 2, 3]  # the interrupted epoch was not checkpointed, so it is not logged twice


def test_bad_requests_are_clear_errors(shapes_run_plugins, tmp_path):
    from harness.errors import UnknownNameError
    from harness.runner import run

    with pytest.raises(UnknownNameError, match="unknown detector 'nope'"):
        run(request(tmp_path, detector="nope"))
    with pytest.raises(ConfigError, match="dual-stream and needs a thermal encoding"):
        run(request(tmp_path, detector="tinydet-dual", encoding="test-none"))
    with pytest.raises(ConfigError, match="selects no fold|unknown fold|no fold"):
        run(request(tmp_path, folds="Z"))
    with pytest.raises(ConfigError, match="not TinyDet options"):
        run(request(tmp_path, overrides=[*FAST, "model.depth=3"]))


@pytest.mark.slow
def test_cli_run_and_ablate_print_aligned_tables(shapes_run_plugins, tmp_path, cli_runner):
    store = str(tmp_path / "store")
    sets = [a for s in FAST for a in ("--set", s)]
    res = cli_runner(
        [
            "run",
            "--detector",
            "tinydet-dual",
            "--dataset",
            "shapes",
            "--encoding",
            "test-ir8",
            "--folds",
            "A,B",
            "--store",
            store,
            "--no-progress",
            *sets,
        ]
    )
    assert res.exit_code == 0, res.output
    out = res.output
    assert "tinydet-dual on shapes, encoding test-ir8" in out and "mean ± SD" in out and "per category" in out
    header = next(line for line in out.splitlines() if line.startswith("fold"))
    rule = out.splitlines()[out.splitlines().index(header) + 1]
    assert len(header) == len(rule.rstrip())  # the columns line up under their headers

    res = cli_runner(
        [
            "ablate",
            "--detector",
            "tinydet",
            "--dataset",
            "shapes",
            "--encodings",
            "test-none,test-ir8",
            "--folds",
            "B",
            "--categories",
            "warm,cold",
            "--store",
            store,
            "--no-progress",
            *sets,
        ]
    )
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    lines = lines[next(i for i, line in enumerate(lines) if line.startswith("encoding ablation:")) :]
    assert lines[0].startswith("encoding ablation: tinydet on shapes, fold B")
    assert lines[1].split() == ["encoding", "P", "R", "mAP50", "mAP50:95", "AP50", "warm", "AP50", "cold"]
    assert [line.split()[0] for line in lines[3:]] == ["test-none", "test-ir8"]

    res = cli_runner(
        [
            "ablate",
            "--dataset",
            "shapes",
            "--detector",
            "tinydet",
            "--encodings",
            "test-ir8",
            "--folds",
            "B",
            "--categories",
            "delamination",
            "--store",
            store,
            "--no-progress",
            *sets,
        ]
    )
    assert res.exit_code == 2 and "category 'delamination' is not in the dataset" in res.output


PLUGIN_CODE = '''
"""A dataset plugin whose code a test edits: the shapes dataset under another name."""
from engine_helpers import CATEGORIES, ShapesSource
from harness.api import DatasetSpec
from harness.hookspecs import hookimpl

SKIP = 0  # samples left out: the edit changes what is yielded, not what fingerprint() says


class Edited(ShapesSource):
    def samples(self, report):
        for k, s in enumerate(super().samples(report)):
            if k >= SKIP:
                yield s


@hookimpl
def register_datasets(register):
    register(DatasetSpec(name="edited-shapes", open=lambda root=None, **o: Edited(), categories=CATEGORIES,
                         default_encoding="test-ir8"))
'''


def test_a_finished_run_is_not_reused_once_its_dataset_plugins_code_changed(shapes_run_plugins, tmp_path, monkeypatch):
    """The plugin's code changes what it yields while its fingerprint() stays the same: the cache key changes with
    the code, and so does the run's identity, so the finished run is refused, not skipped as the same run."""
    import importlib

    from harness.runner import plan, run

    folder = tmp_path / "plug"
    folder.mkdir()
    (folder / "edited_shapes.py").write_text(PLUGIN_CODE)
    monkeypatch.syspath_prepend(str(folder))
    module = importlib.import_module("edited_shapes")
    with temporary_plugin(module, name="edited-shapes-plugin"):
        first = plan(request(tmp_path, dataset="edited-shapes", folds="A")).runs[0]
        first.run.path.mkdir(parents=True)
        first.run.write_config(first.config)
        first.run.write_metrics({"metrics": {}, "support": {}})  # what a finished run leaves behind
        first.run.set_status("finished", config_hash=first.digest)
        assert plan(request(tmp_path, dataset="edited-shapes", folds="A")).runs[0].state == "finished"

        (folder / "edited_shapes.py").write_text(PLUGIN_CODE.replace("SKIP = 0", "SKIP = 1"))
        module.SKIP = 1  # the edited code, as a new process would import it
        again = plan(request(tmp_path, dataset="edited-shapes", folds="A")).runs[0]
        assert again.config["meta"]["prepared_fingerprint"] == first.config["meta"]["prepared_fingerprint"]
        assert again.state == "conflict"
        assert any(d.startswith("meta.prepared_key: ") for d in again.differences())
        with pytest.raises(StoreError, match="different configuration.*meta.prepared_key"):
            run(request(tmp_path, dataset="edited-shapes", folds="A"))
