"""The ``harness`` command line: a thin layer that parses, calls one library function and prints.

Sub-commands come from plugins through the ``register_commands`` hook; the built-in ones live in
``harness/commands/``. Errors a user can cause (``HarnessError``) are printed as one line without a traceback.
"""

from __future__ import annotations

import logging
import sys

import click

from harness import __version__
from harness.errors import HarnessError


class HarnessGroup(click.Group):
    """A click group that turns ``HarnessError`` into a clean message and exit status 2."""

    def invoke(self, ctx: click.Context):  # type: ignore[override]
        try:
            return super().invoke(ctx)
        except HarnessError as exc:
            click.secho(f"error: {exc}", err=True, fg="red")
            ctx.exit(2)
        except KeyboardInterrupt:  # Ctrl-C: the conventional 128 + SIGINT, not click's generic 1
            click.secho("interrupted", err=True, fg="red")
            ctx.exit(130)

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(self.commands)


@click.group(cls=HarnessGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="harness")
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
def cli(verbose: int, quiet: bool) -> None:
    """Benchmark RGB-thermal fusion detectors on aligned, sample-matched data.

    \b
    Start here:
      harness list              what detectors, datasets and encodings are installed
      harness run --detector ours --dataset m3t-synth --profile smoke
    """
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    setup_logging(level)


def setup_logging(level: int = logging.INFO) -> None:
    root = logging.getLogger()
    if any(getattr(h, "_harness", False) for h in root.handlers):
        root.setLevel(level)
        return
    try:
        import rich
        from rich.logging import RichHandler

        # logs and progress bars go to stderr: stdout carries only a command's output (tables, JSON)
        rich.reconfigure(stderr=True)
        handler: logging.Handler = RichHandler(show_path=False, show_time=False, markup=False)
    except ImportError:  # pragma: no cover
        handler = logging.StreamHandler(sys.stderr)
    handler._harness = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(level)


def get_cli() -> click.Group:
    """The CLI with every plugin's commands added (loads plugins once)."""
    from harness.plugins import load_plugins

    host = load_plugins()
    host.add_commands(cli)
    return cli


def main(argv: list[str] | None = None) -> None:
    get_cli().main(args=argv, prog_name="harness")
