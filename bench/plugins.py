"""Plugin loading and the registries of datasets, methods and metrics.

Built-ins and third-party plugins load the same way: entry points of the ``pcfbench``
group. Built-ins are the entry points of the ``pcfbench`` distribution itself
(``ep.dist.name``), never recognised by their name: a third-party entry point called
``builtin-...`` is a third-party plugin like any other, and one that takes the name of a
built-in is refused (reported, never loaded). ``PCFBENCH_PLUGINS`` (comma-separated
entry-point names) allow-lists third-party plugins (empty: none); ``PCFBENCH_BLOCK_PLUGINS``
blocks plugins by name, built-ins too.

Registration is transactional per plugin: a plugin whose registration hook raises (a
duplicate name, a bad target, its own error) keeps nothing it registered, in any registry.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys
import traceback
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Iterable

import pluggy

from pcfbench import hookspecs
from pcfbench.errors import PluginError, unknown_name
from pcfbench.registry import (
    DatasetRegister, MethodRegister, MetricRegister, Register, Registry, SettingRegister,
)

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.protocol import Setting

BUILTIN_PREFIX = "builtin-"
#: the distribution whose entry points are the built-ins
BUILTIN_DISTRIBUTION = "pcfbench"


def is_builtin_entry_point(ep: importlib.metadata.EntryPoint) -> bool:
    """True for an entry point of the ``pcfbench`` distribution itself (whatever its name)."""
    dist = getattr(ep, "dist", None)
    name = getattr(dist, "name", None) if dist is not None else None
    return name is not None and name.replace("_", "-").lower() == BUILTIN_DISTRIBUTION


def _setting_check(obj: Any) -> str | None:
    from pcfbench.protocol import Setting

    return None if isinstance(obj, Setting) else f"must be a pcfbench.Setting, got {obj!r}"


def _is_subclass_check(base_path: str) -> Callable[[Any], str | None]:
    def check(obj: Any) -> str | None:
        module_name, _, attr = base_path.partition(":")
        base = getattr(importlib.import_module(module_name), attr)
        if not (isinstance(obj, type) and issubclass(obj, base)):
            return f"must be a subclass of {base.__module__}.{base.__name__}, got {obj!r}"
        return None

    return check


def _metric_check(obj: Any) -> str | None:
    from pcfbench.metrics.base import Metric

    if not isinstance(obj, Metric):
        return f"must be a pcfbench.metrics.Metric instance, got {obj!r}"
    return None


@dataclass
class PluginInfo:
    name: str
    source: str
    error: str | None = None
    registered: dict[str, list[str]] = field(default_factory=dict)
    #: an entry point of the pcfbench distribution itself
    builtin: bool = False


class Plugins:
    """The plugin manager and the registries of datasets, methods, metrics and settings.

    Plugins are first added to the pluggy manager (``register``), then their registration
    hooks are called (``collect``) hook by hook in pluggy's call order (``call_order``), so
    ``@pcfbench.hookimpl(tryfirst=True)`` / ``(trylast=True)`` take effect. Each plugin's
    implementation is called on its own, through ``pm.subset_hook_caller``, with a ``register``
    that records the plugin's name: what it registers is attributed to it (``pcfbench
    plugins``), and an exception in it marks that plugin failed without touching the others.
    """

    def __init__(self) -> None:
        self.pm = pluggy.PluginManager("pcfbench")
        self.pm.add_hookspecs(hookspecs)
        self.datasets = Registry("dataset", _is_subclass_check("pcfbench.dataset:DatasetAdapter"))
        self.methods = Registry("method", _is_subclass_check("pcfbench.method:Method"))
        self.metrics = Registry("metric", _metric_check)
        self.settings = Registry("setting", _setting_check)
        self.info: dict[str, PluginInfo] = {}

    def registries(self) -> dict[str, tuple[Registry, type[Register], str]]:
        return {
            "datasets": (self.datasets, DatasetRegister, "register_datasets"),
            "methods": (self.methods, MethodRegister, "register_methods"),
            "metrics": (self.metrics, MetricRegister, "register_metrics"),
            "settings": (self.settings, SettingRegister, "register_settings"),
        }

    def _fail(self, name: str, source: str, error: str) -> None:
        self.info[name] = PluginInfo(name, source, error)
        for registry, _, _ in self.registries().values():
            registry.failed_plugins[name] = error

    def register(self, plugin: Any, name: str, source: str = "") -> bool:
        """Add a plugin object or module to the manager without calling its hooks (``collect``
        does). False, with the plugin marked failed, when pluggy rejects it (a misspelled hook,
        an argument the hook spec does not have)."""
        try:
            self.pm.register(plugin, name=name)
            self.pm.check_pending()
        except Exception as exc:  # noqa: BLE001 - a bad plugin is reported, never raised
            try:
                self.pm.unregister(name=name)
            except Exception:  # noqa: BLE001 - it may not have been registered at all
                pass
            self._fail(name, source, f"{type(exc).__name__}: {exc}")
            return False
        self.info[name] = PluginInfo(name, source or getattr(plugin, "__name__", repr(plugin)))
        return True

    def add_plugin(self, plugin: Any, name: str, source: str = "") -> None:
        """Register a plugin object or module and collect what it registers now."""
        if self.register(plugin, name, source):
            self.collect([name])

    def call_order(self, hook_name: str) -> list[str]:
        """The plugins implementing ``hook_name``, in the order ``pm.hook.<hook_name>(...)``
        calls them: ``tryfirst`` implementations first, ``trylast`` ones last, and within each
        group the plugin registered last first."""
        return [impl.plugin_name for impl in reversed(getattr(self.pm.hook, hook_name).get_hookimpls())]

    def _call(self, hook_name: str, plugin_name: str, **kwargs: Any) -> None:
        """Call ``plugin_name``'s implementation of ``hook_name`` alone, through pluggy."""
        impl = next(i for i in getattr(self.pm.hook, hook_name).get_hookimpls() if i.plugin_name == plugin_name)
        if impl.hookwrapper or impl.wrapper:
            raise PluginError(f"{hook_name} cannot be a hook wrapper (each plugin's registrations are made on their own)")
        others = [p for n, p in self.pm.list_name_plugin() if n != plugin_name and p is not None]
        self.pm.subset_hook_caller(hook_name, others)(**kwargs)

    def _record_error(self, plugin_name: str, hook_name: str, exc: Exception) -> str:
        info = self.info[plugin_name]
        error = f"{hook_name}: {type(exc).__name__}: {exc}"
        info.error = error if not info.error else f"{info.error}; {error}"
        return error

    def collect(self, names: Iterable[str] | None = None) -> None:
        """Call the registration hooks (``register_datasets``, ``register_methods``,
        ``register_metrics``, ``register_settings``) of the plugins ``names`` (default: every
        registered plugin), each hook over the plugins in ``call_order``."""
        only = None if names is None else set(names)
        failed: set[str] = set()
        for kind, (registry, register_cls, hook_name) in self.registries().items():
            for plugin_name in self.call_order(hook_name):
                if (only is not None and plugin_name not in only) or plugin_name in failed:
                    continue
                before = set(registry.entries)
                register = register_cls(registry, plugin_name)
                try:
                    self._call(hook_name, plugin_name, register=register)
                except Exception as exc:  # noqa: BLE001 - a broken plugin stays isolated
                    error = self._record_error(plugin_name, hook_name, exc)
                    self._roll_back(plugin_name, error)
                    failed.add(plugin_name)
                    continue
                finally:
                    register.closed = True
                added = set(registry.entries) - before
                if added:
                    registered = self.info[plugin_name].registered
                    registered[kind] = sorted(set(registered.get(kind, ())) | added)

    def _roll_back(self, plugin_name: str, error: str) -> None:
        """A plugin's registration failed: remove what it registered from every registry and
        mark it failed in each (an unknown name then says that it may have provided it)."""
        for registry, _, _ in self.registries().values():
            registry.remove_plugin(plugin_name)
            registry.failed_plugins[plugin_name] = error
        self.info[plugin_name].registered = {}

    def add_commands(self, cli: Any) -> None:
        """Call ``register_commands`` of every plugin in ``call_order``; a plugin whose hook
        raises is marked failed and the others' commands stay."""
        for plugin_name in self.call_order("register_commands"):
            try:
                self._call("register_commands", plugin_name, cli=cli)
            except Exception as exc:  # noqa: BLE001 - a broken command must not break the CLI
                if plugin_name in self.info:
                    self._record_error(plugin_name, "register_commands", exc)


