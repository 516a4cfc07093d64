"""Scoring predictions made elsewhere (``harness score``) and exporting a run's (``harness export-predictions``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("harness.prepare")

from engine_helpers import CATEGORIES, ShapesSource, tinydet_module
from harness import DatasetSpec, hookimpl
from harness.errors import DataError
from harness.plugins import temporary_plugin
from harness.scoring.frames import from_prepared, to_prepared
from harness.sensing.warp import transform_boxes
from scale_helpers import TINY

ORIGIN = (6, 4)
H = [[0.5, 0.0, -3.0], [0.0, 0.5, -1.5], [0.0, 0.0, 1.0]]  # RGB at twice the thermal resolution -> cropped frame


class FramedShapes(ShapesSource):
    """The shapes dataset as if it had come through the sensing pipeline: crop origin, homography, file names."""

    def samples(self, report):
        for s in super().samples(report):
            s.meta.update(crop_origin=list(ORIGIN), crop_size=[s.width, s.height], H_rgb_to_frame=H,
                          file_name=f"{s.group}/IMG_{s.image_id:04d}_W.JPG",
                          thermal_file=f"{s.group}/IMG_{s.image_id:04d}_T.JPG")
            yield s


class FramedPlugin:
    @hookimpl
    def register_datasets(self, register):
        register(DatasetSpec(name="framed", open=lambda root=None, sensing=None, **o: FramedShapes(per_group=10),
                             categories=CATEGORIES, default_encoding="test-ir8", description="framed shapes"))


# ------------------------------------------------------------------------------------------------ frames
META = {"crop_origin": list(ORIGIN), "crop_size": [80, 64], "H_rgb_to_frame": H}
BOXES = np.array([[10.25, 12.5, 30.75, 40.0], [0.0, 0.0, 5.5, 7.25], [60.0, 50.0, 80.0, 64.0]])


@pytest.mark.parametrize("frame", ["thermal", "rgb", "prepared"])
def test_boxes_go_out_to_an_original_frame_and_back_unchanged(frame):
    out = from_prepared(BOXES, frame, META)
    back, keep = to_prepared(out, frame, META)
    assert keep.all() and np.array_equal(back, BOXES)


def test_rgb_boxes_move_exactly_like_the_ground_truth_did():
    rgb = np.array([[100.0, 40.0, 180.5, 90.0], [5.0, 300.0, 60.0, 400.0]])
    theirs, keep_gt = transform_boxes(rgb, np.asarray(H), (0, 0), (80, 64))
    ours, keep = to_prepared(rgb, "rgb", META)
    assert np.array_equal(keep, keep_gt) and np.allclose(ours, theirs, atol=1e-4)


def test_undistortion_is_undone_on_export_and_redone_on_scoring():
    from harness.sensing.calibration import CameraModel, undistorted_camera

    cam = CameraModel(np.array([[300.0, 0, 160], [0, 300.0, 128], [0, 0, 1]]), [-0.12, 0.03], (320, 256))
    new, _ = undistorted_camera(cam, 0.0)
    meta = {**META, "cameras": {"rgb": {"camera": cam.to_dict(), "undistorted": new.to_dict()}}}
    rgb = from_prepared(BOXES[:1], "rgb", meta)
    assert not np.allclose(rgb, from_prepared(BOXES[:1], "rgb", META), atol=0.5)  # distortion moved it
    back, _ = to_prepared(rgb, "rgb", meta)
    # a lens bends box edges: the bounding box of moved corners grows a little each way (documented)
    assert np.allclose(back, BOXES[:1], atol=1.0) and (back[0, :2] <= BOXES[0, :2]).all()


def test_boxes_outside_the_prepared_frame_are_clipped_or_dropped():
    b, keep = to_prepared(np.array([[-20.0, -20.0, -10.0, -10.0], [70.0, 60.0, 120.0, 90.0]]), "prepared", META)
    assert keep.tolist() == [False, True] and b.tolist() == [[70.0, 60.0, 80.0, 64.0]]


# ------------------------------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, one_torch_thread):
    """One tiny finished run on fold A of the framed dataset, shared by the module's tests."""
    import os

    from harness.plugins import load_plugins

    load_plugins()
    tmp = tmp_path_factory.mktemp("score")

    old = os.environ.get("HARNESS_CACHE")
    os.environ["HARNESS_CACHE"] = str(tmp / "cache")
    tinydet_module()
    import harness_tinydet.plugin as tinydet_plugin
    from engine_helpers import ShapesPlugin

    from harness.runner import RunRequest, run

    with temporary_plugin(ShapesPlugin(), name="shapes-test"), temporary_plugin(tinydet_plugin, name="tinydet-t"), \
            temporary_plugin(FramedPlugin(), name="framed-test"):
        summary = run(RunRequest(detector="tinydet", dataset="framed", folds="A", store=tmp / "store",
                                 overrides=TINY, progress=False))
        yield tmp, summary.results[0]
    if old is None:
        os.environ.pop("HARNESS_CACHE", None)
    else:
        os.environ["HARNESS_CACHE"] = old


def _score(tmp, name, predictions, **kw):
    from harness.scoring.external import score_external

    return score_external("framed", "A", predictions, name, overrides=TINY, store=tmp / "store", **kw)


