"""The command-line vocabulary, declared once: the options commands share, and the spellings they replaced.

Every built-in command takes its shared options from here, and a plugin's command should too, so that one word means
one thing everywhere (docs/plugins.md, "Commands"):

=======================  ==============================================================================================
``--folds``              held-out fold(s): ``all`` or comma-separated names (``P1,P4+P5``); one name where a command
                         works on one fold (``ablate``, ``pretrain``, ``score``)
``--seeds``              training seed(s), comma-separated (``0,1,2``) [default: the protocol's]; one seed where a
                         command trains one run (``pretrain``)
``--dataset``            one dataset; ``--datasets``: several, comma-separated or repeated (``compare``, ``report``,
                         ``sweep``)
``--detector``           one detector; ``--detectors``: several, comma-separated or repeated (``profile``, ``show``,
                         ``sweep``)
``--init``               a checkpoint a model starts from (``run``, ``pretrain``)
``--out``                the file or folder a command writes (``export``'s ONNX file included; ``--onnx`` is
                         ``profile``'s switch for timing onnxruntime)
``--bootstrap-seed``     seed of the paired bootstrap's resamples
``--format``             what a command prints on stdout: ``text`` (aligned, 100 columns), ``json``, ``md``
                         (Markdown), ``csv``; each command accepts the ones it can print
``--profile``            run profile (``configs/profiles/``), which also names the default results store
``--store``              results store root [default: ``results/<profile>``, the same rule in every command]
``--config``, ``--set``  extra YAML config files and ``KEY=VALUE`` overrides, applied after the profile
``--no-progress``        no progress bars and no progress lines (bars show only on a terminal anyway)
``--approximate``,       how the R-JPEGs the harness cannot correct itself are decoded (``sensing decode``,
``--converter``,         ``screen``): approximate temperatures with their measured bound, or DJI's own SDK
``--dji-irp``,
``--converter-timeout``
=======================  ==============================================================================================

Usage (decorators, applied like ``click.option``)::

    from harness.commands import options as opt

    @cli.command(name="screen")
    @opt.profile_option()
    @opt.store_option()
    @opt.format_option("text", "json")
    @opt.no_progress_option()
    def screen_cmd(profile: str, store: Path | None, fmt: str) -> None:
        root = opt.resolve_store(store, profile)
        ...

Options of a common kind rather than a shared word have builders too: ``choice_option`` (its default shown),
``input_file_option`` and ``input_path_option`` (an existing file, or file or folder, read), ``folder_option`` (a
folder written), ``path_option`` (any ``click.Path``) and ``workers_option``.

Old spellings (``--fold``, ``--seed`` for the bootstrap seed, ``--json``, ``--format markdown``, ``report --dataset``,
``show``/``profile --detector``, ``export --onnx``, ``synth --profile``, ``sensing register --init``, ...) keep
working for one release: the CLI rewrites them to the new ones before parsing and prints one ``deprecated:`` line on
stderr (``rewrite_deprecated``). An option declares its old spellings with ``old=``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import click

F = TypeVar("F", bound=Callable[..., Any])

#: The run profile a command uses when given no ``--profile``.
DEFAULT_PROFILE = "smoke"
#: Where results stores live: ``results/<profile>`` unless ``--store`` says otherwise.
STORE_PARENT = Path("results")
#: Every value ``--format`` can take, in the order help lists them.
FORMATS = ("text", "json", "md", "csv")
DEPRECATION_NOTE = "the old spelling goes in the next release"


class SharedOption(click.Option):
    """A ``click.Option`` that knows its place in the vocabulary (``shared``: its name there, ``None`` for a
    command's own option) and its deprecated spellings (``old``: old argv token -> the tokens that replace it)."""

    def __init__(
        self, *args: Any, shared: str | None = None, old: Mapping[str, Sequence[str]] | None = None, **kwargs: Any
    ):
        super().__init__(*args, **kwargs)
        self.shared = shared
        self.old = {k: tuple(v) for k, v in (old or {}).items()}


def option(
    *decls: str, shared: str | None = None, old: Sequence[str] | Mapping[str, Sequence[str]] = (), **kwargs: Any
) -> Callable[[F], F]:
    """``click.option`` with deprecated spellings: ``old=("--fold",)`` renames to this option's first long name;
    a mapping (``{"--json": ("--format", "json")}``) gives the replacement tokens."""
    new = next(d for d in decls if d.startswith("--"))
    mapping = dict(old) if isinstance(old, Mapping) else {o: (new,) for o in old}
    return click.option(*decls, cls=SharedOption, shared=shared, old=mapping, **kwargs)


def _join(*parts: str | None) -> str:
    return " ".join(p for p in parts if p)


# ------------------------------------------------------------------------------------------------ the vocabulary
def folds_option(
    *,
    one: bool = False,
    required: bool = False,
    default: str | None = "all",
    help: str | None = None,
    old: Sequence[str] = ("--fold",),
) -> Callable[[F], F]:
    """``--folds`` -> parameter ``folds`` (a string: ``all``, ``P1`` or ``P1,P4+P5``). ``one=True``: the command
    works on one fold, and a comma is a usage error. ``--fold`` is the deprecated spelling everywhere."""
    text = help or (
        "The one held-out fold to use, e.g. P4+P5."
        if one
        else "Held-out folds: 'all' or comma-separated fold names, e.g. P1,P4+P5."
    )

    def check(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
        if one and value is not None and "," in value:
            raise click.BadParameter(f"{value!r}: this command works on one fold; give one name, e.g. P4+P5")
        return value

    return option(
        "--folds",
        "folds",
        shared="folds",
        old=old,
        required=required,
        default=None if required else default,
        show_default=default is not None and not required,
        callback=check,
        metavar="FOLD" if one else "FOLDS",
        help=text,
    )


def seeds_option(
    *, one: bool = False, default: str | int | None = None, help: str | None = None, old: Sequence[str] = ()
) -> Callable[[F], F]:
    """``--seeds`` -> parameter ``seeds``: training seeds, a comma-separated string (``None``: the protocol's, or all
    runs' for a filter). ``one=True``: the command trains one run, so one seed, as an ``int`` (or ``None`` when not
    given and no ``default``); a comma is a usage error, as for ``folds_option(one=True)``."""
    if one:

        def check(ctx: click.Context, param: click.Parameter, value: str | int | None) -> int | None:
            if value is None or isinstance(value, int):
                return value
            if "," in value:
                raise click.BadParameter(f"{value!r}: this command trains one run; give one seed, e.g. 0")
            try:
                return int(value)
            except ValueError:
                raise click.BadParameter(f"{value!r} is not an integer seed") from None

        return option(
            "--seeds",
            "seeds",
            shared="seeds",
            old=old,
            type=str,
            default=None if default is None else str(int(default)),
            show_default=default is not None,
            callback=check,
            metavar="SEED",
            help=help or "The training seed.",
        )
    return option(
        "--seeds",
        "seeds",
        shared="seeds",
        old=old,
        default=default,
        show_default=default is not None,
        metavar="SEEDS",
        help=help or "Training seeds, comma-separated, e.g. 0,1,2 [default: protocol.seeds].",
    )


def names_option(
    plural: str, *, required: bool = False, help: str, old: Sequence[str] = (), metavar: str | None = None
) -> Callable[[F], F]:
    """``--datasets`` / ``--detectors`` (``plural``) -> a parameter of that name: a tuple of names, in the order given,
    comma-separated, repeated or both (``--datasets m3t,rgbt-tiny`` is ``--datasets m3t --datasets rgbt-tiny``); an
    empty tuple when not given. The singular (``--dataset``, ``--detector``) always names one."""
    name = plural.lstrip("-")

    def flatten(ctx: click.Context, param: click.Parameter, value: Sequence[str]) -> tuple[str, ...]:
        return tuple(n for item in value or () for n in split_list(item))

    return option(
        plural,
        name,
        shared=name,
        old=old,
        multiple=True,
        required=required,
        callback=flatten,
        metavar=metavar or name.upper().rstrip("S"),
        help=help,
    )


def bootstrap_seed_option(*, old: Sequence[str] = ()) -> Callable[[F], F]:
    """``--bootstrap-seed`` -> parameter ``bootstrap_seed`` (int, default 0)."""
    return option(
        "--bootstrap-seed",
        "bootstrap_seed",
        shared="bootstrap-seed",
        old=old,
        type=int,
        default=0,
        show_default=True,
        help="Seed of the paired bootstrap's resamples (same seed, same intervals).",
    )


class _FormatChoice(click.Choice):
    """A ``click.Choice`` that maps deprecated values (``markdown``) to their new names, with the deprecation line."""

    def __init__(self, choices: Sequence[str], aliases: Mapping[str, str]):
        super().__init__(list(choices))
        self.aliases = dict(aliases)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and value in self.aliases:
            new = self.aliases[value]
            deprecation(f"--format {value}", f"--format {new}")
            value = new
        return super().convert(value, param, ctx)


_FORMAT_WORDS = {"text": "text (aligned, 100 columns)", "json": "json", "md": "md (Markdown)", "csv": "csv"}


def format_option(
    *formats: str, default: str = "text", old_json: bool = False, aliases: Mapping[str, str] | None = None
) -> Callable[[F], F]:
    """``--format`` -> parameter ``fmt``: what the command prints on stdout, one of ``formats`` (a subset of
    ``FORMATS``). ``old_json=True`` keeps ``--json`` as a deprecated spelling of ``--format json``."""
    bad = [f for f in formats if f not in FORMATS]
    if bad or default not in formats:
        raise ValueError(f"format_option: {bad or default!r} is not one of {FORMATS}")
    ordered = [f for f in FORMATS if f in formats]
    words = ", ".join(_FORMAT_WORDS[f] for f in ordered[:-1]) + f" or {_FORMAT_WORDS[ordered[-1]]}"
    old = {"--json": ("--format", "json")} if old_json and "json" in formats else {}
    return option(
        "--format",
        "fmt",
        shared="format",
        old=old,
        type=_FormatChoice(ordered, aliases or {}),
        default=default,
        show_default=True,
        help=f"What to print on stdout: {words}.",
    )


#: ``ctx.meta`` key: ``--no-progress`` was given to the command being invoked
_NO_PROGRESS = "harness.no_progress"


def no_progress_option() -> Callable[[F], F]:
    """``--no-progress``: switches progress bars and progress lines off while this command runs (no parameter; code
    that needs a bool asks ``harness.progress.progress_on()``). The switch wraps the command's body, so a usage error
    found while parsing (after ``--no-progress`` was read) leaves progress as it was."""

    def given(ctx: click.Context, param: click.Parameter, value: bool) -> None:
        if value:
            ctx.meta[_NO_PROGRESS] = True

    def deco(f: F) -> F:
        @functools.wraps(f)
        def run(*args: Any, **kwargs: Any) -> Any:
            ctx = click.get_current_context(silent=True)
            if ctx is None or not ctx.meta.get(_NO_PROGRESS):
                return f(*args, **kwargs)
            from harness import progress

            with progress.switched_off():
                return f(*args, **kwargs)

        return option(  # type: ignore[return-value]
            "--no-progress",
            shared="no-progress",
            is_flag=True,
            expose_value=False,
            callback=given,
            help="No progress bars or progress lines on stderr (bars show only on a terminal anyway).",
        )(run)

    return deco


def profile_option(
    *, uses_config: bool = True, param: str = "profile", help: str | None = None, default: str = DEFAULT_PROFILE
) -> Callable[[F], F]:
    """``--profile`` (default ``smoke``, or the profile a command is about: ``benchmark``) -> parameter ``profile``
    (or ``param``). ``uses_config=False``: the command uses the profile only for its default store."""
    text = help or (
        "Run profile under configs/profiles/ (smoke: small, CPU; demo: `make demo`'s; benchmark: the reference "
        "results'; paper: the seed's protocol); it also names the default store, results/<profile>."
        if uses_config
        else "Run profile whose results store (results/<profile>) is used when --store is not given."
    )
    return option("--profile", param, shared="profile", default=default, show_default=True, help=text)


def store_option(*, reads: bool = False, help: str | None = None) -> Callable[[F], F]:
    """``--store`` -> parameter ``store`` (a ``Path`` or ``None``; ``resolve_store`` applies the default rule)."""
    text = help or _join("Results store root" + (" to read" if reads else ""), "[default: results/<profile>].")
    return option(
        "--store", "store", shared="store", type=click.Path(file_okay=False, path_type=Path), default=None, help=text
    )


def config_options(*, help_set: str | None = None, after_profile: bool = True) -> Callable[[F], F]:
    """``--config`` (parameter ``config_files``) and ``--set`` (parameter ``overrides``), both repeatable."""
    where = ", applied after the profile" if after_profile else ""

    def bundled(ctx: click.Context, param: click.Parameter, value: tuple[str, ...]) -> tuple[str, ...]:
        from harness.config import config_file

        # configs/... not in the working folder: the copy installed with the harness (config_file)
        found = [(v, config_file(v)) for v in value]
        return tuple(v if path == Path(v) else str(path) for v, path in found)

    def deco(f: F) -> F:
        f = option(
            "--set",
            "overrides",
            shared="set",
            multiple=True,
            metavar="KEY=VALUE",
            help=help_set or "Override one config key, e.g. --set protocol.epochs=5 (repeatable).",
        )(f)
        return option(
            "--config",
            "config_files",
            shared="config",
            multiple=True,
            type=click.Path(dir_okay=False),
            callback=bundled,
            help=f"Extra YAML config file(s){where}; configs/... names the installed copy when the working folder "
            "has no such file (repeatable).",
        )(f)

    return deco


def decode_route_options() -> Callable[[F], F]:
    """``--approximate`` (parameter ``approximate``), ``--converter`` (``converter``), ``--dji-irp`` (``dji_irp``)
    and ``--converter-timeout`` (``converter_timeout``): the routes for R-JPEGs the harness cannot correct itself,
    as ``sensing.radiometry.approximate``, ``converter``, ``dji_irp`` and ``converter_timeout_s`` set them."""

    def deco(f: F) -> F:
        f = option(
            "--converter-timeout",
            shared="converter-timeout",
            type=click.FloatRange(min=0, min_open=True),
            default=None,
            help="Seconds one converter run may take (default 120).",
        )(f)
        f = option(
            "--dji-irp",
            "dji_irp",
            shared="dji-irp",
            default=None,
            metavar="PATH",
            help="DJI Thermal SDK's dji_irp (the program or its folder); implies --converter dji_irp.",
        )(f)
        f = option(
            "--converter",
            shared="converter",
            default=None,
            metavar="dji_irp|TEMPLATE",
            help="Decode the files the harness cannot correct with DJI's own SDK (dji_irp, on PATH or "
            "--dji-irp) or a command template holding {input} and {output}.",
        )(f)
        return option(
            "--approximate",
            shared="approximate",
            is_flag=True,
            help="Accept approximate temperatures, each with its measured bound, for files whose exact "
            "correction needs DJI's own tables (M4T, H30T, some M2EA); labelled in every output.",
        )(f)

    return deco


def stack(*decorators: Callable[[F], F]) -> Callable[[F], F]:
    """Several option decorators as one, listed in the order they appear in ``--help`` (top first)."""

    def deco(f: F) -> F:
        for d in reversed(decorators):
            f = d(f)
        return f

    return deco


# ------------------------------------------------------------------------------------------------ option kinds
def choice_option(*decls: str, choices: Sequence[str], help: str, default: str | None = None) -> Callable[[F], F]:
    """One of ``choices`` (``click.Choice``), by default the first, shown in help."""
    return click.option(
        *decls,
        type=click.Choice(list(choices)),
        default=choices[0] if default is None else default,
        show_default=True,
        help=help,
    )


def path_option(*decls: str, help: str, required: bool = False, **path: Any) -> Callable[[F], F]:
    """A ``click.Path(**path)`` option, ``None`` when not given."""
    return click.option(*decls, type=click.Path(**path), required=required, default=None, help=help)


def input_file_option(*decls: str, help: str, required: bool = False) -> Callable[[F], F]:
    """An existing file the command reads (a ``str``; ``None`` when not given)."""
    return path_option(*decls, help=help, required=required, dir_okay=False, exists=True)


def input_path_option(*decls: str, help: str, required: bool = False) -> Callable[[F], F]:
    """An existing file or folder the command reads (a ``Path``; ``None`` when not given)."""
    return path_option(*decls, help=help, required=required, exists=True, path_type=Path)


def folder_option(*decls: str, help: str, required: bool = False) -> Callable[[F], F]:
    """A folder the command writes (a ``Path``; ``None`` when not given)."""
    return path_option(*decls, help=help, required=required, file_okay=False, path_type=Path)


def workers_option(help: str) -> Callable[[F], F]:
    """``--workers`` -> parameter ``workers``: processes, at least 1 and at most ``config.worker_cap()`` (4 per CPU
    core) [default: 1]."""
    from harness.config import worker_cap

    return click.option(
        "--workers", type=click.IntRange(min=1, max=worker_cap()), default=1, show_default=True, help=help
    )


def model_shape_options(*, imgsz_help: str = "Square input size.") -> Callable[[F], F]:
    """``--imgsz`` (640), ``--num-classes`` (8) and ``--in-channels`` (4): the model a command builds (``profile``,
    ``export``) -> parameters ``imgsz``, ``num_classes``, ``in_channels``."""
    return stack(
        click.option("--imgsz", type=int, default=640, show_default=True, help=imgsz_help),
        click.option("--num-classes", type=int, default=8, show_default=True, help="Classes of the detection head."),
        click.option(
            "--in-channels",
            type=int,
            default=4,
            show_default=True,
            help="Channels of a single-stream detector's input (3 + encoding channels).",
        ),
    )


def bootstrap_options(*, resamples: int, help_resamples: str, old_seed: Sequence[str] = ()) -> Callable[[F], F]:
    """``--resamples`` (default ``resamples``), ``--bootstrap-seed`` and ``--workers``: the paired bootstrap of
    ``report`` and ``compare-detectors`` -> parameters ``resamples``, ``bootstrap_seed``, ``workers``."""
    return stack(
        click.option(
            "--resamples", type=click.IntRange(min=0), default=resamples, show_default=True, help=help_resamples
        ),
        bootstrap_seed_option(old=old_seed),
        workers_option("Processes for the bootstrap's re-scoring."),
    )


def reference_results_option() -> Callable[[F], F]:
    """``--reference-results shipped|DIR`` -> parameter ``reference_results`` (``None`` when not given): reference
    results read beside the store (``harness.references.load_references``)."""
    return option(
        "--reference-results",
        "reference_results",
        shared="reference-results",
        default=None,
        metavar="shipped|DIR",
        help="Also read reference results beside the store: `shipped` (the project's benchmark results) or a folder "
        "`harness benchmark export` wrote. Their entries are named ref:DETECTOR; refused when the store's runs "
        "used other samples.",
    )


def echo_plan(groups: Sequence[tuple[str, Iterable[Any]]], total: str) -> None:
    """What a ``--dry-run`` prints: one line per item of each ``(label, items)`` group, the label first, then
    ``total``."""
    for label, items in groups:
        for item in items:
            click.echo(f"{label}{item}")
    click.echo(total)


def default_store(profile: str | None) -> Path:
    """The one rule for a store not named with ``--store``: ``results/<profile>`` (``smoke`` when none)."""
    return STORE_PARENT / (profile or DEFAULT_PROFILE)


def resolve_store(store: str | Path | None, profile: str | None) -> Path:
    return Path(store) if store is not None else default_store(profile)


def split_list(text: str | None) -> list[str]:
    """``"a, b,,c"`` -> ``["a", "b", "c"]`` (comma-separated option values)."""
    return [t.strip() for t in (text or "").split(",") if t.strip()]


def parse_seeds(text: str | None) -> list[int] | None:
    """``--seeds 0,1,2`` -> ``[0, 1, 2]``; ``None`` (not given) stays ``None``."""
    if text is None or not text.strip():
        return None
    try:
        return [int(s) for s in split_list(text)]
    except ValueError:
        from harness.errors import ConfigError

        raise ConfigError(f"--seeds {text!r}: expected comma-separated integers such as 0,1,2") from None


# ------------------------------------------------------------------------------------------------ old spellings
def deprecation(old: str, new: str) -> None:
    """The one line on stderr that a deprecated spelling was used."""
    click.secho(f"deprecated: {old}, use {new} ({DEPRECATION_NOTE})", err=True, fg="yellow")


def deprecated_spellings(command: click.Command) -> dict[str, tuple[str, ...]]:
    """Old argv token -> new tokens, for every option of ``command``."""
    out: dict[str, tuple[str, ...]] = {}
    for p in command.params:
        out.update(getattr(p, "old", None) or {})
    return out


def rewrite_deprecated(command: click.Command, args: Sequence[str]) -> list[str]:
    """``args`` with every deprecated spelling of ``command``'s options replaced by the new one (``--fold P1`` ->
    ``--folds P1``, ``--fold=P1`` -> ``--folds=P1``, ``--json`` -> ``--format json``), one ``deprecated:`` line on
    stderr per spelling used. Nothing after ``--`` is touched."""
    mapping = deprecated_spellings(command)
    if not mapping:
        return list(args)
    out: list[str] = []
    warned: set[str] = set()
    for i, tok in enumerate(args):
        if tok == "--":
            out.extend(args[i:])
            break
        head, eq, value = tok.partition("=")
        new = mapping.get(head) if tok.startswith("--") else None
        if new is None or (eq and len(new) != 1):
            out.append(tok)
            continue
        if head not in warned:
            warned.add(head)
            deprecation(head, " ".join(new))
        out.extend([f"{new[0]}={value}"] if eq else new)
    return out


def shared_options(command: click.Command) -> dict[str, click.Parameter]:
    """The vocabulary's options of ``command`` by their shared name (what the CLI's tests check)."""
    return {p.shared: p for p in command.params if isinstance(p, SharedOption) and p.shared}
