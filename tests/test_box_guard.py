"""The box guard shared by every producer of boxes: predictions scored from elsewhere (``harness score``) and a
detector plugin's eval-mode output. A misread convention (corners for x, y, w, h; normalised coordinates; another
frame or scale) stops with what was seen, instead of scoring near zero as an ordinary result."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("harness.cache")

from harness.errors import DataError
from harness.scoring import plausibility as guard
from harness.testing import temporary_plugin
from scale_helpers import TINY


# ------------------------------------------------------------------------------------------------ pure helpers
def test_inside_share_counts_the_area_in_the_frame():
    boxes = np.array([[0, 0, 10, 10], [-10, 0, 10, 10], [20, 20, 30, 30], [np.nan, 0, 1, 1]], dtype=float)
    assert guard.inside_share(boxes, 20, 20).tolist() == [1.0, 0.5, 0.0, 0.0]
    assert guard.mostly_outside(boxes, 20, 20).tolist() == [False, False, True, True]


def test_normalised_boxes_are_found_only_in_frames_wide_enough_to_tell():
    boxes = np.array([[0.1, 0.2, 0.5, 0.9]] * 4)
    [f] = guard.box_findings(boxes, 64, 64, "boxes", "input", "", "scale them")
    assert f.kind == "normalised" and "4 of 4 boxes (100%)" in f.message and "scale them" in f.message
    assert guard.box_findings(boxes, 4, 4, "boxes", "input", "", "") == []


# ------------------------------------------------------------------------------------------------ harness score
@pytest.fixture(scope="module")
def framed(tmp_path_factory):
    """The framed shapes dataset of ``test_scoring`` prepared once, and fold A's ground truth as perfect
    predictions in every frame: ``(tmp, {frame: predictions})``."""
    import os

    from engine_helpers import ShapesPlugin
    from harness.cache import fold_indices, prepare, resolve_folds
    from harness.config import load_config
    from harness.plugins import get_host, load_plugins
    from harness.scoring.frames import from_prepared, image_name
    from test_scoring import FramedPlugin

    load_plugins()
    tmp = tmp_path_factory.mktemp("guard")
    old = os.environ.get("HARNESS_CACHE")
    os.environ["HARNESS_CACHE"] = str(tmp / "cache")
    with temporary_plugin(ShapesPlugin(), name="shapes-guard"), temporary_plugin(FramedPlugin(), name="framed-g"):
        spec = get_host().dataset("framed")
        cfg = load_config("smoke", protocol=spec.protocol, overrides=TINY)
        prepared = prepare("framed", cfg)
        [fold] = resolve_folds(spec, prepared, cfg, "A")
        _, val = fold_indices(prepared, fold)
        perfect: dict[str, list] = {f: [] for f in ("prepared", "thermal", "rgb")}
        for i in val:
            r = prepared.records[i]
            boxes, labels = prepared.targets(i)
            for frame, out in perfect.items():
                b = np.asarray(boxes, float).reshape(-1, 4)
                b = b if frame == "prepared" else from_prepared(b, frame, r["meta"])
                out += [
                    {
                        "file_name": image_name(r["meta"], frame, r["image_id"]),
                        "category_id": int(c) + 1,
                        "bbox": [x1, y1, x2 - x1, y2 - y1],
                        "score": 0.9,
                    }
                    for (x1, y1, x2, y2), c in zip(b.tolist(), np.asarray(labels).tolist())
                ]
        yield tmp, perfect
    if old is None:
        os.environ.pop("HARNESS_CACHE", None)
    else:
        os.environ["HARNESS_CACHE"] = old


def _score(tmp, name, preds, **kw):
    from harness.scoring.external import score_external

    path = tmp / f"{name}.json"
    path.write_text(json.dumps(preds))
    return score_external("framed", "A", path, name, overrides=TINY, store=tmp / "store", **kw)


def _corners(preds):
    return [
        {**d, "bbox": [d["bbox"][0], d["bbox"][1], d["bbox"][0] + d["bbox"][2], d["bbox"][1] + d["bbox"][3]]}
        for d in preds
    ]


def test_perfect_predictions_score_one_in_every_frame_with_no_finding(framed):
    tmp, perfect = framed
    for frame, preds in perfect.items():
        res = _score(tmp, f"perfect-{frame}", preds, frame=frame)
        assert res.metrics["metrics"]["mAP50"] == 1.0 and not res.matching.findings, frame


def test_corner_boxes_where_xywh_is_expected_stop_and_name_the_option(framed):
    tmp, perfect = framed
    corners = _corners(perfect["prepared"])
    with pytest.raises(DataError) as err:
        _score(tmp, "corners", corners)
    text = str(err.value)
    assert "as corners x1, y1, x2, y2" in text and "--box-format xyxy" in text and "100% as corners" in text
    assert not (tmp / "store" / "framed" / "external.corners").exists()
    res = _score(tmp, "corners-read", corners, box_format="xyxy")
    assert res.metrics["metrics"]["mAP50"] == 1.0 and not res.matching.findings
    accepted = _score(tmp, "corners-accepted", corners, allow_implausible=True)
    assert accepted.metrics["metrics"]["mAP50"] < 0.5
    assert any("box_format" not in lab and "as corners" in lab for lab in accepted.metrics["labels"])


@pytest.mark.parametrize("given, actual", [("rgb", "prepared"), ("prepared", "rgb")])
def test_the_wrong_frame_stops_with_the_boxes_outside_and_the_frame_that_fits(framed, given, actual):
    tmp, perfect = framed
    with pytest.raises(DataError) as err:
        _score(tmp, f"frame-{given}", perfect[actual], frame=given)
    text = str(err.value)
    assert f"--frame {actual}" in text and "100%" in text
    assert "mostly outside" in text or "agree with the ground truth far better" in text


def test_normalised_predictions_stop(framed):
    tmp, perfect = framed
    w, h = 80, 64  # the framed dataset's prepared frame
    norm = [{**d, "bbox": [v / (w if k % 2 == 0 else h) for k, v in enumerate(d["bbox"])]} for d in perfect["prepared"]]
    with pytest.raises(DataError, match=r"lie within 0\.\.1 of the 80x64 px prepared frame.*normalised"):
        _score(tmp, "normalised", norm)


def test_unknown_categories_left_out_are_counted_in_metrics_json(framed):
    tmp, perfect = framed
    preds = perfect["prepared"] + [{**d, "category_id": 99} for d in perfect["prepared"][:1]]
    res = _score(tmp, "unknown-cat", preds)
    stored = json.loads((res.run_path / "metrics.json").read_text())
    assert stored["metrics"]["dropped_detections"]["unknown_category"] == 1
    assert res.metrics["metrics"]["mAP50"] == 1.0


def test_a_negative_width_is_malformed_not_outside_the_frame(framed):
    tmp, perfect = framed
    bad = {**perfect["prepared"][0]}
    bad["bbox"] = [bad["bbox"][0], bad["bbox"][1], -bad["bbox"][2], bad["bbox"][3]]
    res = _score(tmp, "negative", perfect["prepared"] + [bad])
    m = res.matching
    assert m.dropped_outside_frame == 0 and m.invalid == 1
    assert m.invalid_reasons == {"negative width or height": 1}
    assert any("malformed" in line and "negative width or height" in line for line in m.lines())
    stored = json.loads((res.run_path / "metrics.json").read_text())
    assert stored["metrics"]["dropped_detections"]["malformed"] == 1


# ------------------------------------------------------------------------------------------------ a detector's output
def _boxes_through(boxes_per_image, shape=(64, 80)):
    """``DegenerateBoxes`` after the host mapped each image's eval-mode boxes (input pixels, 80x64 unpadded)."""
    import torch

    from harness.engine.augment import Letterbox
    from harness.engine.predict import DegenerateBoxes, detections_to_coco

    counts = DegenerateBoxes()
    lb = Letterbox(ratio=1.0, pad=(0.0, 0.0), shape=shape)
    for k, boxes in enumerate(boxes_per_image):
        b = torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4)
        det = {"boxes": b, "scores": torch.full((len(b),), 0.5), "labels": torch.zeros(len(b), dtype=torch.long)}
        detections_to_coco(det, k + 1, lb, num_classes=1, name="d", degenerate=counts)
    return counts


