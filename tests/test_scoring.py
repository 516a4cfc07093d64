"""Scoring predictions made elsewhere (``harness score``) and exporting a run's (``harness export-predictions``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("harness.cache")

from engine_helpers import CATEGORIES, ShapesSource, tinydet_module
from harness import DatasetSpec, hookimpl
from harness.errors import DataError
from harness.scoring.frames import from_prepared, to_prepared
from harness.sensing.warp import transform_boxes
from harness.testing import temporary_plugin
from scale_helpers import TINY

ORIGIN = (6, 4)
H = [[0.5, 0.0, -3.0], [0.0, 0.5, -1.5], [0.0, 0.0, 1.0]]  # RGB at twice the thermal resolution -> cropped frame


def rotated_homography(scale: float = 0.5, degrees: float = 2.0, shift=(-3.0, -1.5), tilt=(2e-5, -1e-5)):
    """RGB -> frame: a scale, a rotation, a shift and a little perspective, as a registration fit gives them."""
    t = np.deg2rad(degrees)
    return np.array(
        [
            [scale * np.cos(t), -scale * np.sin(t), shift[0]],
            [scale * np.sin(t), scale * np.cos(t), shift[1]],
            [tilt[0], tilt[1], 1.0],
        ]
    )


def lens(width: int, height: int, k1: float = -0.12, k2: float = 0.03):
    """A calibrated camera with barrel distortion and its undistorted camera, as prepared samples record them."""
    from harness.sensing.calibration import CameraModel, undistorted_camera

    f = 1.2 * width
    cam = CameraModel(np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]), [k1, k2], (width, height))
    return {"camera": cam.to_dict(), "undistorted": undistorted_camera(cam, 0.0)[0].to_dict()}


class FramedShapes(ShapesSource):
    """The shapes dataset as if it had come through the sensing pipeline: crop origin, a rotated homography with
    perspective, lens models of both cameras, file names."""

    def samples(self, report):
        for s in super().samples(report):
            w, h = s.width + 2 * ORIGIN[0], s.height + 2 * ORIGIN[1]  # the thermal image before the crop
            s.meta.update(
                crop_origin=list(ORIGIN),
                crop_size=[s.width, s.height],
                H_rgb_to_frame=rotated_homography().tolist(),
                cameras={"thermal": lens(w, h), "rgb": lens(2 * w, 2 * h, -0.08, 0.01)},
                file_name=f"{s.group}/IMG_{s.image_id:04d}_W.JPG",
                thermal_file=f"{s.group}/IMG_{s.image_id:04d}_T.JPG",
            )
            yield s


class FramedPlugin:
    @hookimpl
    def register_datasets(self, register):
        register(
            DatasetSpec(
                name="framed",
                open=lambda root=None, sensing=None, **o: FramedShapes(per_group=10),
                categories=CATEGORIES,
                default_encoding="test-ir8",
                description="framed shapes",
            )
        )


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
    # a lens bends box edges, but the export is the exact preimage of the way boxes come in: nothing grows
    assert np.array_equal(back, BOXES[:1])


FRAME_SIZES = [(80, 64), (320, 256), (640, 512)]
HOMOGRAPHIES = {
    "scale": np.array(H),
    "rotation 0.5 deg": rotated_homography(0.5, 0.5),
    "rotation 2 deg, perspective": rotated_homography(0.5, 2.0, (4.0, -7.0), (3e-5, -2e-5)),
    "same resolution, -1.5 deg": rotated_homography(1.02, -1.5, (-10.0, 6.0), (-1e-5, 1e-5)),
}


def _float32_boxes(size, n=40, seed=0):
    """Boxes as a detector returns them (float32 values) over the whole frame, at its edges and 1-3 px small."""
    rng = np.random.default_rng(seed)
    w, h = size
    xy = rng.uniform(0, 1, (n, 2)) * [w - 4, h - 4]
    wh = np.exp(rng.uniform(np.log(3), np.log(min(w, h) / 3), (n, 2)))
    b = np.c_[xy, np.minimum(xy + wh, [w, h])]
    b[:4] = [[0, 0, 9.5, 7.25], [w - 12.3, h - 8.1, w, h], [0, h / 2, 3, h / 2 + 2.5], [w / 3, 0, w / 3 + 1.5, 2]]
    return b.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize("size", FRAME_SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
@pytest.mark.parametrize("hname", list(HOMOGRAPHIES))
@pytest.mark.parametrize("frame, lenses", [("thermal", False), ("thermal", True), ("rgb", False), ("rgb", True)])
def test_export_is_the_exact_inverse_of_scoring_in_every_frame(size, hname, frame, lenses):
    """Out of the prepared frame and back: every box returns to the bit (well under a thousandth of a pixel), on
    frames of several sizes, homographies with rotation and perspective, with and without lens models."""
    from harness.scoring.frames import preimage

    w, h = size
    meta = {"crop_origin": [7, 5], "crop_size": [w, h], "H_rgb_to_frame": HOMOGRAPHIES[hname].tolist()}
    if lenses:
        meta["cameras"] = {"thermal": lens(w + 14, h + 10), "rgb": lens(2 * w, 2 * h, -0.08, 0.01)}
    boxes = _float32_boxes(size)
    back, keep = to_prepared(from_prepared(boxes, frame, meta), frame, meta, min_size=None)
    assert keep.all() and np.array_equal(back, boxes)
    assert preimage(boxes, frame, meta).exact.all()


def test_a_box_too_thin_for_the_rotation_is_counted_and_stays_close():
    """Under a 3 degree rotation a 1 x 40 px box is the bounding box of no box of the RGB image (any box there comes
    back at least 40 tan 3 deg = 2.1 px wide): it is exported as the closest box, counted as inexact, and comes back
    about that wide, not 5 px as moving its corners back gives."""
    from harness.scoring.frames import preimage

    meta = {"crop_origin": [0, 0], "crop_size": [320, 256], "H_rgb_to_frame": rotated_homography(0.5, 3.0).tolist()}
    boxes = np.array([[100.0, 50.0, 101.0, 90.0], [10.0, 10.0, 60.0, 40.0]])
    out = preimage(boxes, "rgb", meta)
    assert out.exact.tolist() == [False, True] and out.inexact == 1
    back, _ = to_prepared(out.boxes, "rgb", meta, min_size=None)
    assert np.array_equal(back[1], boxes[1])
    width = back[0, 2] - back[0, 0]
    assert 40 * np.tan(np.deg2rad(3.0)) - 0.1 < width < 40 * np.tan(np.deg2rad(3.0)) + 0.1


def test_boxes_outside_the_prepared_frame_are_clipped_or_dropped():
    b, keep = to_prepared(np.array([[-20.0, -20.0, -10.0, -10.0], [70.0, 60.0, 120.0, 90.0]]), "prepared", META)
    assert keep.tolist() == [False, True] and b.tolist() == [[70.0, 60.0, 80.0, 64.0]]


def test_image_names_match_by_path_name_stem_and_numeric_stem():
    from harness.scoring.external import _ImageIndex

    index = _ImageIndex([(0, ["day/010001.jpg", "ir/010001_T.jpg"]), (1, ["day/010002.jpg"]), (2, ["A/IMG_7_T.JPG"])])
    assert index.find("day/010001.jpg") == 0 and index.find("010002.jpg") == 1 and index.find("img_7_t") == 2
    assert index.find(10001) == 0 and index.find("10002") == 1  # Ultralytics' int(stem)
    assert index.find("nowhere.jpg") is None


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

    with (
        temporary_plugin(ShapesPlugin(), name="shapes-test"),
        temporary_plugin(tinydet_plugin, name="tinydet-t"),
        temporary_plugin(FramedPlugin(), name="framed-test"),
    ):
        summary = run(
            RunRequest(
                detector="tinydet", dataset="framed", folds="A", store=tmp / "store", overrides=TINY, progress=False
            )
        )
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
    # the scored run stores its error analysis too, and it is the trained run's own
    trained = json.loads((result.path / "analysis.json").read_text())
    scored = json.loads((res.run_path / "analysis.json").read_text())
    assert scored["run"]["detector"] == f"external/roundtrip-{frame}"
    assert {k: v for k, v in scored.items() if k != "run"} == {k: v for k, v in trained.items() if k != "run"}


@pytest.mark.slow
@pytest.mark.parametrize("frame", ["thermal", "rgb", "prepared"])
def test_shuffled_and_renumbered_exports_score_to_the_last_digit(finished_run, frame):
    """Another codebase reorders the predictions and numbers images and categories its own way; given that mapping
    (its image list), the score is the run's own, to the last digit, in every frame."""
    from harness.scoring.export import export_predictions

    tmp, result = finished_run
    [e] = export_predictions(tmp / "store", "framed", "tinydet", frame=frame, out=tmp / f"renum-{frame}.json")
    assert e.images_path.name == f"renum-{frame}.images.json" and e.inexact == 0
    exported = json.loads(e.path.read_text())
    listing = json.loads(e.images_path.read_text())
    rng = np.random.default_rng(7)
    new_image = {im["id"]: 5000 + int(k) for im, k in zip(listing["images"], rng.permutation(len(listing["images"])))}
    new_cat = {c["id"]: 40 - c["id"] for c in listing["categories"]}  # reversed, far from 1..3
    theirs = [
        {
            "image_id": new_image[d["image_id"]],
            "category_id": new_cat[d["category_id"]],
            "bbox": d["bbox"],
            "score": d["score"],
        }
        for d in exported
    ]  # no file names or category names: ids only
    theirs = [theirs[i] for i in rng.permutation(len(theirs))]
    their_list = {
        "images": [{**im, "id": new_image[im["id"]]} for im in listing["images"]],
        "categories": [{**c, "id": new_cat[c["id"]]} for c in listing["categories"]],
    }
    (tmp / f"theirs-{frame}.json").write_text(json.dumps(theirs))
    (tmp / f"theirs-{frame}.images.json").write_text(json.dumps(their_list))
    res = _score(
        tmp,
        f"renumbered-{frame}",
        tmp / f"theirs-{frame}.json",
        frame=frame,
        images=tmp / f"theirs-{frame}.images.json",
    )
    assert res.matching.scored == len(exported) and not res.matching.findings
    assert res.metrics["metrics"] == result.metrics["metrics"]
    assert res.metrics["per_category"] == result.metrics["per_category"]
    assert res.metrics["support"] == result.metrics["support"]
    stored = sorted(map(json.dumps, json.loads((res.run_path / "predictions.json").read_text())))
    assert stored == sorted(map(json.dumps, json.loads((result.path / "predictions.json").read_text())))


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
    images = {
        "images": [
            {"id": r["id"], "file_name": r["file_name"]}
            for r in json.loads((result.path / "gt.json").read_text())["images"]
        ],
        "categories": [{"id": 6 + k, "name": n} for k, n in names.items()] + [{"id": 99, "name": "person"}],
    }
    (tmp / "cat_preds.json").write_text(json.dumps(theirs))
    (tmp / "cat_images.json").write_text(json.dumps(images))
    res = _score(tmp, "cats", tmp / "cat_preds.json", images=tmp / "cat_images.json")
    assert res.matching.unmatched_categories == {"person": 1}

    def but_dropped(m):  # the prediction left out is counted in metrics.json; every number is the run's own
        return {k: v for k, v in m.items() if k != "dropped_detections"}

    assert but_dropped(res.metrics["metrics"]) == but_dropped(result.metrics["metrics"])
    assert res.metrics["metrics"]["dropped_detections"]["unknown_category"] == 1
    res2 = _score(tmp, "catmap", tmp / "cat_preds.json", category_map={"7": "window", "8": "warm", "9": "cold"})
    assert res2.matching.unmatched_categories == {"99": 1}
    assert but_dropped(res2.metrics["metrics"]) == but_dropped(result.metrics["metrics"])
    assert res2.metrics["metrics"]["dropped_detections"]["unknown_category"] == 1


