"""The plugin host: one pluggy manager, the built-in plugins, entry-point discovery and a small facade.

Order of loading (``load_plugins``, idempotent):

1. the built-in modules listed in ``DEFAULT_PLUGINS`` (detectors, datasets, encodings and CLI commands of the
   harness are plugins like any other);
2. third-party plugins from the ``harness`` entry-point group of installed distributions, unless
   ``HARNESS_DISABLE_PLUGIN_AUTOLOAD`` is set (the test suite sets it); ``HARNESS_LOAD_PLUGINS`` is an allow-list
   of distribution names (comma separated, empty for none) that is honoured even when auto-loading is off;
3. ``*.py`` files in the folders named by ``HARNESS_PLUGINS_DIR`` (``os.pathsep`` separated), for plugins that
   are not packaged;
4. ``check_pending()``: a plugin implementing a hook that does not exist (a typo) is reported with the nearest
   hook name and dropped; asking for a name it would have registered says so.

A plugin with a function named like a hook but without ``@hookimpl`` (which the harness never calls) is reported
by name, with a warning.

A plugin that fails to import, to validate or to register is recorded in ``host.problems`` with its name and the
error; the others still load. A name registered twice (a detector, dataset, encoding, logger, command, or the plugin
name itself) is a conflict naming both plugins: the first registration stays, and asking for the name is a
``PluginError`` until one of them is removed. No code outside this module calls ``pm.hook`` directly: it goes
through ``host``. Fixtures for tests (throwaway plugins, a fresh host) are in ``harness.testing``.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import importlib.metadata
import importlib.util
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import pluggy

from harness import hookspecs
from harness.api import REGISTRATIONS, DatasetSpec, DetectorSpec, EncodingSpec, LoggerSpec
from harness.contracts import check_registered, set_owner_lookup, where
from harness.errors import PluginError, UnknownNameError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "harness"
ENV_ALLOW = "HARNESS_LOAD_PLUGINS"
ENV_DISABLE = "HARNESS_DISABLE_PLUGIN_AUTOLOAD"
ENV_DIRS = "HARNESS_PLUGINS_DIR"

#: Built-in plugins, registered in this order before any third-party plugin.
DEFAULT_PLUGINS: tuple[str, ...] = (
    "harness.commands.core",
    "adapters.detectors.icafusion",
    "adapters.detectors.eme",
    "adapters.detectors.cmadet",
    "harness.commands.profile",
    "harness.encodings",
    "harness.commands.sensing",
    "harness.commands.data",
    "harness.commands.cache",
    "adapters.datasets.m3t",
    "adapters.datasets.synthetic",
    "adapters.datasets.synth_command",
    "adapters.detectors.ours",
    "adapters.datasets.rgbt_tiny",
    "adapters.datasets.m3fd",
    "adapters.datasets.coco_rgbt",
    "adapters.datasets.llvip",
    "adapters.datasets.flir_aligned",
    "harness.commands.compare",
    "harness.commands.pretrain",
    "harness.commands.run",
    "harness.commands.sweep",
    "harness.commands.benchmark",
    "harness.commands.report",
    "harness.commands.weights",
    "harness.commands.score",
    "harness.commands.evidence",
    "harness.commands.screen",
    "harness.tracking.tensorboard_logger",
    "harness.tracking.mlflow_logger",
)

#: hook name -> (kind shown to users, record class): the registries (commands are kept by their click group)
_REGISTRATION_HOOKS: dict[str, tuple[str, type]] = REGISTRATIONS


def conflict_message(kind: str, name: str, owners: list[str]) -> str:
    """``detector name 'x' is registered by more than one plugin: 'a', 'b'`` (or twice by one plugin)."""
    distinct = list(dict.fromkeys(owners))
    if len(distinct) == 1:
        return f"{kind} name {name!r} is registered {len(owners)} times by plugin {distinct[0]!r}"
    return f"{kind} name {name!r} is registered by more than one plugin: {', '.join(repr(o) for o in distinct)}"


@dataclass(frozen=True)
class PluginProblem:
    """Something a plugin did wrong, reported by plugin name instead of stopping the others."""

    plugin: str
    stage: str  # "import", "validate", a hook name, or "conflict"
    message: str
    #: for a misspelled hook: the hook it was most likely meant to be
    hook: str | None = None

    def __str__(self) -> str:
        return f"plugin {self.plugin!r} ({self.stage}): {self.message}"


class PluginHost:
    """Typed facade over the plugin manager: the only place that calls hooks.

    Registries are built lazily, once per kind, and rebuilt after ``refresh()`` (which ``register_plugin`` and
    ``unregister_plugin`` call).
    """

    def __init__(self, pm: pluggy.PluginManager):
        self.pm = pm
        self.load_problems: list[PluginProblem] = []
        self.distributions: dict[str, importlib.metadata.Distribution] = {}
        self._registries: dict[str, dict[str, tuple[Any, str]]] = {}
        self._conflicts: dict[str, dict[str, list[str]]] = {}
        self._hook_problems: dict[str, list[PluginProblem]] = {}
        self._commands_added: set[int] = set()
        self._command_owners: dict[str, str] = {}
        #: command name -> every plugin that added it, in order (only names added more than once)
        self._command_conflicts: dict[str, list[str]] = {}

    # ----------------------------------------------------------------- registries
    def refresh(self) -> None:
        self._registries.clear()
        self._conflicts.clear()
        self._hook_problems.clear()

    def _registry(self, hook_name: str) -> dict[str, tuple[Any, str]]:
        if hook_name in self._registries:
            return self._registries[hook_name]
        kind, spec_cls = _REGISTRATION_HOOKS[hook_name]
        registry: dict[str, tuple[Any, str]] = {}
        conflicts: dict[str, list[str]] = {}
        problems: list[PluginProblem] = []
        for impl in getattr(self.pm.hook, hook_name).get_hookimpls():
            plugin_name = impl.plugin_name
            pending: list[Any] = []

            def register(spec: Any, _pending: list = pending, _cls: type = spec_cls) -> None:
                _pending.append(check_registered(spec, _cls))

            try:
                _call_impl(impl, register=register)
            except Exception as exc:  # a broken plugin must not take the others down
                problems.append(PluginProblem(plugin_name, hook_name, f"{type(exc).__name__}: {exc}{where(exc)}"))
                log.warning("plugin %r failed in %s: %s%s", plugin_name, hook_name, exc, where(exc))
                log.debug("traceback of plugin %r in %s", plugin_name, hook_name, exc_info=exc)
                continue
            for spec in pending:
                if spec.name in registry:
                    owners = conflicts.setdefault(spec.name, [registry[spec.name][1]])
                    owners.append(plugin_name)
                    continue
                registry[spec.name] = (spec, plugin_name)
        for name, owners in conflicts.items():
            problems.append(PluginProblem(owners[-1], "conflict", conflict_message(kind, name, owners)))
        self._registries[hook_name] = registry
        self._conflicts[hook_name] = conflicts
        self._hook_problems[hook_name] = problems
        return registry

    def _get(self, hook_name: str, name: str) -> Any:
        kind = _REGISTRATION_HOOKS[hook_name][0]
        registry = self._registry(hook_name)
        owners = self._conflicts[hook_name].get(name)
        if owners:
            raise PluginError(
                f"{conflict_message(kind, name, owners)}; uninstall one of them or restrict loading with {ENV_ALLOW}"
            )
        if name not in registry:
            broken = [p.plugin for p in self._hook_problems[hook_name] if p.stage == hook_name]
            misspelled = [p for p in self.load_problems if p.hook == hook_name]
            err = UnknownNameError(kind, name, list(registry))
            if broken:
                err.args = (err.args[0] + f" (plugins that failed to register: {', '.join(broken)})",)
            if misspelled:
                err.args = (
                    err.args[0]
                    + " Possibly why: "
                    + "; ".join(f"plugin {p.plugin!r}: {p.message}" for p in misspelled),
                )
            raise err
        return registry[name][0]

    def detectors(self) -> dict[str, DetectorSpec]:
        return {n: s for n, (s, _) in self._registry("register_detectors").items()}

    def datasets(self) -> dict[str, DatasetSpec]:
        return {n: s for n, (s, _) in self._registry("register_datasets").items()}

    def encodings(self) -> dict[str, EncodingSpec]:
        return {n: s for n, (s, _) in self._registry("register_encodings").items()}

    def loggers(self) -> dict[str, LoggerSpec]:
        return {n: s for n, (s, _) in self._registry("register_loggers").items()}

    def logger(self, name: str) -> LoggerSpec:
        return self._get("register_loggers", name)

    def detector(self, name: str) -> DetectorSpec:
        return self._get("register_detectors", name)

    def dataset(self, name: str) -> DatasetSpec:
        return self._get("register_datasets", name)

    def encoding(self, name: str) -> EncodingSpec:
        return self._get("register_encodings", name)

    def owner(self, kind: str, name: str) -> str:
        """Name of the plugin that registered ``name`` (``kind`` is 'detector', 'dataset', 'encoding' or 'command')."""
        if kind == "command":
            return self._command_owners[name]
        hook = {v[0]: k for k, v in _REGISTRATION_HOOKS.items()}[kind]
        return self._registry(hook)[name][1]

    @property
    def problems(self) -> list[PluginProblem]:
        out = list(self.load_problems)
        for hook in _REGISTRATION_HOOKS:
            self._registry(hook)
            out.extend(self._hook_problems[hook])
        out.extend(
            PluginProblem(owners[-1], "conflict", conflict_message("command", name, owners))
            for name, owners in self._command_conflicts.items()
        )
        return out

    def conflicts(self) -> dict[str, dict[str, list[str]]]:
        """``{kind: {name: [plugins that registered it, in order]}}`` for every name registered more than once."""
        out: dict[str, dict[str, list[str]]] = {}
        for hook, (kind, _) in _REGISTRATION_HOOKS.items():
            self._registry(hook)
            if self._conflicts[hook]:
                out[kind] = dict(self._conflicts[hook])
        if self._command_conflicts:
            out["command"] = dict(self._command_conflicts)
        return out

    def forget(self, plugin_name: str) -> None:
        """Drop what the host recorded about a plugin that was unregistered (its problems and command names)."""
        self.load_problems = [p for p in self.load_problems if p.plugin != plugin_name]
        self._command_owners = {n: o for n, o in self._command_owners.items() if o != plugin_name}
        self._command_conflicts = {n: o for n, o in self._command_conflicts.items() if plugin_name not in o}
        self.refresh()

    # ----------------------------------------------------------------- commands
    def add_commands(self, cli: Any) -> None:
        """Let every plugin add its sub-commands to ``cli`` (once per group object), built-ins first.

        A plugin that raises contributes no command. A name that is already taken is a conflict naming both plugins
        (``problems``): the command added first is kept in the listing, and running it is a ``PluginError`` until one
        of the plugins is uninstalled or excluded, as for any other name two plugins register.
        """
        if id(cli) in self._commands_added:
            return
        self._commands_added.add(id(cli))
        for impl in self.pm.hook.register_commands.get_hookimpls():
            before = dict(cli.commands)
            try:
                _call_impl(impl, cli=cli)
            except Exception as exc:
                cli.commands.clear()
                cli.commands.update(before)
                self.load_problems.append(
                    PluginProblem(impl.plugin_name, "register_commands", f"{type(exc).__name__}: {exc}{where(exc)}")
                )
                log.warning("plugin %r failed in register_commands: %s%s", impl.plugin_name, exc, where(exc))
                continue
            for name, command in list(cli.commands.items()):
                if before.get(name) is command:
                    continue
                first = getattr(before.get(name), _OWNER, None) or self._command_owners.get(name, "harness")
                if name not in before or first == impl.plugin_name:  # new, or its own again (host reset)
                    setattr(command, _OWNER, impl.plugin_name)
                    self._command_owners[name] = impl.plugin_name
                    continue
                owners = self._command_conflicts.setdefault(name, [first])
                if impl.plugin_name not in owners[1:]:  # the same plugin seen again by another group
                    owners.append(impl.plugin_name)
                cli.commands[name] = _conflicted(before[name], first, conflict_message("command", name, owners))
                log.warning("plugin %r: %s", impl.plugin_name, conflict_message("command", name, owners))

    # ----------------------------------------------------------------- listing
    def plugin_info(self, hook: str | None = None) -> list[dict[str, Any]]:
        """One record per registered plugin: name, distribution and version, hooks implemented, names registered."""
        from harness import __version__

        names_by_plugin: dict[str, dict[str, list[str]]] = {}
        for hook_name, (kind, _) in _REGISTRATION_HOOKS.items():
            for name, (_, owner) in self._registry(hook_name).items():
                names_by_plugin.setdefault(owner, {}).setdefault(kind + "s", []).append(name)
        for name, owner in self._command_owners.items():
            names_by_plugin.setdefault(owner, {}).setdefault("commands", []).append(name)
        clashes_by_plugin: dict[str, dict[str, list[str]]] = {}
        for kind, names in self.conflicts().items():
            for name, owners in names.items():
                for owner in dict.fromkeys(owners):
                    clashes_by_plugin.setdefault(owner, {}).setdefault(kind + "s", []).append(name)
        out = []
        for plugin_name, plugin in self.pm.list_name_plugin():
            if plugin is None or plugin_name in ("harness.hookspecs",):
                continue
            hooks = sorted(h.name for h in self.pm.get_hookcallers(plugin) or [])
            if hook and hook not in hooks:
                continue
            dist = self.distributions.get(plugin_name)
            builtin = plugin_name in DEFAULT_PLUGINS
            record: dict[str, Any] = {
                "name": plugin_name,
                "builtin": builtin,
                "distribution": dist.metadata["Name"] if dist else ("rgbt-harness" if builtin else None),
                "version": dist.version if dist else (__version__ if builtin else None),
                "hooks": hooks,
                "registered": {k: sorted(v) for k, v in sorted(names_by_plugin.get(plugin_name, {}).items())},
            }
            if plugin_name in clashes_by_plugin:  # names it shares with another plugin: errors until one goes
                record["conflicts"] = {k: sorted(v) for k, v in sorted(clashes_by_plugin[plugin_name].items())}
            out.append(record)
        return out


def _call_impl(impl: pluggy.HookImpl, **kwargs: Any) -> Any:
    """Call one hook implementation with the arguments it asks for (implementations may take fewer)."""
    return impl.function(*[kwargs[a] for a in impl.argnames])


#: Attribute naming the plugin that added a command (set by the host on every command it adds).
_OWNER = "harness_plugin"


def _conflicted(command: Any, owner: str, message: str) -> Any:
    """A stand-in for a command two plugins added: listed like the first one, and an error naming both when run."""
    import click

    def refuse(**_: Any) -> None:
        raise PluginError(f"{message}; uninstall one of them or restrict loading with {ENV_ALLOW}")

    stand_in = click.Command(
        command.name,
        callback=refuse,
        help=command.help,
        short_help=command.short_help,
        context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
        add_help_option=False,
        hidden=command.hidden,
    )
    setattr(stand_in, _OWNER, owner)
    return stand_in


# ------------------------------------------------------------------------------------------ the manager
pm = pluggy.PluginManager(hookspecs.PROJECT)
pm.add_hookspecs(hookspecs)
host = PluginHost(pm)
_loaded = False


def load_plugins() -> PluginHost:
    """Register built-in and third-party plugins once; return the host. Safe to call many times."""
    global _loaded
    if _loaded:
        return host
    _loaded = True
    for module_name in DEFAULT_PLUGINS:
        if pm.has_plugin(module_name):
            continue
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:
            host.load_problems.append(PluginProblem(module_name, "import", f"{type(exc).__name__}: {exc}{where(exc)}"))
            log.error("built-in plugin %s failed to import: %s%s", module_name, exc, where(exc))
            log.debug("traceback of plugin %s", module_name, exc_info=exc)
            continue
        _safe_register(module, module_name)
    allow = os.environ.get(ENV_ALLOW)
    if allow is not None:
        _load_entry_points({n.strip().lower() for n in allow.split(",") if n.strip()})
    elif not os.environ.get(ENV_DISABLE):
        _load_entry_points(None)
    for folder in filter(None, os.environ.get(ENV_DIRS, "").split(os.pathsep)):
        load_plugins_dir(Path(folder))
    _check_pending()
    host.refresh()
    return host


def _normalise(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


def _load_entry_points(allow: set[str] | None) -> None:
    allow_n = {_normalise(a) for a in allow} if allow is not None else None
    seen: dict[str, str] = {}  # entry-point name -> the distribution that declared it first
    for dist in importlib.metadata.distributions():
        dist_name = dist.metadata["Name"] or ""
        if allow_n is not None and _normalise(dist_name) not in allow_n:
            continue
        for ep in dist.entry_points:
            if ep.group != ENTRY_POINT_GROUP or pm.is_blocked(ep.name) or seen.get(ep.name) == dist_name:
                continue
            if ep.name in seen or pm.has_plugin(ep.name):
                _name_taken(ep.name, f"distribution {dist_name!r}", seen.get(ep.name))
                continue
            seen[ep.name] = dist_name
            try:
                plugin = ep.load()
            except Exception as exc:
                host.load_problems.append(PluginProblem(ep.name, "import", f"{type(exc).__name__}: {exc}{where(exc)}"))
                log.warning("plugin %r (%s) failed to import: %s%s", ep.name, dist_name, exc, where(exc))
                log.debug("traceback of plugin %r", ep.name, exc_info=exc)
                continue
            if _safe_register(plugin, ep.name):
                host.distributions[ep.name] = dist


def load_plugins_dir(folder: Path) -> None:
    """Register every ``*.py`` file in ``folder`` as a plugin module named after the file."""
    if not folder.is_dir():
        host.load_problems.append(PluginProblem(str(folder), "import", f"{ENV_DIRS} entry is not a folder"))
        return
    for path in sorted(folder.glob("*.py")):
        name = f"harness_plugins_dir.{path.stem}"
        try:
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
            sys.modules[name] = module
            spec.loader.exec_module(module)  # type: ignore[union-attr]
        except Exception as exc:
            host.load_problems.append(PluginProblem(str(path), "import", f"{type(exc).__name__}: {exc}{where(exc)}"))
            log.debug("traceback of plugin %s", path, exc_info=exc)
            continue
        _safe_register(module, path.stem)


def _name_taken(name: str, newcomer: str, first: str | None = None) -> None:
    """Record that ``newcomer`` (a distribution or a file) declares a plugin name another plugin already has."""
    holder = f"distribution {first!r}" if first else _holder(name)
    msg = (
        f"plugin name {name!r} is declared by more than one plugin: {holder} and {newcomer}; only the first is "
        f"loaded (rename one, or restrict loading with {ENV_ALLOW})"
    )
    host.load_problems.append(PluginProblem(name, "conflict", msg))
    log.warning("%s", msg)


def _holder(name: str) -> str:
    """How a registered plugin is named in a conflict: its distribution, file or module."""
    dist = host.distributions.get(name)
    if dist is not None:
        return f"distribution {dist.metadata['Name']!r}"
    plugin = pm.get_plugin(name)
    where_from = getattr(plugin, "__file__", None) or getattr(plugin, "__name__", None) or type(plugin).__name__
    return f"{where_from!r}"


def _safe_register(plugin: Any, name: str) -> bool:
    if pm.has_plugin(name):
        _name_taken(name, repr(getattr(plugin, "__file__", None) or getattr(plugin, "__name__", name)))
        return False
    try:
        pm.register(plugin, name=name)
    except Exception as exc:  # PluginValidationError (bad signature) or ValueError (name taken)
        host.load_problems.append(PluginProblem(name, "validate", f"{type(exc).__name__}: {exc}"))
        log.warning("plugin %r rejected: %s", name, exc)
        return False
    _check_unmarked(plugin, name)
    return True


def hook_names() -> list[str]:
    """The hooks the host defines (``harness.hookspecs``)."""
    marker = f"{hookspecs.PROJECT}_spec"
    return sorted(n for n in dir(hookspecs) if hasattr(getattr(hookspecs, n), marker))


def nearest_hook(name: str) -> str | None:
    """The defined hook a misspelled ``name`` most likely means."""
    close = difflib.get_close_matches(name, hook_names(), n=1, cutoff=0.6)
    return close[0] if close else None


def _check_unmarked(plugin: Any, name: str) -> None:
    """Warn about functions named like a hook (or nearly) that lack ``@hookimpl``: the harness never calls them."""
    marker = f"{hookspecs.PROJECT}_impl"
    for attr in sorted(a for a in dir(plugin) if a.startswith("register_")):
        try:
            fn = getattr(plugin, attr)
        except Exception:  # noqa: BLE001 - a property that fails is not a hook
            continue
        near = [attr] if attr in hook_names() else difflib.get_close_matches(attr, hook_names(), n=1, cutoff=0.85)
        hook = near[0] if near else None
        if hook is None or not callable(fn) or hasattr(fn, marker):
            continue
        msg = (
            f"function {attr!r} looks like the hook {hook!r} but has no @hookimpl, so the harness never calls "
            f"it; decorate it with @harness.hookimpl"
        )
        host.load_problems.append(PluginProblem(name, "validate", msg, hook))
        log.warning("plugin %r: %s", name, msg)


def _unknown_hooks(plugin: Any) -> list[str]:
    return sorted(hc.name for hc in pm.get_hookcallers(plugin) or [] if not hc.has_spec())


def _pending_problem(plugin: Any, name: str) -> PluginProblem:
    """A plugin implementing hooks the host does not define, with the nearest hook for each."""
    parts, nearest = [], None
    for hook in _unknown_hooks(plugin) or ["?"]:
        near = nearest_hook(hook)
        nearest = nearest or near
        parts.append(
            f"unknown hook {hook!r}, "
            + (f"did you mean {near!r}?" if near else f"the hooks are {', '.join(hook_names())}")
        )
    return PluginProblem(name, "validate", "not loaded: " + "; ".join(parts), nearest)


def _check_pending() -> None:
    """Drop plugins that implement hooks the host does not define (usually a misspelled hook name)."""
    for _ in range(100):
        try:
            pm.check_pending()
            return
        except pluggy.PluginValidationError as exc:
            name = pm.get_name(exc.plugin) or repr(exc.plugin)
            problem = _pending_problem(exc.plugin, name)
            host.load_problems.append(problem)
            log.warning("plugin %r %s", name, problem.message)
            pm.unregister(exc.plugin)


def register_plugin(plugin: Any, name: str | None = None) -> str:
    """Register a plugin object at run time (tests, notebooks); returns its name. A misspelled hook is a
    ``PluginError`` naming the plugin and the nearest hook (the plugin is not kept)."""
    load_plugins()
    if name is not None and pm.has_plugin(name):
        raise PluginError(f"plugin name {name!r} is already registered ({_holder(name)}); choose another name")
    pm.register(plugin, name=name)
    registered = pm.get_name(plugin) or repr(plugin)
    try:
        pm.check_pending()
    except pluggy.PluginValidationError:
        problem = _pending_problem(plugin, registered)
        pm.unregister(plugin)
        raise PluginError(str(problem)) from None
    _check_unmarked(plugin, registered)
    host.refresh()
    return registered


def unregister_plugin(name: str) -> None:
    """Unregister a plugin by name and forget what the host recorded about it."""
    if pm.has_plugin(name):
        pm.unregister(name=name)
    host.forget(name)


def unload_plugins() -> None:
    """Unregister every plugin and forget every record, so that the next ``load_plugins`` starts again."""
    global _loaded
    for _, plugin in list(pm.list_name_plugin()):
        if plugin is not None:
            pm.unregister(plugin)
    host.__init__(pm)  # type: ignore[misc]
    _loaded = False


def get_host() -> PluginHost:
    return load_plugins()


# how ``harness.contracts`` (below the host) names the plugin that registered a record in its errors
set_owner_lookup(lambda kind, name: get_host().owner(kind, name))


@contextlib.contextmanager
def _temporary_plugin(plugin: Any, name: str | None = None) -> Iterator[str]:
    """Register ``plugin`` for the duration of a ``with`` block, then unregister it, whatever happens; yields the name
    it is registered under."""
    registered = register_plugin(plugin, name)
    try:
        yield registered
    finally:
        unregister_plugin(registered)


def reset_plugins(loader: Callable[[], Any] | None = None) -> None:
    """Forget every registered plugin so that ``load_plugins`` starts again; then call ``loader`` when given."""
    unload_plugins()
    if loader is not None:
        loader()


def __getattr__(name: str) -> Any:
    """``reset_for_tests`` is now ``reset_plugins``, and both it and ``temporary_plugin`` are documented in
    ``harness.testing``; the old spellings still work."""
    if name in ("temporary_plugin", "reset_for_tests"):
        import warnings

        warnings.warn(f"harness.plugins.{name} moved to harness.testing", DeprecationWarning, stacklevel=2)
        return _temporary_plugin if name == "temporary_plugin" else reset_plugins
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
