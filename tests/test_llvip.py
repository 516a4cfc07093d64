"""LLVIP adapter on a few pairs written by the test in the release layout (LLVIP/{Annotations,infrared,visible})."""

from __future__ import annotations

import numpy as np
import pytest

from adapters.datasets import llvip
from eightbit_fixtures import check_layout_errors, collect, collect_with_drops, write_voc
from harness.contracts import validate_sample
from public_fixtures import LLVIP_FRAMES, write_llvip


@pytest.fixture
def release(tmp_path):
    return tmp_path, write_llvip(tmp_path)


def test_pairs_by_name_per_split_with_the_voc_rule(release):
    root, expected = release
    samples, report = collect(llvip.open_llvip(root))
    assert not report.skipped and len(samples) == 5
    for s in samples:
        validate_sample(s, num_classes=1)
        stem = s.meta["file_name"].rsplit("/", 1)[1][:-4]
        assert (
            s.meta["file_name"] == f"infrared/{s.group}/{stem}.jpg"
            and s.meta["rgb_file"] == f"visible/{s.group}/{stem}.jpg"
        )
        assert stem in LLVIP_FRAMES[s.group] and s.meta["split"] == s.group
        # the XML holds (x + 1, y + 1, x + bw, y + bh): prepared boxes are the drawn pixels' corners exactly
        assert s.boxes.tolist() == [list(map(float, b)) for b in expected[stem]] and s.labels.tolist() == [0, 0]
        assert s.thermal is None and s.ir8.shape == (64, 80)
    assert [s.image_id for s in samples] == [1, 2, 3, 4, 5]
    assert any("1-based inclusive" in n for n in report.notes) and "3 train / 2 test pairs, 0 dropped" in report.notes


def test_official_split_is_the_one_fold(release):
    root, _ = release
    source = llvip.open_llvip(root)
    assert source.groups() == ["train", "test"]
    (fold,) = source.folds()
    assert (fold.name, fold.train_groups, fold.val_groups) == ("test", ("train",), ("test",))
    assert llvip.open_llvip(root / "LLVIP").root == source.root == root / "LLVIP"


def test_missing_partner_and_unknown_class_are_counted(release):
    root, _ = release
    base = root / "LLVIP"
    (base / "visible" / "test" / "190002.jpg").unlink()
    write_voc(base / "Annotations" / "010002.xml", "010002.jpg", 80, 64, [("person", 1, 1, 9, 9), ("dog", 2, 2, 8, 8)])
    collect_with_drops(llvip.open_llvip, root, 3, {"missing visible frame": 1, "unknown class": 1}, "strict.*190002")


def test_difficult_person_and_zero_based_option(release):
    root, _ = release
    ann = root / "LLVIP" / "Annotations" / "010001.xml"
    write_voc(ann, "010001.jpg", 80, 64, [("person", 1, 1, 80, 64), ("person", 5, 5, 20, 30, 1)])
    (s, *_), report = collect(llvip.open_llvip(root))
    np.testing.assert_array_equal(s.boxes, [[0, 0, 80, 64]])
    assert any("1 difficult box(es) left out" in n for n in report.notes)
    (s, *_), _ = collect(llvip.open_llvip(root, voc_convention="zero-based", difficult="keep"))
    np.testing.assert_array_equal(s.boxes, [[1, 1, 80, 64], [5, 5, 20, 30]])


def test_layout_errors(tmp_path, monkeypatch):
    check_layout_errors(llvip.open_llvip, "HARNESS_LLVIP", tmp_path, "infrared", "Annotations, visible", monkeypatch)


def test_registered_and_prepares_with_its_protocol(host, release, tmp_path):
    from harness.cache import prepare, resolve_folds
    from harness.config import load_config

    spec = host.dataset("llvip")
    assert spec.categories == ("person",) and spec.thermal == "8bit" and spec.protocol == "llvip"
    root, _ = release
    cfg = load_config(protocol="llvip", overrides=[f"dataset.root={root}"])
    ds = prepare("llvip", cfg, cache_root=tmp_path / "cache", progress=False)
    (fold,) = resolve_folds("llvip", ds, cfg)
    assert len(ds) == 5 and len(ds.indices(fold.val_groups)) == 2 and ds.manifest["instances"] == 10