@pytest.mark.slow
def test_predictions_of_no_known_image_are_a_clear_error(finished_run):
    tmp, _ = finished_run
    (tmp / "bad.json").write_text(
        json.dumps([{"file_name": "nowhere.jpg", "category_id": 1, "bbox": [1, 1, 5, 5], "score": 0.9}])
    )
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
    from harness.report.reader import StoreView
    from harness.report.tables import project_table

    table = project_table(StoreView(Store(tmp / "store")), "framed")
    text = table.to_markdown()
    row = next(line for line in text.splitlines() if "external/listed" in line)
    cells = [c.strip(" *") for c in row.split("|")]
    assert "1.5" in cells and "2" in cells
    assert any("as given with `harness score`" in n for n in table.notes)


# ------------------------------------------------------------------------------------------------ other codebases
def _thermal_truth(tmp, result):
    """The fold's ground truth in the original thermal images: (thermal file name, xywh box, 0-based class), as a
    perfect detector run on those images by another codebase would find them."""
    from harness.scoring.export import _prepared_of
    from harness.scoring.frames import from_prepared
    from harness.store import Store

    run = next(iter(Store(tmp / "store").runs(dataset="framed", detector="tinydet")))
    prepared = _prepared_of(run)
    records = {int(r["image_id"]): r for r in prepared.records}
    gt = json.loads((result.path / "gt.json").read_text())
    out = []
    for a in gt["annotations"]:
        meta = records[a["image_id"]]["meta"]
        x, y, w, h = a["bbox"]
        ((x1, y1, x2, y2),) = from_prepared(np.array([[x, y, x + w, y + h]]), "thermal", meta).tolist()
        out.append((meta["thermal_file"], [x1, y1, x2 - x1, y2 - y1], a["category_id"] - 1))
    return out


