"""The dataset guards beside the label checks: categories in another order than the spec's, temperatures outside the
plausible range, a plugin's fold left without samples, and a plugin whose sample order changes between calls. Each
stops with what it saw and names the option that accepts it."""

from __future__ import annotations

import numpy as np
import pytest

from harness.api import AlignedSample, DatasetSpec, Fold
from harness.errors import ConfigError, DataError

H, W = 24, 32


def _sample(i: int, group: str, label: int = 0, thermal: np.ndarray | None = None) -> AlignedSample:
    return AlignedSample(
        i,
        np.zeros((H, W, 3), np.uint8),
        np.full((H, W), 20.0 + i, np.float32) if thermal is None else thermal,
        np.full((H, W), 40 + i, np.uint8),
        np.array([[2, 2, 10, 10]], np.float32),
        np.array([label], np.int64),
        group,
        meta={"file_name": f"{group}/frame_{i:03d}.png"},
    )


class _Source:
    def __init__(self, samples, categories=None, groups=("a", "b"), folds=None):
        self._samples, self._groups, self._folds = samples, list(groups), folds
        if categories is not None:
            self.categories = categories

    def groups(self):
        return self._groups

    def folds(self):
        return self._folds if self._folds is not None else [Fold("b", ("a",), ("b",))]

    def fingerprint(self):
        return "guards-test-1"

    def samples(self, report):
        yield from self._samples


def _spec(samples, categories=("thing", "other"), **source) -> DatasetSpec:
    return DatasetSpec(
        "guards-test", lambda root=None, **kw: _Source(samples, **source), categories, thermal="radiometric"
    )


def _prepare(spec, tmp_path, *overrides, **kw):
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default", overrides=list(overrides))
    return prepare(spec, cfg, cache_root=tmp_path / "cache", progress=False, **kw)


def _pairs(n=6):
    return [_sample(i, "a" if i <= n // 2 else "b", label=i % 2) for i in range(1, n + 1)]


# ------------------------------------------------------------------------------------------- category order
def test_categories_swapped_between_spec_and_source_stop_naming_both_orders(tmp_path):
    spec = DatasetSpec(
        "guards-test",
        lambda root=None, **kw: _Source(_pairs(), categories=("other", "thing")),
        ("thing", "other"),
    )
    with pytest.raises(DataError) as err:
        _prepare(spec, tmp_path)
    text = " ".join(str(err.value).split())
    assert (
        "category-order: the dataset's spec lists its categories as thing, other but the opened source as "
        "other, thing" in text
    )
    assert "e.g. label 0: 'other' (the spec's label 1, 'thing')" in text
    assert "--set 'inputs.accept=[category-order]'" in text
    ds = _prepare(spec, tmp_path, "inputs.accept=[category-order]")
    assert ds.categories == ["other", "thing"] and [r["kind"] for r in ds.input_risks] == ["category-order"]


def test_a_source_naming_other_categories_than_the_spec_is_no_finding(tmp_path):
    spec = DatasetSpec(
        "guards-test", lambda root=None, **kw: _Source(_pairs(), categories=("thing", "x")), ("thing", "other")
    )
    assert _prepare(spec, tmp_path).input_risks == []


# ------------------------------------------------------------------------------------------- temperatures
def test_eight_bit_counts_read_as_centi_kelvin_stop_with_the_range_seen(tmp_path):
    counts = np.arange(H * W, dtype=np.float64).reshape(H, W) % 256
    cold = (counts * 0.01 - 273.15).astype(np.float32)  # -273.15 .. -270.6 C
    samples = [_sample(i, "a" if i <= 3 else "b", thermal=cold.copy()) for i in range(1, 7)]
    with pytest.raises(DataError) as err:
        _prepare(_spec(samples), tmp_path)
    text = " ".join(str(err.value).split())
    assert "temperature-range: 6 of 6 sample(s) hold temperatures mostly outside the plausible -100..800 C" in text
    assert "e.g. a/frame_001.png: 768 of 768 values outside, -273.15..-270.6 C" in text
    assert "--set 'inputs.accept=[temperature-range]'" in text
    ds = _prepare(_spec(samples), tmp_path, "inputs.accept=[temperature-range]")
    assert [r["kind"] for r in ds.input_risks] == ["temperature-range"]


def test_a_few_implausible_pixels_become_missing_and_are_counted(tmp_path):
    samples = _pairs()
    hot = samples[0].thermal.copy()
    hot[0, :3] = [-273.5, 1e30, 5000.0]
    samples[0] = _sample(1, "a", label=1, thermal=hot)
    ds = _prepare(_spec(samples), tmp_path)
    assert ds.input_risks == []
    t = ds[0].thermal
    assert np.isnan(t[0, :3]).all() and np.isfinite(t[0, 3:]).all() and t[1, 1] == pytest.approx(21.0)
    rep = ds.manifest["report"]
    assert rep["implausible_temperatures"]["pixels"] == 3 and rep["missing_temperatures"]["pixels"] == 3


# ------------------------------------------------------------------------------------------- folds
def test_a_fold_whose_groups_have_no_samples_stops_at_prepare_and_is_named_when_asked_for(tmp_path):
    folds = [Fold("b", ("a", "c"), ("b",)), Fold("c", ("a", "b"), ("c",))]
    spec = DatasetSpec(
        "guards-test",
        lambda root=None, **kw: _Source(_pairs(), groups=("a", "b", "c"), folds=folds),
        ("thing", "other"),
    )
    with pytest.raises(DataError) as err:
        _prepare(spec, tmp_path)
    text = " ".join(str(err.value).split())
    assert (
        "empty-folds: 1 of the dataset's folds hold out only groups without prepared samples and are left out" in text
    )
    assert "e.g. fold 'c' holds out 'c': no prepared sample" in text and "inputs.accept=[empty-folds]" in text
    ds = _prepare(spec, tmp_path, "inputs.accept=[empty-folds]")
    from harness.cache import resolve_folds
    from harness.config import load_config

    with pytest.raises(
        ConfigError,
        match=r"fold 'c' of dataset 'guards-test' holds out 'c', which has no prepared "
        r"sample, so the fold is left out",
    ):
        resolve_folds(spec, ds, load_config(protocol="default"), "c")


# ------------------------------------------------------------------------------------------- crowd boxes
def test_coco_rgbt_keeps_crowd_boxes_as_crowd_regions_not_instances(tmp_path):
    """``iscrowd: 1`` reaches the ground truth as a crowd region (ignored by the evaluation, as COCO does) and is left
    out of the training targets and the support, with a note; before, it became an ordinary instance."""
    import json

    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json
    from harness.cache import coco_path, prepare
    from harness.config import load_config

    root = make_coco_rgbt(tmp_path / "coco", n=6)
    coco = read_json(root)
    crowd_ids = {a["id"] for a in coco["annotations"][::3]}
    for a in coco["annotations"]:
        a["iscrowd"] = int(a["id"] in crowd_ids)
    write_json(root, coco)
    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root)}
    ds = prepare(
        "coco-rgbt",
        cfg,
        cache_root=tmp_path / "cache",
        progress=False,
    )
    gt = json.loads(coco_path(ds).read_text())
    assert sum(a["iscrowd"] for a in gt["annotations"]) == len(crowd_ids)
    assert len(gt["annotations"]) == len(coco["annotations"])
    n_targets = sum(len(ds.targets(i)[0]) for i in range(len(ds)))
    assert n_targets == len(coco["annotations"]) - len(crowd_ids)
    assert ds.support()["instances"] == n_targets
    assert any(
        f"{len(crowd_ids)} crowd box(es) (iscrowd 1) kept as crowd regions" in n for n in ds.manifest["report"]["notes"]
    )


