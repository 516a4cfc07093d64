"""RGBT-Tiny adapter on a tiny copy of the release written in the official layout by the test itself."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from adapters.datasets import rgbt_tiny
from adapters.datasets._eightbit import clip_boxes, read_thermal8
from datasets_helpers import edited_json
from eightbit_fixtures import RGBT_CLASSES, collect, rgbt_json, write_rgbt_tiny
from harness.api import PrepareReport
from harness.cache import PreparedDataset, PreparedWriter
from harness.contracts import validate_sample
from harness.errors import ConfigError, DataError


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("rgbt") / "RGBT-Tiny"
    expected = write_rgbt_tiny(root)
    return root, expected


@pytest.fixture
def copy_release(tmp_path):
    """A fresh release the test may damage."""
    root = tmp_path / "RGBT-Tiny"
    expected = write_rgbt_tiny(root, train_seqs=("DJI_0001_1",), test_seqs=("DJI_0101_1",), frames=2)
    return root, expected


def xywh_to_xyxy(boxes):
    return np.array([[x, y, x + w, y + h] for x, y, w, h, _ in boxes], np.float32).reshape(-1, 4)


# ------------------------------------------------------------------ pairing, classes, annotation source
@pytest.mark.parametrize(
    "gt, key",
    [("thermal", "thermal_boxes"), ("T", "thermal_boxes"), ("visible", "visible_boxes"), ("RGB", "visible_boxes")],
)
def test_frames_pair_by_file_name_and_boxes_follow_the_chosen_source(release, gt, key):
    root, expected = release
    source = rgbt_tiny.open_rgbt_tiny(root, gt=gt)
    samples, report = collect(source)
    assert len(samples) == len(expected["frames"]) == 9 and not report.skipped
    for s in samples:
        validate_sample(s, num_classes=len(RGBT_CLASSES))
        frame = (s.meta["sequence"], s.meta["frame"])
        want = expected[key][frame]
        np.testing.assert_allclose(s.boxes, xywh_to_xyxy(want))
        # labels: the fixture lists categories shuffled, so only a mapping by name gets these right
        assert s.labels.tolist() == [c for *_, c in want]
        # the two JSONs number this frame differently; the pair still refers to the same frame
        ids = s.meta["coco_image_ids"]
        assert ids["00"] != ids["01"] and ids["00"] >= 5000
        assert (
            s.meta["file_name"] == f"{frame[0]}/01/{frame[1]}.jpg"
            and s.meta["rgb_file"] == f"{frame[0]}/00/{frame[1]}.jpg"
        )
        assert s.thermal is None and s.ir8.dtype == np.uint8 and s.ir8.shape == (48, 64) and s.rgb.shape == (48, 64, 3)
        assert s.group == frame[0] and s.meta["gt"] == rgbt_tiny.normalise_gt(gt)
    # the visible-only box on every first frame is class id 0 = ship, a real class (not background)
    if key == "visible_boxes":
        first = [s for s in samples if s.meta["frame"] == "00000"]
        assert all(s.labels[-1] == RGBT_CLASSES.index("ship") == 0 for s in first)


def test_thermal_frame_is_the_ir8_channel_and_visible_is_rgb_order(release):
    root, _ = release
    s = next(iter(rgbt_tiny.open_rgbt_tiny(root).samples(PrepareReport())))
    x1, y1, x2, y2 = s.boxes[0].astype(int)
    inside, outside = s.ir8[y1 + 2 : y2 - 2, x1 + 2 : x2 - 2], s.ir8[s.ir8 < 100]
    assert inside.mean() > 200 and outside.mean() < 70  # hot blob where the thermal box is
    r, g, b = s.rgb[y1 + 3, x1 + 3].astype(int)  # visible box shifted by +1 px; drawn as BGR (30, 200, 220)
    assert r > 180 and b < 80


def test_split_and_groups_come_from_the_dataset_files(release):
    root, _ = release
    t = rgbt_tiny.open_rgbt_tiny(root)
    assert t.groups() == ["DJI_0001_1", "DJI_0002_1", "DJI_0101_1"]
    (fold,) = t.folds()
    assert (
        fold.name == "test-T"
        and fold.train_groups == ("DJI_0001_1", "DJI_0002_1")
        and fold.val_groups == ("DJI_0101_1",)
    )
    assert rgbt_tiny.open_rgbt_tiny(root, gt="visible").folds()[0].name == "test-RGB"


def test_image_ids_are_stable_across_annotation_sources_and_unique(release):
    root, _ = release
    a, _ = collect(rgbt_tiny.open_rgbt_tiny(root, gt="thermal"))
    b, _ = collect(rgbt_tiny.open_rgbt_tiny(root, gt="visible"))
    assert [s.image_id for s in a] == [s.image_id for s in b]
    assert len({s.image_id for s in a}) == len(a)
    assert rgbt_tiny.open_rgbt_tiny(root).fingerprint() != rgbt_tiny.open_rgbt_tiny(root, gt="visible").fingerprint()


def test_samples_prepare_and_give_coco_ground_truth(release, tmp_path):
    root, expected = release
    source = rgbt_tiny.open_rgbt_tiny(root)
    report = PrepareReport()
    with PreparedWriter(tmp_path / "prep", source.name, source.categories, source.fingerprint()) as w:
        for s in source.samples(report):
            w.add(s)
    ds = PreparedDataset(tmp_path / "prep")
    assert not ds.radiometric and len(ds) == 9
    coco = ds.coco()
    assert len(coco["annotations"]) == sum(len(v) for v in expected["thermal_boxes"].values())
    assert {c["name"] for c in coco["categories"]} == set(RGBT_CLASSES)
    assert any("annotation source: thermal (T)" in n for n in report.notes)


# ------------------------------------------------------------------ mismatches between the two modalities
def test_missing_thermal_frame_is_dropped_counted_and_reported(copy_release):
    root, expected = copy_release
    (root / "images" / "DJI_0101_1" / "01" / "00001.jpg").unlink()
    source = rgbt_tiny.open_rgbt_tiny(root)
    samples, report = collect(source)
    assert len(samples) == len(expected["frames"]) - 1
    assert report.summary()["skip_reasons"] == {"missing thermal frame": 1}
    assert report.skipped[0][0].endswith("DJI_0101_1/01/00001.jpg")
    assert any("1 frames dropped (1 missing thermal frame)" in n for n in report.notes)
    with pytest.raises(DataError, match="strict.*missing thermal frame"):
        rgbt_tiny.open_rgbt_tiny(root, strict=True)


def test_mismatched_image_counts_drop_the_unpaired_frames(copy_release, caplog):
    root, expected = copy_release
    path = rgbt_json(root, "00", "test")
    with edited_json(path) as doc:
        gone = doc["images"].pop(0)
        doc["annotations"] = [a for a in doc["annotations"] if a["image_id"] != gone["id"]]
    with caplog.at_level(logging.WARNING):
        source = rgbt_tiny.open_rgbt_tiny(root)
    assert "different numbers of images (1 vs 2)" in caplog.text
    samples, report = collect(source)
    assert len(samples) == len(expected["frames"]) - 1
    assert report.summary()["skip_reasons"] == {"only in thermal annotations": 1}
    note = next(n for n in report.notes if n.startswith("test:"))
    assert "lists 1 images" in note and "lists 2" in note and "1 pairs kept" in note


def test_size_mismatch_between_modalities_is_a_counted_drop(copy_release):
    import cv2

    root, _ = copy_release
    p = root / "images" / "DJI_0001_1" / "00" / "00000.jpg"
    cv2.imwrite(str(p), np.zeros((40, 50, 3), np.uint8))
    samples, report = collect(rgbt_tiny.open_rgbt_tiny(root))
    assert report.summary()["skip_reasons"] == {"size mismatch": 1} and len(samples) == 3


def test_unreadable_image_is_a_counted_drop(copy_release):
    root, _ = copy_release
    (root / "images" / "DJI_0001_1" / "01" / "00001.jpg").write_bytes(b"not a jpeg")
    samples, report = collect(rgbt_tiny.open_rgbt_tiny(root))
    assert report.summary()["skip_reasons"] == {"unreadable image": 1} and len(samples) == 3


# ------------------------------------------------------------------ bad annotation files
def test_malformed_json_names_the_file_and_position(copy_release):
    root, _ = copy_release
    path = rgbt_json(root, "01", "train")
    text = path.read_text()
    cut = text.index('"annotations"')
    path.write_text(text[:cut])  # truncated download
    line = text[:cut].count("\n") + 1
    with pytest.raises(DataError) as err:
        rgbt_tiny.open_rgbt_tiny(root)
    msg = str(err.value)
    assert "instances_01_train2017.json" in msg and f"invalid JSON at line {line} column " in msg


def test_extra_data_after_json_is_reported_like_the_known_release_problem(copy_release):
    root, _ = copy_release
    path = rgbt_json(root, "00", "test")
    path.write_text(path.read_text() + "\n{}")
    with pytest.raises(DataError, match=r"instances_00_test2017.json: invalid JSON at line \d+ column 1: Extra data"):
        rgbt_tiny.open_rgbt_tiny(root)


def test_class_name_not_in_the_list_is_an_error_naming_file_and_class(copy_release):
    root, _ = copy_release
    path = rgbt_json(root, "00", "train")
    with edited_json(path) as doc:
        doc["categories"][2]["name"] = "tractor"
    with pytest.raises(
        DataError, match=r"instances_00_train2017.json: categories\[2\]: class 'tractor' is not an RGBT-Tiny class"
    ):
        rgbt_tiny.open_rgbt_tiny(root)


@pytest.mark.parametrize(
    "damage, match",
    [
        (
            lambda d: d["annotations"][0].update(category_id=17),
            r"annotations\[0\]: category_id 17 is not in 'categories'",
        ),
        (lambda d: d["annotations"][1].update(image_id=-3), r"annotations\[1\]: image_id -3 is not in 'images'"),
        (lambda d: d["annotations"][0].update(bbox=[1, 2, 3]), r"annotations\[0\]: bbox must be four finite numbers"),
        (
            lambda d: d["images"][0].update(file_name="DJI_0001_1/00/00000.jpg"),
            r"images\[0\]: file_name .* folder '00' but this is the thermal",
        ),
        (lambda d: d["images"][1].update(file_name="flat.jpg"), r"images\[1\]: file_name: expected"),
        (lambda d: d.pop("annotations"), r"missing or non-list field 'annotations'"),
    ],
)
def test_inconsistent_annotation_records_name_the_record(copy_release, damage, match):
    root, _ = copy_release
    path = rgbt_json(root, "01", "train")
    doc = json.loads(path.read_text())
    damage(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(DataError, match="instances_01_train2017.json: " + match):
        rgbt_tiny.open_rgbt_tiny(root)


def test_missing_annotation_file_is_named(copy_release):
    root, _ = copy_release
    rgbt_json(root, "01", "test").unlink()
    with pytest.raises(DataError, match="instances_01_test2017.json"):
        rgbt_tiny.open_rgbt_tiny(root)


# ------------------------------------------------------------------ split files, strides, options, root
def test_split_files_are_cross_checked(copy_release):
    root, _ = copy_release
    (root / "data_split" / "test.txt").write_text("DJI_0101_1/00/00000\nDJI_0101_1/00/00001\nDJI_0101_1/00/00007\n")
    source = rgbt_tiny.open_rgbt_tiny(root)
    assert any(n.startswith("test.txt: 1 listed frame(s) have no annotation entry, 0 annotated") for n in source.notes)
    (root / "data_split" / "train.txt").write_text("DJI_0101_1/00/00000\n")
    with pytest.raises(DataError, match="train.txt: lists frames of sequence.*DJI_0101_1.*test split"):
        rgbt_tiny.open_rgbt_tiny(root)


def test_strides_keep_every_kth_frame_per_sequence(release):
    root, _ = release
    source = rgbt_tiny.open_rgbt_tiny(root, train_stride=2)
    frames = [(p.key.sequence, p.key.frame) for p in source.pairs]
    assert (
        ("DJI_0001_1", "00000") in frames
        and ("DJI_0001_1", "00001") not in frames
        and ("DJI_0001_1", "00002") in frames
    )
    assert sum(p.split == "test" for p in source.pairs) == 3 and len(source.pairs) == 7
    assert any("every 2th frame" in n and "not the official protocol" in n for n in source.notes)


def test_options_are_checked(release):
    root, _ = release
    with pytest.raises(ConfigError, match="'gt' must be thermal"):
        rgbt_tiny.open_rgbt_tiny(root, gt="lwir")
    with pytest.raises(ConfigError, match="'train_stride' must be a positive integer"):
        rgbt_tiny.open_rgbt_tiny(root, train_stride=0)


def test_root_from_environment_or_a_clear_error(release, monkeypatch, tmp_path):
    root, _ = release
    monkeypatch.delenv(rgbt_tiny.ROOT_ENV, raising=False)
    with pytest.raises(DataError, match="dataset.root=.*HARNESS_RGBT_TINY"):
        rgbt_tiny.open_rgbt_tiny()
    monkeypatch.setenv(rgbt_tiny.ROOT_ENV, str(root))
    assert rgbt_tiny.open_rgbt_tiny().root == root
    with pytest.raises(DataError, match="missing images, annotations_coco"):
        rgbt_tiny.open_rgbt_tiny(tmp_path)


# ------------------------------------------------------------------ the two ways of unpacking the three archives
def _sample_fields(samples):
    return [
        (s.image_id, s.group, s.rgb.tobytes(), s.ir8.tobytes(), s.boxes.tobytes(), s.labels.tolist(), s.meta)
        for s in samples
    ]


def test_flat_unzip_prepares_the_same_samples_as_the_folder_layout(tmp_path):
    folders, flat = tmp_path / "folders", tmp_path / "flat"
    assert write_rgbt_tiny(folders) == write_rgbt_tiny(flat, flat=True)
    assert not (flat / "images").exists() and (flat / "instances_01_test2017.json").is_file()
    assert (flat / "DJI_0001_1" / "01" / "00000.jpg").is_file() and (flat / "test.txt").is_file()
    a, b = rgbt_tiny.open_rgbt_tiny(folders), rgbt_tiny.open_rgbt_tiny(flat)
    assert (a.layout.kind, b.layout.kind) == ("folders", "flat")
    (sa, ra), (sb, rb) = collect(a), collect(b)
    assert len(sa) == 9 and _sample_fields(sa) == _sample_fields(sb)
    assert a.folds() == b.folds() and not ra.skipped and not rb.skipped
    assert not any("in no annotation file" in n for n in rb.notes)  # the flat root's other entries are not sequences
    # the split lists beside the JSON files are still cross-checked
    (flat / "train.txt").write_text("DJI_0101_1/00/00000\n")
    with pytest.raises(DataError, match="train.txt: lists frames of sequence.*DJI_0101_1"):
        rgbt_tiny.open_rgbt_tiny(flat)


def test_unrecognised_layout_names_the_folders_and_the_unzip_commands(tmp_path):
    root = tmp_path / "rgbt"
    write_rgbt_tiny(root, train_seqs=("DJI_0001_1",), test_seqs=("DJI_0101_1",), frames=1)
    (root / "annotations_coco").rename(root / "labels")
    with pytest.raises(DataError) as err:
        rgbt_tiny.open_rgbt_tiny(root)
    text = str(err.value)
    assert "missing annotations_coco" in text and "found: data_split, images, labels" in text
    for archive in ("images", "annotations_coco", "data_split"):
        assert f"unzip {archive}.zip -d {root / archive}" in text  # each archive into its own folder
        assert text.count(f"unzip {archive}.zip -d {root}") == 2  # ... or all three into the root


def test_registered_with_the_8bit_defaults(host):
    spec = host.dataset("rgbt-tiny")
    assert spec.thermal == "8bit" and spec.default_encoding == "proxy8" and spec.protocol == "rgbt-tiny"
    assert spec.categories == RGBT_CLASSES and spec.root_env == "HARNESS_RGBT_TINY"


# ------------------------------------------------------------------ small helpers
def test_thermal8_reads_grey_exactly_and_flags_colour(tmp_path):
    import cv2

    grey = np.arange(48 * 64, dtype=np.uint16).reshape(48, 64).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "g.png"), cv2.merge([grey, grey, grey]))
    out, colour = read_thermal8(tmp_path / "g.png")
    np.testing.assert_array_equal(out, grey)
    assert not colour
    palette = cv2.applyColorMap(grey, cv2.COLORMAP_JET)
    cv2.imwrite(str(tmp_path / "c.png"), palette)
    out, colour = read_thermal8(tmp_path / "c.png")
    assert colour and out.shape == (48, 64)


def test_clip_boxes_by_hand():
    boxes, keep, changed = clip_boxes(np.array([[-2, 1, 5, 4], [10, 10, 12, 14], [60, 40, 70, 50]]), 64, 48)
    np.testing.assert_array_equal(boxes[0], [0, 1, 5, 4])
    np.testing.assert_array_equal(boxes[2], [60, 40, 64, 48])
    assert keep.tolist() == [True, True, True] and changed == 2
    _, keep, _ = clip_boxes(np.array([[70, 10, 80, 20]]), 64, 48)
    assert keep.tolist() == [False]


# ------------------------------------------------------------------ end to end through the harness
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from eightbit_fixtures import trained_store

    return trained_store(tmp_path_factory)


@pytest.mark.slow
def test_harness_run_ours_on_rgbt_tiny_end_to_end(trained):
    from harness.store import RunKey, Store

    out = trained["run_init"]
    assert "test-T" in out and "trained" in out and "pedestrian" in out  # fold table and per-category table
    run = Store(trained["store"]).run(RunKey("rgbt-tiny", "ours", "proxy8", "test-T", 0))
    assert run.is_finished()
    m = run.read_metrics()
    expected = trained["expected"]
    test_frames = [k for k, split in expected["frames"].items() if split == "test"]
    # held out: exactly the test2017 sequence, scored against the thermal annotations
    assert m["support"]["images"] == len(test_frames) == 3
    assert m["support"]["instances"] == sum(len(expected["thermal_boxes"][k]) for k in test_frames)
    assert m["train"]["images"] == 6
    for key in ("mAP50", "mAP50_95"):
        assert 0.0 <= m["metrics"][key] <= 1.0
        assert 0.0 <= m["metrics"]["safit"][key] <= 1.0  # the protocol evaluates with SAFit beside standard mAP
    gt = json.loads(run.gt_path.read_text())
    assert sorted(i["file_name"] for i in gt["images"]) == [f"{s}/01/{f}.jpg" for s, f in sorted(test_frames)]
    assert isinstance(json.loads(run.predictions_path.read_text()), list)
    # fine-tuned from the M3FD checkpoint: everything but the class outputs (6 -> 7 classes) was loaded
    init = m["train"]["init"]
    assert init["loaded"] > 100 and init["checkpoint_nc"] == 6
    visible = Store(trained["store"]).run(RunKey("rgbt-tiny", "ours", "proxy8", "test-RGB", 0)).read_metrics()
    assert visible["support"]["instances"] == sum(len(expected["visible_boxes"][k]) for k in test_frames)
    assert visible["support"]["image_ids_sha1"] == m["support"]["image_ids_sha1"]


# ------------------------------------------------------------------ through the prepared-sample cache
def test_prepare_records_drops_folds_and_options(copy_release, tmp_path):
    from harness.cache import prepare
    from harness.config import load_config

    root, expected = copy_release
    (root / "images" / "DJI_0101_1" / "01" / "00001.jpg").unlink()
    cfg = load_config(protocol="rgbt-tiny", overrides=[f"dataset.root={root}", "dataset.gt=RGB"])
    ds = prepare("rgbt-tiny", cfg, cache_root=tmp_path / "cache", progress=False)
    assert len(ds) == len(expected["frames"]) - 1 and not ds.radiometric
    report = ds.manifest["report"]
    assert report["skip_reasons"] == {"missing thermal frame": 1}
    assert any("annotation source: visible (RGB)" in n for n in report["notes"])
    assert ds.manifest["folds"] == [{"name": "test-RGB", "train_groups": ["DJI_0001_1"], "val_groups": ["DJI_0101_1"]}]
    bad = load_config(protocol="rgbt-tiny", overrides=[f"dataset.root={root}", "dataset.annotations=T"])
    with pytest.raises(ConfigError, match="does not take option.*'annotations'.*gt, train_stride"):
        prepare("rgbt-tiny", bad, cache_root=tmp_path / "cache", progress=False)
