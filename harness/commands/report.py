"""``harness report`` (tables, figure, paired statistics as Markdown, CSV and HTML) and ``harness compare-detectors``
(paired comparison of two detectors or encodings), both from the results store alone."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def _check_reference(root: Path, reference: str, datasets: list[str] | None) -> None:
    """A ``--reference`` the user named must have finished runs in the store (in one of ``datasets``)."""
    from harness.report.reader import StoreView

    if not Path(root).is_dir():
        return  # the report itself says the store is missing
    view = StoreView(root)
    found = sorted({e.detector for ds in (datasets or view.datasets()) for e in view.entries(ds)})
    if reference in found or any(d == f"external/{reference}" for d in found):
        return
    where = f" of {', '.join(datasets)}" if datasets else ""
    raise click.BadParameter(
        f"{reference!r} has no runs in {root}{where}; detectors there: {', '.join(found) or 'none'}",
        param_hint="--reference",
    )


def _check_categories(root: Path, categories: list[str], datasets: list[str] | None) -> None:
    """Category names the user gave ``--ablation-categories`` must name categories of the store's runs (spelling as
    the report matches them: case, spaces and underscores aside)."""
    from harness.report.reader import StoreView, find_category

    if not Path(root).is_dir():
        return  # the report itself says the store is missing
    view = StoreView(root)
    present = sorted(
        {
            c
            for ds in (datasets or view.datasets())
            for e in view.entries(ds)
            for f in e.folds.values()
            for c in f.metrics.get("per_category") or {}
        }
    )
    unknown = [c for c in categories if find_category(c, present) is None]
    if present and unknown:
        raise click.BadParameter(
            f"{', '.join(map(repr, unknown))}: no such category in the runs of {root}; categories there: "
            f"{', '.join(present)}",
            param_hint="--ablation-categories",
        )


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="report")
    @opt.names_option(
        "--datasets",
        old=("--dataset",),
        help="Datasets to report, comma-separated or repeated [default: every dataset in the store].",
    )
    @opt.store_option(reads=True)
    @opt.profile_option(uses_config=False)
    @opt.folder_option("--out", help="Output folder [default: reports/<store folder name>].")
    @opt.option(
        "--file-types",
        "formats",
        old=("--format",),
        default="md,csv,html",
        show_default=True,
        help="Comma-separated file types to write: md, csv, html.",
    )
    @click.option(
        "--print",
        "print_tables",
        is_flag=True,
        help="Print every table in the terminal (aligned) instead of writing the report files (with --out, as well "
        "as writing them).",
    )
    @opt.bootstrap_options(
        resamples=200,
        old_seed=("--seed",),
        help_resamples="Paired-bootstrap resamples per comparison (0: per-fold differences only).",
    )
    @click.option(
        "--ablation-categories",
        default="delamination,water seepage",
        show_default=True,
        help="Comma-separated categories whose AP50 the encoding-ablation table shows.",
    )
    @click.option("--title", default=None, help="Title of the report.")
    @click.option(
        "--reference",
        default="ours",
        show_default=True,
        help="Detector compared with each other one in the paired comparisons (the most accurate when it was not run).",
    )
    @click.option(
        "--log-to",
        "log_to",
        default=None,
        metavar="LOGGERS",
        help="Also log the report's files as artefacts to these trackers, e.g. mlflow,tensorboard.",
    )
    @opt.reference_results_option()
    @click.option(
        "--references-optional",
        "references_optional",
        is_flag=True,
        help="Write the report without the reference results when they cannot be compared (the store's runs used "
        "other samples) or read, saying why in one line at its top and on stderr, instead of stopping.",
    )
    @opt.no_progress_option()
    def report_cmd(
        datasets: tuple[str, ...],
        store: Path | None,
        profile: str,
        out: Path | None,
        formats: str,
        print_tables: bool,
        bootstrap_seed: int,
        ablation_categories: str,
        reference: str,
        log_to: str | None = None,
        reference_results: str | None = None,
        references_optional: bool = False,
        **settings: Any,
    ) -> None:
        """Write the benchmark report of a results store: Markdown, CSV and one self-contained HTML page.

        Per dataset: the project-grouped folds table (per-fold mAP50 and mAP50:95, mean ± sample SD, Params,
        GFLOPs), the per-category table, the encoding ablation, object sizes and AP per size bin, paired comparisons
        (per-fold differences, a bootstrap, a verdict only with three or more training seeds per fold), error types
        (TIDE), confusion matrices, PR curves per category, one gallery per detector (pictures from the prepared
        cache in HARNESS_CACHE), the registration-error and C2-displacement tables; then the accuracy-versus-GFLOPs
        figure and the cross-dataset table. Absent data is stated with the command that fills it; tables whose rows
        were not scored on the same samples are labelled.
        """
        from harness.errors import StoreError
        from harness.references import load_references
        from harness.report import build_report
        from harness.report.build import FORMATS as file_types

        root = opt.resolve_store(store, profile)
        names = list(datasets) or None
        fmts = [f.lower() for f in opt.split_list(formats)]
        bad = [f for f in fmts if f not in file_types]
        if bad:
            raise click.BadParameter(
                f"unknown file type(s) {', '.join(bad)}; use any of {', '.join(file_types)}", param_hint="--file-types"
            )
        target = out or Path("reports") / Path(root).resolve().name
        ctx = click.get_current_context()
        if ctx.get_parameter_source("reference") is not click.core.ParameterSource.DEFAULT:
            _check_reference(root, reference, names)  # the default falls back to the best; a named one must exist
        cats = [c.strip() for c in ablation_categories.split(",") if c.strip()]
        if ctx.get_parameter_source("ablation_categories") is not click.core.ParameterSource.DEFAULT:
            _check_categories(root, cats, names)  # the default names the paper's two; a typed name must exist
        refs, unread = None, None
        try:
            refs = load_references(reference_results)
        except StoreError as exc:
            if not references_optional:
                raise
            unread = f"Reference results not shown: {str(exc).rstrip('.')}."
        report = build_report(
            root,
            names,
            out=None if print_tables and out is None else target,
            formats=fmts,
            seed=bootstrap_seed,
            ablation_categories=cats,
            progress=True,
            reference=reference,
            references=refs,
            references_optional=references_optional,
            references_note=unread,
            **settings,  # resamples, workers, title
        )
        if print_tables:
            click.echo(report.to_text())
            if out is None:
                return  # with --out the files were written too: say which below
        warned = [t.title for t in report.tables if t.warning]
        absent = [f"{s.dataset or 'all'}: {s.title}" for s in report.sections if s.absent]
        aside = print_tables  # with --print the report is standard output; what was written goes to stderr
        click.echo(
            f"report of {report.store} ({', '.join(report.datasets)}): {len(report.tables)} tables, "
            f"{sum(len(s.figures) for s in report.sections)} figure(s)",
            err=aside,
        )
        if warned:
            click.secho(
                f"NOT sample-matched: {len(warned)} table(s) labelled: " + "; ".join(warned), fg="red", err=True
            )
        if absent:
            from harness.textable import fit_text

            click.echo(
                fit_text("absent (see the report for the command that fills each): " + "; ".join(absent)), err=aside
            )
        for path in report.files:
            click.echo(f"-> {path}", err=aside)
        if log_to:
            from harness.tracking import log_report, parse_names

            for problem in log_report(parse_names(log_to), root, report.files, report.title):
                click.secho(problem, fg="red", err=True)

    @cli.command(name="compare-detectors")
    @click.argument("a")
    @click.argument("b")
    @click.option("--dataset", required=True, help="Dataset both were evaluated on.")
    @opt.store_option(reads=True)
    @opt.profile_option(uses_config=False)
    @opt.bootstrap_options(
        resamples=1000,
        old_seed=("--seed",),
        help_resamples="Paired-bootstrap resamples of the held-out images (0: per-fold differences only).",
    )
    @opt.format_option("text", "json", old_json=True)
    @opt.reference_results_option()
    @opt.no_progress_option()
    def compare_detectors_cmd(
        a: str,
        b: str,
        dataset: str,
        store: Path | None,
        profile: str,
        resamples: int,
        bootstrap_seed: int,
        workers: int,
        fmt: str,
        reference_results: str | None = None,
    ) -> None:
        """Paired comparison of A and B (DETECTOR or DETECTOR/ENCODING) on the same held-out images.

        Per-fold differences of mAP50 and mAP50:95, and a paired bootstrap over images: each fold's held-out images
        are resampled with replacement, both detectors' stored predictions are re-scored on the same resamples, and
        the percentile 95 % interval of the difference of the mean over folds is reported. With one training seed
        per fold this compares trained models and gives no verdict; with three or more (`harness run --seeds
        0,1,2`) the training runs are resampled too, with the probability that a new run of A beats one of B and
        the seeds the difference needs. Refused when A and B were scored on different samples.
        """
        import json

        from harness.progress import bar
        from harness.references import load_references
        from harness.report import compare_detectors
        from harness.report.reader import StoreView

        root = opt.resolve_store(store, profile)
        view = StoreView(root, references=load_references(reference_results))
        with bar("bootstrap") as b_bar:
            comp = compare_detectors(
                view,
                dataset,
                a,
                b,
                resamples=resamples,
                seed=bootstrap_seed,
                progress=b_bar.advance,
                on_total=lambda n: b_bar.update(total=n),
                workers=workers,
            )
        if fmt == "json":
            click.echo(json.dumps(comp.to_dict(), indent=2))
        else:
            click.echo(comp.to_text())
