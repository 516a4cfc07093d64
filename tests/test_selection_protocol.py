"""Model selection (``protocol.selection``): the validation split carved from the training groups, the last epoch,
the seed's held-out protocol; which images are predicted during training; what a run records; the plateau record."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("harness.cache")
pytest.importorskip("harness.evaluation")

from engine_helpers import fast_overrides, write_dataset
from harness import Fold
from harness.errors import ConfigError

FAST = fast_overrides(epochs=3, close_mosaic=1)


def request(tmp_path, *extra: str, **kw):
    from harness.runner import RunRequest

    base = dict(
        detector="tinydet",
        dataset="shapes",
        store=tmp_path / "store",
        overrides=[*FAST, *extra],
        progress=False,
        folds="A",
    )
    base.update(kw)
    return RunRequest(**base)


# ------------------------------------------------------------------------------------------- the split
@pytest.fixture
def uneven(tmp_path):
    """Groups A (2 images), B (4), C (2), D (6): ``write_dataset`` adds ``per_group`` images per group it names."""
    return write_dataset(tmp_path / "ds", groups=("A", "B", "B", "C", "D", "D", "D"), per_group=2)


def test_the_validation_split_is_the_smallest_training_group_disjoint_and_deterministic(uneven):
    from harness.cache.folds import fold_indices, validation_split

    fold = Fold("A", ("B", "C", "D"), ("A",))
    split = validation_split(uneven, fold)
    assert split.groups == ("C",) and split.how == "smallest-group"
    train_idx, held = fold_indices(uneven, fold)
    assert {uneven.groups[i] for i in split.validation} == {"C"}
    assert {uneven.groups[i] for i in split.train} == {"B", "D"}
    assert not set(split.validation) & set(held) and not set(split.train) & set(held)
    assert not set(split.validation) & set(split.train)
    assert sorted(split.train + split.validation) == sorted(train_idx)
    assert validation_split(uneven, fold) == split  # deterministic
    # ties go to the first group by name: A and C both hold 2 images when B is held out
    assert validation_split(uneven, Fold("B", ("D", "C", "A"), ("B",))).groups == ("A",)
    assert split.record() == {
        "validation_groups": ["C"],
        "validation_images": 2,
        "train_images": 10,
        "how": "smallest-group",
    }


def test_configured_validation_groups_and_their_errors(uneven):
    from harness.cache.folds import validation_split

    fold = Fold("A", ("B", "C", "D"), ("A",))
    cfg = {"protocol": {"validation_groups": {"A": ["B", "C"]}}}
    split = validation_split(uneven, fold, cfg)
    assert split.groups == ("B", "C") and split.how == "configured"
    assert {uneven.groups[i] for i in split.train} == {"D"}
    with pytest.raises(ConfigError, match=r"fold 'A' must name one or more of its training groups.*'A' is not"):
        validation_split(uneven, fold, {"protocol": {"validation_groups": {"A": ["A"]}}})
    with pytest.raises(ConfigError, match="nothing is left to train on"):
        validation_split(uneven, fold, {"protocol": {"validation_groups": {"A": ["B", "C", "D"]}}})


def test_a_single_training_group_gives_a_documented_image_split(tmp_path):
    from harness.cache.folds import IMAGE_SPLIT_EVERY, validation_split

    prepared = write_dataset(tmp_path / "ds", groups=("A", "B"), per_group=10)
    split = validation_split(prepared, Fold("A", ("B",), ("A",)))
    b = prepared.indices(["B"])
    assert split.how == "images" and split.groups == ()
    assert list(split.validation) == b[IMAGE_SPLIT_EVERY - 1 :: IMAGE_SPLIT_EVERY] and len(split.validation) == 2
    assert sorted(split.train + split.validation) == b


# ------------------------------------------------------------------------------------------- the plateau
def test_the_plateau_record_is_the_least_squares_slope_of_the_last_epochs():
    from harness.engine.trainer import PLATEAU_EPOCHS, PLATEAU_SLOPE, plateau

    rising = [{"epoch": e, "fitness": 0.01 * e} for e in range(1, 16)]  # 1 point per epoch
    p = plateau(rising)
    assert p == {"slope_per_epoch": 1.0, "epochs": PLATEAU_EPOCHS, "reached": False, "threshold": PLATEAU_SLOPE}
    flat = rising[:5] + [{"epoch": e, "fitness": 0.3 + (0.0001 if e % 2 else 0.0)} for e in range(6, 16)]
    assert plateau(flat)["reached"] is True and abs(plateau(flat)["slope_per_epoch"]) < 0.01
    assert plateau(flat[:7])["epochs"] == 7  # fewer scored epochs than the window: all of them
    # epochs without a score are skipped; fewer than two scored epochs: no record
    assert plateau([{"epoch": 1, "fitness": None}, {"epoch": 2, "fitness": 0.2}]) is None


# ------------------------------------------------------------------------------------------- whole runs
@pytest.fixture
def predicted(monkeypatch):
    """Every ``predict`` call's image indices, in order."""
    import harness.engine.predict as p

    calls: list[list[int]] = []
    real = p.predict

    def counting(model, source, *a, **k):
        calls.append(list(source.indices))
        return real(model, source, *a, **k)

    monkeypatch.setattr(p, "predict", counting)
    return calls


