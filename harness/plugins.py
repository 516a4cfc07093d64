"""The plugin host: one pluggy manager, the built-in plugins, entry-point discovery and a small facade.

Order of loading (``load_plugins``, idempotent):

1. the built-in modules listed in ``DEFAULT_PLUGINS`` (detectors, datasets, encodings and CLI commands of the
   harness are plugins like any other);
2. third-party plugins from the ``harness`` entry-point group of installed distributions, unless
   ``HARNESS_DISABLE_PLUGIN_AUTOLOAD`` is set (the test suite sets it); ``HARNESS_LOAD_PLUGINS`` is an allow-list
   of distribution names (comma separated, empty for none) that is honoured even when auto-loading is off;
3. ``*.py`` files in the folders named by ``HARNESS_PLUGINS_DIR`` (``os.pathsep`` separated), for plugins that
   are not packaged;
4. ``check_pending()``: a plugin implementing a hook that does not exist (a typo) is reported and dropped.

A plugin that fails to import, to validate or to register is recorded in ``host.problems`` with its name and the
error; the others still load. No code outside this module calls ``pm.hook`` directly: it goes through ``host``.
"""

from __future__ import annotations

import contextlib
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
from harness.api import DatasetSpec, DetectorSpec, EncodingSpec
from harness.errors import PluginError, UnknownNameError
from harness.tracking.spec import LoggerSpec

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
    "harness.commands.report",
    "harness.commands.weights",
    "harness.commands.score",
    "harness.commands.screen",
    "harness.tracking.tensorboard_logger",
    "harness.tracking.mlflow_logger",
)

#: hook name -> (kind shown to users, spec class)
_REGISTRATION_HOOKS: dict[str, tuple[str, type]] = {
    "register_detectors": ("detector", DetectorSpec),
    "register_datasets": ("dataset", DatasetSpec),
    "register_encodings": ("encoding", EncodingSpec),
    "register_loggers": ("logger", LoggerSpec),
}


@dataclass(frozen=True)
class PluginProblem:
    """Something a plugin did wrong, reported by plugin name instead of stopping the others."""

    plugin: str
    stage: str  # "import", "validate", a hook name, or "conflict"
    message: str

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

            def register(spec: Any, _pending: list = pending, _kind: str = kind, _cls: type = spec_cls) -> None:
                if not isinstance(spec, _cls):
                    raise PluginError(f"register() expects a {_cls.__name__}, got {type(spec).__name__}")
                _pending.append(spec)

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
            problems.append(
                PluginProblem(
                    owners[-1],
                    "conflict",
                    f"{kind} name {name!r} is registered by more than one plugin: {', '.join(repr(o) for o in owners)}",
                )
            )
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
                f"{kind} name {name!r} is registered by more than one plugin ({', '.join(owners)}); "
                f"uninstall one of them or restrict loading with {ENV_ALLOW}"
            )
        if name not in registry:
            broken = [p.plugin for p in self._hook_problems[hook_name] if p.stage == hook_name]
            err = UnknownNameError(kind, name, list(registry))
            if broken:
                err.args = (err.args[0] + f" (plugins that failed to register: {', '.join(broken)})",)
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
        return out

    # ----------------------------------------------------------------- commands
    def add_commands(self, cli: Any) -> None:
        """Let every plugin add its sub-commands to ``cli`` (once per group object)."""
        if id(cli) in self._commands_added:
            return
        self._commands_added.add(id(cli))
        for impl in self.pm.hook.register_commands.get_hookimpls():
            before = set(cli.commands)
            try:
                _call_impl(impl, cli=cli)
            except Exception as exc:
                self.load_problems.append(PluginProblem(impl.plugin_name, "register_commands", f"{type(exc).__name__}: {exc}"))
                log.warning("plugin %r failed in register_commands: %s", impl.plugin_name, exc)
                continue
            for name in set(cli.commands) - before:
                self._command_owners[name] = impl.plugin_name

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
            out.append(record)
        return out


def where(exc: BaseException) -> str:
    """`` (at file:line)``: the innermost frame outside the harness (the plugin's code) where ``exc`` was raised."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    own = str(Path(__file__).resolve().parent)
    outside = [f for f in frames if not f.filename.startswith("<") and "pluggy" not in Path(f.filename).parts
               and not str(Path(f.filename).resolve()).startswith(own)] or frames
    if isinstance(exc, SyntaxError) and exc.filename:
        return f" (at {exc.filename}:{exc.lineno})"
    return f" (at {outside[-1].filename}:{outside[-1].lineno})" if outside else ""


def _call_impl(impl: pluggy.HookImpl, **kwargs: Any) -> Any:
    """Call one hook implementation with the arguments it asks for (implementations may take fewer)."""
    return impl.function(*[kwargs[a] for a in impl.argnames])


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
    seen: set[str] = set()
    for dist in importlib.metadata.distributions():
        dist_name = dist.metadata["Name"] or ""
        if allow_n is not None and _normalise(dist_name) not in allow_n:
            continue
        for ep in dist.entry_points:
            if ep.group != ENTRY_POINT_GROUP or ep.name in seen or pm.has_plugin(ep.name) or pm.is_blocked(ep.name):
                continue
            seen.add(ep.name)
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


def _safe_register(plugin: Any, name: str) -> bool:
    try:
        pm.register(plugin, name=name)
    except Exception as exc:  # PluginValidationError (bad signature) or ValueError (name taken)
        host.load_problems.append(PluginProblem(name, "validate", f"{type(exc).__name__}: {exc}"))
        log.warning("plugin %r rejected: %s", name, exc)
        return False
    return True


def _check_pending() -> None:
    """Drop plugins that implement hooks the host does not define (usually a misspelled hook name)."""
    for _ in range(100):
        try:
            pm.check_pending()
            return
        except pluggy.PluginValidationError as exc:
            name = pm.get_name(exc.plugin) or repr(exc.plugin)
            host.load_problems.append(PluginProblem(name, "validate", str(exc)))
            pm.unregister(exc.plugin)


def register_plugin(plugin: Any, name: str | None = None) -> str:
    """Register a plugin object at run time (tests, notebooks); returns its name."""
    load_plugins()
    pm.register(plugin, name=name)
    pm.check_pending()
    host.refresh()
    return pm.get_name(plugin)  # type: ignore[return-value]


def unregister_plugin(name: str) -> None:
    if pm.has_plugin(name):
        pm.unregister(name=name)
    host.refresh()


@contextlib.contextmanager
def temporary_plugin(plugin: Any, name: str | None = None) -> Iterator[str]:
    """Register ``plugin`` for the duration of a ``with`` block, then unregister it, whatever happens."""
    registered = register_plugin(plugin, name)
    try:
        yield registered
    finally:
        unregister_plugin(registered)


def get_host() -> PluginHost:
    return load_plugins()


def reset_for_tests(loader: Callable[[], Any] | None = None) -> None:
    """Forget everything registered so ``load_plugins`` starts again (test helper)."""
    global _loaded
    for name, plugin in list(pm.list_name_plugin()):
        if plugin is not None:
            pm.unregister(plugin)
    host.__init__(pm)  # type: ignore[misc]
    _loaded = False
    if loader is not None:
        loader()
