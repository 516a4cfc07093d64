"""``harness synth``: the synthetic generators' command (``--family m3t``, the ``m3t-synth`` data, or ``rgbt-tiny``),
a plugin of its own beside the ``m3t-synth`` dataset."""

from __future__ import annotations

from pathlib import Path

import click

from harness.commands import options as opt
from harness.hookspecs import hookimpl


def add_synth_command(cli: click.Group) -> None:
    """Add ``harness synth`` to ``cli``."""

    @cli.command(name="synth")
    @click.option(
        "--family",
        type=click.Choice(["m3t", "rgbt-tiny"]),
        default="m3t",
        show_default=True,
        help="m3t: M3T-like facades (m3t-synth); rgbt-tiny: RGBT-Tiny-like tiny targets in that release's layout "
        "(tiny: 20 pairs, small: 240 pairs, full: 1,400 pairs, all 640x512 but tiny; small-320: small's "
        "sequences at 320x256).",
    )
    @opt.option(
        "--size",
        "profile",
        old=("--profile",),
        type=click.Choice(["tiny", "small", "small-320", "full"]),
        default="small",
        show_default=True,
        help="small: 112 pairs, thermal 320x256 (demo, CPU); full: the seed's 674 pairs at 640x512; small-320: "
        "--family rgbt-tiny only.",
    )
    @opt.folder_option(
        "--out",
        help="Output folder (default: $HARNESS_DATA or ./data, /m3t-synth-<size>-seed<seed> or "
        "/rgbt-tiny-synth-<size>-seed<seed>).",
    )
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
        family: str, profile: str, out: Path | None, seed: int, thermal_format: str, force: bool, workers: int | None
    ) -> None:
        """Generate a synthetic dataset: M3T-like (raw M3T layout + ground truth) or, with --family rgbt-tiny,
        RGBT-Tiny-like (the release's layout). Deterministic in --seed."""
        if family == "rgbt-tiny":
            _synth_rgbt_tiny(profile, out, seed, thermal_format, force, workers)
            return
        from adapters.datasets.synthetic import generate

        s = generate(out, profile=profile, seed=seed, thermal_format=thermal_format, force=force, workers=workers)
        click.echo(
            f"m3t-synth {s.profile} (seed {s.seed}): {sum(s.images.values())} pairs in {s.root} ({s.seconds:.1f} s)"
        )
        click.echo("images per project: " + ", ".join(f"{p} {n}" for p, n in s.images.items()))
        click.echo(f"inspection groups: {len(s.groups)}")
        click.echo(s.table())


def _synth_rgbt_tiny(
    profile: str, out: Path | None, seed: int, thermal_format: str, force: bool, workers: int | None
) -> None:
    from adapters.datasets.synthetic_tiny import generate

    ctx = click.get_current_context()
    if ctx.get_parameter_source("thermal_format") not in (None, click.core.ParameterSource.DEFAULT):
        raise click.UsageError("--thermal-format is for --family m3t; the RGBT-Tiny-like set has 8-bit thermal JPEGs")
    s = generate(out, profile=profile, seed=seed, force=force, workers=workers)
    click.echo(
        f"rgbt-tiny-synth {s.profile} (seed {s.seed}): {sum(s.pairs.values())} pairs in {s.root} ({s.seconds:.1f} s)"
    )
    click.echo(
        "sequences: "
        + ", ".join(f"{split} {n} ({s.pairs[split]} pairs)" for split, n in s.sequences.items())
        + f"; read it with: harness prepare --dataset rgbt-tiny --root {s.root}"
    )
    click.echo(s.table())


@hookimpl
def register_commands(cli: click.Group) -> None:
    add_synth_command(cli)