def _env_list(var: str) -> set[str] | None:
    value = os.environ.get(var)
    if value is None:
        return None
    return {v.strip() for v in value.split(",") if v.strip()}


def load_plugins() -> Plugins:
    """Load every allowed entry point of the ``pcfbench`` group, isolating failures."""
    plugins = Plugins()
    allow = _env_list("PCFBENCH_PLUGINS")
    block = _env_list("PCFBENCH_BLOCK_PLUGINS") or set()
    all_eps = list(importlib.metadata.entry_points(group="pcfbench"))
    builtin_names = {ep.name for ep in all_eps if is_builtin_entry_point(ep)}
    # the built-ins first, then the others by name (a stable order, whatever the metadata's)
    eps = sorted(all_eps, key=lambda ep: (not is_builtin_entry_point(ep), ep.name, ep.value))
    seen: set[str] = set()
    loaded: list[tuple[importlib.metadata.EntryPoint, Any, bool]] = []
    for ep in eps:
        builtin = is_builtin_entry_point(ep)
        if not builtin and ep.name in builtin_names:
            dist = getattr(getattr(ep, "dist", None), "name", None) or "an unknown distribution"
            key = f"{ep.name} ({dist})"
            plugins._fail(key, ep.value, f"entry point {ep.name!r} of {dist} takes the name of a pcfbench built-in; not loaded")
            continue
        if ep.name in seen or ep.name in block:
            continue
        seen.add(ep.name)
        if allow is not None and not builtin and ep.name not in allow:
            continue
        try:
            module = ep.load()
        except Exception as exc:
            detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            plugins._fail(ep.name, ep.value, detail)
            plugins.info[ep.name].builtin = builtin
            continue
        loaded.append((ep, module, builtin))
    # pluggy calls the plugin registered last first (among implementations without tryfirst or
    # trylast): registering in reverse calls the built-ins first, then the others by name
    for ep, module, builtin in reversed(loaded):
        if plugins.register(module, ep.name, ep.value) or ep.name in plugins.info:
            plugins.info[ep.name].builtin = builtin
    plugins.collect()
    return plugins