def _ultralytics(truth, zero_based: bool):
    """predictions.json as Ultralytics' DetectionValidator.pred_to_json writes it: image_id the file stem (an int
    when numeric), bbox top-left xywh rounded to 3 decimals, score to 5; class ids through its class_map, which
    is range(1000) (0-based) in 8.0 and range(1, nc + 1) with a file_name field in later releases."""
    from pathlib import PurePosixPath

    out = []
    for k, (fname, box, cls) in enumerate(truth):
        stem = PurePosixPath(fname).stem
        d = {"image_id": int(stem) if stem.isnumeric() else stem}
        if not zero_based:
            d["file_name"] = PurePosixPath(fname).name
        d.update(
            category_id=cls if zero_based else cls + 1,
            bbox=[round(v, 3) for v in box],
            score=round(0.95 - 0.001 * k, 5),
        )
        out.append(d)
    return out


def _mmdetection(truth):
    """MMDetection's test annotation file (its own image ids, 0-based in file order, and category ids) and the
    ``results.bbox.json`` that ``--format-only`` (CocoMetric.results2json) writes from it: image_id and
    category_id of that file, bbox [x, y, w, h] and score as float32 values."""
    names = sorted({f for f, _, _ in truth})
    their = {
        "images": [{"id": k, "file_name": f, "width": 92, "height": 76} for k, f in enumerate(names)],
        "categories": [{"id": k + 1, "name": n} for k, n in enumerate(CATEGORIES)],
    }
    ids = {f: k for k, f in enumerate(names)}
    results = [
        {
            "image_id": ids[f],
            "bbox": np.asarray(box, np.float32).tolist(),
            "score": float(np.float32(0.95 - 0.001 * k)),
            "category_id": cls + 1,
        }
        for k, (f, box, cls) in enumerate(truth)
    ]
    return their, results


