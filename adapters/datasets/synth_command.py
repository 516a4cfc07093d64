"""``harness synth``: the synthetic generator's command, a plugin of its own beside the ``m3t-synth`` dataset."""

from __future__ import annotations

from pathlib import Path

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def add_synth_command(cli: click.Group) -> None:
    """Add ``harness synth`` to ``cli``."""

    @cli.command(name="synth")
    @opt.option(
        "--size",
        "profile",
        old=("--profile",),
        type=click.Choice(["tiny", "small", "full"]),
        default="small",
        show_default=True,
        help="small: 112 pairs, thermal 320x256 (demo, CPU); full: the seed's 674 pairs at 640x512.",
    )
    @opt.folder_option("--out", help="Output folder (default: $HARNESS_DATA or ./data, /m3t-synth-<size>-seed<seed>).")
    @click.option(
        "--seed",
        type=int,
        default=0,
        show_default=True,
        help="Seed of the generator (part of the folder name); the same seed gives the same files.",
    )
    @click.option(
        "--thermal-format",
        type=click.Choice(["rjpeg", "centikelvin"]),
        default="rjpeg",
        show_default=True,
        help="Thermal files as DJI R-JPEGs (_T.JPG) or 16-bit centi-Kelvin PNGs with sidecars.",
    )
    @click.option("--force", is_flag=True, help="Replace an existing output folder.")
    @click.option("--workers", type=int, default=None, help="Rendering processes (default: up to 4, CPU count).")
    @opt.no_progress_option()
    def synth_cmd(
        profile: str, out: Path | None, seed: int, thermal_format: str, force: bool, workers: int | None
    ) -> None:
        """Generate the synthetic M3T-like dataset (raw M3T layout + ground truth). Deterministic in --seed."""
        from adapters.datasets.synthetic import generate

        s = generate(out, profile=profile, seed=seed, thermal_format=thermal_format, force=force, workers=workers)
        click.echo(
            f"m3t-synth {s.profile} (seed {s.seed}): {sum(s.images.values())} pairs in {s.root} ({s.seconds:.1f} s)"
        )
        click.echo("images per project: " + ", ".join(f"{p} {n}" for p, n in s.images.items()))
        click.echo(f"inspection groups: {len(s.groups)}")
        click.echo(s.table())


@hookimpl
def register_commands(cli: click.Group) -> None:
    add_synth_command(cli)
