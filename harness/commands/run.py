"""``harness run`` (train and evaluate every fold and seed) and ``harness ablate`` (the encoding ablation)."""

from __future__ import annotations

import os
from typing import Any

import click

# Training runs on CPUs that other processes share (CI runners, laptops): OpenMP threads that spin while they wait
# for a busy core slow every step down several times over. Passive waiting costs little on an idle machine. It must
# be set before torch is first imported, which the commands below do lazily; an explicit setting is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from harness.commands import options as opt  # noqa: E402
from harness.hookspecs import hookimpl  # noqa: E402

_split = opt.split_list


def _common(f):
    """The options ``run``, ``ablate`` and ``sweep`` share (applied bottom-up, so they list in this order)."""
    options = [
        opt.profile_option(),
        opt.config_options(),
        opt.seeds_option(),
        opt.store_option(),
        click.option("--force", is_flag=True, help="Redo runs that already finished."),
        opt.no_progress_option(),
        click.option(
            "--log-to",
            "log_to",
            default=None,
            metavar="LOGGERS",
            help="Also log runs to these trackers, e.g. mlflow,tensorboard (same as --set "
            "tracking.loggers=[...]; built in: tensorboard, mlflow).",
        ),
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


def _keep_weights_option(f):
    """``--keep-weights all|final`` -> ``RunRequest.keep_weights`` (``harness.store.KEEP_WEIGHTS``)."""
    return opt.choice_option(
        "--keep-weights",
        "keep_weights",
        choices=("all", "final"),
        help="Checkpoints a finished run keeps: all (last.pt, to resume from, and best.pt) or final (only the "
        "weights that predicted the held-out fold, which `harness screen --run` loads; a report reads none). "
        "Runs finished earlier are trimmed too.",
    )(f)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="run")
    @click.option("--detector", required=True, help="Detector name (see `harness list`).")
    @click.option("--dataset", required=True, help="Dataset name (see `harness list`).")
    @click.option(
        "--encoding",
        default=None,
        help="Encoding of the extra channel [default: the dataset's, or the detector's for dual-stream].",
    )
    @opt.folds_option()
    @opt.input_file_option(
        "--init", help="Initialise the model from this checkpoint (a harness best.pt/last.pt or a state dict)."
    )
    @click.option("--root", default=None, help="Dataset folder (same as --set dataset.root=...).")
    @_keep_weights_option
    @_common
    def run_cmd(root: str | None, overrides: tuple[str, ...], **request: Any) -> None:
        """Train and evaluate DETECTOR on every selected fold and seed of DATASET.

        Finished runs with the same configuration are skipped, interrupted ones resume from their last checkpoint.
        Prints the per-fold table (mean ± sample SD) and the per-category table; everything is written to the
        results store (results/<profile>/<dataset>/<detector>/<encoding>/<fold>/seed<k>/).

        \b
        Example:
          harness run --detector ours --dataset m3t-synth --folds all --profile smoke
        """
        from harness import distributed as hd
        from harness.progress import progress_on
        from harness.report.run_tables import category_table, fold_table
        from harness.runner import RunRequest, run

        try:
            overrides = (*overrides, *([f"dataset.root={root}"] if root else []))
            summary = run(RunRequest(overrides=overrides, progress=progress_on(), **request))
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
    @click.option(
        "--encodings", default="none,ir8,linear16,c2", show_default=True, help="Comma-separated encodings to compare."
    )
    @opt.folds_option(one=True, required=True, help="The one fold to train and evaluate, e.g. P4+P5.", old=("--fold",))
    @click.option(
        "--categories",
        default="delamination,water seepage",
        show_default=True,
        help="Categories whose AP50 gets a column.",
    )
    @_keep_weights_option
    @_common
    def ablate_cmd(
        detector: str, dataset: str, encodings: str, folds: str, categories: str, seeds: str | None, **settings: Any
    ) -> None:
        """The encoding ablation: train DETECTOR on one fold once per encoding and compare.

        Prints P, R, mAP50, mAP50:95 and the AP50 of the chosen categories per encoding (the seed's ablation
        table). The runs are ordinary runs in the results store, so finished ones are reused.

        \b
        Example:
          harness ablate --detector ours --dataset m3t-synth --encodings none,ir8,linear16,c2 \\
              --folds P4+P5
        """
        from harness.progress import progress_on
        from harness.report.run_tables import ablation_table
        from harness.runner import ablate, parse_seeds

        ab = ablate(
            detector,
            dataset,
            _split(encodings),
            folds,
            parse_seeds(seeds),
            categories=_split(categories),
            progress=progress_on(),
            **settings,
        )
        click.echo(ablation_table(ab))
