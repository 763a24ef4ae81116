"""What a plugin registers into: one :class:`Registry` per kind of item (names to lazy or
resolved targets, with type checks on resolution) and the ``register`` callables the
``register_*`` hooks receive (:mod:`pcfbench.hookspecs` names their types; the loading of
plugins is :mod:`pcfbench.plugins`, above both).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable

from pcfbench.errors import PluginError, UnknownNameError, unknown_name

__all__ = ["DatasetRegister", "Entry", "MethodRegister", "MetricRegister", "Register", "Registry", "SettingRegister"]


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

    def remove_plugin(self, plugin: str) -> list[str]:
        """Drop every entry ``plugin`` registered (a failed plugin keeps nothing); their names."""
        gone = [name for name, entry in self.entries.items() if entry.plugin == plugin]
        for name in gone:
            del self.entries[name]
        return gone

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
            raise self.unknown(name)
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

    def unknown(self, name: str) -> UnknownNameError:
        """The error for an unknown ``name`` (``errors.unknown_name``), naming the plugins that
        failed to load, since one of them may have provided it."""
        note = ""
        if self.failed_plugins:
            note = f"plugin(s) that failed to load and may provide it: {', '.join(sorted(self.failed_plugins))}"
        return unknown_name(self.kind, name, self.names(), note)


class Register:
    """The callable a ``register_*`` hook receives; records which plugin registered what."""

    def __init__(self, registry: Registry, plugin: str) -> None:
        self._registry = registry
        self.plugin = plugin
        self.closed = False

    def _check_open(self) -> None:
        if self.closed:
            raise PluginError(f"plugin {self.plugin!r}: register called after its registration hook returned")

    def __call__(self, name: str, target: Any, description: str = "") -> None:
        self._check_open()
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

        self._check_open()
        if not isinstance(setting, Setting):
            raise PluginError(f"plugin {self.plugin!r}: register_settings takes a pcfbench.Setting, got {setting!r}")
        protocol = active_protocol()
        if setting.name in protocol.settings:
            raise PluginError(
                f"plugin {self.plugin!r}: setting {setting.name!r} is already a setting of the protocol file "
                f"{protocol.source}; register it under another name"
            )
        self._registry.add(setting.name, setting, self.plugin, setting.description)
