"""The training loop: the loss falls, a resumed run reaches the same state, the 4th channel is used, errors are
clear."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from engine_helpers import ENCODINGS, tinydet_module, train_settings, write_dataset
from harness.engine import checkpoint as ckpt
from harness.engine.data import AugmentSettings, SampleSource, TrainDataset
from harness.engine.predict import predict
from harness.engine.runtime import seed_everything
from harness.engine.trainer import Trainer, TrainingError, TrainSettings
from harness.errors import PluginError

IR8, NONE = ENCODINGS


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("shapes") / "ds", groups=("A", "B"), per_group=16)


def settings(**kw) -> TrainSettings:
    return train_settings(**{"epochs": 4, "batch": 8, "nominal_batch": 8, "patience": 100, **kw})


def build(in_channels: int = 4, seed: int = 0) -> nn.Module:
    seed_everything(seed)
    return tinydet_module().build_tinydet(3, in_channels=in_channels)


def test_loss_decreases_on_a_tiny_batch(prepared):
    src = SampleSource(prepared, list(range(8)), IR8)
    model = build()
    result = Trainer(model, TrainDataset(src, 64, AugmentSettings.off()), settings(epochs=12), progress=False).fit()
    losses = [sum(r["loss"].values()) for r in result.history]
    assert len(losses) == 12
    assert losses[-1] < 0.8 * losses[0], losses
    assert sum(b < a for a, b in zip(losses, losses[1:])) >= 9, losses  # it falls nearly every step
    assert result.best_fitness == pytest.approx(-min(losses[result.best_epoch - 1 : result.best_epoch]))


def _validate(src):
    def validate(model):
        dets = predict(model, src, 64, batch=8, conf=0.05, iou=0.6, max_det=50)
        return {
            "mAP50": len(dets) / (10 * len(src)) % 1.0,
            "mAP50_95": float(np.mean([d["score"] for d in dets]) if dets else 0.0),
        }

    return validate


def test_resume_reaches_the_same_state_as_an_uninterrupted_run(prepared, tmp_path):
    """4 epochs straight vs 2 epochs, a crash, and a resume from last.pt: identical weights, EMA, metrics, log.

    The run exercises mosaic (closed for the last epoch), warm-up across the interruption, gradient accumulation
    (batch 4 to a nominal 8), EMA, validation and best-checkpoint selection.
    """
    train = SampleSource(prepared, prepared.indices(["A"]), IR8)
    val = SampleSource(prepared, prepared.indices(["B"])[:6], IR8)
    s = settings(epochs=4, batch=4, nominal_batch=8, warmup_epochs=2.5, close_mosaic=1, max_images=12)
    aug = AugmentSettings(mosaic=0.7)

    def trainer(model: nn.Module, folder: str, on_epoch=None) -> Trainer:
        data = TrainDataset(train, 64, aug, seed=0)
        kw = dict(validate=_validate(val), on_epoch=on_epoch, progress=False, config_hash="h")
        return Trainer(model, data, s, checkpoint_dir=tmp_path / folder, **kw)

    straight_log: list[dict] = []
    model_a = build()
    trainer_a = trainer(model_a, "a", straight_log.append)
    res_a = trainer_a.fit()

    class Crash(Exception):
        pass

    resumed_log: list[dict] = []

    def crash_after_two(record):
        resumed_log.append(record)
        if record["epoch"] == 2:
            raise Crash

    model_b = build()
    with pytest.raises(Crash):
        trainer(model_b, "b", crash_after_two).fit()
    assert ckpt.load(tmp_path / "b" / "last.pt")["epoch"] == 1  # 0-based: two epochs done
    model_c = build(seed=123)  # a different initialisation: everything must come from the checkpoint
    trainer_c = trainer(model_c, "b", resumed_log.append)
    res_c = trainer_c.fit(resume=True)

    assert res_c.resumed_from == 2 and res_c.epochs_run == 4
    for (k, va), (_, vc) in zip(model_a.state_dict().items(), model_c.state_dict().items()):
        assert torch.equal(va, vc), k
    for (k, va), (_, vc) in zip(trainer_a.eval_model.state_dict().items(), trainer_c.eval_model.state_dict().items()):
        assert torch.equal(va, vc), f"EMA {k}"
    strip = lambda log: [{k: v for k, v in r.items() if k not in ("time_s", "images_per_s")} for r in log]  # noqa: E731
    assert strip(resumed_log) == strip(straight_log)
    assert (res_a.best_epoch, res_a.best_fitness) == (res_c.best_epoch, res_c.best_fitness)
    best_a, best_c = ckpt.load(res_a.best_path), ckpt.load(res_c.best_path)
    assert best_a["epoch"] == best_c["epoch"]
    assert all(torch.equal(best_a["model"][k], best_c["model"][k]) for k in best_a["model"])
    # a finished run resumed again trains nothing and reports the same result
    again = trainer(build(), "b").fit(resume=True)
    assert again.epochs_run == 4 and again.best_fitness == res_a.best_fitness


def _label_accuracy(model, src, classes=(1, 2)) -> float:
    """Among ground-truth boxes of ``classes``, the share whose best-overlapping confident detection has the right
    label."""
    from harness.boxes import box_iou

    dets = predict(model, src, 64, batch=8, conf=0.2, iou=0.6, max_det=50)
    hits = total = 0
    for k in range(len(src)):
        boxes, labels = src.targets(k)
        mine = [d for d in dets if d["image_id"] == src.image_id(k)]
        for b, lab in zip(boxes, labels):
            if lab not in classes:
                continue
            total += 1
            if not mine:
                continue
            xyxy = torch.tensor(
                [[d["bbox"][0], d["bbox"][1], d["bbox"][0] + d["bbox"][2], d["bbox"][1] + d["bbox"][3]] for d in mine]
            )
            iou = box_iou(torch.as_tensor(b)[None], xyxy)[0]
            j = int(iou.argmax())
            hits += int(iou[j] > 0.3 and mine[j]["category_id"] - 1 == lab)
    return hits / max(total, 1)


@pytest.mark.slow
def test_the_fourth_channel_is_what_tells_warm_from_cold(prepared):
    """'warm' and 'cold' squares are identical in RGB: only a model fed the thermal channel can label them."""
    train_idx, val_idx = prepared.indices(["A"]), prepared.indices(["B"])
    acc = {}
    for enc in (IR8, NONE):
        train, val = SampleSource(prepared, train_idx, enc), SampleSource(prepared, val_idx, enc)
        model = build(train.channels)
        trainer = Trainer(
            model,
            TrainDataset(train, 64, AugmentSettings(mosaic=0.0, hsv_h=0, hsv_s=0, hsv_v=0)),
            settings(epochs=30, batch=8, lr0=0.04),
            progress=False,
        )
        trainer.fit()
        acc[enc.name] = _label_accuracy(trainer.eval_model, val)
    assert acc["test-ir8"] > 0.8, acc  # the thermal channel separates them
    assert acc["test-none"] < 0.7, acc  # RGB alone cannot do much better than guessing between the two


class _LossStub(nn.Module):
    """A model of one parameter ``w`` whose training forward returns ``losses(w)``, whatever the batch."""

    def __init__(self, losses):
        super().__init__()
        self.w = nn.Parameter(torch.ones(1))
        self.losses = losses

    def forward(self, x, targets=None):
        return self.losses(self.w)


def test_non_finite_loss_is_a_clear_error(prepared):
    exploding = _LossStub(lambda w: {"box": w * float("nan"), "cls": w.sum()})
    src = SampleSource(prepared, list(range(4)), IR8)
    with pytest.raises(TrainingError, match=r"loss box became nan at epoch 1, iteration 1.*lr0"):
        Trainer(exploding, TrainDataset(src, 64, AugmentSettings.off()), settings(), progress=False).fit()


def test_a_model_breaking_the_contract_is_named(prepared):
    list_loss = _LossStub(lambda w: [w.sum()])
    src = SampleSource(prepared, list(range(4)), IR8)
    with pytest.raises(PluginError, match="'broken'.*dict of scalar loss"):
        Trainer(
            list_loss, TrainDataset(src, 64, AugmentSettings.off()), settings(), progress=False, name="broken"
        ).fit()


def test_early_stopping_after_patience_epochs(prepared):
    scores = iter([0.5, 0.4, 0.45, 0.3, 0.9, 0.9])
    src = SampleSource(prepared, list(range(8)), IR8)
    res = Trainer(
        build(),
        TrainDataset(src, 64, AugmentSettings.off()),
        settings(epochs=6, patience=3),
        validate=lambda m: {"mAP50": 0.0, "mAP50_95": next(scores)},
        progress=False,
    ).fit()
    assert res.stopped_early and res.epochs_run == 4 and res.best_epoch == 1
    assert res.best_fitness == pytest.approx(0.9 * 0.5)


def test_init_from_checkpoint_loads_matching_tensors(prepared, tmp_path):
    src = SampleSource(prepared, list(range(8)), IR8)
    trained = build()
    Trainer(
        trained,
        TrainDataset(src, 64, AugmentSettings.off()),
        settings(epochs=1),
        checkpoint_dir=tmp_path,
        progress=False,
    ).fit()
    fresh = build(seed=5)
    report = ckpt.init_from(fresh, tmp_path / "last.pt")
    assert report["loaded"] == report["total"] and not report["missing"]
    ema_state = ckpt.load(tmp_path / "last.pt")["ema"]["module"]
    assert all(torch.equal(v, ema_state[k]) for k, v in fresh.state_dict().items())
    # a 3-channel model takes everything but the stem's first convolution
    rgb_only = build(in_channels=3)
    report = ckpt.init_from(rgb_only, tmp_path / "last.pt")
    assert report["shape_mismatch"] == ["stem.0.conv.weight"] and report["loaded"] == report["total"] - 1
    # a detector's own importer is used when it has one
    calls = []
    ckpt.init_from(build(), tmp_path / "best.pt", load_official=lambda m, sd: calls.append(sorted(sd)) or {"loaded": 1})
    assert calls and "stem.0.conv.weight" in calls[0]


def test_init_from_a_foreign_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "model.pt"
    torch.save({"model": nn.Linear(2, 2)}, bad)  # a pickled module, not a state dict
    with pytest.raises(ckpt.CheckpointError, match="weights-only"):
        ckpt.init_from(build(), bad)
    other = tmp_path / "other.pt"
    torch.save({"x.weight": torch.zeros(3, 3)}, other)
    with pytest.raises(ckpt.CheckpointError, match="none of its 1 tensors"):
        ckpt.init_from(build(), other)
    with pytest.raises(ckpt.CheckpointError, match="not found"):
        ckpt.init_from(build(), tmp_path / "missing.pt")
