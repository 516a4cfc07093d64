"""FLIR-aligned adapter on a few pairs written by the tests in each layout its docs name: ICAFusion's (labels in
``labels/<split>/``), YOLOv5's (``<modality>/<split>/images|labels/``) and the authors' release (``align/``)."""

from __future__ import annotations

import numpy as np
import pytest

from adapters.datasets import flir_aligned
from eightbit_fixtures import collect, collect_with_drops
from harness.contracts import validate_sample
from harness.errors import ConfigError, DataError
from public_fixtures import FLIR_FRAMES, write_flir_aligned


@pytest.fixture
def release(tmp_path):
    return tmp_path, write_flir_aligned(tmp_path)


def test_label_path_follows_the_yolo_rule():
    img = flir_aligned.Path("/d/FLIR-align-3class/visible/train/images/FLIR_00002_RGB.jpg")
    assert flir_aligned.label_path(img).as_posix() == "/d/FLIR-align-3class/visible/train/labels/FLIR_00002_RGB.txt"
    root = flir_aligned.Path("/d/FLIR-align-3class")
    for image, label in (
        ("visible/train/FLIR_00002_RGB.jpg", "labels/train/FLIR_00002_RGB.txt"),
        ("infrared/test/FLIR_08863_PreviewData.jpeg", "labels/test/FLIR_08863_PreviewData.txt"),
    ):
        assert flir_aligned.icafusion_label_path(root / image, root) == root / label  # ICAFusion's img2label_paths
    assert flir_aligned.frame_key("FLIR_00002_PreviewData") == flir_aligned.frame_key("FLIR_00002_RGB") == "FLIR_00002"


@pytest.mark.parametrize("side, index", [("visible", 0), ("infrared", 1), ("IR", 1)])
def test_pairs_by_frame_and_converts_normalised_boxes(release, side, index):
    root, expected = release
    samples, report = collect(flir_aligned.open_flir_aligned(root, labels=side))
    assert not report.skipped and len(samples) == 5
    for s in samples:
        validate_sample(s, num_classes=3)
        n = s.meta["frame"].split("_")[1]
        assert n in FLIR_FRAMES[s.group]
        assert s.meta["rgb_file"] == f"visible/{s.group}/images/FLIR_{n}_RGB.jpg"
        assert s.meta["file_name"] == f"infrared/{s.group}/images/FLIR_{n}_PreviewData.jpeg"
        want = expected[n][index]
        np.testing.assert_allclose(s.boxes, [b[:4] for b in want], atol=1e-3)  # 6-decimal normalised labels
        assert s.labels.tolist() == [b[4] for b in want]
    (fold,) = flir_aligned.open_flir_aligned(root).folds()
    assert (fold.name, fold.train_groups, fold.val_groups) == ("test", ("train",), ("test",))


def test_missing_partner_missing_labels_and_bad_lines(release):
    root, _ = release
    base = root / "FLIR-align-3class"
    (base / "infrared" / "test" / "images" / "FLIR_08865_PreviewData.jpeg").unlink()
    (base / "visible" / "train" / "labels" / "FLIR_00003_RGB.txt").unlink()
    (base / "visible" / "train" / "labels" / "FLIR_00005_RGB.txt").write_text("0 0.5 0.5 0.1 0.1\n3 0.5 0.5 0.1 0.1\n")
    samples, report = collect_with_drops(
        flir_aligned.open_flir_aligned, root, 3, {"missing infrared frame": 1, "malformed labels": 1}
    )
    reason = dict(report.skipped)[str(base / "visible" / "train" / "labels" / "FLIR_00005_RGB.txt")]
    assert "FLIR_00005_RGB.txt: line 2: class 3 outside 0..2" in reason
    unlabelled = next(s for s in samples if s.meta["frame"] == "FLIR_00003")
    assert unlabelled.boxes.shape == (0, 4) and any("1 image(s) without a label file" in n for n in report.notes)


def test_one_class_variant_and_option_errors(release, tmp_path, monkeypatch):
    root, expected = release
    with pytest.raises(ConfigError, match="'labels' must be visible or infrared"):
        flir_aligned.open_flir_aligned(root, labels="both")
    with pytest.raises(ConfigError, match="'classes' must list distinct"):
        flir_aligned.open_flir_aligned(root, classes="person,person")
    label = root / "FLIR-align-3class" / "visible" / "train" / "labels" / "FLIR_00002_RGB.txt"
    label.write_text("0 0.5 0.5 0.25 0.25\n")  # 80x64 frame: a 20x16 box centred at (40, 32)
    expected["00002"] = ([(30, 24, 50, 40, 0)], [])
    source = flir_aligned.open_flir_aligned(root, classes=["person"])
    samples, report = collect(source)
    assert source.categories == ("person",)
    persons_only = sorted(f"FLIR_{n}" for n, (vis, _) in expected.items() if all(b[4] == 0 for b in vis))
    assert sorted(s.meta["frame"] for s in samples) == persons_only  # a car or bicycle id is out of range
    assert report.summary()["skip_reasons"] == {"malformed labels": 5 - len(persons_only)}
    one = next(s for s in samples if s.meta["frame"] == "FLIR_00002")
    np.testing.assert_allclose(one.boxes, [[30, 24, 50, 40]])
    assert one.labels.tolist() == [0]
    monkeypatch.delenv(flir_aligned.ROOT_ENV, raising=False)
    with pytest.raises(DataError, match="missing visible, infrared"):
        flir_aligned.open_flir_aligned(tmp_path / "FLIR-align-3class" / "visible")


