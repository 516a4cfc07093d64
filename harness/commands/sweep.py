"""``harness sweep``: many runs (detectors x datasets x encodings x folds x seeds) on one machine, Ray or Slurm."""

from __future__ import annotations

import os
from typing import Any

import click

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `harness run`: set before torch is first imported

from harness.commands import options as opt  # noqa: E402
from harness.commands.run import _common, _split  # noqa: E402  (the options run and ablate share)
from harness.hookspecs import hookimpl  # noqa: E402


def _key_values(items: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    from harness.errors import ConfigError

    out = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--slurm-opt {item!r}: expected KEY=VALUE, e.g. constraint=a100")
        k, v = item.split("=", 1)
        out.append((k.strip(), v.strip()))
    return tuple(out)


def _executor_options(command: Any) -> Any:
    """The options that set ``harness.sweep.ExecutorOptions`` (resources per run, Ray and Slurm settings), in the order
    of ``--help``. Each passes its field by name (``sweep_cmd``'s ``resources``), except ``--slurm-setup``,
    ``--slurm-opt`` and ``--submitit-cluster``, which the command turns into ``slurm_setup``, ``slurm_extra`` and
    ``cluster``."""
    return opt.stack(
        click.option("--cpus-per-run", type=int, default=1, show_default=True, help="CPUs per run (ray, slurm)."),
        click.option(
            "--gpus-per-run",
            type=int,
            default=None,
            help="GPUs per run (ray, slurm) [default: 1 where there are GPUs, else 0].",
        ),
        click.option(
            "--ray-address",
            default=None,
            help="Ray cluster to join, e.g. auto or ray://host:10001 [default: $RAY_ADDRESS, else a local one].",
        ),
        click.option("--slurm-partition", "partition", default=None, help="Slurm partition."),
        click.option("--slurm-account", "account", default=None, help="Slurm account."),
        click.option("--slurm-qos", "qos", default=None, help="Slurm QOS."),
        click.option(
            "--slurm-time",
            "timeout_min",
            type=int,
            default=24 * 60,
            show_default=True,
            help="Time limit per run, minutes.",
        ),
        click.option("--slurm-mem-gb", "mem_gb", type=float, default=None, help="Memory per run, GB."),
        click.option(
            "--slurm-array-parallelism",
            "array_parallelism",
            type=int,
            default=16,
            show_default=True,
            help="At most this many runs of the job array at once.",
        ),
        click.option(
            "--slurm-setup",
            multiple=True,
            metavar="LINE",
            help="Shell line run before each job, e.g. 'source .venv/bin/activate' (repeatable).",
        ),
        click.option(
            "--slurm-opt",
            multiple=True,
            metavar="KEY=VALUE",
            help="Any other sbatch option, e.g. constraint=a100 (repeatable).",
        ),
        click.option(
            "--submitit-cluster",
            type=click.Choice(["auto", "slurm", "local", "debug"]),
            default="auto",
            show_default=True,
            help="For --executor slurm: auto uses Slurm when present, else local processes.",
        ),
        opt.path_option("--log-dir", file_okay=False, help="submitit job logs [default: <store>/_sweeps/<time>]."),
    )(command)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="sweep")
    @opt.names_option(
        "--detectors", required=True, help="Detectors, comma-separated or repeated, e.g. ours,eme,icafusion,cmadet."
    )
    @opt.names_option("--datasets", required=True, help="Datasets, comma-separated or repeated, e.g. m3t.")
    @click.option(
        "--encodings", default=None, help="Comma-separated encodings [default: each detector's / dataset's own]."
    )
    @opt.folds_option()
    @click.option(
        "--executor",
        type=click.Choice(["local", "ray", "slurm"]),
        default="local",
        show_default=True,
        help="local: one run after the other here; ray: one Ray task per run; slurm: a submitit job array.",
    )
    @click.option("--dry-run", is_flag=True, help="List the runs the sweep would do, and stop.")
    @_executor_options
    @_common
    def sweep_cmd(
        detectors,
        datasets,
        encodings,
        folds,
        executor,
        dry_run,
        slurm_setup,
        slurm_opt,
        submitit_cluster,
        profile,
        config_files,
        overrides,
        store,
        seeds,
        force,
        **resources,
    ):
        """Run every combination of DETECTORS x DATASETS x ENCODINGS x FOLDS x SEEDS into one results store.

        Each run is an ordinary `harness run` of one fold and seed: finished runs with the same configuration are
        skipped (unless --force), interrupted ones resume from their last checkpoint, and reports see each result
        as soon as its run is done. See docs/scaling.md.

        \b
        Examples:
          harness sweep --detectors ours,eme,icafusion,cmadet --datasets m3t --folds all --seeds 0,1,2
          harness sweep --detectors ours --datasets m3t --encodings none,ir8,linear16,c2 --executor ray
          harness sweep --detectors ours,eme --datasets m3t --seeds 0,1,2 --executor slurm \\
              --slurm-partition gpu
        """
        from harness.errors import PartlyDone
        from harness.progress import progress_on
        from harness.runner import parse_seeds
        from harness.sweep import ExecutorOptions, SweepSpec, expand, sweep, sweep_table

        parsed = parse_seeds(seeds)
        spec = SweepSpec(
            detectors=tuple(detectors),
            datasets=tuple(datasets),
            folds=folds,
            seeds=tuple(parsed) if parsed is not None else None,
            encodings=tuple(_split(encodings)),
            profile=profile,
            config_files=tuple(config_files),
            overrides=tuple(overrides),
            store=None if store is None else str(store),
            force=force,
        )
        if dry_run:
            planned = expand(spec)
            skipped = [f"{r.run} (finished)" for r in planned.skipped]
            opt.echo_plan(
                [("run   ", planned.jobs), ("skip  ", skipped), ("left out  ", planned.invalid)],
                f"{len(planned.jobs)} runs to do, {len(planned.skipped)} finished, store {planned.store}",
            )
            return
        options = ExecutorOptions(
            cluster=None if submitit_cluster == "auto" else submitit_cluster,
            slurm_setup=tuple(slurm_setup),
            slurm_extra=_key_values(slurm_opt),
            **resources,
        )
        summary = sweep(spec, executor, options, progress=progress_on())
        click.echo(sweep_table(summary))
        click.echo(f"\nresults: {summary.store}")
        if summary.failed:
            raise PartlyDone(f"{len(summary.failed)} of {len(summary.results)} runs failed (see the table)")