def test_coco_rgbt_with_every_box_a_crowd_region_is_an_error_naming_the_file(tmp_path):
    """Nothing would be left to train on or score: an error, not a run on zero instances."""
    from coco_rgbt_helpers import make_coco_rgbt, prepare_coco_rgbt, read_json, write_json
    from harness.errors import DataError

    root = make_coco_rgbt(tmp_path / "coco", n=4)
    coco = read_json(root)
    for a in coco["annotations"]:
        a["iscrowd"] = 1
    write_json(root, coco)
    with pytest.raises(DataError, match=r"every one of its \d+ box\(es\) is a crowd region \(iscrowd 1\)") as err:
        prepare_coco_rgbt(root, tmp_path / "cache")
    assert ".json" in str(err.value)
    assert not any((tmp_path / "cache").rglob("manifest.json"))


# ------------------------------------------------------------------------------------------- sample order
class _Shuffling(_Source):
    """Numbers its samples in call order, and the order turns at every call (a set or folder listing unsorted)."""

    calls = 0

    def samples(self, report):
        type(self).calls += 1
        k = type(self).calls % len(self._samples)
        order = self._samples[k:] + self._samples[:k]
        for k, s in enumerate(order, start=1):
            yield AlignedSample(k, s.rgb, s.thermal, s.ir8, s.boxes, s.labels, s.group, s.meta)


def test_a_plugin_whose_sample_order_changes_between_calls_is_stopped_before_it_replaces_samples(tmp_path):
    _Shuffling.calls = 0
    spec = DatasetSpec("guards-test", lambda root=None, **kw: _Shuffling(_pairs()), ("thing", "other"))
    first = _prepare(spec, tmp_path)
    with pytest.raises(DataError) as err:  # the other cache form, same key: ids now name other pictures
        _prepare(spec, tmp_path, form="raw")
    text = str(err.value)
    assert (
        "samples() gave other samples under the same image ids than the earlier preparation with the same cache key"
        in text
        and "6 of 6 id(s) hold another picture" in text
    )
    assert "image_id 1: a/frame_002.png before, a/frame_003.png now" in text
    with pytest.raises(DataError, match="other samples under the same image ids"):
        _prepare(spec, tmp_path, force=True)
    again = _prepare(spec, tmp_path)  # the earlier samples were kept
    assert again.from_cache and again[0].meta == first[0].meta


