"""Plugin loading and the registries of datasets, methods and metrics.

Built-ins and third-party plugins load the same way: entry points of the ``pcfbench``
group. ``PCFBENCH_PLUGINS`` (comma-separated entry-point names) allow-lists third-party
plugins (empty: none); ``PCFBENCH_BLOCK_PLUGINS`` blocks plugins by name, built-ins too.
"""

from __future__ import annotations

import difflib
import importlib
import importlib.metadata
import os
import sys
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable

import pluggy

from pcfbench import hookspecs
from pcfbench.errors import PluginError, UnknownNameError

BUILTIN_PREFIX = "builtin-"


@dataclass
class Entry:
    """One registered item: its name, lazy or resolved target, and who registered it."""

    name: str
    target: Any
    plugin: str
    description: str = ""
    _resolved: Any = None
    error: str | None = None

    @property
    def lazy(self) -> bool:
        return isinstance(self.target, str)


class Registry:
    """Names -> entries for one kind of plugin item, with type checks on resolution."""

    def __init__(self, kind: str, check: Callable[[Any], str | None]) -> None:
        self.kind = kind
        self._check = check
        self.entries: dict[str, Entry] = {}
        self.failed_plugins: dict[str, str] = {}

    def add(self, name: str, target: Any, plugin: str, description: str = "") -> None:
        if not isinstance(name, str) or not name or any(c.isspace() for c in name):
            raise PluginError(f"plugin {plugin!r} registered a {self.kind} with an invalid name {name!r}")
        if name in self.entries:
            other = self.entries[name].plugin
            raise PluginError(f"{self.kind} {name!r} is registered twice: by plugin {other!r} and by plugin {plugin!r}")
        if isinstance(target, str):
            if ":" not in target:
                raise PluginError(f"plugin {plugin!r}: lazy {self.kind} target {target!r} must look like 'module:attribute'")
        else:
            problem = self._check(target)
            if problem:
                raise PluginError(f"plugin {plugin!r}: {self.kind} {name!r} {problem}")
        self.entries[name] = Entry(name, target, plugin, description)

    def names(self) -> list[str]:
        return sorted(self.entries)

    def __contains__(self, name: str) -> bool:
        return name in self.entries

    def get(self, name: str) -> Any:
        """The resolved object for ``name``; imports lazy targets on first use."""
        entry = self.entries.get(name)
        if entry is None:
            raise UnknownNameError(self.unknown_message(name))
        if entry.lazy and entry._resolved is None:
            module_name, _, attr = entry.target.partition(":")
            try:
                obj = importlib.import_module(module_name)
                for part in attr.split("."):
                    obj = getattr(obj, part)
            except Exception as exc:
                entry.error = f"{type(exc).__name__}: {exc}"
                raise PluginError(
                    f"{self.kind} {name!r} (plugin {entry.plugin!r}) failed to load {entry.target}: {entry.error}"
                ) from exc
            problem = self._check(obj)
            if problem:
                raise PluginError(f"{self.kind} {name!r} (plugin {entry.plugin!r}, {entry.target}) {problem}")
            entry._resolved = obj
        return entry._resolved if entry.lazy else entry.target

    def unknown_message(self, name: str) -> str:
        msg = f"unknown {self.kind} {name!r}"
        close = difflib.get_close_matches(name, self.names(), n=3, cutoff=0.5)
        if close:
            msg += f"; did you mean {' or '.join(repr(c) for c in close)}?"
        msg += f" (known: {', '.join(self.names()) or 'none'})"
        if self.failed_plugins:
            msg += f"; plugin(s) that failed to load and may provide it: {', '.join(sorted(self.failed_plugins))}"
        return msg


class Register:
    """The callable a ``register_*`` hook receives; records which plugin registered what."""

    def __init__(self, registry: Registry, plugin: str) -> None:
        self._registry = registry
        self.plugin = plugin

    def __call__(self, name: str, target: Any, description: str = "") -> None:
        self._registry.add(name, target, self.plugin, description)


class DatasetRegister(Register):
    """``register(name, "module:AdapterClass" | AdapterClass, description="")``."""


class MethodRegister(Register):
    """``register(name, "module:MethodClass" | MethodClass, description="")``."""


class MetricRegister(Register):
    """``register(name, "module:METRIC" | Metric, description="")``."""


class SettingRegister(Register):
    """``register(setting)``: a ``pcfbench.Setting`` whose name the protocol file does not use."""

    def __call__(self, setting: Any) -> None:  # type: ignore[override]
        from pcfbench.protocol import Setting, active_protocol

        if not isinstance(setting, Setting):
            raise PluginError(f"plugin {self.plugin!r}: register_settings takes a pcfbench.Setting, got {setting!r}")
        protocol = active_protocol()
        if setting.name in protocol.settings:
            raise PluginError(
                f"plugin {self.plugin!r}: setting {setting.name!r} is already a setting of the protocol file "
                f"{protocol.source}; register it under another name"
            )
        self._registry.add(setting.name, setting, self.plugin, setting.description)


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


class Plugins:
    """The loaded plugin manager and the three registries."""

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

    def add_plugin(self, plugin: Any, name: str, source: str = "") -> None:
        """Register a plugin object or module and collect what it registers."""
        try:
            self.pm.register(plugin, name=name)
            self.pm.check_pending()
        except Exception as exc:  # a misspelled hook or a bad hookimpl signature
            try:
                self.pm.unregister(name=name)
            except Exception:  # noqa: BLE001 - it may not have been registered at all
                pass
            self._fail(name, source, f"{type(exc).__name__}: {exc}")
            return
        info = PluginInfo(name, source or getattr(plugin, "__name__", repr(plugin)))
        self.info[name] = info
        for kind, (registry, register_cls, hook_name) in self.registries().items():
            before = set(registry.entries)
            for impl in getattr(self.pm.hook, hook_name).get_hookimpls():
                if impl.plugin_name != name:
                    continue
                try:
                    impl.function(register=register_cls(registry, name))
                except Exception as exc:
                    info.error = f"{hook_name}: {type(exc).__name__}: {exc}"
                    registry.failed_plugins[name] = info.error
            added = sorted(set(registry.entries) - before)
            if added:
                info.registered[kind] = added

    def add_commands(self, cli: Any) -> None:
        for impl in self.pm.hook.register_commands.get_hookimpls():
            try:
                impl.function(cli=cli)
            except Exception as exc:  # noqa: BLE001 - a broken command must not break the CLI
                info = self.info.get(impl.plugin_name)
                if info is not None:
                    info.error = f"register_commands: {type(exc).__name__}: {exc}"


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
    eps = sorted(importlib.metadata.entry_points(group="pcfbench"), key=lambda ep: (not ep.name.startswith(BUILTIN_PREFIX), ep.name))
    seen: set[str] = set()
    for ep in eps:
        if ep.name in seen or ep.name in block:
            continue
        seen.add(ep.name)
        if allow is not None and not ep.name.startswith(BUILTIN_PREFIX) and ep.name not in allow:
            continue
        try:
            module = ep.load()
        except Exception as exc:
            detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            plugins._fail(ep.name, ep.value, detail)
            continue
        plugins.add_plugin(module, ep.name, ep.value)
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