GOOD = [[10.0, 8.0, 30.0, 40.0], [40.0, 20.0, 70.0, 50.0], [5.0, 5.0, 20.0, 20.0], [50.0, 30.0, 60.0, 60.0]]


def test_good_boxes_pass_the_detector_guard_silently():
    counts = _boxes_through([GOOD] * 5)
    assert counts.check("d") is None and counts.warning("d") is None and counts.label("d") is None
    assert "normalised" not in counts.to_dict() and "mostly_outside" not in counts.to_dict()


def test_normalised_detector_boxes_stop_the_run_naming_the_detector():
    from harness.errors import PluginError

    norm = [[x1 / 80, y1 / 64, x2 / 80, y2 / 64] for x1, y1, x2, y2 in GOOD]
    counts = _boxes_through([norm] * 5)
    with pytest.raises(PluginError, match=r"detector 'd': 20 of the 20 boxes .* within 0\.\.1 .*allow_degenerate"):
        counts.check("d")
    assert counts.to_dict()["normalised"] == 20
    assert "stored anyway" in counts.check("d", allow=True)


def test_detector_boxes_at_ten_times_the_scale_stop_the_run():
    from harness.errors import PluginError

    scaled = [[10 * v for v in b] for b in GOOD]
    counts = _boxes_through([scaled] * 5)
    with pytest.raises(PluginError, match=r"detector 'd': \d+ of the 20 boxes .* mostly outside the image"):
        counts.check("d")


