"""The pcfbench hooks: what a plugin implements, with which arguments, and when each is called.

A plugin is a module (or object) whose functions are marked ``@pcfbench.hookimpl``, found
through an entry point of the ``pcfbench`` group (``[project.entry-points.pcfbench]``); the
built-in datasets, methods and metrics are plugins of this kind too. An implementation may
declare fewer arguments than its hook spec, never other ones (pluggy rejects the plugin and
``pcfbench plugins`` names it).

When: every hook is called once per plugin when plugins load (``pcfbench.plugins.get_plugins``,
on the first command that needs them), except ``register_commands``, which is called when
the command line is built. The ``register_*`` hooks of the registries run in this order:
``register_datasets``, ``register_methods``, ``register_metrics``, ``register_settings``.

Order among plugins: pluggy's. ``@pcfbench.hookimpl(tryfirst=True)`` runs before the others,
``@pcfbench.hookimpl(trylast=True)`` after them; otherwise the built-ins run first, then the
other plugins by entry-point name. The order decides who wins a conflict: a name registered
twice is an error of the plugin that registered it second. Hook wrappers are not supported on
these hooks.

Isolation: each plugin's implementation is called on its own with a ``register`` that records
the plugin's name, so ``pcfbench plugins`` shows who registered what. An exception raised by an
implementation (or by ``register``, for an invalid or duplicate name) marks that plugin
failed with the message, keeps what it registered before, and leaves the other plugins alone.

Targets may be lazy ``"module:attribute"`` strings: listing stays fast, and a broken import
only breaks what uses it (with an error naming the plugin and the target).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:  # pragma: no cover
    import click

    from pcfbench.registry import DatasetRegister, MethodRegister, MetricRegister, SettingRegister

hookspec = pluggy.HookspecMarker("pcfbench")
hookimpl = pluggy.HookimplMarker("pcfbench")


@hookspec
def register_datasets(register: DatasetRegister) -> None:
    """Register dataset adapters.

    :param register: call ``register(name, target, description="")`` once per adapter.
        ``name`` is what ``--dataset NAME[=ROOT]`` selects (no whitespace; unique over all
        plugins); ``target`` is a ``pcfbench.DatasetAdapter`` subclass or a lazy
        ``"module:Class"`` string naming one; ``description`` is the line ``pcfbench ls
        datasets`` prints.

    The adapter's root options (``ROOT?key=value&...``) are the fields of its ``Options``
    dataclass, declared with ``pcfbench.option(default, help=...)``; ``pcfbench ls datasets
    --options`` prints them. Called once per plugin when plugins load.
    """


@hookspec
def register_methods(register: MethodRegister) -> None:
    """Register forecasting methods.

    :param register: call ``register(name, target, description="")`` once per method.
        ``name`` is what ``--method NAME[:key=value,...]`` selects (no whitespace; unique over
        all plugins); ``target`` is a ``pcfbench.Method`` subclass or a lazy ``"module:Class"``
        string naming one; ``description`` is the line ``pcfbench ls methods`` prints.

    The method's options are the fields of its ``Options`` dataclass, declared with
    ``pcfbench.option(default, help=...)``; ``pcfbench ls methods --options`` prints them and
    their values' hash is part of every cell's identity. A method whose class sets
    ``ready = False`` is registered but left out of a ``pcfbench run`` that names no method.
    Called once per plugin when plugins load.
    """


@hookspec
def register_metrics(register: MetricRegister) -> None:
    """Register metrics.

    :param register: call ``register(name, target, description="")`` once per metric.
        ``name`` is what ``--metric NAME`` selects (no whitespace; unique over all plugins);
        ``target`` is a ``pcfbench.Metric`` instance or a lazy ``"module:ATTRIBUTE"`` string
        naming one; ``description`` is the line ``pcfbench ls metrics`` prints.

    Called once per plugin when plugins load.
    """


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
def register_commands(cli: click.Group) -> None:
    """Add subcommands to the command line.

    :param cli: the ``pcfbench`` click group: add commands with ``@cli.command()`` or
        ``cli.add_command``, or extend a group another plugin added (``cli.commands.get(name)``,
        which is ``None`` when that plugin did not run first: use ``trylast=True`` to run after).

    Called once per plugin when the command line is built (``pcfbench.cli.build_cli``), in the
    order above, after the registries are loaded. Keep imports of heavy modules inside the
    commands, so ``pcfbench --help`` stays fast. An exception marks the plugin failed; the
    other plugins' commands stay.
    """
