"""The dataset input boundary: the plausibility guard (no labels, mostly unlabelled images, dropped annotations),
the shared COCO checks (ids as the evaluation reads them, duplicates), plugin failures named by plugin, and an 8-bit
``coco-rgbt`` cache that references its sources."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.api import AlignedSample, DatasetSpec, Fold
from harness.errors import ConfigError, DataError, PluginError

H, W = 24, 32


def _sample(i: int, group: str, boxes: int = 1, inside: bool = True) -> AlignedSample:
    box = [[2, 2, 10, 10]] if inside else [[2, 2, 10, 10 + 2 * H]]
    return AlignedSample(
        i,
        np.zeros((H, W, 3), np.uint8),
        None,
        np.full((H, W), 40 + i, np.uint8),
        np.array(box * boxes, np.float32).reshape(-1, 4),
        np.zeros(boxes, np.int64),
        group,
        meta={"file_name": f"{group}/frame_{i:03d}.png"},
    )


class _Source:
    """``samples`` as given (or the exception ``fail`` raised after the first one); groups a and b, one fold."""

    def __init__(self, samples, fail: Exception | None = None):
        self._samples, self.fail = samples, fail

    def groups(self):
        return ["a", "b"]

    def folds(self):
        return [Fold("b", ("a",), ("b",))]

    def fingerprint(self):
        return f"guard-test-{len(self._samples)}-{[(s.image_id, len(s.boxes)) for s in self._samples]}"

    def samples(self, report):
        for k, s in enumerate(self._samples):
            if self.fail is not None and k == 1:
                raise self.fail
            yield s


def _spec(samples, fail=None) -> DatasetSpec:
    return DatasetSpec("guard-test", lambda root=None, **kw: _Source(samples, fail), ("thing",), thermal="8bit")


def _prepare(spec, tmp_path, *overrides):
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default", overrides=list(overrides))
    return prepare(spec, cfg, cache_root=tmp_path / "cache", progress=False)


def _published(tmp_path) -> list[Path]:
    return list((tmp_path / "cache").rglob("manifest.json"))


# ------------------------------------------------------------------------------------------- the guard
def test_a_fold_part_without_labels_stops_with_counts_and_examples(tmp_path):
    samples = [_sample(i, "a") for i in range(1, 7)] + [_sample(i, "b", boxes=0) for i in range(7, 13)]
    with pytest.raises(DataError) as err:
        _prepare(_spec(samples), tmp_path)
    lines = str(err.value).splitlines()
    assert lines[1] == "  no-labels: fold 'b' held-out part (b): 6 image(s) and not one box"
    assert lines[2:5] == [f"    e.g. b/frame_{i:03d}.png" for i in (7, 8)] + ["    e.g. b/frame_009.png (and 3 more)"]
    assert "--set 'inputs.accept=[no-labels]'" in str(err.value)
    assert len(_published(tmp_path)) == 1  # the samples are kept: accepting the risk reads them from the cache
    ds = _prepare(_spec(samples), tmp_path, "inputs.accept=[no-labels]")
    assert ds.from_cache and ds.input_risks == [
        {"kind": "no-labels", "message": "fold 'b' held-out part (b): 6 image(s) and not one box"}
    ]
    with pytest.raises(DataError, match="no-labels"):  # the cached samples are checked again without the option
        _prepare(_spec(samples), tmp_path)


def test_more_than_a_small_share_of_unlabelled_images_stops(tmp_path):
    samples = [_sample(i, "a", boxes=int(i % 3 == 0)) for i in range(1, 13)] + [_sample(13, "b"), _sample(14, "b")]
    with pytest.raises(
        DataError,
        match=r"unlabelled-images: fold 'b' training part \(a\): 8 of 12 images \(67%\) "
        r"have no box, more than 20%",
    ):
        _prepare(_spec(samples), tmp_path)
    assert _prepare(_spec(samples), tmp_path, "inputs.max_unlabelled=0.7").input_risks == []
    ds = _prepare(_spec(samples), tmp_path, "inputs.accept=[all]")
    assert [r["kind"] for r in ds.input_risks] == ["unlabelled-images", "unlabelled-images"]  # the dataset, the part


@pytest.mark.parametrize(
    "override, message",
    [
        ("inputs.accept=[no-lables]", "inputs.accept: unknown finding.*'no-lables'.*no-labels, unlabelled-images"),
        ("inputs.max_unlabelled=1.5", "inputs.max_unlabelled must be a share between 0 and 1"),
    ],
)
def test_bad_guard_settings_are_config_errors(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message):
        _prepare(_spec([_sample(1, "a"), _sample(2, "b")]), tmp_path, override)


def test_an_accepted_risk_labels_the_run_but_is_not_part_of_its_identity():
    from harness.runner import run_hash

    base = {"train": {"lr0": 0.01}, "meta": {"prepared_key": "k"}, "inputs": {"accept": []}}
    labelled = {
        "train": {"lr0": 0.01},
        "meta": {"prepared_key": "k", "input_risks": ["no-labels: ..."]},
        "inputs": {"accept": ["no-labels"]},
    }
    assert run_hash(base) == run_hash(labelled)
    assert run_hash(base) != run_hash({**base, "meta": {"prepared_key": "other"}})


def test_the_run_table_shows_an_accepted_risk(tmp_path):
    from harness.report.reader import read_run
    from harness.report.run_tables import fold_table
    from harness.runner import RunOutcome, RunSummary
    from harness.store import RunKey, Store

    risk = "no-labels: fold 'b' held-out part (b): 6 image(s) and not one box"
    run = Store(tmp_path).run(RunKey("guard-test", "det", "ir8", "b", 0))
    run.write_metrics(
        {"metrics": {"mAP50": 0.5}, "support": {"instances": 3}, "per_category": {}, "train": {}, "input_risks": [risk]}
    )
    summary = RunSummary(
        "det", "guard-test", "ir8", "smoke", tmp_path, {}, ["thing"], [RunOutcome(read_run(run), "trained")]
    )
    lines = fold_table(summary).splitlines()
    assert lines[-1] == f"† accepted input risk: {risk}"
    assert next(line for line in lines if line.startswith("b ")).split()[-5:] == ["0.500", "†", "-", "-/-", "trained"]


# ------------------------------------------------------------------------------------------- plugin failures
def test_duplicate_image_ids_stop_before_anything_is_cached(tmp_path):
    samples = [_sample(1, "a"), _sample(2, "a"), _sample(2, "b"), _sample(3, "b")]
    with pytest.raises(
        DataError,
        match=r"dataset 'guard-test'.*image_id 2 is given to two samples "
        r"\(a/frame_002.png and b/frame_002.png\).*Nothing was cached",
    ):
        _prepare(_spec(samples), tmp_path)
    assert not _published(tmp_path)


def test_a_plugin_whose_samples_raise_is_named(tmp_path):
    samples = [_sample(1, "a"), _sample(2, "b")]
    with pytest.raises(
        PluginError,
        match=r"dataset 'guard-test'.*samples\(\) raised KeyError: 'frame'.*"
        r"test_datasets_input_guard.py:\d+.*nothing was cached",
    ):
        _prepare(_spec(samples, fail=KeyError("frame")), tmp_path)
    assert not _published(tmp_path)


def test_a_plugin_error_through_the_cli_is_one_clear_line(host, tmp_path, cli_runner, monkeypatch):
    from harness.hookspecs import hookimpl
    from harness.testing import temporary_plugin

    class Broken:
        @hookimpl
        def register_datasets(self, register):
            register(_spec([_sample(1, "a"), _sample(2, "b")], fail=ZeroDivisionError("division by zero")))

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    with temporary_plugin(Broken(), name="broken-samples"):
        res = cli_runner(["prepare", "--dataset", "guard-test"])
    assert res.exit_code != 0 and "Traceback" not in res.output
    assert "dataset 'guard-test' (plugin broken-samples): samples() raised ZeroDivisionError" in res.output


def test_boxes_outside_the_frame_are_counted_under_one_reason(tmp_path):
    from harness.commands.data import prepare_summary

    samples = [_sample(i, "ab"[i % 2], inside=i > 8) for i in range(1, 21)]
    with pytest.raises(DataError, match=r"invalid-samples: 8 of the 20 samples"):
        _prepare(_spec(samples), tmp_path)
    ds = _prepare(_spec(samples), tmp_path, "inputs.accept=[invalid-samples]")
    reasons = ds.manifest["report"]["skip_reasons"]
    assert reasons == {"invalid sample, field 'boxes': a box lies outside its frame": 8}
    text = prepare_summary(ds)
    assert "skipped pairs: 8 (invalid sample, field 'boxes': a box lies outside its frame: 8)" in text
    examples = [line for line in text.splitlines() if line.startswith("  e.g. ")]
    assert len(examples) == 3 and all(len(line) <= 100 for line in examples)
    assert examples[0].startswith("  e.g. b/frame_001.png: invalid sample: sample 1 (b/frame_001.png): field 'boxes'")


# ------------------------------------------------------------------------------------------- COCO files
def _coco_rgbt(tmp_path) -> Path:
    from coco_rgbt_helpers import make_coco_rgbt

    return make_coco_rgbt(tmp_path / "d")


def _prepare_coco(root, tmp_path, **options):
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root), **options}
    return prepare("coco-rgbt", cfg, cache_root=tmp_path / "cache", progress=False)


def test_coco_ids_follow_the_evaluation_rule():
    from adapters.datasets._coco import coco_id
    from harness.evaluation.inputs import _norm_id

    for value in (12, "12", " 12", 12.0, "+12", "a_001", "-3"):
        assert coco_id(value) == _norm_id(value, "test")
    assert coco_id(True) is coco_id("") is coco_id(1.5) is None


def test_numeric_string_ids_are_read_as_the_evaluation_reads_them(tmp_path):
    from coco_rgbt_helpers import read_json, write_json

    root = _coco_rgbt(tmp_path)
    coco = read_json(root)
    for im in coco["images"]:
        im["id"] = str(im["id"] + 99)  # "100", "101", ...
    for a in coco["annotations"]:
        a["image_id"] = str(a["image_id"] + 99)
    coco["categories"][0]["id"] = "1"
    write_json(root, coco)
    ds = _prepare_coco(root, tmp_path)
    assert sorted(ds.image_ids) == list(range(100, 112)) and ds.manifest["instances"] == 24


def test_non_numeric_string_ids_are_numbered_in_file_order_as_the_evaluation_does(tmp_path):
    from coco_rgbt_helpers import read_json, write_json

    root = _coco_rgbt(tmp_path)
    coco = read_json(root)
    names = {im["id"]: f"img-{chr(ord('l') - k)}" for k, im in enumerate(coco["images"])}
    for im in coco["images"]:
        im["id"] = names[im["id"]]
    for a in coco["annotations"]:
        a["image_id"] = names[a["image_id"]]
    write_json(root, coco)
    ds = _prepare_coco(root, tmp_path)
    assert sorted(ds.image_ids) == list(range(1, 13)) and ds.manifest["instances"] == 24
    first = ds[ds.index_of(1)]
    assert first.meta["file_name"] == "rgb/000.png" and len(first.boxes) == 2


@pytest.mark.parametrize("first, second", [(7, "7"), (7, 7.0)])
def test_duplicate_image_ids_in_the_json_are_one_clear_error(tmp_path, first, second):
    from coco_rgbt_helpers import read_json, write_json

    root = _coco_rgbt(tmp_path)
    coco = read_json(root)
    coco["images"][0]["id"], coco["images"][1]["id"] = first, second
    write_json(root, coco)
    with pytest.raises(DataError, match=r"annotations.json: duplicate image id 7 \('rgb/000.png' and 'rgb/001.png'\)"):
        _prepare_coco(root, tmp_path)
    assert not _published(tmp_path)


def test_the_m3t_adapter_uses_the_same_coco_checks(tmp_path):
    import json

    from adapters.datasets.m3t import read_coco_annotations

    path = tmp_path / "instances_rgb.json"
    images = [{"id": "5", "file_name": "P1/a_W.JPG"}, {"id": 5, "file_name": "P1/b_W.JPG"}]
    path.write_text(json.dumps({"images": images, "annotations": [], "categories": [{"id": 1, "name": "crack"}]}))
    with pytest.raises(DataError, match=r"duplicate image id 5 \('P1/a_W.JPG' and 'P1/b_W.JPG'\)"):
        read_coco_annotations(path)
    images[1]["id"] = "6"
    anns = [
        {"id": 1, "image_id": "6", "category_id": "1", "bbox": [1, 2, 3, 4]},
        {"id": 2, "image_id": 6, "category_id": 3, "bbox": [1, 2, 3, 4]},
    ]
    path.write_text(json.dumps({"images": images, "annotations": anns, "categories": [{"id": 1, "name": "crack"}]}))
    ann = read_coco_annotations(path)
    assert [(r.image_id, len(r.boxes)) for r in ann.images] == [(5, 0), (6, 1)]
    assert [reason.split(":")[0] for _, reason in ann.issues] == ["annotation with an unknown category id"]


# ------------------------------------------------------------------------------------------- 8-bit references
def test_an_eight_bit_coco_rgbt_cache_references_its_sources(tmp_path):
    import cv2

    from harness.cache.admin import folder_bytes

    root = _coco_rgbt(tmp_path)
    rng = np.random.default_rng(0)
    for p in (root / "thermal").glob("*.png"):
        cv2.imwrite(str(p), rng.integers(0, 256, (48, 64), dtype=np.uint8))
    ds = _prepare_coco(root, tmp_path, thermal="8bit")
    assert len(ds) == 12 and all("src" in r for r in ds.records)  # every pair read from its own files
    assert folder_bytes(ds.folder) < folder_bytes(root)
    sample = ds[0]
    np.testing.assert_array_equal(sample.ir8, cv2.imread(str(root / "thermal" / "000.png"), cv2.IMREAD_UNCHANGED))


# ------------------------------------------------------------------------------------------- the docs
def test_the_datasets_table_says_what_happens_to_a_few_missing_temperatures():
    doc = (Path(__file__).resolve().parent.parent / "docs" / "datasets.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| a few NaN or infinite temperatures"))
    assert "kept as missing" in row and "never zero" in row
    assert "| more than half of the temperatures NaN or infinite | skip `non-finite temperatures` |" in doc


def test_a_fold_that_holds_out_every_group_says_so(tmp_path):
    class OneGroup(_Source):
        def groups(self):
            return ["a"]

        def folds(self):
            return []

    spec = DatasetSpec(
        "guard-test", lambda root=None, **kw: OneGroup([_sample(1, "a"), _sample(2, "a")]), ("x",), thermal="8bit"
    )
    with pytest.raises(
        DataError,
        match=r"fold 'a' holds out every group of the prepared data \(a\): nothing is "
        r"left to train on",
    ):
        _prepare(spec, tmp_path)
