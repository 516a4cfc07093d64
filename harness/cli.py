"""The ``harness`` command line: a thin layer that parses, calls one library function and prints.

Sub-commands come from plugins through the ``register_commands`` hook; the built-in ones live in
``harness/commands/``, and the options they share are declared once in ``harness/commands/options.py``.

Exit statuses (``harness.errors.ExitCode``; README, "Exit status"):

====  =============================================================================================================
0     done
1     partly done: a batch finished what it could and listed what failed (``PartlyDone``)
2     usage or input error, one line, no traceback: a bad option, a ``HarnessError`` (a file, field or plugin at
      fault), a file the system cannot read or write
70    a bug: any other exception. One ``bug:`` line says what and where, and where to report it; ``-v`` adds the
      traceback, and ``HARNESS_DEBUG=1`` lets the exception propagate (for a debugger or pytest)
130   interrupted (Ctrl-C); finished runs are kept and an interrupted run resumes
====  =============================================================================================================
"""

from __future__ import annotations

import logging
import os
import sys
import traceback
from pathlib import Path
from typing import Any, NoReturn

import click

from harness import __version__
from harness.errors import ExitCode, HarnessError, PartlyDone

#: Where a user reports a bug (printed with the ``bug:`` line).
REPORT_BUGS = "the harness's issue tracker"


class HarnessGroup(click.Group):
    """A click group that maps errors to the exit-code table above and accepts deprecated option spellings."""

    group_class = type  # sub-groups (`harness sensing ...`) behave the same

    def resolve_command(self, ctx: click.Context, args: list[str]):  # type: ignore[override]
        name, cmd, rest = super().resolve_command(ctx, args)
        if cmd is not None and not isinstance(cmd, click.Group):
            from harness.commands.options import rewrite_deprecated

            rest = rewrite_deprecated(cmd, rest)
        return name, cmd, rest

    def invoke(self, ctx: click.Context):  # type: ignore[override]
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except HarnessError as exc:
            click.secho(f"error: {exc}", err=True, fg="red")
            ctx.exit(ExitCode.USAGE)
        except PartlyDone as exc:
            click.secho(f"partly done: {exc}", err=True, fg="red")
            ctx.exit(ExitCode.PARTLY_DONE)
        except KeyboardInterrupt:  # Ctrl-C: the conventional 128 + SIGINT, not click's generic 1
            click.secho("interrupted", err=True, fg="red")
            ctx.exit(ExitCode.INTERRUPTED)
        except BrokenPipeError:  # `harness ... | head`: click's own handling
            raise
        except OSError as exc:  # a file the user named is missing, unreadable, or the disk is full
            click.secho(f"error: {exc}", err=True, fg="red")
            ctx.exit(ExitCode.USAGE)
        except Exception as exc:
            if os.environ.get("HARNESS_DEBUG"):
                raise
            report_bug(ctx, exc)

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(self.commands)


def where(exc: BaseException) -> str:
    """``harness/x.py:12`` of the innermost frame, and of the innermost frame of the project's own code when that
    is not the innermost (``numpy/...:9, called from harness/x.py:12``)."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return "?"
    root = Path(__file__).resolve().parent.parent

    def short(f: traceback.FrameSummary) -> str:
        path = Path(f.filename)
        try:
            rel = path.resolve().relative_to(root)
        except ValueError:
            rel = Path(*path.parts[-3:])
        return f"{rel.as_posix()}:{f.lineno}"

    last = frames[-1]
    own = next((f for f in reversed(frames) if Path(f.filename).resolve().is_relative_to(root)), None)
    if own is None or own is last:
        return short(last)
    return f"{short(last)}, called from {short(own)}"


def report_bug(ctx: click.Context, exc: Exception) -> NoReturn:
    """The short ``bug:`` message (with the traceback at ``-v``) and exit status 70."""
    verbose = (ctx.find_root().params.get("verbose") or 0) > 0
    text = str(exc).strip().splitlines()
    first = text[0][:300] if text else ""
    click.secho(f"bug: {type(exc).__name__}{': ' + first if first else ''} (at {where(exc)})", err=True, fg="red")
    click.echo(
        f"This is a bug in the harness or a plugin, not a problem with your input. Please report it to "
        f"{REPORT_BUGS} with the command line and the traceback, which `harness -v ...` prints.",
        err=True,
    )
    if verbose:
        click.echo("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)).rstrip(), err=True)
    raise click.exceptions.Exit(ExitCode.BUG)


@click.group(cls=HarnessGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="harness", help="Show the version and exit.")
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug); tracebacks of bugs.")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
def cli(verbose: int, quiet: bool) -> None:
    """Benchmark RGB-thermal fusion detectors on aligned, sample-matched data.

    \b
    Start here:
      harness list              what detectors, datasets and encodings are installed
      harness run --detector ours --dataset m3t-synth --profile smoke

    \b
    Exit status: 0 done, 1 partly done (a batch listed what failed), 2 usage or input error,
    70 a bug (-v shows the traceback), 130 interrupted.
    """
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    setup_logging(level)


class _LazyRichHandler(logging.Handler):
    """Log records through rich on stderr; rich is imported at the first record, not when a command starts."""

    def __init__(self) -> None:
        super().__init__()
        self._inner: logging.Handler | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self._inner is None:
            try:
                from rich.logging import RichHandler

                from harness.progress import console

                # logs and progress bars share one console on stderr: stdout carries only a command's output
                self._inner = RichHandler(console=console(), show_path=False, show_time=False, markup=False)
            except ImportError:  # pragma: no cover
                self._inner = logging.StreamHandler(sys.stderr)
        self._inner.emit(record)


def setup_logging(level: int = logging.INFO) -> None:
    root = logging.getLogger()
    if any(getattr(h, "_harness", False) for h in root.handlers):
        root.setLevel(level)
        return
    handler: Any = _LazyRichHandler()
    handler._harness = True
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
