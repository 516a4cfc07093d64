"""``harness prepare`` and ``harness folds``: cache aligned samples, show the folds (``harness synth`` is registered
by the synthetic dataset's plugin, ``adapters.datasets.synth_command``)."""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def format_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A plain table: text left-aligned, numbers right-aligned (integers with thousands separators)."""
    from harness.textable import text_table

    numeric = [bool(rows) and all(isinstance(r[i], (int, float)) for r in rows) for i in range(len(header))]
    cells = [[f"{v:,}" if isinstance(v, int) else str(v) for v in r] for r in rows]
    return text_table(header, cells, "".join("r" if n else "l" for n in numeric))


def _config(dataset: str, configs: Sequence[str], overrides: Sequence[str], root: str | None) -> tuple[Any, dict]:
    from harness.config import load_config
    from harness.plugins import get_host

    spec = get_host().dataset(dataset)
    extra = list(overrides) + ([f"dataset.root={root}"] if root else [])
    return spec, load_config(protocol=spec.protocol, files=configs, overrides=extra)


@dataclass(frozen=True)
class DatasetArgs:
    """The dataset a command prepares or reads, as ``_dataset_options`` gives it: ``--dataset``, ``--root``,
    ``--cache``, ``--config`` and ``--set``."""

    dataset: str
    root: str | None
    cache: Path | None
    config_files: tuple[str, ...]
    overrides: tuple[str, ...]

    def config(self) -> tuple[Any, dict]:
        """The dataset's plugin spec and its configuration (protocol, files, overrides, root)."""
        return _config(self.dataset, self.config_files, self.overrides, self.root)


def _dataset_options(command: Any) -> Any:
    """The options of ``DatasetArgs``; the command gets them as one parameter, ``data``."""

    @functools.wraps(command)
    def with_dataset(*args: Any, **kwargs: Any) -> Any:
        data = DatasetArgs(**{f.name: kwargs.pop(f.name) for f in fields(DatasetArgs)})
        return command(*args, data=data, **kwargs)

    func = opt.no_progress_option()(with_dataset)
    func = opt.config_options(
        after_profile=False,
        help_set="Override a config key, e.g. --set dataset.profile=full "
        "or --set sensing.warp.crop=false (repeatable).",
    )(func)
    func = click.option(
        "--cache",
        type=click.Path(file_okay=False, path_type=Path),
        default=None,
        help="Cache folder (default: $HARNESS_CACHE or ./cache).",
    )(func)
    func = click.option("--root", default=None, help="Dataset folder (same as --set dataset.root=...).")(func)
    func = click.option("--dataset", required=True, help="Dataset name (see `harness list`).")(func)
    return func


def prepare_summary(ds: Any) -> str:
    """What ``harness prepare`` prints: where, how many, what was skipped and why."""
    m = ds.manifest
    rep = m.get("report", {})
    lines = [
        f"{'reused' if getattr(ds, 'from_cache', False) else 'prepared'} {m['dataset']}: {m['count']} aligned "
        f"samples, {m['instances']} instances -> {ds.folder}"
    ]
    from harness.cache.admin import size_line

    lines.append(size_line(ds))
    pairs = {k: v for k, v in rep.get("skip_reasons", {}).items() if not k.startswith("annotation")}
    anns = {k: v for k, v in rep.get("skip_reasons", {}).items() if k.startswith("annotation")}
    lines.append(
        f"skipped pairs: {sum(pairs.values())}"
        + (" (" + ", ".join(f"{k}: {v}" for k, v in pairs.items()) + ")" if pairs else "")
    )
    lines.append(
        f"skipped annotations: {sum(anns.values())}"
        + (" (" + ", ".join(f"{k}: {v}" for k, v in anns.items()) + ")" if anns else "")
    )
    from harness.input_guard import describe
    from harness.textable import fit_text

    shown: set[str] = set()  # the first example of each kind of reason in full (its advice), the others cut
    for where, reason in (rep.get("skipped_files") or [])[:3]:
        kind = str(reason).split(":")[0]
        lines.append(_cut(f"  e.g. {where}: {reason}") if kind in shown else fit_text(f"  e.g. {where}: {reason}"))
        shown.add(kind)

    lines += [fit_text(line) for line in describe(getattr(ds, "input_risks", None) or [])]
    missing = rep.get("missing_temperatures") or {}
    if missing.get("pixels"):
        lines.append(
            f"missing temperatures (NaN/inf, left out of the encodings): {missing['pixels']} pixels in "
            f"{missing['samples']} sample(s)"
        )
    for note in rep.get("notes", []):
        lines.append(f"note: {note}")
    from harness.summary import SizeSummary

    sizes = SizeSummary.of_prepared(ds)
    lines += [
        sizes.headline(),
        "boxes per category and size bin (SAFit bins, box side sqrt(w*h) in px):",
        sizes.to_text(),
    ]
    return "\n".join(lines)


def _cut(line: str, width: int = 100) -> str:
    """``line`` cut to ``width`` characters (an example of a long reason: its start says what it is)."""
    return line if len(line) <= width else line[: width - 3] + "..."


def folds_table(ds: Any, folds: Sequence[Any]) -> str:
    from harness.cache import fold_support

    rows = []
    for s in fold_support(ds, folds):
        rows.append([s.fold, "+".join(s.val_groups), s.train_images, s.train_instances, s.val_images, s.val_instances])
    return format_table(["fold", "held out", "train images", "train instances", "val images", "val instances"], rows)


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.command(name="prepare")
    @_dataset_options
    @click.option("--force", is_flag=True, help="Prepare again even if a cached copy exists.")
    @click.option(
        "--cache-form",
        type=click.Choice(["compact", "raw"]),
        default=None,
        help="compact (default, lossless, 8-bit sources referenced) or raw (uncompressed, memory-mapped); "
        "default $HARNESS_CACHE_FORM or compact.",
    )
    def prepare_cmd(data: DatasetArgs, force: bool, cache_form: str | None) -> None:
        """Run the sensing pipeline once and cache the aligned samples (+ COCO JSON per fold split)."""
        from harness.cache import prepare

        _, cfg = data.config()
        ds = prepare(data.dataset, cfg, cache_root=data.cache, force=force, form=cache_form)
        click.echo(prepare_summary(ds))

    @cli.command(name="folds")
    @_dataset_options
    @opt.folds_option()
    def folds_cmd(data: DatasetArgs, folds: str) -> None:
        """Print train/val image and instance counts per fold (prepares the dataset if needed)."""
        from harness.cache import prepare, resolve_folds

        spec, cfg = data.config()
        ds = prepare(data.dataset, cfg, cache_root=data.cache)
        selected = resolve_folds(spec, ds, cfg, folds)
        click.echo(
            f"{spec.name}: {len(ds)} images, {ds.manifest['instances']} instances, groups "
            f"{', '.join(sorted(set(ds.groups)))}"
        )
        click.echo(folds_table(ds, selected))
        from harness.input_guard import describe
        from harness.textable import fit_text

        for line in describe(getattr(ds, "input_risks", None) or []):
            click.echo(fit_text(line))
