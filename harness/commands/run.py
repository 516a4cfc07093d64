"""``harness run`` (train and evaluate every fold and seed) and ``harness ablate`` (the encoding ablation)."""

from __future__ import annotations

import os

import click

# Training runs on CPUs that other processes share (CI runners, laptops): OpenMP threads that spin while they wait
# for a busy core slow every step down several times over. Passive waiting costs little on an idle machine. It must
# be set before torch is first imported, which the commands below do lazily; an explicit setting is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from harness.hookspecs import hookimpl


def _split(text: str | None) -> list[str]:
    return [t.strip() for t in (text or "").split(",") if t.strip()]


def _common(f):
    """The options ``run`` and ``ablate`` share (applied bottom-up, so they list in this order)."""
    options = [
        click.option("--profile", default="smoke", show_default=True,
                     help="Run profile under configs/profiles/: smoke (small, CPU) or paper (the seed's protocol)."),
        click.option("--config", "config_files", multiple=True, type=click.Path(dir_okay=False),
                     help="Extra YAML config file(s), applied after the profile."),
        click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
                     help="Override one config key, e.g. --set protocol.epochs=5 (repeatable)."),
        click.option("--seeds", default=None, help="Comma-separated seeds [default: protocol.seeds]."),
        click.option("--store", type=click.Path(file_okay=False), default=None,
                     help="Results store root [default: results/<profile>]."),
        click.option("--force", is_flag=True, help="Redo runs that already finished."),
        click.option("--no-progress", is_flag=True, help="No progress bars (log lines only)."),
        click.option("--log-to", "log_to", default=None, metavar="LOGGERS",
                     help="Also log runs to these trackers, e.g. mlflow,tensorboard (same as --set "
                          "tracking.loggers=[...]; built in: tensorboard, mlflow)."),
    ]
    f = _with_log_to(f)
    for option in reversed(options):
        f = option(f)
    return f


def _with_log_to(f):
    """``--log-to A,B`` becomes the override ``tracking.loggers=[A,B]`` appended to ``--set``."""
    import functools

    @functools.wraps(f)
    def wrapper(*args, log_to=None, overrides=(), **kwargs):
        from harness.tracking import log_to_overrides

        return f(*args, overrides=(*overrides, *log_to_overrides(log_to)), **kwargs)

    return wrapper


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="run")
    @click.option("--detector", required=True, help="Detector name (see `harness list`).")
    @click.option("--dataset", required=True, help="Dataset name (see `harness list`).")
    @click.option("--encoding", default=None,
                  help="Encoding of the extra channel [default: the dataset's, or the detector's for dual-stream].")
    @click.option("--folds", default="all", show_default=True, help="'all' or comma-separated fold names, e.g. P1,P4+P5.")
    @click.option("--init", type=click.Path(dir_okay=False, exists=True), default=None,
                  help="Initialise the model from this checkpoint (a harness best.pt/last.pt or a state dict).")
    @click.option("--root", default=None, help="Dataset folder (same as --set dataset.root=...).")
    @_common
    def run_cmd(detector, dataset, encoding, folds, init, root, profile, config_files, overrides, store, seeds, force,
                no_progress):
        """Train and evaluate DETECTOR on every selected fold and seed of DATASET.

        Finished runs with the same configuration are skipped, interrupted ones resume from their last checkpoint.
        Prints the per-fold table (mean ± sample SD) and the per-category table; everything is written to the
        results store (results/<profile>/<dataset>/<detector>/<encoding>/<fold>/seed<k>/).

        \b
        Example:
          harness run --detector ours --dataset m3t-synth --folds all --profile smoke
        """
        from harness import distributed as hd
        from harness.report.run_tables import category_table, fold_table
        from harness.runner import RunRequest, run

        try:
            overrides = (*overrides, *([f"dataset.root={root}"] if root else []))
            summary = run(RunRequest(detector=detector, dataset=dataset, encoding=encoding, folds=folds, seeds=seeds,
                                     profile=profile, config_files=config_files, overrides=overrides, store=store,
                                     force=force, init=init, progress=not no_progress))
            if not hd.is_main():  # under torchrun rank 0 prints the tables
                return
        finally:
            hd.shutdown()
        click.echo(fold_table(summary))
        click.echo()
        click.echo(category_table(summary))
        click.echo(f"\nresults: {summary.store}")

    @cli.command(name="ablate")
    @click.option("--detector", default="ours", show_default=True, help="Detector name.")
    @click.option("--dataset", required=True, help="Dataset name.")
    @click.option("--encodings", default="none,ir8,linear16,c2", show_default=True,
                  help="Comma-separated encodings to compare.")
    @click.option("--fold", required=True, help="The one fold to train and evaluate, e.g. P4+P5.")
    @click.option("--categories", default="delamination,water seepage", show_default=True,
                  help="Categories whose AP50 gets a column.")
    @_common
    def ablate_cmd(detector, dataset, encodings, fold, categories, profile, config_files, overrides, store, seeds,
                   force, no_progress):
        """The encoding ablation: train DETECTOR on one fold once per encoding and compare.

        Prints P, R, mAP50, mAP50:95 and the AP50 of the chosen categories per encoding (the seed's ablation
        table). The runs are ordinary runs in the results store, so finished ones are reused.

        \b
        Example:
          harness ablate --detector ours --dataset m3t-synth --encodings none,ir8,linear16,c2 --fold P4+P5
        """
        from harness.report.run_tables import ablation_table
        from harness.runner import ablate, parse_seeds

        ab = ablate(detector, dataset, _split(encodings), fold, seeds=parse_seeds(seeds), profile=profile,
                    config_files=config_files, overrides=overrides, store=store, force=force,
                    progress=not no_progress, categories=_split(categories))
        click.echo(ablation_table(ab))
