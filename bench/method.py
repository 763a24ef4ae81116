"""The method contract: a sample in, a forecast out; options are a typed dataclass.

``resolve_method`` is the one place a method spec (``NAME[:key=value,...]``) becomes a method:
the command line, the runner and ``pcfbench export`` all go through it.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar, Iterable, Mapping

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.execution import ExecutionContext, current
from pcfbench.options import NoOptions, check_options, options_dict, options_hash, parse_options

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.plugins import Plugins

__all__ = [
    "Method", "MethodSpec", "NoOptions", "options_dict", "options_hash", "parse_method_spec", "parse_options",
    "resolve_method",
]


class Method(ABC):
    """Base class of every method plugin.

    Subclasses set ``name``, ``version`` (bump it when outputs change) and ``Options`` (a
    frozen dataclass whose fields are declared with ``pcfbench.option(default, help=...)``;
    unknown keys are rejected) and implement ``forecast``. A method that learns subclasses
    ``pcfbench.TrainedMethod`` (``pcfbench.training``) instead.
    """

    name: ClassVar[str]
    version: ClassVar[str] = "1"
    Options: ClassVar[type] = NoOptions
    #: In a run of the default method set (``pcfbench run`` without ``--method``), score at most
    #: this many of each cell's samples, evenly spaced (``CellSpec.subset``; None: every sample).
    #: For methods too slow for the default run's budget; the run prints and the leaderboard
    #: shows their sample count, and ``--subset 0`` scores every sample (docs/protocol.md).
    default_run_subset: ClassVar[int | None] = None
    #: The option sets a run of the default method set scores this method with, each a row of
    #: its own (``{}``: its defaults). More than one for a method whose other configuration is
    #: another method's reference: the world models' own token-copy (docs/protocol.md).
    default_run_options: ClassVar[tuple[dict[str, str], ...]] = ({},)

    def __init__(self, options: Any = None) -> None:
        """``options``: an instance of ``Options`` (default: its defaults); from a spec's
        strings, ``resolve_method`` builds it."""
        who = getattr(type(self), "name", type(self).__name__)
        if options is None:
            options = self.Options()
        elif not isinstance(options, self.Options):
            raise PcfbenchError(f"method {who}: options must be a {self.Options.__qualname__}, got {options!r}")
        # built directly (Options(voxel=nan)) as well as parsed: the same declared ranges
        self.options = check_options(options, f"method {who}")

    @property
    def execution(self) -> ExecutionContext:
        """The thread budget the method's own threads stay within (``pcfbench.execution``): what
        the runner gave it, else the process's (``current()``). Methods that run no threads of
        their own can ignore it; parallel work goes through ``self.execution.map``."""
        return self.__dict__.get("_execution") or current()

    @execution.setter
    def execution(self, context: ExecutionContext) -> None:
        if not isinstance(context, ExecutionContext):
            raise PcfbenchError(f"{type(self).__name__}.execution must be an ExecutionContext, not {context!r}")
        self.__dict__["_execution"] = context

    @abstractmethod
    def forecast(self, sample: Sample) -> Forecast:
        """Predict every future sweep of ``sample`` (points in the reference frame and/or depths)."""


def parse_method_spec(text: str) -> tuple[str, dict[str, str]]:
    """``name`` or ``name:key=value,key=value`` into the name and the raw option strings."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if not name:
        raise PcfbenchError(f"--method {text!r}: no method name (expected NAME[:key=value,...])")
    options: dict[str, str] = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise PcfbenchError(f"--method {text!r}: option {item!r} must look like key=value")
        if key.strip() in options:
            raise PcfbenchError(f"--method {text!r}: option {key.strip()!r} is given twice")
        options[key.strip()] = value.strip()
    return name, options


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A method spec resolved against the plugins: the registered ``name``, the ``raw``
    options as given (what a cell records), the typed ``options`` built from them, their
    ``options_hash`` (part of the cell's identity) and the method class."""

    name: str
    raw: Mapping[str, Any]
    options: Any
    options_hash: str
    cls: type[Method]

    def create(self) -> Method:
        """A new instance of the method with these options."""
        return self.cls(self.options)

    def text(self, drop: Iterable[str] = ()) -> str:
        """The spec as a command line writes it, ``name[:key=value,...]`` (keys sorted), less the
        options named in ``drop`` (a method's ``inference_options``: the command that trains it)."""
        opts = ",".join(f"{k}={v}" for k, v in sorted(self.raw.items()) if k not in set(drop))
        return self.name + (f":{opts}" if opts else "")


def resolve_method(spec: str | tuple[str, Mapping[str, Any]], plugins: Plugins | None = None) -> MethodSpec:
    """Turn ``"NAME[:key=value,...]"`` (or ``(name, raw options)``, as a stored cell holds
    them) into a ``MethodSpec``. An unknown name, a plugin that fails to load, an unknown
    option or an unreadable value is one ``PcfbenchError`` naming it."""
    if plugins is None:
        from pcfbench.plugins import get_plugins

        plugins = get_plugins()
    name, raw = parse_method_spec(spec) if isinstance(spec, str) else (spec[0], dict(spec[1]))
    cls = plugins.methods.get(name)
    options = parse_options(cls.Options, raw, f"method {name}")
    return MethodSpec(name, raw, options, options_hash(options), cls)
