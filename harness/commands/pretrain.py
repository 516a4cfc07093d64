"""``harness pretrain``: train a detector on a pretraining dataset (M3FD by default) and hand its checkpoint to
``harness run --init`` for fine-tuning.

Pretraining is an ordinary run in the results store (``<store>/m3fd/<detector>/<encoding>/val/seed<k>/``): it
trains on the dataset's training groups, selects the best epoch on its held-out fold, and is skipped when it
already finished with the same configuration. In the run folder it writes ``pretrain.json``, which records
what the input channels meant, because that changes at fine-tuning (docs/datasets.md, "Pretraining on M3FD"):

* 4th channel in pretraining: the dataset's encoding, by default ``ir8`` (8-bit infrared *intensity*);
* 4th channel on M3T: ``c2`` (signed local radiometric *contrast*) unless ``--encoding`` says otherwise.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Unpack

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl
from harness.io import file_digest

if TYPE_CHECKING:
    from harness.runner import RunSettings

log = logging.getLogger(__name__)

#: What each encoding puts in the extra channel, in words (for pretrain.json and the printed hint).
CHANNEL_MEANING = {
    "ir8": "8-bit thermal intensity (bright = warm, per-image camera gain)",
    "proxy8": "local contrast of the 8-bit thermal intensity (0.5 = local background)",
    "c2": "signed local radiometric contrast from temperatures in C (0.5 = local background temperature)",
    "linear16": "temperature in C, linearly scaled",
    "none": "no extra channel (RGB only)",
}


@dataclass
class PretrainResult:
    checkpoint: Path
    record: dict[str, Any]
    state: str


def pretrain(
    detector: str,
    dataset: str = "m3fd",
    encoding: str | None = None,
    fold: str | None = None,
    seed: int = 0,
    *,
    out: str | Path | None = None,
    **settings: Unpack[RunSettings],
) -> PretrainResult:
    """Train ``detector`` on ``dataset``'s training groups and return the checkpoint for ``harness run --init``
    (``settings`` as for ``harness run``; ``out``: also copy the checkpoint there)."""
    from harness.errors import ConfigError, StoreError
    from harness.io import atomic_write_json
    from harness.plugins import get_host
    from harness.runner import RunRequest, resolve_config, run

    host = get_host()
    spec = host.dataset(dataset)
    request = RunRequest(detector, dataset, encoding, "all" if fold is None else fold, [seed], **settings)
    if fold is None:
        folds = resolve_config(request, None, spec)["protocol"].get("folds") or {}
        if len(folds) > 1:
            raise ConfigError(
                f"dataset {dataset!r} has folds {', '.join(folds)}; choose the one to select on with --folds"
            )
        fold = next(iter(folds), "all")
        request = replace(request, folds=fold)
    summary = run(request)
    if len(summary.results) != 1:
        raise ConfigError(
            f"pretraining needs exactly one fold of {dataset!r}; {fold!r} selected {len(summary.results)}; use --folds"
        )
    result = summary.results[0]
    ckpt_dir = Path(result.path) / "checkpoints"
    checkpoint = next((p for p in (ckpt_dir / "best.pt", ckpt_dir / "last.pt") if p.exists()), None)
    if checkpoint is None:
        raise StoreError(f"{ckpt_dir}: the pretraining run finished but left no best.pt or last.pt")
    det = host.detector(detector)
    metrics = result.metrics.get("metrics", {})
    record = {
        "detector": detector,
        "input_kind": det.input_kind,
        "dataset": dataset,
        "categories": summary.categories,
        "encoding": summary.encoding,
        "extra_channel": CHANNEL_MEANING.get(summary.encoding, summary.encoding),
        "fold": result.key.fold,
        "seed": seed,
        "train_images": result.train_images,
        "val_images": result.val_images,
        "val_mAP50": metrics.get("mAP50"),
        "val_mAP50_95": metrics.get("mAP50_95"),
        "checkpoint": str(checkpoint),
        "checkpoint_sha1": file_digest(checkpoint),
        "fine_tuning": (
            f"`harness run --init {checkpoint}` loads it through the detector's importer (else by tensor name and "
            f"shape): backbone, neck and box regression carry over; the class outputs, sized for "
            f"{len(summary.categories)} classes, are re-initialised when the target dataset has another number (the "
            f"run's metrics.json lists what was loaded under train.init). The extra input channel meant "
            f"'{CHANNEL_MEANING.get(summary.encoding, summary.encoding)}' here; on M3T it is the run's encoding (c2 "
            f"by default: '{CHANNEL_MEANING['c2']}'), so the first layer's filters for it adapt during fine-tuning."
        ),
    }
    atomic_write_json(Path(result.path) / "pretrain.json", record)
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        shutil.copyfile(checkpoint, tmp)
        tmp.replace(out)
        atomic_write_json(
            out.with_name(out.name + ".json"), {**record, "copied_from": str(checkpoint), "checkpoint": str(out)}
        )
        checkpoint = out
    return PretrainResult(checkpoint, record, result.state)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="pretrain")
    @click.option("--detector", required=True, help="Detector name (see `harness list`).")
    @click.option("--dataset", default="m3fd", show_default=True, help="Pretraining dataset.")
    @click.option(
        "--encoding",
        default=None,
        help="Extra-channel encoding [default: the dataset's, ir8 for m3fd; proxy8 is closer to c2].",
    )
    @opt.folds_option(
        one=True,
        default=None,
        old=("--fold",),
        help="Held-out fold to select the checkpoint on [default: the protocol's only fold].",
    )
    @opt.seeds_option(one=True, default=0, old=("--seed",), help="The training seed of the pretraining run.")
    @opt.profile_option()
    @opt.config_options()
    @opt.store_option()
    @click.option("--out", type=click.Path(dir_okay=False), default=None, help="Also copy the checkpoint here.")
    @opt.input_file_option(
        "--init", help="Start from these weights (e.g. `harness weights import` output, COCO-pretrained)."
    )
    @click.option("--force", is_flag=True, help="Redo the pretraining run even if it finished.")
    @opt.no_progress_option()
    def pretrain_cmd(
        detector: str, dataset: str, encoding: str | None, folds: str | None, seeds: int, **settings: Any
    ) -> None:
        """Pretrain DETECTOR on DATASET (M3FD) and print the checkpoint to fine-tune from.

        \b
        Example:
          harness pretrain --detector ours --dataset m3fd --profile paper
          harness run --detector ours --dataset m3t --init <printed checkpoint>
        """
        from harness.progress import progress_on

        res = pretrain(detector, dataset, encoding, folds, seeds, progress=progress_on(), **settings)
        r = res.record
        click.echo(
            f"pretrained {r['detector']} on {r['dataset']} ({r['train_images']} train / {r['val_images']} val "
            f"images, encoding {r['encoding']}): val mAP50 {_fmt(r['val_mAP50'])}, mAP50:95 "
            f"{_fmt(r['val_mAP50_95'])} [{res.state}]"
        )
        click.echo(f"checkpoint: {res.checkpoint}")
        click.echo(f"fine-tune:  harness run --detector {r['detector']} --dataset m3t --init {res.checkpoint}")
        record_path = Path(r["checkpoint"]).parent.parent / "pretrain.json"
        click.echo(f"note: the extra channel was '{r['extra_channel']}' here; see {record_path}")


def _fmt(v: Any) -> str:
    return "-" if v is None else f"{100 * float(v):.1f}%"