def test_a_stable_plugin_prepares_the_other_form_and_again_without_a_finding(tmp_path):
    spec = _spec(_pairs())
    a = _prepare(spec, tmp_path)
    b = _prepare(spec, tmp_path, form="raw")
    c = _prepare(spec, tmp_path, force=True)
    digests = {x.manifest["report"]["samples_identity"] for x in (a, b, c)}
    assert len(digests) == 1


def test_the_report_does_not_draw_a_run_on_samples_its_ids_no_longer_name(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from harness.report.gallery import prepared_of

    spec = _spec(_pairs())
    ds = _prepare(spec, tmp_path)
    meta = {
        "prepared_key": ds.key,
        "prepared_fingerprint": ds.manifest["fingerprint"],
        "prepared_samples": ds.manifest["report"]["samples_identity"],
    }
    run = SimpleNamespace(config={"meta": meta}, key=SimpleNamespace(dataset="guards-test"))
    assert prepared_of(run, tmp_path / "cache")[0] is not None
    meta["prepared_samples"] = "0123456789abcdef"
    got, why = prepared_of(run, tmp_path / "cache")
    assert got is None and "now holds other samples under the run's image ids" in why


def test_a_finished_run_on_other_samples_under_the_same_key_is_a_conflict_not_skipped(tmp_path):
    from types import SimpleNamespace

    from harness.config import dump_yaml
    from harness.runner import PlannedRun, run_hash

    then = {"train": {"lr0": 0.01}, "meta": {"prepared_key": "k", "prepared_samples": "aaaa"}}
    now = {"train": {"lr0": 0.01}, "meta": {"prepared_key": "k", "prepared_samples": "bbbb"}}
    assert run_hash(then) == run_hash(now)  # not part of the identity: runs stored before it stay comparable
    (tmp_path / "config.yaml").write_text(dump_yaml(then))
    run = SimpleNamespace(
        is_finished=lambda: True,
        status=lambda: {"config_hash": run_hash(then)},
        config_path=tmp_path / "config.yaml",
        key="d/det/enc/P1/0",
    )
    planned = PlannedRun(Fold("P1", ("a",), ("b",)), 0, run, now, run_hash(now))
    assert planned.state == "conflict"
    assert "the same cache key now holds other samples" in planned.differences()[0]
    same = PlannedRun(Fold("P1", ("a",), ("b",)), 0, run, then, run_hash(then))
    assert same.state == "finished"
    old = PlannedRun(Fold("P1", ("a",), ("b",)), 0, run, {**now, "meta": {"prepared_key": "k"}}, run_hash(now))
    assert old.state == "finished"  # a run or plan without the record is compared as before


def test_coco_rgbt_reads_the_nodata_pixels_sensing_decode_writes_as_missing(tmp_path):
    """A decoded file with a few missing pixels (the sidecar's ``nodata`` value) is kept, those pixels missing and
    counted, not a whole file skipped as implausible (0 centi-Kelvin read as -273.15 C)."""
    import cv2

    from coco_rgbt_helpers import make_coco_rgbt
    from harness.cache import prepare
    from harness.config import load_config
    from harness.sensing.radiometry import sidecar_path

    root = make_coco_rgbt(tmp_path / "coco", n=6)
    for p in sorted((root / "thermal").glob("*.png")):
        a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        a[0, :2] = 0
        cv2.imwrite(str(p), a)
        sidecar_path(p).write_text('{"unit": "centikelvin", "nodata": 0, "missing": 2}')
    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root)}
    ds = prepare("coco-rgbt", cfg, cache_root=tmp_path / "cache", progress=False)
    assert len(ds) == 6 and np.isnan(ds[0].thermal[0, :2]).all() and np.isfinite(ds[0].thermal[1:]).all()
    assert ds.manifest["report"]["missing_temperatures"]["pixels"] == 12


def test_temperatures_left_in_kelvin_stop_although_each_lies_in_the_plausible_range(tmp_path):
    samples = [_sample(i, "a" if i <= 3 else "b", thermal=np.full((H, W), 293.15 + i, np.float32)) for i in range(1, 7)]
    with pytest.raises(DataError) as err:
        _prepare(_spec(samples), tmp_path)
    text = " ".join(str(err.value).split())
    assert "temperature-range: the coolest pixel of all 6 sample(s) is 294.15 C" in text and "Kelvin" in text
    assert [r["kind"] for r in _prepare(_spec(samples), tmp_path, "inputs.accept=[temperature-range]").input_risks] == [
        "temperature-range"
    ]