@pytest.mark.slow
def test_ultralytics_zero_based_classes_without_a_map_stop_and_name_the_shift(finished_run):
    tmp, result = finished_run
    truth = _thermal_truth(tmp, result)
    (tmp / "yolo8.0.json").write_text(json.dumps(_ultralytics(truth, zero_based=True)))
    with pytest.raises(DataError) as err:
        _score(tmp, "yolo-zero", tmp / "yolo8.0.json", frame="thermal")
    text = str(err.value)
    assert "shift of +1" in text and "--category-map 0=window,1=warm,2=cold" in text
    assert "categories the dataset does not have: 0 (" in text and "--allow-implausible" in text
    assert not (tmp / "store" / "framed" / "external.yolo-zero").exists()  # nothing stored
    mapped = _score(
        tmp,
        "yolo-zero-mapped",
        tmp / "yolo8.0.json",
        frame="thermal",
        category_map={"0": "window", "1": "warm", "2": "cold"},
    )
    assert mapped.metrics["metrics"]["mAP50"] == 1.0 and not mapped.matching.findings


@pytest.mark.slow
def test_current_ultralytics_predictions_score_without_any_option(finished_run):
    tmp, result = finished_run
    (tmp / "yolo.json").write_text(json.dumps(_ultralytics(_thermal_truth(tmp, result), zero_based=False)))
    res = _score(tmp, "yolo", tmp / "yolo.json", frame="thermal")
    assert res.metrics["metrics"]["mAP50"] == 1.0 and res.matching.scored == res.matching.predictions