def _run(tmp_path, *extra: str, store: str = "store"):
    from harness.runner import run

    summary = run(request(tmp_path, *extra, store=tmp_path / store))
    (r,) = summary.results
    metrics = json.loads((r.path / "metrics.json").read_text())
    log = [json.loads(line) for line in (r.path / "log.jsonl").read_text().splitlines()]
    return r, metrics, log


def _held_out(tmp_path):
    from harness.cache.reader import PreparedDataset

    (folder,) = [p.parent for p in (tmp_path / "cache").rglob("manifest.json")]
    prepared = PreparedDataset(folder)
    return set(prepared.indices(["A"])), set(prepared.indices(["B"]))


@pytest.mark.slow
def test_validation_never_predicts_the_held_out_fold_until_the_end(shapes_run_plugins, tmp_path, predicted):
    r, m, log = _run(tmp_path, "protocol.selection=validation")
    held, train = _held_out(tmp_path)
    on_held = [c for c in predicted if set(c) & held]
    assert len(on_held) == 1 and set(on_held[0]) == held  # once: the selected weights, after training
    assert predicted[-1] == on_held[0]
    during = predicted[:-1]
    assert len(during) == 3 and all(set(c) <= train for c in during)  # the validation image, each epoch
    sel = m["selection"]
    assert sel["protocol"] == "validation" and sel["how"] == "images" and sel["validation_images"] == 1
    assert set(during[0]) == {sorted(train)[4]} and m["train"]["images"] == 7 == sel["train_images"]
    assert sel["best_epoch"] == m["train"]["best_epoch"] and sel["weights"] == "best"
    assert m["train"]["plateau"]["metric"] == "validation fitness" and m["train"]["plateau"]["epochs"] == 3  # all 3
    assert all("observed" not in rec for rec in log)
    cfg = (r.path / "config.yaml").read_text()
    assert "selection: validation" in cfg


def test_last_takes_the_last_epoch_and_scores_nothing_during_training(shapes_run_plugins, tmp_path, predicted):
    from harness.engine import checkpoint as ckpt

    r, m, log = _run(tmp_path, "protocol.selection=last")
    held, _ = _held_out(tmp_path)
    assert len(predicted) == 1 and set(predicted[0]) == held
    assert m["selection"]["protocol"] == "last" and m["selection"]["weights"] == "last"
    assert m["selection"]["best_epoch"] is None and m["model"]["weights"] == "last"
    assert m["train"]["epochs_run"] == 3 and m["train"]["images"] == 8 and m["train"]["plateau"] is None
    assert [rec["fitness"] for rec in log] == [None] * 3 and not (r.path / "checkpoints" / "best.pt").exists()
    # the predictions come from the last epoch's EMA weights
    state = ckpt.load(r.path / "checkpoints" / "last.pt")
    assert state["epoch"] == 2 and state["done"]
    from harness.store import Store

    assert Store(tmp_path / "store").run(r.key).final_checkpoint().name == "last.pt"


