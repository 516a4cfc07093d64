"""``harness benchmark``: the reference benchmark (``run``), its export as shipped reference results (``export``), and
one cell rerun against the shipped references (``rerun``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from harness.commands import options as opt
from harness.commands.sweep import _executor_options, _key_values
from harness.hookspecs import hookimpl


def _cell_key(text: str) -> tuple[str, str, str, int]:
    """``ours/c2/P1/seed0`` (or ``ours/c2/P1/0``) -> (detector, encoding, fold, seed)."""
    parts = text.strip().strip("/").split("/")
    if len(parts) == 5:  # with the dataset in front
        parts = parts[1:]
    if len(parts) != 4:
        raise click.BadParameter(
            f"{text!r}: name a cell as DETECTOR/ENCODING/FOLD/seedN, e.g. ours/c2/P1/seed0", param_hint="CELL"
        )
    det, enc, fold, seed = parts
    try:
        return det, enc, fold, int(seed.removeprefix("seed"))
    except ValueError:
        raise click.BadParameter(f"{text!r}: the seed part must be seedN or N", param_hint="CELL") from None


def suite_option() -> Any:
    """``--suite NAME`` -> parameter ``suite``: which reference benchmark (``harness.benchmark.SUITES``)."""
    from harness.benchmark import DEFAULT_SUITE, SUITES

    return click.option(
        "--suite",
        type=click.Choice(list(SUITES)),
        default=DEFAULT_SUITE,
        show_default=True,
        help="Which reference benchmark: m3t-synth (the four M3T-like folds and the c2 ablation) or rgbt-tiny-synth "
        "(the RGBT-Tiny-like stand-in, both annotation sources, the proxy8 ablation).",
    )


def _suite_store(suite: Any, store: Path | None, profile: str) -> Path:
    """``--store``, else the suite's own store at its profile, else ``results/<profile>``."""
    if store is not None:
        return store
    return suite.store if profile == suite.profile else opt.resolve_store(None, profile)


