"""The pcfbench hooks. A plugin is a module (or object) with functions marked ``@hookimpl``.

Each ``register_*`` hook receives a typed ``register`` object owned by the host: call it once
per item. Targets may be lazy ``"module:attr"`` strings so listing stays fast and a broken
import only breaks what uses it.
"""

from __future__ import annotations

import pluggy

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
def register_commands(cli):  # noqa: ANN001
    """Add subcommands to the ``pcfbench`` click group ``cli``."""
