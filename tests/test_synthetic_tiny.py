"""The RGBT-Tiny-like generator: deterministic, read by the real release's adapter, tiny targets in every SAFit bin,
two annotation sources that differ as the release's do, and an extended thermal signature."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from adapters.datasets import rgbt_tiny
from adapters.datasets.synthetic_tiny import CATEGORIES, SIZE_BINS, coco_documents, generate, plan_dataset
from harness.api import PrepareReport


def _digests(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("rgbt-tiny-synth") / "tiny"
    generate(root, "tiny", seed=0, progress=False, workers=1)
    return root


def _bin(area: float) -> str:
    return next(b for b, (lo, hi) in SIZE_BINS.items() if lo <= math.sqrt(area) < hi)


def test_same_seed_same_bytes_whatever_the_workers_and_another_seed_differs(tiny, tmp_path):
    again = generate(tmp_path / "again", "tiny", seed=0, progress=False, workers=2).root
    other = generate(tmp_path / "other", "tiny", seed=1, progress=False, workers=1).root
    first = _digests(tiny)
    assert first == _digests(again)
    assert any(f.endswith(".jpg") for f in first)
    differ = {k for k, v in _digests(other).items() if first.get(k) != v}
    assert any(k.endswith(".jpg") for k in differ) and any(k.endswith(".json") for k in differ)


def test_release_layout_readme_and_generator_record(tiny):
    for m in ("00", "01"):
        for s in ("train", "test"):
            assert (tiny / "annotations_coco" / f"instances_{m}_{s}2017.json").is_file()
            assert (tiny / "data_split" / f"{m}_{s}.txt").read_text().splitlines()[0].count("/") == 2
    info = json.loads((tiny / "synth.json").read_text())
    assert (info["generator"], info["profile"], info["seed"]) == ("rgbt-tiny-synth", "tiny", 0)
    assert isinstance(info["generator_version"], int)
    assert "--dataset rgbt-tiny" in (tiny / "README.md").read_text()
    assert not list(tiny.parent.glob(".tiny.*"))  # the temporary folder was renamed into place


@pytest.mark.parametrize("gt", ["thermal", "visible"])
def test_the_rgbt_tiny_adapter_reads_both_annotation_sources_unchanged(tiny, gt):
    source = rgbt_tiny.open_rgbt_tiny(tiny, gt=gt)
    assert not source.dropped and len(source) == 20
    (fold,) = source.folds()
    assert (
        fold.name == f"test-{rgbt_tiny.SOURCE_LABEL[gt]}" and len(fold.train_groups) == 3 and len(fold.val_groups) == 2
    )
    docs = coco_documents(plan_dataset("tiny", 0))
    mdir = rgbt_tiny.MODALITY_DIR[gt]
    want = sum(len(docs[mdir, s]["annotations"]) for s in ("train", "test"))
    samples = list(source.samples(PrepareReport()))
    assert sum(len(s.boxes) for s in samples) == want > 0
    s = samples[0]
    assert s.ir8.shape == (256, 320) and s.rgb.shape == (256, 320, 3) and s.thermal is None


def test_the_two_sources_differ_by_a_registration_offset_and_by_objects_seen_in_one_modality():
    docs = coco_documents(plan_dataset("small", 0))
    boxes = {}
    for m in ("00", "01"):
        names = {}
        boxes[m] = {}
        for s in ("train", "test"):
            names.update({im["id"]: im["file_name"].replace(f"/{m}/", "/") for im in docs[m, s]["images"]})
            for a in docs[m, s]["annotations"]:
                boxes[m][names[a["image_id"]], a["track_id"]] = a["bbox"]
    both = sorted(set(boxes["00"]) & set(boxes["01"]))
    thermal_only, visible_only = set(boxes["01"]) - set(boxes["00"]), set(boxes["00"]) - set(boxes["01"])
    assert len(thermal_only) > 0.05 * len(boxes["01"]) and len(visible_only) > 0.02 * len(boxes["00"])
    dy = np.array([boxes["00"][k][1] + boxes["00"][k][3] / 2 - boxes["01"][k][1] - boxes["01"][k][3] / 2 for k in both])
    dx = np.array([boxes["00"][k][0] + boxes["00"][k][2] / 2 - boxes["01"][k][0] - boxes["01"][k][2] / 2 for k in both])
    shift = np.hypot(dx, dy)
    assert 1.0 < np.median(shift) < 6.0 and shift.max() > 8.0  # a few px, some (airborne) above 8
    assert np.median(dy) > 1.0 > abs(np.median(dx))  # the lenses sit one above the other


@pytest.mark.parametrize("profile", ["small", "small-320", "full"])
def test_targets_are_mostly_tiny_and_every_safit_bin_is_populated_in_each_split_and_source(profile):
    docs = coco_documents(plan_dataset(profile, 0))
    for (m, s), doc in docs.items():
        areas = [a["bbox"][2] * a["bbox"][3] for a in doc["annotations"]]
        assert sum(a < 16 * 16 for a in areas) / len(areas) > 0.75, (m, s)
        bins = {_bin(a) for a in areas}
        assert bins == set(SIZE_BINS), (m, s, bins)
        assert {a["category_id"] for a in doc["annotations"]} <= set(range(len(CATEGORIES)))
    train = {im["file_name"].split("/")[0] for im in docs["01", "train"]["images"]}
    test = {im["file_name"].split("/")[0] for im in docs["01", "test"]["images"]}
    assert train and test and not train & test  # split by sequence


def test_small_320_is_small_on_a_quarter_of_the_frame_with_targets_of_the_same_sizes():
    small, quarter = plan_dataset("small", 0), plan_dataset("small-320", 0)
    assert quarter.profile.size == (320, 256) and quarter.profile.total == small.profile.total == 240
    assert quarter.profile.sequences == small.profile.sequences

    def share_under_16(plan):
        docs = coco_documents(plan)
        areas = [a["bbox"][2] * a["bbox"][3] for d in docs.values() for a in d["annotations"]]
        return sum(a < 16 * 16 for a in areas) / len(areas)

    assert abs(share_under_16(quarter) - share_under_16(small)) < 0.02  # the same sizes in px, not halved


def test_targets_move_smoothly_through_their_sequence():
    plan = plan_dataset("small", 0)
    for seq in plan.sequences:
        for tr in seq.tracks:
            step = np.diff(tr.centres, axis=0)
            assert np.abs(np.diff(step, axis=0)).max() < 0.2  # no jumps: speed and heading change slowly


def test_the_thermal_signature_is_a_soft_blob_wider_than_the_box():
    from adapters.datasets.synthetic_tiny.rendering import add_signature

    track = plan_dataset("small", 0).sequences[0].tracks[0]
    track.warmth = 5.0
    img = np.zeros((64, 64), np.float32)
    box = (28.0, 29.0, 36.0, 35.0)  # 8x6 px
    add_signature(img, track, box)
    inside = img[29:35, 28:36].sum()
    assert img.sum() - inside > 0.3 * img.sum()  # much of the warmth lies outside the box
    row = img[32, 20:44]
    assert np.all(np.abs(np.diff(row)) < 0.5 * row.max())  # no sharp edge at the box border


def test_cli_generates_and_harness_prepare_reads_it(cli_runner, tmp_path):
    out = tmp_path / "set"
    res = cli_runner(["synth", "--family", "rgbt-tiny", "--size", "tiny", "--out", str(out), "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "rgbt-tiny-synth tiny (seed 0): 20 pairs" in res.stdout
    res = cli_runner(
        ["prepare", "--dataset", "rgbt-tiny", "--root", str(out), "--cache", str(tmp_path / "c"), "--no-progress"]
    )
    assert res.exit_code == 0, res.output
    bad = cli_runner(
        ["synth", "--family", "rgbt-tiny", "--thermal-format", "centikelvin", "--out", str(tmp_path / "x")]
    )
    assert bad.exit_code == 2 and "--thermal-format is for --family m3t" in bad.output