def test_held_out_is_the_seeds_protocol_with_an_unchanged_identity(shapes_run_plugins, tmp_path, predicted):
    from harness.runner import run_hash

    r, m, log = _run(tmp_path, "protocol.selection=held-out")
    held, _ = _held_out(tmp_path)
    assert len(predicted) == 4 and all(set(c) == held for c in predicted)  # each epoch, then the final prediction
    best = max(log, key=lambda rec: rec["fitness"])
    assert m["selection"]["protocol"] == "held-out" and m["selection"]["best_epoch"] == best["epoch"]
    assert m["train"]["plateau"]["metric"] == "held-out fitness"
    from harness.config import read_yaml

    cfg = read_yaml(r.path / "config.yaml")
    assert cfg["protocol"]["selection"] == "held-out"
    seed_cfg = json.loads(json.dumps(cfg))
    del seed_cfg["protocol"]["selection"], seed_cfg["protocol"]["validation_groups"], seed_cfg["eval"]["log_held_out"]
    assert run_hash(cfg) == run_hash(seed_cfg)  # runs stored before the setting existed keep their identity
    other = json.loads(json.dumps(cfg))
    other["protocol"]["selection"] = "validation"
    assert run_hash(other) != run_hash(cfg)


@pytest.mark.slow
@pytest.mark.parametrize("selection", ["validation", "last"])
def test_logging_the_held_out_fold_changes_no_number(shapes_run_plugins, tmp_path, predicted, selection):
    _, quiet, _ = _run(tmp_path, f"protocol.selection={selection}", store="a")
    _, logged, log = _run(tmp_path, f"protocol.selection={selection}", "eval.log_held_out=true", store="b")
    assert quiet["metrics"] == logged["metrics"] and quiet["selection"] == logged["selection"]
    assert all(rec["observed"]["mAP50_95"] is not None for rec in log)
    # the final held-out score is the one logged at the selected epoch (the last under selection=last)
    epoch = logged["selection"]["best_epoch"] or logged["selection"]["epochs_run"]
    at_best = next(rec for rec in log if rec["epoch"] == epoch)
    assert at_best["observed"]["mAP50_95"] == pytest.approx(logged["metrics"]["mAP50_95"], abs=1e-9)
    # the plateau record: of the selecting score, or of the logged one when nothing selects
    expected = {"validation": "validation fitness", "last": "held-out fitness, logged only"}[selection]
    assert logged["train"]["plateau"]["metric"] == expected
    assert (quiet["train"]["plateau"] is None) == (selection == "last")


def test_an_unknown_selection_is_a_clear_error(shapes_run_plugins, tmp_path):
    from harness.runner import selection_of

    assert selection_of({"protocol": {}}) == "held-out"
    with pytest.raises(ConfigError, match="protocol.selection: 'best' is not one of validation, last, held-out"):
        selection_of({"protocol": {"selection": "best"}})


def test_the_report_reads_each_runs_selection_and_plateau():
    from harness.report.reader import run_plateau, run_selection

    new = {
        "selection": {"protocol": "validation", "validation_groups": ["P4"], "best_epoch": 7},
        "train": {"plateau": {"slope_per_epoch": 0.02, "epochs": 5, "reached": True}},
    }
    assert run_selection(new)["validation_groups"] == ["P4"] and run_plateau(new)["reached"] is True
    old = {"model": {"weights": "best"}, "train": {"best_epoch": 12, "epochs_run": 20}}  # stored before the fields
    assert run_selection(old) == {
        "protocol": "held-out",
        "weights": "best",
        "best_epoch": 12,
        "epochs_run": 20,
        "validation_groups": [],
    }
    assert run_plateau(old) is None
