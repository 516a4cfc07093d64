"""``harness cache``: list the prepared datasets with their sizes, check them, remove the ones no longer used."""

from __future__ import annotations

from pathlib import Path

import click

from harness.hookspecs import hookimpl


@hookimpl
def register_commands(cli: click.Group) -> None:
    @cli.group(name="cache")
    def cache_group() -> None:
        """The prepared-sample cache ($HARNESS_CACHE or ./cache): list, verify, rm."""

    root_option = click.option(
        "--cache",
        type=click.Path(file_okay=False, path_type=Path),
        default=None,
        help="Cache folder (default: $HARNESS_CACHE or ./cache).",
    )
    days_option = click.option(
        "--days",
        type=float,
        default=30.0,
        show_default=True,
        help="A prepared dataset not used for this many days counts as unused.",
    )

    @cache_group.command(name="list")
    @root_option
    @days_option
    def list_cmd(cache: Path | None, days: float) -> None:
        """Prepared datasets with their form, sample count, size, source size and last use."""
        from harness.cache import cache_root
        from harness.cache.admin import entries, table

        click.echo(table(entries(cache_root(cache), days)))

    @cache_group.command(name="rm")
    @click.argument("names", nargs=-1)
    @click.option("--unused", is_flag=True, help="Remove every unused prepared dataset (see `harness cache list`).")
    @click.option("--dry-run", is_flag=True, help="Only print what would be removed.")
    @root_option
    @days_option
    def rm_cmd(names: tuple[str, ...], unused: bool, dry_run: bool, cache: Path | None, days: float) -> None:
        """Remove prepared datasets: NAME is a dataset (all its preparations) or DATASET/FOLDER."""
        from harness.cache import cache_root
        from harness.cache.admin import entries, human, remove, select
        from harness.errors import ConfigError

        if bool(names) == unused:
            raise ConfigError("name the prepared dataset(s) to remove, or pass --unused (not both)")
        picked = select(entries(cache_root(cache), days), list(names), unused)
        for e in picked:
            click.echo(
                f"{'would remove' if dry_run else 'removing'} {e.ref} ({human(e.bytes)})"
                + (f": {e.why_unused}" if e.why_unused else "")
            )
        total = sum(e.bytes for e in picked)
        freed = total if dry_run else remove(picked)
        click.echo(f"{'would free' if dry_run else 'freed'} {human(freed)} ({len(picked)} prepared dataset(s))")

    @cache_group.command(name="verify")
    @click.argument("names", nargs=-1)
    @root_option
    def verify_cmd(names: tuple[str, ...], cache: Path | None) -> None:
        """Decode every sample of the prepared datasets (all when none named) and check referenced source files."""
        from harness.cache import PreparedDataset, cache_root
        from harness.cache.admin import entries, select
        from harness.errors import PartlyDone

        items = [e for e in entries(cache_root(cache), 1e9) if e.form != "-"]
        failed = 0
        for e in select(items, list(names), False) if names else items:
            errors = PreparedDataset(e.path).verify()
            failed += bool(errors)
            click.echo(f"{e.ref}: {'ok' if not errors else f'{len(errors)} sample(s) failed'} ({e.count} samples)")
            for msg in errors[:20]:
                click.echo(f"  {msg}", err=True)
        if failed:
            raise PartlyDone(f"{failed} prepared dataset(s) failed verification; prepare them again with --force")