def _suite_references(suite: Any, reference_results: str | None) -> Any:
    """``--reference-results`` loaded; not given or ``shipped``: the suite's shipped folder."""
    from harness.errors import StoreError
    from harness.references import SHIPPED, load_references, shipped_root

    if reference_results not in (None, "shipped"):
        return load_references(reference_results)
    if suite.references == SHIPPED:
        return load_references("shipped")
    folder = shipped_root() / suite.references
    if not (folder / "references.json").is_file():
        raise StoreError(
            f"{folder}: the {suite.name} suite's reference results are missing (no references.json); make them "
            f"with `harness benchmark run --suite {suite.name}` and `harness benchmark export --suite {suite.name}`, "
            f"or pass "
            f"--reference-results DIR (a folder `harness benchmark export` wrote)"
        )
    return load_references(folder)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.group(name="benchmark")
    def benchmark_group() -> None:
        """The reference benchmarks (--suite): four detectors x four folds x three seeds and the encoding ablation on
        m3t-synth, or the four detectors x two annotation sources x three seeds and the proxy8 ablation on the
        RGBT-Tiny-like stand-in, at the benchmark profile (docs/benchmark.md)."""

    @benchmark_group.command(name="run")
    @suite_option()
    @opt.profile_option(default="benchmark")
    @opt.store_option()
    @click.option(
        "--lanes",
        type=click.IntRange(min=1),
        default=None,
        help="Cells trained side by side, one core each (--executor local) [default: one per core].",
    )
    @click.option(
        "--executor",
        type=click.Choice(["local", "ray", "slurm"]),
        default="local",
        show_default=True,
        help="local: lanes on this machine; ray: one Ray task per cell (one GPU each where the cluster has GPUs); "
        "slurm: one submitit job array (submitit's local executor where there is no Slurm).",
    )
    @opt.names_option(
        "--detectors",
        help="Detectors of the detector grid, comma-separated or repeated [default: ours,eme,icafusion,cmadet].",
    )
    @opt.folds_option()
    @opt.seeds_option(default="0,1,2")
    @click.option(
        "--ablation/--no-ablation",
        default=True,
        show_default=True,
        help="Also run the encoding ablation (m3t-synth: ours with none, ir8, linear16, c2 on P4+P5; "
        "rgbt-tiny-synth: ours with none, proxy8, ir8 on the thermal-source annotations, test-T).",
    )
    @opt.config_options(
        help_set="Override one config key of every cell, e.g. --set protocol.imgsz=256 (such a "
        "store is not comparable with the shipped references; a report says so)."
    )
    @click.option("--dry-run", is_flag=True, help="List the cells left to do, and stop.")
    @click.option("--force", is_flag=True, help="Redo cells that already finished.")
    @_executor_options
    @opt.no_progress_option()
    def run_cmd(
        suite: str,
        profile: str,
        store: Path | None,
        lanes: int | None,
        executor: str,
        detectors: tuple[str, ...],
        folds: str,
        seeds: str,
        ablation: bool,
        config_files: tuple[str, ...],
        overrides: tuple[str, ...],
        dry_run: bool,
        force: bool,
        slurm_setup: tuple[str, ...],
        slurm_opt: tuple[str, ...],
        submitit_cluster: str,
        **resources: Any,
    ) -> None:
        """Run the benchmark's cells that are left to do, in lanes or on a cluster, with overall progress and ETA
        on stderr.

        Finished cells are skipped and interrupted ones resume from their last epoch, so running it again after an
        interrupt (Ctrl-C, a closed laptop, a cancelled job) does only what is left. With --executor ray or slurm
        every worker must reach the store, the prepared-data cache and the plugins ($HARNESS_* is handed on); the
        store is the same as the lanes'. Prints one line per cell on stdout and the wall and CPU time; exits 1
        when a cell failed (the others still ran).

        \b
        Examples:
          harness benchmark run                       # the reference benchmark, one lane per core
          harness benchmark run --executor ray --ray-address auto
          harness benchmark run --profile paper --executor slurm --slurm-partition gpu \\
              --slurm-setup 'source .venv/bin/activate'   # 640 px, the detectors' s sizes: GPUs
        """
        from harness import benchmark as B
        from harness.progress import progress_on
        from harness.sweep import ExecutorOptions, SweepSummary, sweep_table

        chosen = B.get_suite(suite)
        seed_list = opt.parse_seeds(seeds) or list(chosen.seeds)
        spec = B.suite_spec(
            chosen,
            store=_suite_store(chosen, store, profile),
            detectors=detectors or chosen.detectors,
            folds=folds,
            seeds=tuple(seed_list),
            ablation=ablation,
            overrides=overrides,
            config_files=tuple(config_files),
            force=force,
            profile=profile,
        )
        if dry_run:
            plan = B.plan_benchmark(spec)
            opt.echo_plan(
                [("todo  ", plan.jobs), ("done  ", [done.run for done in plan.skipped])],
                f"{len(plan.jobs)} cell(s) to run, {len(plan.skipped)} finished, in {plan.store}",
            )
            return
        options = ExecutorOptions(
            cluster=None if submitit_cluster == "auto" else submitit_cluster,
            slurm_setup=tuple(slurm_setup),
            slurm_extra=_key_values(slurm_opt),
            **resources,
        )
        summary = B.run_benchmark(spec, lanes=lanes, progress=progress_on(), executor=executor, options=options)
        B.write_timing(summary)
        click.echo(sweep_table(SweepSummary(summary.store, summary.results, summary.invalid)))
        where = f"{summary.lanes} lane(s)" if executor == "local" else f"--executor {executor}"
        click.echo(
            f"benchmark: {len(summary.results)} cells in {summary.store}; this call ({where}) "
            f"{summary.wall_s:.0f} s wall, {summary.cpu_s:.0f} s CPU ({B.cpu_name()})"
        )
        if summary.failed:
            click.secho(
                f"{len(summary.failed)} cell(s) failed; run `harness benchmark run"
                f"{'' if suite == B.DEFAULT_SUITE else ' --suite ' + suite}` again to retry them "
                f"(logs in {summary.store / '_benchmark' / 'logs'})",
                fg="red",
                err=True,
            )
            raise SystemExit(1)

    @benchmark_group.command(name="export")
    @suite_option()
    @opt.profile_option(default="benchmark", uses_config=False)
    @opt.store_option(reads=True)
    @opt.folder_option(
        "--out",
        help="Folder to write [default: the suite's shipped references, references/m3t-synth-benchmark or "
        "references/rgbt-tiny-synth-benchmark].",
    )
    def export_cmd(suite: str, profile: str, store: Path | None, out: Path | None) -> None:
        """Export a finished benchmark store as reference results: metrics, error analysis, logs, and the ground
        truth and predictions the paired bootstrap re-scores (gzip), with the samples' digests (at most 10 MiB)."""
        from harness import benchmark as B
        from harness.errors import StoreError
        from harness.references import export_references, shipped_root

        chosen = B.get_suite(suite)
        spec = B.suite_spec(chosen, store=_suite_store(chosen, store, profile), profile=profile)
        out = out or shipped_root() / chosen.references
        root = Path(spec.store)
        if not root.is_dir():
            raise StoreError(f"{root}: no results store here; run `harness benchmark run` first")
        found, missing = B.finished_cells(spec)
        if missing:
            raise StoreError(
                f"the benchmark in {root} is not finished: {len(missing)} missing (e.g. {', '.join(missing[:3])}); "
                f"run `harness benchmark run --suite {suite} --store {root}` first"
            )
        manifest = export_references(root, out, found, benchmark=B.read_timing(root))
        click.echo(f"reference results: {len(manifest['cells'])} runs, {manifest['bytes'] / 2**20:.2f} MiB -> {out}")

    @benchmark_group.command(name="fingerprint")
    @suite_option()
    @opt.reference_results_option()
    @click.option(
        "--prepared",
        type=click.Path(file_okay=False, exists=True, path_type=Path),
        default=None,
        help="A prepared-data folder holding the references' samples [default: prepare the references' dataset "
        "with default options, in $HARNESS_CACHE or ./cache].",
    )
    def fingerprint_cmd(suite: str, reference_results: str | None, prepared: Path | None) -> None:
        """Store the fingerprint of the reference results' samples beside them (what matching across library
        releases measures against), after checking that the prepared samples are exactly the references'."""
        from harness import benchmark as B
        from harness.cache import PreparedDataset
        from harness.config import load_config
        from harness.references import write_fingerprint
        from harness.runner import prepare_dataset

        chosen = B.get_suite(suite)
        refs = _suite_references(chosen, reference_results)
        if prepared:
            data = PreparedDataset(prepared)
        else:
            B.ensure_data(chosen)
            cfg = load_config(refs.profile, files=chosen.layers(), overrides=list(chosen.data_overrides()))
            data = prepare_dataset(refs.dataset, cfg)
        out = write_fingerprint(refs.root, data)
        click.echo(f"sample fingerprint: {out['bytes'] / 2**10:.0f} KiB -> {out['fingerprint']}")

    @benchmark_group.command(name="rerun")
    @click.argument("cell")
    @click.option(
        "--work-dir",
        "work_dir",
        type=click.Path(file_okay=False, path_type=Path),
        default=Path("results") / "benchmark-rerun",
        show_default=True,
        help="Results store the cell is trained into (a finished cell there is trained again).",
    )
    @suite_option()
    @opt.reference_results_option()
    @opt.format_option("text", "json")
    @opt.no_progress_option()
    def rerun_cmd(cell: str, work_dir: Path, suite: str, reference_results: str | None, fmt: str) -> None:
        """Train one reference CELL again (DETECTOR/ENCODING/FOLD/seedN, e.g. ours/c2/P1/seed0) and compare it with the
        reference results' (default: the shipped ones).

        Before training it checks the samples (their digests, or within a library release's tolerance), the
        configuration and the environment: other samples stop it at once, naming the digests, the measured
        difference and the package versions that differ. After training: identical, or a verdict against the
        references' training variance (the cell's seeds: within or outside a 95 % prediction interval for one
        training run), with the environment facts that differ. Exits 1 when a number differs."""
        from harness import benchmark as B
        from harness.progress import progress_on

        det, enc, fold, seed = _cell_key(cell)
        chosen = B.get_suite(suite)
        refs = _suite_references(chosen, reference_results)
        B.ensure_data(chosen)
        result = B.rerun_cell(
            refs, det, enc, fold, seed, work_dir, progress=progress_on(), overrides=chosen.data_overrides()
        )
        if fmt == "json":
            click.echo(json.dumps(result, indent=2))
        else:
            click.echo(B.rerun_text(result))
        if not result["identical"]:
            raise SystemExit(1)
