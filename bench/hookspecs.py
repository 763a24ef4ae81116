"""The pcfbench hooks. A plugin is a module (or object) with functions marked ``@hookimpl``.

Each ``register_*`` hook receives a typed ``register`` object owned by the host: call it once
per item. Targets may be lazy ``"module:attr"`` strings so listing stays fast and a broken
import only breaks what uses it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.plugins import SettingRegister

hookspec = pluggy.HookspecMarker("pcfbench")
hookimpl = pluggy.HookimplMarker("pcfbench")


@hookspec
def register_datasets(register):  # noqa: ANN001
    """Register dataset adapters: ``register("name", "module:AdapterClass")`` (a DatasetAdapter)."""


@hookspec
def register_methods(register):  # noqa: ANN001
    """Register forecasting methods: ``register("name", "module:MethodClass")`` (a Method)."""


@hookspec
def register_metrics(register):  # noqa: ANN001
    """Register metrics: ``register("name", "module:METRIC")`` (a pcfbench.metrics.Metric)."""


@hookspec
def register_settings(register: "SettingRegister") -> None:
    """Register protocol settings beyond those of the protocol file (``protocol.toml``).

    :param register: call ``register(pcfbench.Setting(name, rate_hz, past, future, stride,
        description))`` once per setting.

    A name the protocol file already uses, or that another plugin registered, is an error
    reported against this plugin (``pcfbench plugins``). The setting's parameters are part of
    the identity of every cell computed with it, so changing them later stops a rerun of such
    a cell rather than mixing rows. Called once per plugin, when plugins load.
    """


@hookspec
def register_commands(cli):  # noqa: ANN001
    """Add subcommands to the ``pcfbench`` click group ``cli``."""