@pytest.mark.parametrize("side, index", [("visible", 0), ("infrared", 1)])
def test_icafusion_layout_reads_the_labels_where_icafusion_finds_them(tmp_path, side, index):
    expected = write_flir_aligned(tmp_path, layout="icafusion")
    base = tmp_path / "FLIR-align-3class"
    assert (base / "labels" / "train" / "FLIR_00002_RGB.txt").is_file()
    assert not (base / "visible" / "train" / "labels").exists()
    source = flir_aligned.open_flir_aligned(tmp_path, labels=side)
    samples, report = collect(source)
    assert source.layout == "icafusion" and not report.skipped and len(samples) == 5
    assert any("0 image(s) without a label file" in n for n in report.notes)
    for s in samples:
        n = s.meta["frame"].split("_")[1]
        assert s.meta["rgb_file"] == f"visible/{s.group}/FLIR_{n}_RGB.jpg"
        np.testing.assert_allclose(s.boxes, [b[:4] for b in expected[n][index]], atol=1e-3)
        assert s.labels.tolist() == [b[4] for b in expected[n][index]]


def test_a_tree_with_both_kinds_of_label_folder_must_name_its_layout(tmp_path):
    write_flir_aligned(tmp_path)
    (tmp_path / "FLIR-align-3class" / "labels" / "train").mkdir(parents=True)
    with pytest.raises(ConfigError, match="set dataset.layout=icafusion or dataset.layout=yolov5"):
        flir_aligned.open_flir_aligned(tmp_path)
    assert flir_aligned.open_flir_aligned(tmp_path, layout="yolov5").layout == "yolov5"
    with pytest.raises(ConfigError, match="option 'layout'"):
        flir_aligned.open_flir_aligned(tmp_path, layout="voc")


def test_registered_and_prepares_with_its_protocol(host, release, tmp_path):
    from harness.cache import prepare
    from harness.config import load_config

    spec = host.dataset("flir-aligned")
    assert spec.categories == ("person", "car", "bicycle") and spec.protocol == "flir-aligned"
    root, _ = release
    cfg = load_config(protocol="flir-aligned", overrides=[f"dataset.root={root}"])
    ds = prepare("flir-aligned", cfg, cache_root=tmp_path / "cache", progress=False)
    assert len(ds) == 5 and ds.manifest["instances"] == 15 and sorted(set(ds.groups)) == ["test", "train"]


# ------------------------------------------------------------------ the authors' release layout (align/, VOC)
def test_release_layout_gives_the_thermal_boxes_of_the_yolo_layout(tmp_path):
    from public_fixtures import write_flir_release

    write_flir_release(tmp_path / "release")
    write_flir_aligned(tmp_path / "yolo")
    release = flir_aligned.open_flir_aligned(tmp_path / "release")
    assert release.layout == "release" and release.labels == "infrared" and release.root.name == "align"
    (a, ra), (b, _) = collect(release), collect(flir_aligned.open_flir_aligned(tmp_path / "yolo", labels="infrared"))
    assert not ra.skipped and len(a) == len(b) == 5
    for s, t in zip(a, b):
        assert (s.group, s.meta["frame"]) == (t.group, t.meta["frame"]) and s.labels.tolist() == t.labels.tolist()
        np.testing.assert_allclose(s.boxes, t.boxes, atol=1e-3)
        np.testing.assert_array_equal(s.ir8, t.ir8)
    assert any("(xmin - 1, ymin - 1, xmax, ymax)" in n for n in ra.notes)
    assert [f.name for f in release.folds()] == ["test"]
    with pytest.raises(ConfigError, match="set dataset.labels=infrared"):
        flir_aligned.open_flir_aligned(tmp_path / "release", labels="visible")


def test_release_layout_missing_list_or_frame_and_unknown_class(tmp_path):
    from eightbit_fixtures import write_voc
    from public_fixtures import write_flir_release

    write_flir_release(tmp_path)
    base = tmp_path / "align"
    (base / "JPEGImages" / "FLIR_00003_RGB.jpg").unlink()
    write_voc(base / "Annotations" / "FLIR_08863_PreviewData.xml", "x.jpeg", 80, 64, [("dog", 1, 1, 9, 9)])
    samples, report = collect(flir_aligned.open_flir_aligned(tmp_path))
    assert len(samples) == 3
    assert report.summary()["skip_reasons"] == {"missing visible frame": 1, "unknown class": 1}
    (base / "align_validation.txt").rename(base / "val.txt")
    with pytest.raises(DataError, match="split list align_validation.txt not found"):
        flir_aligned.open_flir_aligned(tmp_path)


def test_labels_where_the_adapter_does_not_find_them_stop_the_preparation(tmp_path):
    """ICAFusion's tree without its labels/ folder reads as 'no objects': the guard stops instead of training on
    nothing, and names the images; with the folder the same tree prepares every box."""
    import shutil

    from harness.cache import prepare
    from harness.config import load_config

    write_flir_aligned(tmp_path, layout="icafusion")
    labels = tmp_path / "FLIR-align-3class" / "labels"
    shutil.move(str(labels), str(tmp_path / "elsewhere"))
    cfg = load_config(protocol="flir-aligned", overrides=[f"dataset.root={tmp_path}"])
    with pytest.raises(DataError, match=r"no-labels: the dataset: 5 image\(s\) and not one box"):
        prepare("flir-aligned", cfg, cache_root=tmp_path / "cache", progress=False)
    shutil.move(str(tmp_path / "elsewhere"), str(labels))
    ds = prepare("flir-aligned", cfg, cache_root=tmp_path / "cache", progress=False)
    assert ds.manifest["instances"] == 15 and ds.input_risks == []
