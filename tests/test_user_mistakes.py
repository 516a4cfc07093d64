"""Mistakes a user makes at the command line, each answered with what to do: an option given is not asked for
again, and a number is printed with its unit."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from harness.errors import ConfigError


def _wide_camera(path):
    from harness.sensing.calibration import CameraModel

    k = [[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]
    return CameraModel(np.array(k), np.zeros(5), (64, 48), name="wide").save(path)


@pytest.mark.parametrize("given", ["rgb", "thermal", None])
def test_a_calibration_unknown_without_the_prepared_data_is_asked_for_by_its_own_option(given, tmp_path, monkeypatch):
    """The run's prepared data is not in the cache: the calibration still missing is asked for, never the one given."""
    from harness.screen.job import ScreenRequest, resolve_cameras

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    cam = str(_wide_camera(tmp_path / "camera.yaml"))
    req = ScreenRequest(
        flight=tmp_path,
        out=tmp_path / "out",
        run=tmp_path / "run",
        rgb_camera=cam if given == "rgb" else None,
        thermal_camera=cam if given == "thermal" else None,
    )
    model = SimpleNamespace(sensing={}, config={"meta": {"prepared_fingerprint": "f" * 16, "dataset": "m3t"}})
    with pytest.raises(ConfigError) as exc:
        resolve_cameras(req, model)  # type: ignore[arg-type]
    text = str(exc.value)
    assert "not in the cache" in text
    wanted = "--thermal-camera FILE" if given == "rgb" else "--rgb-camera FILE"
    assert wanted in text and f"--{given}-camera FILE" not in text
    if given is not None:  # the one given still counts: --no-undistort only for the other
        assert "--no-undistort if its dataset had no" in text


def test_the_screening_route_numbers_are_printed_with_their_unit():
    """``harness score-route`` and the report's screening-route table show mAP as percentages, with a "%"."""
    from harness.report.tables import screening_route_table
    from harness.screen.route import summary_lines

    result = {
        "routes": {
            "landmarks": {"mAP50_95": 0.4321, "mAP50": 0.6},
            "automatic": {"mAP50_95": 0.4012, "mAP50": 0.55, "registered_automatically": 1, "screened": 2},
            "prior": {"mAP50_95": 0.3, "mAP50": None},
        },
        "recorded_route": {"route": "landmarks"},
    }
    lines = summary_lines(result)
    assert lines[0].split() == ["landmarks", "mAP50-95", "43.2", "%", "mAP50", "60.0", "%"]
    assert lines[2].endswith("mAP50 -")
    run = SimpleNamespace(
        key=SimpleNamespace(detector="ours", encoding="c2", fold="P4", seed=0),
        name="P4/seed0",
        screening_route=lambda: result,
    )
    table = screening_route_table([run], "m3t")
    assert table is not None
    text = table.to_text()
    assert "(held-out fold, mAP50-95, %)" in text and "mAP50-95 landmarks %" in text
    assert "43.2" in text and "mAP50-95 prior %" in text