_PLUGINS: Plugins | None = None


def get_plugins(reload: bool = False) -> Plugins:
    """The process-wide plugin state (loaded once)."""
    global _PLUGINS
    if _PLUGINS is None or reload:
        _PLUGINS = load_plugins()
    return _PLUGINS


def warn_failed(plugins: Plugins, stream=sys.stderr) -> None:
    for info in plugins.info.values():
        if info.error:
            print(f"pcfbench: warning: plugin {info.name!r} ({info.source}) failed: {info.error.splitlines()[-1]}", file=stream)


# -- settings: the protocol's and the plugins' ------------------------------------------------
def get_setting(name: str, plugins: Plugins | None = None) -> Setting:
    """The protocol's setting ``name``, else one a plugin registered (``register_settings``)."""
    from pcfbench.protocol import active_protocol

    protocol = active_protocol()
    if name in protocol.settings:
        return protocol.settings[name]
    plugins = plugins or get_plugins()
    if name in plugins.settings:
        return plugins.settings.get(name)
    failed = plugins.settings.failed_plugins
    note = f"plugin(s) that failed to load and may provide it: {', '.join(sorted(failed))}" if failed else ""
    raise unknown_name("setting", name, [*protocol.settings, *plugins.settings.names()], note)


def all_settings(plugins: Plugins | None = None) -> dict[str, Setting]:
    """The protocol's settings, then those registered by plugins (``register_settings``)."""
    from pcfbench.protocol import active_protocol

    plugins = plugins or get_plugins()
    out = dict(active_protocol().settings)
    for name in plugins.settings.names():
        out[name] = plugins.settings.get(name)
    return out
