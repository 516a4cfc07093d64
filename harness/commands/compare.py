"""``harness compare``: the cross-dataset table (images, instances, mAP50, mAP50:95 per detector and annotation
source) from the results store."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl

log = logging.getLogger(__name__)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="compare")
    @opt.names_option(
        "--datasets", required=True, help="Datasets, comma-separated or repeated, in table order (e.g. m3t,rgbt-tiny)."
    )
    @opt.store_option(reads=True)
    @opt.profile_option(uses_config=False)
    @click.option(
        "--safit", is_flag=True, help="Add SAFit-AP50 and SAFit-AP50:95, re-scored from the stored predictions."
    )
    @click.option(
        "--allow-mismatched",
        is_flag=True,
        help="Print rows scored on different supports, marked '!', instead of refusing.",
    )
    @opt.format_option("text", "json", "md", "csv", aliases={"markdown": "md"})
    @click.option(
        "--out",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        help="Also write the table to this file.",
    )
    def compare_cmd(
        datasets: tuple[str, ...],
        store: Path | None,
        profile: str | None,
        safit: bool,
        allow_mismatched: bool,
        fmt: str,
        out: Path | None,
    ) -> None:
        """Compare detectors across datasets on identical supports.

        One row per dataset, annotation source (T or RGB), detector and encoding, read from finished runs in the
        results store. Detectors of the same dataset and source must have been scored on the same samples (same
        folds, same image ids, same instances); otherwise the command refuses, unless --allow-mismatched.
        """
        from harness.io import atomic_write_text
        from harness.report.compare import build_table

        root = opt.resolve_store(store, profile)
        table = build_table(root, list(datasets), allow_mismatched=allow_mismatched, safit=safit)
        for m in table.mismatches:  # the report selects its rows itself and says so in its own notes
            log.info("not sample-matched (printed, marked '!'): %s", m)
        text = table.render("markdown" if fmt == "md" else fmt)
        click.echo(text)
        if out is not None:
            atomic_write_text(out, text + ("" if text.endswith("\n") else "\n"))