def test_a_truncated_checkpoint_and_a_safetensors_file_are_named_for_what_they_are(tmp_path, cli_runner):
    """``weights import`` (and ``--init``, through the same reader) on a torch.save file cut in half and on a
    safetensors file: each refusal says what the file is and what to do, not only "not a PyTorch checkpoint"."""
    import torch
    from safetensors.torch import save_file

    state = {"a.weight": torch.randn(64, 32), "a.bias": torch.randn(64)}
    torch.save(state, tmp_path / "good.pt")
    data = (tmp_path / "good.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    save_file(state, str(tmp_path / "w.safetensors"))
    (tmp_path / "noise.pt").write_bytes(bytes(range(256)) * 8)
    for name, says in [
        ("cut.pt", "the file is truncated"),
        ("w.safetensors", "a safetensors file"),
        ("noise.pt", "not a PyTorch checkpoint"),
    ]:
        res = cli_runner(["weights", "import", str(tmp_path / name), "--out", str(tmp_path / "o.safetensors")])
        assert res.exit_code == 2 and says in " ".join(res.output.split()), res.output
    res = cli_runner(["weights", "import", str(tmp_path / "good.pt"), "--out", str(tmp_path / "o.safetensors")])
    assert res.exit_code == 0, res.output


def _toy(width: int = 4):
    from torch import nn

    return nn.Sequential(nn.Conv2d(3, width, 3), nn.BatchNorm2d(width), nn.Conv2d(width, 2, 1))


def _importer(model, state):
    """A detector's own importer, as the YOLOv5-family plugins (EME, CMA-Det, ICAFusion) have: loads by name and
    shape, lists what it skipped, raises nothing."""
    from adapters.detectors.yolo.v5 import load_state_dict_report

    return load_state_dict_report(model, state, "toy")


def test_init_through_a_detectors_importer_refuses_what_does_not_fit(tmp_path, caplog):
    """``--init`` on a detector with its own importer: a foreign state dict (nothing loaded) and a checkpoint of
    another size (most tensors mismatched) are refused, as the name-and-shape importer refuses them; a head for other
    classes (a few tensors) loads, with a warning naming the counts."""
    import logging

    import torch

    from harness.engine import checkpoint as ckpt

    torch.save({"x.weight": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(ckpt.CheckpointError, match="none of its 1 tensors"):
        ckpt.init_from(_toy(), tmp_path / "foreign.pt", _importer)
    torch.save(_toy(width=8).state_dict(), tmp_path / "wider.pt")
    with pytest.raises(ckpt.CheckpointError, match="have the model's names but other shapes"):
        ckpt.init_from(_toy(), tmp_path / "wider.pt", _importer)
    other_head = _toy()
    other_head[2] = torch.nn.Conv2d(4, 5, 1)  # trained for other classes: the last layer's 2 tensors differ
    torch.save(other_head.state_dict(), tmp_path / "head.pt")
    with caplog.at_level(logging.INFO, logger="harness.engine.checkpoint"):
        report = ckpt.init_from(_toy(), tmp_path / "head.pt", _importer)
    assert len(report["loaded"]) == 7 and len(report["mismatched"]) == 2
    (rec,) = [r for r in caplog.records if "initialised" in r.getMessage()]
    assert rec.levelno == logging.WARNING and "mismatched=2" in rec.getMessage()
    torch.save(_toy().state_dict(), tmp_path / "same.pt")
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="harness.engine.checkpoint"):
        ckpt.init_from(_toy(), tmp_path / "same.pt", _importer)
    assert [r.levelno for r in caplog.records if "initialised" in r.getMessage()] == [logging.INFO]


def test_prepare_prints_the_advice_of_a_skip_reason_in_full(tmp_path, cli_runner, monkeypatch):
    """coco-rgbt ``width``/``height`` are the thermal frame's size: pairs given the RGB habit's (here twice the
    thermal size) are skipped, and the summary on stdout shows the first one's reason with its advice, uncut."""
    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json

    root = make_coco_rgbt(tmp_path / "pairs", n=6)
    coco = read_json(root)
    for im in coco["images"][:3]:
        im["width"], im["height"] = 2 * im["width"], 2 * im["height"]
    write_json(root, coco)
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    res = cli_runner(["prepare", "--dataset", "coco-rgbt", "--root", str(root)])
    assert res.exit_code == 0, res.output
    out = " ".join(res.stdout.split())
    assert "skipped pairs: 3 (size mismatch: 3)" in out
    assert "images[].width and height are the thermal frame's size (or leave them out)" in out
    examples = [line for line in res.stdout.splitlines() if "e.g." in line or "images[]" in line]
    assert len(examples) == 4 and max(map(len, examples)) <= 100, examples  # the first wrapped, two cut


@pytest.mark.parametrize("returned", [None, ("model", "config")])
def test_a_builder_that_returns_no_module_is_refused_naming_the_detector(returned, tmp_path):
    """A detector plugin whose ``build`` forgets its ``return`` (or returns a tuple) is refused by name, with the type
    it returned, on the run's path and on profiling's, not left to fail later as a bug."""
    from harness import DetectorSpec
    from harness.errors import PluginError
    from harness.profiling import build_detector
    from harness.runner import build_model

    spec = DetectorSpec(name="forgetful", build=lambda num_classes, in_channels=4, **cfg: returned, description="x")
    with pytest.raises(PluginError, match=f"'forgetful'.*returned {type(returned).__name__}, not a torch.nn.Module"):
        build_model(spec, 2, 4, {})
    host = SimpleNamespace(detector=lambda name: spec)
    with pytest.raises(PluginError, match="returned .*not a torch.nn.Module"):
        build_detector("forgetful", 2, 4, host=host)


def _prepared_pairs(tmp_path, monkeypatch, cli_runner):
    from coco_rgbt_helpers import make_coco_rgbt, read_json

    root = make_coco_rgbt(tmp_path / "pairs", n=6)
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    assert cli_runner(["prepare", "--dataset", "coco-rgbt", "--root", str(root)]).exit_code == 0
    return root, read_json(root)


def test_category_names_written_as_category_id_are_read_as_names_and_a_missing_one_is_named(
    tmp_path, monkeypatch, cli_runner
):
    """Some exporters write the class name in ``category_id``: a word can only be a name, so it is matched by name
    (the score is the ground truth's own). Predictions with neither ``category_id`` nor ``category_name`` (a
    ``label`` key instead) are refused saying so, not as "categories the dataset does not have: None"."""
    root, coco = _prepared_pairs(tmp_path, monkeypatch, cli_runner)
    names = {c["id"]: c["name"] for c in coco["categories"]}
    base = [
        {"image_id": a["image_id"], "bbox": a["bbox"], "score": 0.9, "cid": a["category_id"]}
        for a in coco["annotations"]
    ]
    args = ["score", "--dataset", "coco-rgbt", "--root", str(root), "--folds", "site-a", "--frame", "thermal"]
    args += ["--images", str(root / "annotations.json"), "--store", str(tmp_path / "store")]
    named = [{**{k: v for k, v in p.items() if k != "cid"}, "category_id": names[p["cid"]]} for p in base]
    (tmp_path / "named.json").write_text(json.dumps(named))
    res = cli_runner([*args, "--predictions", str(tmp_path / "named.json"), "--name", "named"])
    assert res.exit_code == 0 and "mAP50 100.0" in res.output, res.output
    unlabelled = [{**{k: v for k, v in p.items() if k != "cid"}, "label": p["cid"]} for p in base]
    (tmp_path / "label.json").write_text(json.dumps(unlabelled))
    res = cli_runner([*args, "--predictions", str(tmp_path / "label.json"), "--name", "label"])
    assert res.exit_code == 2 and "no category_id or category_name" in res.output, res.output


def test_an_absolute_path_inside_the_folder_is_refused_as_absolute_with_the_relative_one(tmp_path, cli_runner):
    """coco-rgbt ``file_name`` written as an absolute path inside the dataset folder: the refusal says the path is
    absolute and gives the relative one to write, not that it "leads outside the dataset root"."""
    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json

    root = make_coco_rgbt(tmp_path / "pairs", n=6)
    coco = read_json(root)
    for im in coco["images"]:
        im["file_name"] = str(root / im["file_name"])
    write_json(root, coco)
    res = cli_runner(["prepare", "--dataset", "coco-rgbt", "--root", str(root), "--cache", str(tmp_path / "c")])
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and "absolute path: 6" in out, res.output
    assert "is absolute; write it relative to the dataset root" in out and "'rgb/000.png'" in out
    assert "leads outside" not in out


def test_weights_import_says_what_a_file_without_a_model_is(tmp_path, cli_runner):
    """``weights import`` of a TorchScript archive and of a dict of numpy arrays saved with torch.save: the refusal
    says which of the two the file is and what to save instead, beside "no model found"."""
    import torch

    torch.jit.save(torch.jit.script(torch.nn.Linear(2, 2)), tmp_path / "scripted.pt")
    torch.save({"a.weight": np.zeros((2, 2), np.float32)}, tmp_path / "arrays.pt")
    for name, says in [
        ("scripted.pt", "it is a TorchScript archive (torch.jit.save): load it with torch.jit.load"),
        ("arrays.pt", "its values are ndarray, not tensors"),
    ]:
        res = cli_runner(["weights", "import", str(tmp_path / name), "--out", str(tmp_path / "o.safetensors")])
        assert res.exit_code == 2 and says in " ".join(res.output.split()), res.output


def test_an_ablation_category_the_store_does_not_have_is_refused_with_those_it_has(tmp_path, cli_runner):
    """A mistyped ``--ablation-categories`` name stops with the store's categories; the spellings the report matches
    (case, spaces for underscores) pass."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from report_fixtures import synthetic_store

    store = synthetic_store(tmp_path / "s", folds=("P1", "P2"), per_fold=3)
    args = ["report", "--print", "--store", str(store.root), "--resamples", "0", "--ablation-categories"]
    res = cli_runner([*args, "windows"])
    text = " ".join(res.output.split())
    assert res.exit_code == 2 and "'windows': no such category in the runs of" in text, res.output
    assert "categories there:" in text and "window" in text.split("categories there:")[1]
    ok = cli_runner([*args, "Window"])
    assert ok.exit_code == 0, ok.output