def test_half_the_boxes_nan_is_said_and_labelled():
    nan = [[float("nan")] * 4] * 4
    counts = _boxes_through([GOOD + nan] * 5)
    assert counts.check("d") is None  # exactly half: under the stop rule
    text = counts.warning("d")
    assert text and "20 of the 40 boxes" in text and "20 non finite" in text and "50%" in text
    assert counts.label("d") == text


# ------------------------------------------------------------------------------------------------ the testing kit
def _det(boxes):
    import torch

    b = torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4)
    return {"boxes": b, "scores": torch.full((len(b),), 0.5), "labels": torch.zeros(len(b), dtype=torch.long)}


@pytest.mark.parametrize(
    "what, boxes, size, match",
    [
        ("nan", GOOD + [[float("nan"), 1.0, 2.0, 3.0]], None, "malformed .*1 non finite"),
        ("xywh", [[30.0, 20.0, 10.0, 8.0]] * 3, None, "malformed .*3 inverted.*not x, y, w, h"),
        ("normalised", [[0.1, 0.1, 0.4, 0.5], [0.5, 0.2, 0.9, 0.6]], None, r"within 0\.\.1"),
        ("outside", [[100.0, 100.0, 300.0, 300.0], [90.0, 0.0, 200.0, 10.0]], (80, 64), "mostly outside the 80x64 px"),
    ],
)
def test_the_testing_kit_refuses_boxes_harness_run_refuses(what, boxes, size, match):
    from harness.contracts import check_detections
    from harness.errors import PluginError

    with pytest.raises(PluginError, match=match):
        check_detections(_det(boxes), "d", num_classes=1, image_size=size)
    check_detections(_det(GOOD), "d", num_classes=1, image_size=(80, 64))  # good boxes pass


def test_the_testing_kit_refuses_a_nan_loss_as_harness_run_does():
    import torch

    from harness.contracts import check_losses
    from harness.errors import PluginError

    with pytest.raises(PluginError, match=r"loss 'box' is nan.*not finite"):
        check_losses({"cls": torch.tensor(1.0), "box": torch.tensor(float("nan"))}, "d")
    assert check_losses({"cls": torch.tensor(1.0)}, "d")


def test_a_scored_run_records_its_prepared_samples_so_a_gallery_can_draw_it(framed):
    from harness.report.gallery import prepared_of
    from harness.report.reader import read_run
    from harness.store import Store

    tmp, perfect = framed
    res = _score(tmp, "drawn", perfect["prepared"])
    run = next(r for r in Store(tmp / "store").runs(detector="external/drawn"))
    assert run.path == res.run_path
    samples, why = prepared_of(read_run(run))
    assert why is None and samples is not None and samples.manifest.get("fingerprint")


def test_mostly_malformed_predictions_stop_and_name_box_format(framed):
    tmp, perfect = framed
    with pytest.raises(
        DataError, match=r"(?s)implausible.*1\d of 20 predictions .* are malformed \(x2 < x1 or y2 < y1.*--box-format"
    ):
        _score(tmp, "read-as-corners", perfect["prepared"], box_format="xyxy")  # x, y, w, h read as corners


def test_a_file_mixing_corner_and_xywh_boxes_stops(framed):
    tmp, perfect = framed
    mixed = [
        corners if k % 2 else d
        for k, (d, corners) in enumerate(zip(perfect["prepared"], _corners(perfect["prepared"])))
    ]
    with pytest.raises(DataError, match=r"only when read as corners x1, y1, x2, y2: a file mixing"):
        _score(tmp, "mixed", mixed)


def test_an_empty_predictions_file_is_refused(framed):
    tmp, _ = framed
    with pytest.raises(DataError, match="holds no predictions; nothing was stored"):
        _score(tmp, "empty", [])
    assert not (tmp / "store" / "framed" / "external.empty").exists()
