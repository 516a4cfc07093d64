"""Which runs the reference results are paired with: those trained at the references' budget, where the benchmark
profile gives each detector its own number of epochs."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from harness.references import ReferenceSet, _training_record, same_training


def _run(detector: str, epochs: int, imgsz: int = 192, selection: str = "last", profile: str | None = "benchmark"):
    cfg = {
        "protocol": {"imgsz": imgsz, "epochs": epochs, "selection": selection},
        "model": {"scale": "n"},
        "train": {"threads": 1},
        "meta": {"profile": profile},
    }
    return SimpleNamespace(key=SimpleNamespace(detector=detector), config=cfg)


def _refs(runs) -> ReferenceSet:
    manifest = {"dataset": "m3t-synth", "profile": "benchmark", "training": _training_record(runs)}
    return ReferenceSet(Path("refs"), manifest)


REFS = [_run("ref:ours", 30), _run("ref:eme", 80), _run("ref:icafusion", 60), _run("ref:cmadet", 60)]


def test_the_record_holds_every_detectors_epochs_and_the_description_names_them():
    refs = _refs(REFS)
    t = refs.manifest["training"]
    assert t["epochs_by_detector"] == {"cmadet": 60, "eme": 80, "icafusion": 60, "ours": 30}
    assert t["selection"] == "last" and t["imgsz"] == 192 and "profile" not in t
    assert "192 px, epochs cmadet 60, eme 80, icafusion 60, ours 30, scale n" in refs.describe()


def test_a_reference_detector_pairs_at_its_own_budget_only():
    refs = _refs(REFS)
    assert same_training(refs, [_run("ours", 30), _run("eme", 80)])
    assert not same_training(refs, [_run("eme", 30)])  # ours's budget is not EME's
    assert not same_training(refs, [_run("ours", 30, imgsz=256)])
    assert not same_training(refs, [_run("ours", 30, selection="held-out")])


def test_a_new_detector_pairs_when_trained_at_the_references_profile():
    refs = _refs(REFS)
    assert same_training(refs, [_run("tinydet", 60)])
    assert same_training(refs, [_run("tinydet", 45)])  # its own config's epochs at that profile
    assert not same_training(refs, [_run("tinydet", 5, profile="demo")])
    assert same_training(refs, [_run("tinydet", 80, profile=None)])  # a reference detector's budget, set by hand
    assert not same_training(refs, [_run("tinydet", 45, profile=None)])
    assert not same_training(refs, [_run("tinydet", 60, imgsz=128)])
    assert not same_training(refs, [])


def test_references_with_one_budget_for_every_run_compare_epochs_as_before():
    refs = ReferenceSet(Path("refs"), {"dataset": "m3t-synth", "training": {"imgsz": 192, "epochs": 20}})
    assert same_training(refs, [_run("tinydet", 20, selection="held-out")])
    assert not same_training(refs, [_run("tinydet", 60)])
    assert "192 px, 20 epochs" in refs.describe()