@pytest.mark.slow
def test_accepting_implausible_predictions_labels_the_stored_result(finished_run):
    tmp, result = finished_run
    (tmp / "yolo8.0b.json").write_text(json.dumps(_ultralytics(_thermal_truth(tmp, result), zero_based=True)))
    res = _score(tmp, "yolo-accepted", tmp / "yolo8.0b.json", frame="thermal", allow_implausible=True)
    stored = json.loads((res.run_path / "metrics.json").read_text())
    assert any("--allow-implausible" in lab and "shift of +1" in lab for lab in stored["labels"])
    assert set(stored["external"]["matching"]["implausible"]) == {"unknown_categories", "category_shift"}
    assert stored["metrics"]["mAP50"] < 0.5  # scored as read: the classes are shifted
    from harness.report.reader import StoreView
    from harness.report.tables import project_table
    from harness.store import Store

    notes = project_table(StoreView(Store(tmp / "store")), "framed").notes
    assert any(n.startswith("† accepted risk (external/yolo-accepted/external): implausible") for n in notes)


@pytest.mark.slow
def test_mmdetection_own_image_ids_without_the_image_list_stop(finished_run):
    tmp, result = finished_run
    their, results = _mmdetection(_thermal_truth(tmp, result))
    (tmp / "mmdet_test.json").write_text(json.dumps(their))
    (tmp / "results.bbox.json").write_text(json.dumps(results))
    with pytest.raises(DataError) as err:
        _score(tmp, "mmdet", tmp / "results.bbox.json", frame="thermal")
    text = str(err.value)
    assert "prediction(s) of 1 unknown image(s) left out, e.g. image_id 0" in text
    assert "image ids read as the harness's match the fold's images only after a shift of +1" in text
    assert "--images" in text
    res = _score(tmp, "mmdet", tmp / "results.bbox.json", frame="thermal", images=tmp / "mmdet_test.json")
    assert res.metrics["metrics"]["mAP50"] == 1.0 and not res.matching.findings


def _compare_with_tinydet(cli_runner, tmp, other: str):
    """``harness compare-detectors tinydet OTHER`` on the framed dataset of the finished run's store, no resamples."""
    args = ["--dataset", "framed", "--store", str(tmp / "store"), "--resamples", "0"]
    return cli_runner(["compare-detectors", "tinydet", other, *args])


@pytest.mark.slow
def test_compare_detectors_addresses_external_runs(finished_run, cli_runner):
    from harness.report import compare_detectors

    tmp, result = finished_run
    _score(tmp, "paired", result.path / "predictions.json")
    for name in ("external/paired", "external/paired/external"):
        comp = compare_detectors(tmp / "store", "framed", "tinydet", name, resamples=0)
        assert comp.b == "external/paired/external" and comp.folds == ["A"]
        assert comp.fold_differences["mAP50_95"].diffs == [0.0]  # the run's own predictions, scored as external
    res = _compare_with_tinydet(cli_runner, tmp, "external/paired")
    assert res.exit_code == 0, res.output
    assert "external/paired" in res.stdout


@pytest.mark.slow
def test_a_refused_pair_suggests_the_command_line_option_not_the_api_one(finished_run, cli_runner):
    from harness.scoring.export import export_predictions

    tmp, _ = finished_run
    [e] = export_predictions(tmp / "store", "framed", "tinydet", frame="prepared", out=tmp / "fewer.json")
    images = json.loads(e.images_path.read_text())
    images["images"].pop(0)
    (tmp / "fewer.images.json").write_text(json.dumps(images))
    _score(tmp, "fewer", e.path, images=tmp / "fewer.images.json")
    res = _compare_with_tinydet(cli_runner, tmp, "external/fewer")
    assert res.exit_code == 2
    assert "refusing to compare" in res.output and "--allow-mismatched" in res.output
    assert "allow=True" not in res.output
