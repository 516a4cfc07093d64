"""The prepared-sample cache (keys, reuse, damage), folds from the protocol, COCO per split, and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from datasets_helpers import synth_cfg
from harness.cache import cache_key, coco_path, fold_indices, prepare, resolve_folds
from harness.errors import ConfigError, DataError


def _prep(root: Path, cache: Path, cfg: dict | None = None, **kw):
    return prepare("m3t-synth", cfg or synth_cfg(root), cache_root=cache, progress=False, **kw)


# ------------------------------------------------------------------------------------------------ cache
def test_cache_key_depends_on_fingerprint_sensing_and_dataset():
    base = cache_key("abc", {}, "m3t")
    assert base == cache_key("abc", {}, "m3t") and len(base) == 16
    assert (
        len(
            {
                base,
                cache_key("abd", {}, "m3t"),
                cache_key("abc", {"warp": {"crop": False}}, "m3t"),
                cache_key("abc", {}, "m3t-synth"),
            }
        )
        == 4
    )
    # the displacement study's settings do not change prepared samples
    assert cache_key("abc", {"displacement": {"shifts": [1]}}, "m3t") == base


def test_prepared_once_then_reused_and_rebuilt_when_inputs_change(tiny, tmp_path):
    cache = tmp_path / "cache"
    first = _prep(tiny, cache)
    assert not first.from_cache and first.folder.parent == cache / "m3t-synth"
    again = _prep(tiny, cache)
    assert again.from_cache and again.folder == first.folder
    assert np.array_equal(np.asarray(again[0].rgb), np.asarray(first[0].rgb))
    # a changed sensing option prepares into a new folder
    cfg = synth_cfg(tiny)
    cfg["sensing"] = {**cfg["sensing"], "warp": {**cfg["sensing"]["warp"], "min_box_size": 2.0}}
    other = _prep(tiny, cache, cfg)
    assert not other.from_cache and other.folder != first.folder
    # so does a changed input file
    lm = tiny / "registration" / "landmarks.json"
    data = json.loads(lm.read_text())
    data["landmarks"][0]["thermal"][0] += 0.5
    lm.write_text(json.dumps(data))
    changed = _prep(tiny, cache)
    assert changed.folder != first.folder
    assert _prep(tiny, cache, force=True).from_cache is False


@pytest.mark.parametrize("form,name", [("raw", "rgb.u8"), ("compact", "rgb.pack")])
def test_a_damaged_cache_is_prepared_again(tiny, tmp_path, form, name):
    first = _prep(tiny, tmp_path / "cache", form=form)
    with open(first.folder / name, "r+b") as f:
        f.truncate(100)
    again = _prep(tiny, tmp_path / "cache", form=form)
    assert not again.from_cache and len(again) == len(first)
    assert (again.folder / name).stat().st_size > 100


def test_relative_dataset_and_cache_paths(tiny, tmp_path, monkeypatch):
    monkeypatch.chdir(tiny.parent)
    ds = prepare("m3t-synth", synth_cfg(Path(tiny.name)), cache_root="rel-cache", progress=False)
    assert len(ds) == 8 and (tiny.parent / "rel-cache" / "m3t-synth").is_dir()
    assert ds[0].meta["thermal_file"].startswith("images/P1/")


def test_cache_root_from_the_environment(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "envcache"))
    ds = prepare("m3t-synth", synth_cfg(tiny), progress=False)
    assert ds.folder.parent == tmp_path / "envcache" / "m3t-synth"


def test_unknown_dataset_option_is_a_config_error(tiny, tmp_path):
    with pytest.raises(ConfigError, match="does not take option.*'colour'"):
        _prep(tiny, tmp_path / "c", synth_cfg(tiny, colour="red"))


def test_samples_satisfy_the_contract_and_keep_provenance(tiny, tmp_path):
    from harness.contracts import validate_sample

    ds = _prep(tiny, tmp_path / "c")
    for s in ds:
        validate_sample(s, num_classes=8)
        assert s.meta["file_name"].endswith("_W.JPG") and s.meta["thermal_file"].endswith("_T.JPG")
        assert len(s.meta["ann_ids"]) == len(s.boxes)
    assert ds.manifest["sensing"]["warp"]["crop"] is True
    assert ds.manifest["groups"] == ["P1", "P2", "P3", "P4", "P5"]


# ------------------------------------------------------------------------------------------------ folds
def test_protocol_folds_hold_each_project_group_out(tiny, tmp_path):
    cfg = synth_cfg(tiny)
    ds = _prep(tiny, tmp_path / "c", cfg)
    folds = resolve_folds("m3t-synth", ds, cfg)
    assert [f.name for f in folds] == ["P1", "P2", "P3", "P4+P5"]
    n = len(ds)
    for f in folds:
        tr, va = fold_indices(ds, f)
        assert not set(tr) & set(va) and len(tr) + len(va) == n
        assert {ds.groups[i] for i in va} == set(f.val_groups)
    tr, va = fold_indices(ds, folds[3])
    assert (len(tr), len(va)) == (6, 2)


def test_dataset_folds_when_the_protocol_sets_none(tiny, tmp_path):
    cfg = synth_cfg(tiny)
    cfg["protocol"]["folds"] = None
    ds = _prep(tiny, tmp_path / "c", cfg)
    assert [f.name for f in resolve_folds("m3t-synth", ds, cfg)] == ["P1", "P2", "P3", "P4+P5"]


def test_fold_selection_and_bad_folds(tiny, tmp_path):
    cfg = synth_cfg(tiny)
    ds = _prep(tiny, tmp_path / "c", cfg)
    assert [f.name for f in resolve_folds("m3t-synth", ds, cfg, "P2,P4+P5")] == ["P2", "P4+P5"]
    with pytest.raises(ConfigError, match="unknown fold.*'P9'.*available: P1, P2, P3, P4\\+P5"):
        resolve_folds("m3t-synth", ds, cfg, "P9")
    cfg["protocol"]["folds"] = {"X": ["P7"]}
    with pytest.raises(ConfigError, match="holds out 'P7'.*groups are P1, P2, P3, P4, P5"):
        resolve_folds("m3t-synth", ds, cfg)
    cfg["protocol"]["folds"] = {"east": ["P1", "P2"], "west": ["P3"]}
    folds = resolve_folds("m3t-synth", ds, cfg)
    assert folds[0].train_groups == ("P3", "P4", "P5") and folds[1].val_groups == ("P3",)


def test_coco_per_fold_split_in_the_thermal_frame(tiny, tmp_path):
    cfg = synth_cfg(tiny)
    ds = _prep(tiny, tmp_path / "c", cfg)
    folds = resolve_folds("m3t-synth", ds, cfg)
    for f in folds:
        for split in ("train", "val"):
            path = ds.folder / "coco" / f"{f.name}-{split}.json"
            assert path.exists() and coco_path(ds, f, split) == path
            coco = json.loads(path.read_text())
            tr, va = fold_indices(ds, f)
            idx = tr if split == "train" else va
            assert sorted(i["id"] for i in coco["images"]) == sorted(ds.image_ids[i] for i in idx)
            assert coco["info"]["frame"] == "thermal" and coco["info"]["fold"] == f.name
            assert [c["id"] for c in coco["categories"]] == list(range(1, 9))
            assert len(coco["annotations"]) == ds.support(idx)["instances"]
    assert json.loads((ds.folder / "coco" / "all.json").read_text())["images"]


# ------------------------------------------------------------------------------------------------ m3t-synth on demand
def test_m3t_synth_is_generated_on_first_use_then_reused(tmp_path, monkeypatch):
    from adapters.datasets.synthetic import open_synthetic

    monkeypatch.setenv("HARNESS_DATA", str(tmp_path / "data"))
    src = open_synthetic(profile="tiny", seed=3)
    root = tmp_path / "data" / "m3t-synth-tiny-seed3"
    assert src.root == root and len(src) == 8
    stamp = (root / "synth.json").stat().st_mtime_ns
    open_synthetic(profile="tiny", seed=3)
    assert (root / "synth.json").stat().st_mtime_ns == stamp


def test_concurrent_first_use_generates_once(tmp_path, monkeypatch):
    import threading

    from adapters.datasets import synthetic
    from adapters.datasets.synthetic import generation

    calls = []
    real = generation.generate

    def counting(*args, **kw):
        calls.append(args[0])
        return real(*args, **{**kw, "progress": False})

    monkeypatch.setattr(generation, "generate", counting)
    monkeypatch.setenv("HARNESS_DATA", str(tmp_path / "data"))
    results = []
    threads = [
        threading.Thread(target=lambda: results.append(len(synthetic.open_synthetic(profile="tiny", seed=5))))
        for _ in range(2)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == [8, 8] and len(calls) == 1


def test_m3t_synth_refuses_a_folder_it_did_not_generate(tmp_path):
    from adapters.datasets.synthetic import open_synthetic

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("my data")
    with pytest.raises(DataError, match="not a generated m3t-synth dataset"):
        open_synthetic(tmp_path / "mine", profile="tiny")


# ------------------------------------------------------------------------------------------------ CLI
def test_cli_synth_prepare_and_folds(tmp_path, cli_runner):
    out = tmp_path / "synth"
    res = cli_runner(["synth", "--size", "tiny", "--out", str(out), "--seed", "0"])
    assert res.exit_code == 0, res.output
    assert "8 pairs" in res.output and "delamination" in res.output
    res = cli_runner(["synth", "--size", "tiny", "--out", str(out)])
    assert res.exit_code == 2 and "--force" in res.output
    args = ["--dataset", "m3t-synth", "--root", str(out), "--cache", str(tmp_path / "cache")]
    res = cli_runner(["prepare", *args])
    assert res.exit_code == 0, res.output
    assert "prepared m3t-synth: 8 aligned samples" in res.output and "skipped pairs: 0" in res.output
    res = cli_runner(["prepare", *args])
    assert "reused m3t-synth" in res.output
    res = cli_runner(["folds", *args])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("fold"))
    rows = [line.split() for line in lines[header + 2 : header + 6]]
    assert [r[0] for r in rows] == ["P1", "P2", "P3", "P4+P5"]
    assert [(int(r[2]), int(r[4])) for r in rows] == [(6, 2), (6, 2), (6, 2), (6, 2)]
    res = cli_runner(["folds", *args, "--folds", "P3"])
    assert res.exit_code == 0 and "P4+P5" not in res.output