@pytest.mark.slow
@pytest.mark.parametrize("frame", ["thermal", "rgb", "prepared"])
def test_exported_predictions_scored_again_reproduce_the_run_exactly(finished_run, frame):
    from harness.scoring.export import export_predictions

    tmp, result = finished_run
    preds = json.loads((result.path / "predictions.json").read_text())
    assert preds, "the tiny run must predict something for this test to mean anything"
    [e] = export_predictions(tmp / "store", "framed", "tinydet", frame=frame, out=tmp / f"{frame}.json")
    exported = json.loads(e.path.read_text())
    assert len(exported) == len(preds) and all("file_name" in d and "category_name" in d for d in exported)
    if frame != "prepared":
        assert exported[0]["bbox"] != preds[0]["bbox"]
    res = _score(tmp, f"roundtrip-{frame}", e.path, frame=frame, images=e.images_path)
    assert res.matching.scored == len(preds) and not res.matching.missing_images
    assert res.metrics["metrics"] == result.metrics["metrics"]
    assert res.metrics["per_category"] == result.metrics["per_category"]
    assert res.metrics["support"] == result.metrics["support"]
    from harness.evaluation import check_sample_matched

    assert check_sample_matched([result.metrics, res.metrics]) is None


@pytest.mark.slow
def test_missing_images_are_reported_and_the_guard_labels_the_comparison(finished_run):
    from harness.evaluation import check_sample_matched
    from harness.scoring.export import export_predictions

    tmp, result = finished_run
    [e] = export_predictions(tmp / "store", "framed", "tinydet", frame="thermal", out=tmp / "t.json")
    images = json.loads(e.images_path.read_text())
    dropped = images["images"].pop(3)
    partial = tmp / "partial.images.json"
    partial.write_text(json.dumps(images))
    res = _score(tmp, "partial", e.path, frame="thermal", images=partial)
    m = res.matching
    assert m.fold_images == 10 and m.images_scored == 9 and len(m.missing_images) == 1
    assert any("missing" in line for line in m.lines())
    assert res.metrics["support"]["images"] == 9
    assert res.metrics["external"]["matching"]["missing_images"] == 1
    assert dropped["file_name"].endswith("_T.JPG")
    label = check_sample_matched([result.metrics, res.metrics], allow=True)
    assert label and label.startswith("NOT sample-matched")


@pytest.mark.slow
def test_categories_by_name_or_map_and_unknown_ones_counted(finished_run):
    tmp, result = finished_run
    preds = json.loads((result.path / "predictions.json").read_text())
    names = {1: "Window", 2: "WARM", 3: "cold"}
    theirs = [{**p, "category_id": {1: 7, 2: 8, 3: 9}[p["category_id"]]} for p in preds]
    theirs.append({**preds[0], "category_id": 99})
    images = {"images": [{"id": r["id"], "file_name": r["file_name"]}
                         for r in json.loads((result.path / "gt.json").read_text())["images"]],
              "categories": [{"id": 6 + k, "name": n} for k, n in names.items()] + [{"id": 99, "name": "person"}]}
    (tmp / "cat_preds.json").write_text(json.dumps(theirs))
    (tmp / "cat_images.json").write_text(json.dumps(images))
    res = _score(tmp, "cats", tmp / "cat_preds.json", images=tmp / "cat_images.json")
    assert res.matching.unmatched_categories == {"person": 1}
    assert res.metrics["metrics"] == result.metrics["metrics"]
    res2 = _score(tmp, "catmap", tmp / "cat_preds.json", category_map={"7": "window", "8": "warm", "9": "cold"})
    assert res2.matching.unmatched_categories == {"99": 1}
    assert res2.metrics["metrics"] == result.metrics["metrics"]


@pytest.mark.slow
def test_predictions_of_no_known_image_are_a_clear_error(finished_run):
    tmp, _ = finished_run
    (tmp / "bad.json").write_text(json.dumps([{"file_name": "nowhere.jpg", "category_id": 1,
                                               "bbox": [1, 1, 5, 5], "score": 0.9}]))
    with pytest.raises(DataError, match="unknown image"):
        _score(tmp, "bad", tmp / "bad.json")


@pytest.mark.slow
def test_scored_runs_are_listed_as_external_detectors(finished_run):
    from harness.store import Store

    tmp, result = finished_run
    _score(tmp, "listed", result.path / "predictions.json", params=1.5, gflops=2.0)
    dets = {r.key.detector for r in Store(tmp / "store").runs(dataset="framed")}
    assert "external/listed" in dets and "tinydet" in dets
    run = next(r for r in Store(tmp / "store").runs(detector="external/listed"))
    assert run.path.parent.parent.parent.name == "external.listed"
    assert run.read_metrics()["complexity"]["params"] == 1_500_000
    from harness.report.collect import StoreView
    from harness.report.tables import project_table

    table = project_table(StoreView(Store(tmp / "store")), "framed")
    text = table.to_markdown()
    row = next(line for line in text.splitlines() if "external/listed" in line)
    cells = [c.strip(" *") for c in row.split("|")]
    assert "1.5" in cells and "2" in cells
    assert any("as given with `harness score`" in n for n in table.notes)
