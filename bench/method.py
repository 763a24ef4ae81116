"""The method contract: a sample in, a forecast out; options are a typed dataclass."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.execution import ExecutionContext, current


@dataclasses.dataclass(frozen=True)
class NoOptions:
    """A method without options."""


class Method(ABC):
    """Base class of every method plugin.

    Subclasses set ``name``, ``version`` (bump it when outputs change) and ``Options`` (a
    frozen dataclass; unknown keys are rejected) and implement ``forecast``. Learned methods
    also override ``fit``, ``save`` and ``load``.
    """

    name: ClassVar[str]
    version: ClassVar[str] = "1"
    Options: ClassVar[type] = NoOptions
    #: False for a method that needs a trained checkpoint before it can run on a dataset.
    ready: ClassVar[bool] = True

    def __init__(self, options: Any = None) -> None:
        self.options = options if options is not None else self.Options()

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

    def fit(self, dataset: Any, split: str, out_dir: Path) -> None:
        raise PcfbenchError(f"method {self.name!r} does not train")


def parse_options(options_cls: type, raw: dict[str, str | object], owner: str) -> Any:
    """Build ``options_cls`` from strings (CLI) or values, converting by the field types."""
    fields = {f.name: f for f in dataclasses.fields(options_cls)}
    unknown = sorted(set(raw) - set(fields))
    if unknown:
        known = ", ".join(sorted(fields)) or "none"
        raise PcfbenchError(f"{owner}: unknown option(s) {', '.join(unknown)} (known: {known})")
    hints = typing.get_type_hints(options_cls)
    values = {}
    for key, value in raw.items():
        values[key] = _convert(value, hints[key], f"{owner} option {key}")
    return options_cls(**values)


def _convert(value: object, typ: Any, where: str) -> object:
    if not isinstance(value, str):
        return value
    origin = typing.get_origin(typ)
    args = typing.get_args(typ)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value.lower() in ("none", "null") and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, where)
            except PcfbenchError:
                continue
        raise PcfbenchError(f"{where}: cannot read {value!r} as {typ}")
    if typing.get_origin(typ) is typing.Literal:
        if value not in args:
            raise PcfbenchError(f"{where}: {value!r} is not one of {', '.join(map(str, args))}")
        return value
    try:
        if typ is bool:
            low = value.lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if typ in (int, float, str):
            return typ(value)
        if origin is tuple:
            return tuple(_convert(v, args[0], where) for v in value.split("/") if v)
    except ValueError:
        raise PcfbenchError(f"{where}: cannot read {value!r} as {getattr(typ, '__name__', typ)}") from None
    raise PcfbenchError(f"{where}: options of type {typ} cannot be given on the command line")


def options_dict(options: Any) -> dict[str, Any]:
    return dataclasses.asdict(options) if dataclasses.is_dataclass(options) else {}


def options_hash(options: Any) -> str:
    """A short, stable hash of the option values (canonical JSON)."""
    blob = json.dumps(options_dict(options), sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]
