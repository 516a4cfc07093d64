"""The plugin API of the harness: every hook a plugin may implement, documented here and nowhere else (the records
the hooks pass are documented in ``harness.api``, their checks in ``harness.contracts``).

Hooks are *registration calls* (the shape of ``llm`` and ``tox``): the host hands each plugin a ``register``
callback, the plugin declares what it provides, and the host owns names, conflicts and error messages. A plugin is
any module, class or object with functions marked ``@hookimpl``; it is found through the ``harness`` entry-point
group of an installed distribution, or listed in ``harness.plugins.DEFAULT_PLUGINS`` when it is built in.

Writing a plugin::

    from harness import hookimpl, DetectorSpec

    @hookimpl
    def register_detectors(register):
        register(DetectorSpec(name="tiny", build=build_tiny, input_kind="single",
                              description="a four-layer toy detector"))

and in the plugin's ``pyproject.toml``::

    [project.entry-points.harness]
    tiny = "harness_tiny"

A hook implementation may accept fewer arguments than the specification lists (pluggy passes only those it names).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import pluggy

if TYPE_CHECKING:  # pragma: no cover
    from harness.api import CommandGroup, DatasetSpec, DetectorSpec, EncodingSpec, LoggerSpec

PROJECT = "harness"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def register_detectors(register: Callable[[DetectorSpec], None]) -> None:
    """Declare detectors.

    Call ``register(DetectorSpec(...))`` once per detector. The spec names the detector, says whether it takes one
    stacked tensor (``input_kind="single"``, channels ``[R, G, B] + encoding``) or an ``(rgb, thermal)`` pair
    (``input_kind="dual"``), and gives ``build(num_classes, in_channels=..., **model_cfg) -> torch.nn.Module``.
    The module returns a dict of scalar losses in train mode when given targets, and a list of
    ``{"boxes", "scores", "labels"}`` dicts per image in eval mode; see ``harness.api.DetectorSpec`` for the
    whole model contract. Names must be unique across all loaded plugins; a duplicate is an error naming both.
    """


@hookspec
def register_datasets(register: Callable[[DatasetSpec], None]) -> None:
    """Declare datasets.

    Call ``register(DatasetSpec(...))`` once per dataset. ``DatasetSpec.open(root, **options)`` returns an object
    following ``harness.api.DatasetSource``: its categories, its groups (projects or sequences), its default folds
    and a generator of ``harness.api.AlignedSample`` records in the thermal frame. The host caches those samples
    once (``harness prepare``) so every detector and encoding reads byte-identical inputs. ``options`` are the
    config's ``dataset`` keys; an ``open`` that names a ``sensing`` parameter also gets the ``sensing`` section.
    ``DatasetSpec.protocol`` may name a YAML shipped in the plugin's package (``"package:protocol.yaml"``). The
    whole contract is in docs/plugins.md, "The dataset contract".
    """


@hookspec
def register_encodings(register: Callable[[EncodingSpec], None]) -> None:
    """Declare encodings: ways to turn an aligned sample into the detector's extra input channel.

    Call ``register(EncodingSpec(...))`` once per encoding. ``EncodingSpec.fn(sample, **params)`` returns a uint8
    HxW array in the thermal frame (or ``None`` for an encoding that adds no channel, such as RGB-only ``none``);
    ``needs`` says which field of the sample it reads (``"thermal"`` for radiometric encodings such as ``c2``,
    ``"ir8"`` for 8-bit ones), so the host can refuse, with a clear message, an encoding a dataset cannot feed.
    """


@hookspec
def register_loggers(register: Callable[[LoggerSpec], None]) -> None:
    """Declare experiment trackers (loggers that mirror runs into a tracking tool, beside ``log.jsonl``).

    Call ``register(LoggerSpec(name=..., create=...))`` once per tracker; ``create(TrackingOptions)`` returns an
    object with ``start(name, params, tags)``, ``log_epoch(step, metrics)``, ``log_final(metrics)``,
    ``log_artifact(path)`` and ``finish(status)`` (``harness.api.RunLogger``). ``requires`` names the packages
    it imports, so a missing one is reported before any run starts. Runs use the trackers named in
    ``tracking.loggers`` (``--log-to``).
    """


@hookspec
def register_commands(cli: CommandGroup) -> None:
    """Add sub-commands to the ``harness`` command line.

    ``cli`` is the top-level ``click.Group`` (``harness.api.CommandGroup``); decorate functions with
    ``@cli.command()`` or add groups with ``cli.add_command(...)``. Keep commands thin: parse, call one library
    function, print. Built-in commands are registered through this same hook, first. A command name another plugin
    (or the harness) already added is a conflict naming both plugins: the first command stays, and running the name
    is an error until one plugin is uninstalled or excluded.
    """
