"""The training loop every detector shares.

``Trainer(model, dataset, settings, ...).fit()`` trains a detector that follows the model contract
(``harness.api.DetectorSpec``): in train mode ``model(inputs, targets)`` returns a dict of scalar losses, which the
engine sums and back-propagates as they are (detectors in the YOLO tradition scale their loss by the batch size, so
that gradients accumulated to the nominal batch are sums over images).

Per iteration: warm-up (``harness.engine.optim``), forward under autocast (CUDA only), backward (through a
gradient scaler on CUDA), and every ``accumulate`` iterations an optimiser step with gradient-norm clipping and an
EMA update. Per epoch: the learning rate of the schedule, mosaic switched off for the last ``close_mosaic`` epochs,
validation of the EMA weights through the ``validate`` callback, ``fitness = 0.1 * mAP50 + 0.9 * mAP50:95``, the best
weights saved to ``best.pt``, a log line and a ``log.jsonl`` record, the full state saved to ``last.pt``, and early
stopping after ``patience`` epochs without a better fitness. ``fit(resume=True)`` continues from ``last.pt`` to the
same state an uninterrupted run would have reached.

Model selection is the caller's choice of ``validate`` (the runner's ``protocol.selection``): a validation split carved
from the training groups, the held-out fold (the seed's protocol), or none with ``select=False`` (the last epoch's
weights: no fitness, no ``best.pt``, no early stopping). ``observe(model) -> metrics`` scores the weights each epoch
for the log only (``record["observed"]``; the runner's ``eval.log_held_out``): it never decides anything.
The run's plateau record (``plateau``) is the least-squares slope of the fitness over the last ``PLATEAU_EPOCHS``
validated epochs, in points (fitness x 100) per epoch, and whether it is under ``PLATEAU_SLOPE``; without ``validate``
it is that of the observed scores (which then chose nothing: the last epoch's weights are the result either way).

Under ``torchrun`` (``harness.distributed``) the model is wrapped in ``DistributedDataParallel``; ``train.batch`` stays
the global batch, split evenly over the processes, each of which takes its share of the epoch's order. The summed
loss is multiplied by the number of processes because DDP averages gradients over them, so a gradient is the same
sum over images as on one process and the hyper-parameters (learning rate, nominal batch, weight decay) carry over.
Validation shards the held-out images over the processes and rank 0 scores them; its metrics are broadcast so that
every process takes the same best-epoch and early-stopping decisions. Only rank 0 writes checkpoints and logs.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import nn

from harness import distributed as hd
from harness.engine import checkpoint as ckpt
from harness.engine import optim
from harness.engine.data import TrainDataset, targets_to, to_inputs, train_loader
from harness.engine.ema import ModelEMA
from harness.engine.flat import FlatOptimizer, FlatState
from harness.engine.runtime import keep_freed_memory, select_device, set_threads
from harness.errors import ConfigError, HarnessError
from harness.progress import bar as progress_bar

log = logging.getLogger(__name__)


class TrainingError(HarnessError):
    """Training cannot go on (e.g. the loss became NaN); the message says at which epoch and what to try."""


#: The plateau record: the slope of the fitness over this many last validated epochs ...
PLATEAU_EPOCHS = 10
#: ... counts as a plateau below this many points (fitness x 100) per epoch. From the learning curves on m3t-synth
#: (docs/learning-curves/): on a 16-image validation group the fitness of a model that no longer improves (ours,
#: epochs 30-60) scatters by 1.0 point (SD) around its trend, so a 10-epoch slope has a standard error of 0.11 and a
#: 5-epoch one of 0.32 points per epoch; 0.2 is under 2 standard errors above a flat curve (a flat curve passes about
#: 96 % of the time) and below the 0.34 of CMA-Det still learning at epoch 40.
PLATEAU_SLOPE = 0.2


def plateau(
    history: Sequence[Mapping[str, Any]], epochs: int = PLATEAU_EPOCHS, key: str = "fitness"
) -> dict[str, Any] | None:
    """``{"slope_per_epoch", "epochs", "reached", "threshold"}``: the least-squares slope of ``key`` (``fitness``, or
    ``observed_fitness``: the fitness of the scores logged only) over the last ``epochs`` records that have one, in
    points (x 100) per epoch; None with fewer than two such records."""
    pts = [(float(r["epoch"]), 100.0 * float(r[key])) for r in history if r.get(key) is not None]
    pts = pts[-epochs:]
    if len(pts) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    slope = sum((x - mx) * (y - my) for x, y in pts) / sxx
    return {
        "slope_per_epoch": round(slope, 4),
        "epochs": len(pts),
        "reached": slope < PLATEAU_SLOPE,
        "threshold": PLATEAU_SLOPE,
    }


def fitness(metrics: Mapping[str, Any]) -> float:
    """``0.1 * mAP50 + 0.9 * mAP50:95``: the checkpoint-selection score."""
    return 0.1 * float(metrics.get("mAP50") or 0.0) + 0.9 * float(metrics.get("mAP50_95") or 0.0)


@dataclass
class TrainSettings:
    """Everything the loop reads, from the ``protocol`` and ``train`` sections of a resolved config."""

    imgsz: int = 640
    epochs: int = 150
    patience: int = 50
    batch: int = 16
    nominal_batch: int = 64
    optimizer: str = "SGD"
    lr0: float = 0.01
    lrf: float = 0.01
    momentum: float = 0.937
    weight_decay: float = 0.0005
    warmup_epochs: float = 3.0
    warmup_min_iters: int = 100
    warmup_momentum: float = 0.8
    warmup_bias_lr: float = 0.1
    cos_lr: bool = False
    ema: bool = True
    ema_decay: float = 0.9999
    ema_tau: float = 2000.0
    amp: bool = True
    close_mosaic: int = 10
    workers: int = 0
    deterministic: bool = True
    threads: int | None = None
    max_images: int | None = None
    device: str = "auto"
    clip_grad: float = 10.0
    val_period: int = 1
    channels_last: bool = False
    fused_validation: bool = False
    seed: int = 0

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], seed: int = 0) -> "TrainSettings":
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in dict(cfg.get("train", {})).items() if k in known}
        proto = cfg.get("protocol", {})
        values.update(
            imgsz=int(proto.get("imgsz", 640)),
            epochs=int(proto.get("epochs", 150)),
            patience=int(proto.get("patience", 50)),
            seed=int(seed),
        )
        s = cls(**values)
        s.check()
        return s

    def check(self) -> None:
        if self.optimizer not in optim.OPTIMIZERS:
            raise ConfigError(f"train.optimizer: {self.optimizer!r} is not one of {', '.join(optim.OPTIMIZERS)}")
        for name in ("epochs", "batch", "nominal_batch", "imgsz", "val_period"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{'protocol' if name in ('epochs', 'imgsz') else 'train'}.{name} must be at least 1")
        if self.imgsz % 32:
            raise ConfigError(f"protocol.imgsz={self.imgsz} must be a multiple of 32 (the detectors' largest stride)")


@dataclass
class TrainResult:
    epochs_run: int
    best_epoch: int | None  # 1-based
    best_fitness: float | None
    stopped_early: bool
    time_s: float
    history: list[dict[str, Any]] = field(default_factory=list)
    best_path: str | None = None
    last_path: str | None = None
    resumed_from: int | None = None  # epochs already done when the run was resumed
    device: str = "cpu"
    plateau: dict[str, Any] | None = None  # ``plateau(history)``: the fitness slope over the last epochs

    def summary(self) -> dict[str, Any]:
        out = asdict(self)
        out.pop("history")
        return out


class Trainer:
    """Train ``model`` on ``dataset``; see the module docstring.

    ``validate(model) -> metrics`` scores a model in eval mode for selection and early stopping (the runner
    predicts its validation split, or the held-out fold under the seed's protocol); without it, the fitness is the
    negative mean training loss, unless ``select=False``: then no fitness, no ``best.pt`` and no early stopping (the
    last epoch's weights are the result). ``observe(model) -> metrics`` scores the EMA weights each epoch for the
    log only (``record["observed"]``). ``on_epoch(record)`` receives each epoch's record (the runner appends it to
    ``log.jsonl``).
    """

    def __init__(
        self,
        model: nn.Module,
        dataset: TrainDataset,
        settings: TrainSettings,
        input_kind: str = "single",
        thermal_channels: int = 3,
        checkpoint_dir: str | Path | None = None,
        validate: Callable[[nn.Module], Mapping[str, Any]] | None = None,
        on_epoch: Callable[[dict[str, Any]], None] | None = None,
        progress: bool = True,
        config_hash: str = "",
        name: str = "model",
        observe: Callable[[nn.Module], Mapping[str, Any] | None] | None = None,
        select: bool = True,
    ):
        self.model, self.dataset, self.s = model, dataset, settings
        self.input_kind, self.thermal_channels = input_kind, thermal_channels
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir is not None else None
        self.validate, self.on_epoch, self.progress = validate, on_epoch, progress
        self.config_hash, self.name = config_hash, name
        self.observe, self.select = observe, select
        self.dist = hd.info()
        self.device = select_device(settings.device)
        if self.dist.active and self.device.type == "cuda":
            self.device = torch.device("cuda", self.dist.local_rank)
        self.ema: ModelEMA | None = None
        self.flat: FlatState | None = None

    # ------------------------------------------------------------------ paths
    @property
    def last_path(self) -> Path | None:
        return self.checkpoint_dir / "last.pt" if self.checkpoint_dir else None

    @property
    def best_path(self) -> Path | None:
        return self.checkpoint_dir / "best.pt" if self.checkpoint_dir else None

    @property
    def eval_model(self) -> nn.Module:
        """The weights that are validated and kept: the EMA when enabled, else the model."""
        return self.ema.module if self.ema is not None else self.model

    # ------------------------------------------------------------------ the loop
    def fit(self, resume: bool = True) -> TrainResult:
        try:
            return self._fit(resume)
        finally:
            for m in (self.model, self.ema.module if self.ema is not None else None):
                if m is not None:
                    pointwise_convs_on_onednn(m, False)

    def _fit(self, resume: bool) -> TrainResult:
        s = self.s
        set_threads(s.threads)
        if self.device.type == "cpu":
            keep_freed_memory()
        model = self.model.to(self.device)
        if s.channels_last:
            model = model.to(memory_format=torch.channels_last)
            if self.device.type == "cpu":
                pointwise_convs_on_onednn(model, True)
        amp = bool(s.amp and self.device.type == "cuda")
        d = self.dist
        main = d.is_main
        batch = s.batch
        if d.active:
            batch = max(1, s.batch // d.world_size)
            if s.batch % d.world_size:
                log.warning(
                    "train.batch=%d is not a multiple of %d processes; each process takes %d images",
                    s.batch,
                    d.world_size,
                    batch,
                )
        loader = train_loader(
            self.dataset, batch, s.workers, s.seed, max_images=s.max_images, rank=d.rank, world=d.world_size
        )
        nb = len(loader)
        accumulate_target = optim.accumulate_steps(s.batch, s.nominal_batch)
        wd = optim.scaled_weight_decay(s.weight_decay, s.batch, accumulate_target, s.nominal_batch)
        opt: Any = optim.build_optimizer(model, s.optimizer, s.lr0, s.momentum, wd)
        self.flat = flat_buffers(model, opt, self.device, d.active, self.name)
        if self.flat is not None:
            opt = FlatOptimizer(opt, self.flat)
        scaler = torch.amp.GradScaler(self.device.type, enabled=amp)
        self.ema = ModelEMA(model, s.ema_decay, s.ema_tau, flat=self.flat) if s.ema else None
        nw = optim.warmup_iterations(s.warmup_epochs, nb, s.warmup_min_iters)

        start_epoch, best_fit, best_epoch, history, resumed_from = 0, None, None, [], None
        last_opt_step = -1
        if resume and self.last_path is not None and self.last_path.exists():
            state = ckpt.load(self.last_path)
            if state.get("config_hash", "") != self.config_hash:
                log.warning("%s was written by a different configuration; starting this run again", self.last_path)
            else:
                try:  # a last.pt that reads as plain tensors may still not fit: a clear error, not a traceback
                    model.load_state_dict(state["model"])
                    opt.load_state_dict(state["optimizer"])
                    if state.get("scaler"):
                        scaler.load_state_dict(state["scaler"])
                    if self.ema is not None and state.get("ema"):
                        self.ema.load_state_dict(state["ema"])
                    ckpt.set_rng_state(state["rng"])
                    start_epoch = int(state["epoch"]) + 1
                    best_fit, best_epoch = state.get("best_fitness"), state.get("best_epoch")
                    history = list(state.get("history", []))
                    if not all(isinstance(h, dict) for h in history):
                        raise TypeError("its history is not a list of epoch records")
                    last_opt_step = int(state.get("last_opt_step", start_epoch * nb - 1))
                except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError) as exc:
                    raise ckpt.CheckpointError(
                        f"{self.last_path}: cannot resume from it ({type(exc).__name__}: "
                        f"{(str(exc).splitlines() or [''])[0][:160]}); delete it to train this run from the start"
                    ) from None
                resumed_from = start_epoch
                if state.get("done"):
                    log.info("%s: training already complete (%d epochs)", self.name, start_epoch)
                    return self._result(
                        start_epoch, best_epoch, best_fit, bool(state.get("stopped_early")), 0.0, history, resumed_from
                    )
                log.info("%s: resuming after epoch %d of %d", self.name, start_epoch, s.epochs)

        train_model: nn.Module = model
        if d.active:  # after resuming, so that every process wraps the same weights
            from torch.nn.parallel import DistributedDataParallel

            # some detectors keep parameters their forward never uses (ICAFusion's checkpoint layout has such
            # layers): DDP must then look for unused parameters at every step, or it waits for their gradients
            unused = self._unused_parameters(model, loader, start_epoch, amp)
            if unused:
                log.info(
                    "%s: %d parameters get no gradient (e.g. %s); DDP looks for unused parameters every step",
                    self.name,
                    len(unused),
                    unused[0],
                )
            train_model = DistributedDataParallel(
                model,
                device_ids=[self.device.index] if self.device.type == "cuda" else None,
                find_unused_parameters=bool(hd.any_process(bool(unused))),
            )

        t_start = time.perf_counter()
        stopped_early = False
        epoch = start_epoch - 1
        with progress_bar(self.name, enabled=self.progress and main, eta=True, note=True) as bar:
            for epoch in range(start_epoch, s.epochs):
                t0 = time.perf_counter()
                mosaic = epoch < s.epochs - s.close_mosaic
                self.dataset.set_epoch(epoch, mosaic=mosaic)
                loader.sampler.set_epoch(epoch)  # type: ignore[attr-defined]
                model.train()
                factor = optim.lr_factor(epoch, s.epochs, s.lrf, s.cos_lr)
                for g in opt.param_groups:
                    g["lr"] = g["initial_lr"] * factor
                sums: dict[str, float] = {}
                seen = 0
                pending = False
                bar.restart(f"{self.name} {epoch + 1}/{s.epochs}", total=nb)
                for i, batch in enumerate(loader):
                    ni = i + nb * epoch
                    accumulate = accumulate_target
                    if ni <= nw and nw > 0:
                        accumulate = max(1, round(optim.interp(ni, nw, 1, s.nominal_batch / s.batch)))
                        for g in opt.param_groups:
                            start = s.warmup_bias_lr if g["name"] == "bias" else 0.0
                            g["lr"] = optim.interp(ni, nw, start, g["initial_lr"] * factor)
                            optim.set_momentum(g, optim.interp(ni, nw, s.warmup_momentum, s.momentum))
                    inputs = to_inputs(
                        batch.images, self.input_kind, self.thermal_channels, self.device, s.channels_last
                    )
                    targets = targets_to(batch.targets, self.device)
                    with torch.autocast(self.device.type, enabled=amp):
                        losses = train_model(inputs, targets)
                    loss = self._total(losses, epoch, i)
                    if d.active:  # DDP averages gradients over processes; the loss is a sum over images
                        loss = loss * d.world_size
                    scaler.scale(loss).backward()
                    pending = True
                    for k, v in losses.items():
                        sums[k] = sums.get(k, 0.0) + float(v.detach())
                    seen += len(batch)
                    if ni - last_opt_step >= accumulate:
                        self._step(model, opt, scaler)
                        last_opt_step, pending = ni, False
                    bar.advance(1, note=" ".join(f"{k} {v / (i + 1):.3f}" for k, v in sums.items()))
                if pending:  # every epoch ends on an optimiser step, so a checkpoint never holds half-summed gradients
                    self._step(model, opt, scaler)
                    last_opt_step = nb * (epoch + 1) - 1

                mean_losses = hd.all_reduce_mean({k: v / max(nb, 1) for k, v in sums.items()})
                seen *= d.world_size
                metrics = None
                validated = self.validate is not None and ((epoch + 1) % s.val_period == 0 or epoch + 1 == s.epochs)
                if validated:
                    metrics = dict(self._validate())
                    fit = fitness(metrics)
                elif self.validate is None and self.select:
                    fit = -sum(mean_losses.values())
                else:
                    fit = None
                observed = None
                if self.observe is not None and ((epoch + 1) % s.val_period == 0 or epoch + 1 == s.epochs):
                    observed = self._validate(self.observe)
                improved = fit is not None and (best_fit is None or fit > best_fit)
                if improved:
                    best_fit, best_epoch = fit, epoch + 1
                    if self.best_path is not None and main:
                        ckpt.save(
                            self.best_path,
                            {
                                "format": ckpt.FORMAT,
                                "version": ckpt.VERSION,
                                "epoch": epoch,
                                "model": _cpu_state(self.eval_model),
                                "fitness": fit,
                                "config_hash": self.config_hash,
                            },
                        )
                dt = time.perf_counter() - t0
                record = {
                    "epoch": epoch + 1,
                    "epochs": s.epochs,
                    "time_s": round(dt, 3),
                    "images_per_s": round(seen / dt, 2) if dt > 0 else None,
                    "lr": {g["name"]: g["lr"] for g in opt.param_groups},
                    "mosaic": mosaic,
                    "loss": {k: round(v, 5) for k, v in mean_losses.items()},
                    "metrics": _brief(metrics),
                    **(
                        {"observed": _brief(observed), "observed_fitness": fitness(observed) if observed else None}
                        if self.observe is not None
                        else {}
                    ),
                    "fitness": fit,
                    "best_fitness": best_fit,
                    "best_epoch": best_epoch,
                    "improved": improved,
                }
                history.append(record)
                if main:
                    log.info(_line(record, self.name))
                stopped_early = (
                    best_epoch is not None and (epoch + 1) - best_epoch >= s.patience and epoch + 1 < s.epochs
                )
                done = stopped_early or epoch + 1 == s.epochs
                if self.last_path is not None and main:
                    ckpt.save(
                        self.last_path,
                        {
                            "format": ckpt.FORMAT,
                            "version": ckpt.VERSION,
                            "epoch": epoch,
                            "done": done,
                            "stopped_early": stopped_early,
                            "model": _cpu_state(model),
                            "optimizer": opt.state_dict(),
                            "scaler": scaler.state_dict() if amp else None,
                            "ema": self.ema.state_dict() if self.ema is not None else None,
                            "rng": ckpt.rng_state(),
                            "best_fitness": best_fit,
                            "best_epoch": best_epoch,
                            "history": history,
                            "last_opt_step": last_opt_step,
                            "config_hash": self.config_hash,
                            "settings": asdict(s),
                        },
                    )
                if self.on_epoch is not None and main:  # after the checkpoint: a resumed run never logs an epoch twice
                    self.on_epoch(record)
                if stopped_early:
                    log.info(
                        "%s: no better fitness for %d epochs, stopping after epoch %d (best: epoch %d)",
                        self.name,
                        s.patience,
                        epoch + 1,
                        best_epoch,
                    )
                    break
        hd.barrier()  # the other processes may now read what rank 0 wrote (best.pt)
        return self._result(
            epoch + 1, best_epoch, best_fit, stopped_early, time.perf_counter() - t_start, history, resumed_from
        )

    # ------------------------------------------------------------------ pieces
    def _total(self, losses: Any, epoch: int, i: int) -> torch.Tensor:
        from harness.contracts import check_losses

        check_losses(losses, self.name, finite=False)  # a loss gone NaN is said below, with what to try
        loss = sum(v.sum() for v in losses.values())
        if not torch.isfinite(loss):
            bad = [k for k, v in losses.items() if not torch.isfinite(v).all()]
            raise TrainingError(
                f"{self.name}: loss {', '.join(bad)} became {float(loss.detach())} at epoch {epoch + 1}, "
                f"iteration {i + 1}; "
                f"try a lower train.lr0, a longer train.warmup_epochs, or train.amp=false"
            )
        return loss

    def _step(self, model: nn.Module, opt: Any, scaler: torch.amp.GradScaler) -> None:
        scaler.unscale_(opt)
        if self.s.clip_grad and self.s.clip_grad > 0:
            if self.flat is not None:
                self.flat.clip_grad_norm_(self.s.clip_grad)
            else:
                torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm=self.s.clip_grad)
        scaler.step(opt)
        scaler.update()
        opt.zero_grad(set_to_none=True)
        if self.ema is not None:
            self.ema.update(model)

    def _unused_parameters(self, model: nn.Module, loader: Any, epoch: int, amp: bool) -> list[str]:
        """Names of the trainable parameters that get no gradient from one training step on this process's first
        batch, found on a copy of the model; the random generators are restored, so training is unaffected."""
        import copy

        from harness.engine.data import collate

        s = self.s
        self.dataset.set_epoch(epoch, mosaic=epoch < s.epochs - s.close_mosaic)
        loader.sampler.set_epoch(epoch)
        order = loader.sampler.order()[: loader.batch_size]
        batch = collate([self.dataset[k] for k in order])
        cpu_rng = torch.get_rng_state()
        cuda_rng = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
        probe = copy.deepcopy(model).train()
        try:
            inputs = to_inputs(batch.images, self.input_kind, self.thermal_channels, self.device, s.channels_last)
            with torch.autocast(self.device.type, enabled=amp):
                losses = probe(inputs, targets_to(batch.targets, self.device))
            self._total(losses, epoch, 0).backward()
            return [n for n, p in probe.named_parameters() if p.requires_grad and p.grad is None]
        finally:
            del probe
            torch.set_rng_state(cpu_rng)
            if cuda_rng is not None:
                torch.cuda.set_rng_state_all(cuda_rng)

    def _validate(self, score: Callable[[nn.Module], Any] | None = None) -> Mapping[str, Any]:
        m = self.eval_model
        was_training = m.training
        m.eval()
        try:
            score = score or self.validate
            assert score is not None
            if self.s.fused_validation:
                m = inference_copy(m)
            # under torchrun rank 0 scores the gathered predictions; every process takes its metrics
            return hd.broadcast_object(score(m))
        finally:
            self.eval_model.train(was_training)

    def _result(
        self,
        epochs_run: int,
        best_epoch: int | None,
        best_fit: float | None,
        stopped: bool,
        t: float,
        history: list[dict[str, Any]],
        resumed_from: int | None,
    ) -> TrainResult:
        return TrainResult(
            epochs_run=epochs_run,
            best_epoch=best_epoch,
            best_fitness=best_fit,
            stopped_early=stopped,
            time_s=round(sum(r.get("time_s", 0.0) for r in history), 3) if history else t,
            history=history,
            best_path=str(self.best_path) if self.best_path and self.best_path.exists() else None,
            last_path=str(self.last_path) if self.last_path and self.last_path.exists() else None,
            resumed_from=resumed_from,
            device=str(self.device),
            plateau=(
                plateau(history)
                if self.validate is not None
                else plateau(history, key="observed_fitness")
                if self.observe is not None
                else None
            ),
        )


def pointwise_convs_on_onednn(model: nn.Module, on: bool) -> int:
    """Route the model's 1x1 convolutions through oneDNN (``on``) or back; returns how many were changed.

    On one thread ATen computes a 1x1, stride-1 convolution of a batch under 16 with its own GEMM path, which takes
    NCHW only: in channels-last training every such call converts its input and output and the backward pass its
    gradients. A dilation means nothing to a 1x1 kernel (its one tap is the same), but a dilated convolution goes to
    oneDNN, which works in channels-last. Measured on the YOLOv8s step at 640 px, batch 2, one thread: about 0.8x the
    NCHW step with AVX-512 with this, 0.9x without (with AVX2 channels-last does not pay: 1.03x and 1.11x). The
    original dilation is restored when training ends."""
    changed = 0
    for m in model.modules():
        if not isinstance(m, nn.Conv2d):
            continue
        if (
            on
            and m.kernel_size == (1, 1)
            and m.stride == (1, 1)
            and m.padding in ((0, 0), "valid")
            and m.dilation == (1, 1)
            and m.padding_mode == "zeros"
        ):
            m.dilation, m._onednn_pointwise = (2, 2), True
            changed += 1
        elif not on and getattr(m, "_onednn_pointwise", False):
            m.dilation = (1, 1)
            del m._onednn_pointwise
            changed += 1
    return changed


def flat_buffers(
    model: nn.Module, opt: torch.optim.Optimizer, device: torch.device, distributed: bool = False, name: str = "model"
) -> FlatState | None:
    """Flat buffers for the optimiser step and the EMA (``harness.engine.flat``) on a CPU in one process, when the
    model and the optimiser allow them; None (torch's optimiser and the per-tensor EMA) otherwise."""
    if device.type != "cpu" or distributed:
        return None
    groups = [g["params"] for g in opt.param_groups]
    why = FlatState.reason(model, groups) or FlatOptimizer.reason(opt)
    if why:
        log.debug("%s: per-tensor optimiser step (%s)", name, why)
        return None
    return FlatState(model, groups)


def inference_copy(model: nn.Module) -> nn.Module:
    """An eval-mode copy of ``model`` with BatchNorm folded into the convolutions by the model's declared fold
    (``harness.contracts.fold_batchnorm``), frozen; ``model`` itself when it declares no fold. The random generators
    are left as they were (a fold that builds layers draws their initial weights)."""
    import copy
    import inspect

    from harness.contracts import FUSE_HOOK, fold_batchnorm

    declared = any(inspect.isfunction(inspect.getattr_static(type(model), n, None)) for n in (FUSE_HOOK, "fuse"))
    if not declared or not any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in model.modules()):
        return model
    cpu_rng = torch.get_rng_state()  # a fold that builds new layers draws their initial weights: training's
    cuda_rng = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None  # dropout must not notice
    try:
        folded, ok = fold_batchnorm(copy.deepcopy(model).eval())
    finally:
        torch.set_rng_state(cpu_rng)
        if cuda_rng is not None:
            torch.cuda.set_rng_state_all(cuda_rng)
    if not ok:
        return model
    return folded.eval().requires_grad_(False)


def _cpu_state(model: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}


def _brief(metrics: Mapping[str, Any] | None) -> dict[str, Any] | None:
    if metrics is None:
        return None
    return {k: metrics[k] for k in ("precision", "recall", "mAP50", "mAP50_95", "AP50_per_category") if k in metrics}


def _line(r: Mapping[str, Any], name: str) -> str:
    loss = " ".join(f"{k} {v:.3f}" for k, v in r["loss"].items())
    parts = [
        f"{name} epoch {r['epoch']}/{r['epochs']}",
        f"loss {sum(r['loss'].values()):.3f} ({loss})",
        f"lr {max(r['lr'].values()):.5f}",
    ]
    m = r.get("metrics")
    if m:
        parts.append(
            f"P {m.get('precision', math.nan):.3f} R {m.get('recall', math.nan):.3f} "
            f"mAP50 {m.get('mAP50', math.nan):.3f} mAP50:95 {m.get('mAP50_95', math.nan):.3f}"
        )
    o = r.get("observed")
    if o:
        parts.append(f"observed mAP50:95 {o.get('mAP50_95', math.nan):.3f}")
    if r.get("fitness") is not None:
        parts.append(f"fitness {r['fitness']:.4f}{' *' if r['improved'] else ''}")
    parts.append(f"{r['time_s']:.1f} s")
    return "  ".join(parts)
