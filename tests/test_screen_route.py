"""One registration route from benchmark to flight: the route a run's samples used is recorded, a run is scored
under the route a new flight gets (``harness score-route``), a screen of the held-out captures with default options
gives exactly those stored predictions, and the report shows the three scores.

One small run is trained per module (the example TinyDet on the tiny synthetic M3T set, fold P4+P5 held out: two
projects flown on different days, so two inspection groups screened in one call; one epoch at 64 px).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest

from report_fixtures import cli, tiny_run

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]

FOLD = "P4+P5"


@dataclass
class Trained:
    run: Path
    store: Path
    tiny: Path
    root: Path


@pytest.fixture(scope="module")
def trained(tiny_source, tmp_path_factory):
    root = tmp_path_factory.mktemp("route")
    with tiny_run(tiny_source, root, FOLD, "route-test") as run:
        yield Trained(run, root / "store", tiny_source, root)


@pytest.fixture(scope="module")
def scored(trained):
    text = cli(["score-route", str(trained.run)])
    return json.loads((trained.run / "screening_route.json").read_text()), text


def _flight(trained: Trained, folder: Path) -> Path:
    """The held-out captures as one flight folder, one sub-folder per project, as the drone's card holds them."""
    for project in ("P4", "P5"):
        shutil.copytree(trained.tiny / "images" / project, folder / project)
    return folder


def _frames(out: Path) -> dict[str, dict]:
    return {json.loads(p.read_text())["frame"]: json.loads(p.read_text()) for p in (out / "frames").glob("*.json")}


def test_a_run_records_the_registration_route_of_its_samples(trained):
    from harness.config import read_yaml
    from harness.runner import run_hash

    cfg = read_yaml(trained.run / "config.yaml")
    reg = cfg["meta"]["registration"]
    assert reg["route"] == "landmarks"
    assert sorted(reg["groups"]) == ["P1-01", "P2-01", "P3-01", "P4-01", "P5-01"]
    assert set(reg["groups"].values()) == {"landmarks"}
    # a record of how the (fingerprinted) samples were made, not a setting: finished runs stay finished
    bare = {**cfg, "meta": {k: v for k, v in cfg["meta"].items() if k != "registration"}}
    assert run_hash(bare) == run_hash(cfg)


def test_a_run_is_scored_under_the_screening_route(trained, scored):
    result, text = scored
    routes = result["routes"]
    metrics = json.loads((trained.run / "metrics.json").read_text())["metrics"]
    assert routes["landmarks"]["mAP50_95"] == metrics["mAP50_95"]
    for route in ("automatic", "prior"):
        assert routes[route]["images"] == routes[route]["screened"] == 2
        assert 0.0 <= routes[route]["mAP50_95"] <= 1.0
        assert result["predictions"][route], route
    assert result["recorded_route"]["route"] == "landmarks"
    frames = result["frames"]["automatic"]
    wide = sorted(f"{p.parent.name}/{p.name[:-6]}" for p in trained.tiny.glob("images/P[45]/*_W.JPG"))
    assert sorted(f["frame"] for f in frames.values()) == wide and len(wide) == 2
    for f in frames.values():  # one frame per group: the single-frame check decides, and the route says which
        assert f["route"].startswith("auto (group G0") or f["route"] == "prior (automatic registration rejected)"
        if not f["registration"]["ok"]:
            assert f["registration"]["expected_error_px"] > 0
    assert {f["route"] for f in result["frames"]["prior"].values()} == {"prior"}
    assert "automatic  mAP50-95" in text and "screening_route.json" in text


def test_screening_a_multi_group_fold_with_default_options_gives_its_stored_predictions(trained, scored, tmp_path):
    """Both held-out projects (two inspection groups) in one call, no option but --run and --out."""
    result, _ = scored
    flight = _flight(trained, tmp_path / "card")
    out = tmp_path / "screen"
    cli(["screen", str(flight), "--run", str(trained.run), "--out", str(out), "--no-progress"])
    manifest = json.loads((out / "manifest.json").read_text())
    threshold = manifest["model"]["threshold"]
    stored = result["predictions"]["automatic"]
    frames = _frames(out)
    route_frames = {f["frame"]: (int(i), f) for i, f in result["frames"]["automatic"].items()}
    assert sorted(frames) == sorted(route_frames)
    compared = 0
    for name, rec in frames.items():
        iid, stored_frame = route_frames[name]
        assert rec["route"] == stored_frame["route"] and rec["crop_origin"] == stored_frame["crop_origin"]
        want = sorted(
            (d["category_id"], d["bbox"], d["score"])
            for d in stored
            if d["image_id"] == iid and d["score"] >= threshold
        )
        got = sorted((f["class_id"] + 1, f["bbox"], f["score"]) for f in rec["findings"])
        assert got == want, name
        compared += len(want)
    # and every stored detection, at the run's NMS threshold
    out_all = tmp_path / "screen-all"
    conf = str(json.loads(json.dumps(manifest["config"]["eval"]["conf"])))
    cli(["screen", str(flight), "--run", str(trained.run), "--out", str(out_all), "--no-progress", "--conf", conf])
    for name, rec in _frames(out_all).items():
        iid, _ = route_frames[name]
        want = sorted((d["category_id"], d["bbox"], d["score"]) for d in stored if d["image_id"] == iid)
        assert want and sorted((f["class_id"] + 1, f["bbox"], f["score"]) for f in rec["findings"]) == want, name
        compared += len(want)
    assert compared > 0


def test_the_report_shows_accuracy_under_the_screening_route(trained, scored):
    from harness.report.build import build_report

    result, _ = scored
    report = build_report(trained.store, datasets=["m3t-synth"], gallery=False)
    (sec,) = [s for s in report.sections if s.key == "screening-route"]
    assert sec.title == "Accuracy under the screening route" and not sec.absent
    (row,) = sec.tables[0].rows
    for route in ("landmarks", "automatic", "prior"):
        assert row[route] == result["routes"][route]["mAP50_95"]
    assert row["route"] == "landmarks"
    assert "m3t-synth: accuracy under the screening route" in report.to_text()
