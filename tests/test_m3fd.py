"""M3FD adapter on a few pairs written by the test in the release layout (M3FD_Detection/{Annotation,Ir,Vis})."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adapters.datasets import m3fd
from eightbit_fixtures import check_layout_errors, collect, collect_with_drops, write_m3fd, write_voc
from harness.contracts import validate_sample
from harness.errors import ConfigError, DataError

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def release(tmp_path):
    expected = write_m3fd(tmp_path)
    return tmp_path, expected


def test_pairs_per_image_sizes_and_classes_by_name(release):
    root, expected = release
    samples, report = collect(m3fd.open_m3fd(root))
    assert [s.image_id for s in samples] == [n + 1 for n in sorted(expected)] and not report.skipped
    for s in samples:
        validate_sample(s, num_classes=6)
        n = s.image_id - 1
        want = expected[n]
        np.testing.assert_allclose(s.boxes, np.array([b[:4] for b in want], np.float32))
        assert s.labels.tolist() == [c for *_, c in want]  # "car " and "People" alike map by name
        assert s.thermal is None and s.ir8.dtype == np.uint8
        assert s.meta["file_name"] == f"Ir/{n:05d}.png" and s.meta["annotation"] == f"Annotation/{n:05d}.xml"
    sizes = {s.image_id - 1: s.ir8.shape for s in samples}
    assert sizes[120] == (40, 72) and sizes[0] == (48, 64)


def test_root_may_be_the_release_folder_or_its_parent(release):
    root, _ = release
    assert m3fd.open_m3fd(root).root == m3fd.open_m3fd(root / "M3FD_Detection").root == root / "M3FD_Detection"


def test_recorded_split_by_frame_blocks_matches_the_protocol_file(release):
    root, _ = release
    source = m3fd.open_m3fd(root)
    assert source.groups() == ["00000-00099", "00100-00199", "00400-00499", "00900-00999"]
    (fold,) = source.folds()
    assert fold.name == "val" and fold.val_groups == ("00400-00499", "00900-00999")
    split = m3fd.recorded_split()
    assert len(split["val"]) == 8 and len(split["train"]) == 34  # 800 / 3,400 of 4,200
    assert split["val"] == [
        "00400-00499",
        "00900-00999",
        "01400-01499",
        "01900-01999",
        "02400-02499",
        "02900-02999",
        "03400-03499",
        "03900-03999",
    ]
    # the split is recorded, block by block, where users look for it
    for doc in (REPO / "docs" / "datasets.md", REPO / "configs" / "protocols" / "m3fd.yaml"):
        text = doc.read_text()
        assert all(block in text for block in split["val"]), doc
    samples, _ = collect(source)
    assert [s.meta["split"] for s in samples] == ["train"] * 5 + ["val"] * 3


def test_class_name_not_in_the_list_skips_the_pair_with_a_counted_reason(release):
    root, _ = release
    ann = root / "M3FD_Detection" / "Annotation" / "00002.xml"
    write_voc(ann, "00002.png", 64, 48, [("Car", 1, 1, 10, 10), ("Dog", 5, 5, 20, 20)])
    samples, report = collect(m3fd.open_m3fd(root))
    assert len(samples) == 7 and 3 not in {s.image_id for s in samples}
    assert report.summary()["skip_reasons"] == {"unknown class": 1}
    path, reason = report.skipped[0]
    assert path.endswith("00002.xml") and "'Dog' is not one of people, car" in reason
    with pytest.raises(DataError, match="00002.xml: unknown class"):
        collect(m3fd.open_m3fd(root, strict=True))


def test_missing_infrared_image_is_a_counted_drop(release):
    root, _ = release
    (root / "M3FD_Detection" / "Ir" / "00003.png").unlink()
    (root / "M3FD_Detection" / "Annotation" / "00401.xml").unlink()
    collect_with_drops(m3fd.open_m3fd, root, 6, {"missing thermal frame": 1, "no annotation": 1})


def test_malformed_xml_names_file_and_position(release):
    root, _ = release
    ann = root / "M3FD_Detection" / "Annotation" / "00001.xml"
    ann.write_text("<annotation>\n  <size><width>64</width>\n</annotation>\n")
    samples, report = collect(m3fd.open_m3fd(root))
    assert len(samples) == 7
    ((path, reason),) = report.skipped
    assert reason.startswith("malformed annotation") and "00001.xml: malformed XML at line 3 column" in reason


def test_non_numeric_coordinates_and_size_mismatch(release):
    root, _ = release
    base = root / "M3FD_Detection" / "Annotation"
    write_voc(base / "00000.xml", "00000.png", 64, 48, [("Car", "a", 1, 10, 10)])
    write_voc(base / "00001.xml", "00001.png", 1024, 768, [("Car", 1, 1, 10, 10)])
    samples, report = collect(m3fd.open_m3fd(root))
    assert len(samples) == 6
    reasons = dict((p.rsplit("/", 1)[-1], r) for p, r in report.skipped)
    assert "<xmin> must be a number" in reasons["00000.xml"]
    assert reasons["00001.xml"] == "size mismatch: <size> says 1024x768, images are 64x48"


def test_boxes_outside_the_frame_are_clipped_or_dropped(release):
    root, _ = release
    ann = root / "M3FD_Detection" / "Annotation" / "00000.xml"
    write_voc(ann, "00000.png", 64, 48, [("Truck", -4, 2, 20, 60), ("Lamp", 70, 10, 80, 20)])
    samples, report = collect(m3fd.open_m3fd(root))
    s = samples[0]
    np.testing.assert_array_equal(s.boxes, [[0, 1, 20, 48]])  # (xmin - 1, ymin - 1, xmax, ymax), then clipped
    assert s.labels.tolist() == [m3fd.CATEGORIES.index("truck")]
    assert any("1 clipped to the frame, 1 dropped" in n for n in report.notes)


def test_errors_for_layout_and_options(tmp_path, monkeypatch):
    check_layout_errors(m3fd.open_m3fd, "HARNESS_M3FD", tmp_path, "Ir", "Annotation, Vis", monkeypatch)


def test_registered_for_pretraining_with_ir8(host):
    spec = host.dataset("m3fd")
    assert spec.thermal == "8bit" and spec.default_encoding == "ir8" and spec.protocol == "m3fd"
    assert spec.categories == ("people", "car", "bus", "motorcycle", "lamp", "truck")


# ------------------------------------------------------------------ pretraining
@pytest.mark.slow
def test_pretrain_writes_a_checkpoint_that_run_init_loads(tmp_path_factory):
    import json

    from eightbit_fixtures import trained_store

    trained = trained_store(tmp_path_factory)
    ckpt = trained["checkpoint"]
    assert ckpt.is_file() and ckpt.parts[-7:-2] == ("m3fd", "ours", "ir8", "val", "seed0")
    record = json.loads((ckpt.parent.parent / "pretrain.json").read_text())
    assert record["encoding"] == "ir8" and record["categories"] == list(m3fd.CATEGORIES)
    assert (record["train_images"], record["val_images"]) == (5, 3)  # the recorded block split of the fixture
    assert "8-bit thermal intensity" in record["extra_channel"] and "c2" in record["fine_tuning"]
    assert f"--init {ckpt}" in trained["pretrain_output"]
    # `harness run --init` on another dataset loaded it (see the RGBT-Tiny end-to-end test for the details)
    from harness.store import RunKey, Store

    init = (
        Store(trained["store"]).run(RunKey("rgbt-tiny", "ours", "proxy8", "test-T", 0)).read_metrics()["train"]["init"]
    )
    assert init["path"] == str(ckpt) and init["loaded"] > 0


def test_prepared_manifest_records_the_split(release, tmp_path):
    from harness.cache import prepare, resolve_folds
    from harness.config import load_config

    root, _ = release
    cfg = load_config(protocol="m3fd", overrides=[f"dataset.root={root}"])
    ds = prepare("m3fd", cfg, cache_root=tmp_path / "cache", progress=False)
    (fold,) = ds.manifest["folds"]
    assert fold == {
        "name": "val",
        "train_groups": ["00000-00099", "00100-00199"],
        "val_groups": ["00400-00499", "00900-00999"],
    }
    (resolved,) = resolve_folds("m3fd", ds, cfg)
    assert resolved.name == "val" and len(ds.indices(resolved.val_groups)) == 3


# ------------------------------------------------------------------ the VOC pixel convention and the nine sizes
#: The nine image sizes of the 4,200 M3FD pairs (width, height) and how many pairs have each.
M3FD_SIZES = {
    (1024, 768): 3926,
    (880, 520): 49,
    (740, 400): 43,
    (780, 420): 41,
    (800, 480): 36,
    (480, 360): 34,
    (440, 320): 32,
    (400, 280): 23,
    (440, 280): 16,
}


def test_size_table_adds_up_to_the_release_and_is_documented():
    assert sum(M3FD_SIZES.values()) == 4200
    doc = (REPO / "docs" / "datasets.md").read_text()
    for (w, h), n in M3FD_SIZES.items():
        assert f"{w}x{h}" in doc and f"{n:,}" in doc, (w, h)


def _one_pair(root: Path, w: int, h: int, objects) -> Path:
    import cv2

    base = root / "M3FD_Detection"
    for d in ("Annotation", "Ir", "Vis"):
        (base / d).mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(base / "Vis" / "00007.png"), np.full((h, w, 3), 90, np.uint8))
    cv2.imwrite(str(base / "Ir" / "00007.png"), np.full((h, w), 40, np.uint8))
    write_voc(base / "Annotation" / "00007.xml", "00007.png", w, h, objects)
    return root


@pytest.mark.parametrize("size", list(M3FD_SIZES), ids=[f"{w}x{h}" for w, h in M3FD_SIZES])
def test_every_release_size_prepares_with_labelimg_edges(tmp_path, size):
    """A labelImg box from pixel 1 to the last column/row covers the frame exactly: [0, y, W, y2]."""
    w, h = size
    root = _one_pair(tmp_path, w, h, [("Car", 1, 5, w, 20), ("People", 3, 1, 9, h), ("Lamp", 1, 1, w, h)])
    (s,), report = collect(m3fd.open_m3fd(root))
    validate_sample(s, num_classes=6)
    assert (s.width, s.height) == (w, h) and not report.skipped
    np.testing.assert_array_equal(s.boxes, [[0, 4, w, 20], [2, 0, 9, h], [0, 0, w, h]])
    assert any("1-based inclusive" in n and "(xmin - 1, ymin - 1, xmax, ymax)" in n for n in report.notes)


def test_fixture_boxes_follow_the_voc_rule_exactly(release):
    """Every prepared box equals (xmin - 1, ymin - 1, xmax, ymax) of the XML on disk, with no clipping needed."""
    import xml.etree.ElementTree as ET

    root, _ = release
    samples, _ = collect(m3fd.open_m3fd(root))
    checked = 0
    for s in samples:
        xml = ET.parse(root / "M3FD_Detection" / s.meta["annotation"]).getroot()
        want = [
            [float(o.findtext(f"bndbox/{t}")) - d for t, d in (("xmin", 1), ("ymin", 1), ("xmax", 0), ("ymax", 0))]
            for o in xml.findall("object")
        ]
        assert s.boxes.tolist() == want
        checked += len(want)
    assert checked == 16


def test_zero_based_option_reads_corners_as_written(tmp_path):
    root = _one_pair(tmp_path, 64, 48, [("Car", 0, 5, 64, 20)])
    (s,), report = collect(m3fd.open_m3fd(root, voc_convention="zero-based"))
    np.testing.assert_array_equal(s.boxes, [[0, 5, 64, 20]])
    assert any("0-based corners, as written" in n for n in report.notes)
    with pytest.raises(ConfigError, match="voc_convention"):
        m3fd.open_m3fd(root, voc_convention="two-based")


def test_float_coordinates_and_difficult_boxes(tmp_path):
    root = _one_pair(tmp_path, 64, 48, [("Car", 10.5, 5, 30.25, 20), ("Bus", 2, 2, 12, 12, 1)])
    (s,), report = collect(m3fd.open_m3fd(root))
    np.testing.assert_allclose(s.boxes, [[9.5, 4, 30.25, 20]])  # the difficult bus is out of targets and GT
    assert s.labels.tolist() == [m3fd.CATEGORIES.index("car")]
    note = next(n for n in report.notes if "VOC boxes" in n)
    assert "2 boxes read, 1 with fractional coordinates; 1 difficult box(es) left out" in note
    (kept,), _ = collect(m3fd.open_m3fd(root, difficult="keep"))
    np.testing.assert_allclose(kept.boxes, [[9.5, 4, 30.25, 20], [1, 1, 12, 12]])
    assert m3fd.open_m3fd(root).fingerprint() != m3fd.open_m3fd(root, difficult="keep").fingerprint()
    with pytest.raises(ConfigError, match="'difficult' must be drop"):
        m3fd.open_m3fd(root, difficult="ignore")
