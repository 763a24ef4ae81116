"""Typed options of methods and dataset adapters: frozen dataclasses with a help text per field.

A method's ``Options`` (``NAME:key=value,...`` on the command line) and a dataset adapter's
``Options`` (``ROOT?key=value&...``) are the same kind of object, declared with ``option``::

    @dataclasses.dataclass(frozen=True)
    class Options:
        voxel: float = pcfbench.option(0.2, help="voxel edge, metres")

and read with the same parser (``parse_options``): values arrive as strings and are converted by
the field's type; an unknown key or an unreadable value is one ``PcfbenchError`` naming the
owner, the key and what was expected. The help lives in the field's metadata, which
``dataclasses.asdict`` (and so ``options_hash``) never sees: adding or editing help texts keeps
every option hash.

An option may declare its valid range in the same metadata (``option(0.2, help=..., gt=0,
max=10)``: ``min``/``max`` inclusive, ``gt``/``lt`` exclusive); ``parse_options`` checks every
value against it, and refuses NaN and infinities in ``float`` options unless the option says
``finite=False``, so an option that parses but means nothing is one error before any work.
Ranges are metadata too: declaring or changing one keeps every option hash.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from typing import Any

from pcfbench.errors import PcfbenchError, unknown_name

#: the field-metadata key holding an option's help text
HELP = "pcfbench.help"
#: the field-metadata key holding an option's valid range (a ``Range``)
RANGE = "pcfbench.range"
#: the field-metadata key marking an option left out of ``options_dict`` (and so of
#: ``options_hash``) while it holds its default
QUIET_DEFAULT = "pcfbench.quiet_default"


@dataclasses.dataclass(frozen=True)
class Range:
    """The valid values of a numeric option: ``min <= v <= max``, ``gt < v < lt`` (each bound
    optional), and finite unless ``finite`` is False. For a tuple option, every item."""

    min: float | None = None
    max: float | None = None
    gt: float | None = None
    lt: float | None = None
    finite: bool = True

    def describe(self) -> str:
        """The range as ``ls --options`` prints it: ``> 0, <= 10``."""
        parts = [f"{op} {v:g}" for op, v in ((">=", self.min), (">", self.gt), ("<=", self.max), ("<", self.lt))
                 if v is not None]
        return ", ".join(parts)

    def problem(self, value: float) -> str | None:
        """Why ``value`` is outside the range, or None."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return None
        if value != value or value in (float("inf"), float("-inf")):
            if self.finite:
                return f"must be a finite number, got {value!r}"
            return None
        for ok, bound, text in (
            (self.min is None or value >= self.min, self.min, ">="),
            (self.gt is None or value > self.gt, self.gt, ">"),
            (self.max is None or value <= self.max, self.max, "<="),
            (self.lt is None or value < self.lt, self.lt, "<"),
        ):
            if not ok:
                return f"must be {text} {bound:g} (valid: {self.describe()}), got {value!r}"
        return None


def option(
    default: Any = dataclasses.MISSING, *, help: str, default_factory: Any = dataclasses.MISSING,  # noqa: A002
    min: float | None = None, max: float | None = None, gt: float | None = None,  # noqa: A002
    lt: float | None = None, finite: bool = True, quiet_default: bool = False,
) -> Any:
    """A dataclass field of an ``Options`` class: its default, a one-line help text and,
    for a number, its valid range.

    ``help`` says what the value means and its unit; ``pcfbench ls methods --options`` and
    ``pcfbench ls datasets --options`` print it. ``min``/``max`` (inclusive) and ``gt``/``lt``
    (exclusive) bound a numeric value; ``finite=False`` admits NaN and infinities in a
    ``float`` option (refused by default). ``parse_options`` checks them. All of it is
    metadata only: it does not enter the option values, ``dataclasses.asdict`` or
    ``options_hash``.

    ``quiet_default=True``: while the option holds its default it is left out of
    ``options_dict`` and ``options_hash``, so that an option added to a method whose
    checkpoints and stored cells exist leaves their identity as it was; any other value
    enters both as usual.
    """
    if not isinstance(help, str) or not help.strip():
        raise TypeError("pcfbench.option needs a non-empty help text (help=...)")
    bounds = {"min": min, "max": max, "gt": gt, "lt": lt}
    for key, bound in bounds.items():
        if bound is not None and (isinstance(bound, bool) or not isinstance(bound, (int, float)) or bound != bound):
            raise TypeError(f"pcfbench.option: {key}= must be a number, got {bound!r}")
    metadata: dict[str, Any] = {HELP: help.strip()}
    if any(b is not None for b in bounds.values()) or not finite:
        metadata[RANGE] = Range(min=min, max=max, gt=gt, lt=lt, finite=bool(finite))
    if quiet_default:
        metadata[QUIET_DEFAULT] = True
    return dataclasses.field(default=default, default_factory=default_factory, metadata=metadata)


def option_range(f: dataclasses.Field) -> Range:
    """The valid range of an option field (finite, unbounded when it declares none)."""
    return f.metadata.get(RANGE) or Range()


@dataclasses.dataclass(frozen=True)
class NoOptions:
    """The options of a method or adapter that takes none."""


@dataclasses.dataclass(frozen=True)
class OptionInfo:
    """One field of an ``Options`` class as ``ls --options`` prints it."""

    name: str
    type: str
    default: Any
    help: str
    #: the declared range (``> 0, <= 10``), "" when none
    range: str = ""


def _check_options_class(options_cls: Any, owner: str) -> None:
    if not (isinstance(options_cls, type) and dataclasses.is_dataclass(options_cls)):
        raise PcfbenchError(f"{owner}: Options must be a dataclass, got {options_cls!r}")


def type_name(typ: Any) -> str:
    """A short, readable name of an option's type: ``float``, ``int | None``, ``'plane' | 'mean'``."""
    origin = typing.get_origin(typ)
    args = typing.get_args(typ)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " | ".join("None" if a is type(None) else type_name(a) for a in args)
    if origin is tuple:
        inner = type_name(args[0]) if args else "Any"
        return f"tuple[{inner}, ...]"
    return getattr(typ, "__name__", str(typ))


def describe_options(options_cls: type, owner: str = "options") -> list[OptionInfo]:
    """Every field of ``options_cls`` in declaration order: name, type, default and help
    (``""`` for a field declared without ``option``)."""
    _check_options_class(options_cls, owner)
    hints = typing.get_type_hints(options_cls)
    out = []
    for f in dataclasses.fields(options_cls):
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        out.append(OptionInfo(f.name, type_name(hints[f.name]), default, f.metadata.get(HELP, ""),
                              option_range(f).describe()))
    return out


def parse_options(options_cls: type, raw: dict[str, str | object], owner: str) -> Any:
    """Build ``options_cls`` from strings (command line, root query) or values, converting
    each string by its field's type. ``owner`` names whose options they are in errors
    (``"method raycast-voxel"``, ``"dataset mcap"``)."""
    _check_options_class(options_cls, owner)
    fields = {f.name: f for f in dataclasses.fields(options_cls)}
    unknown = sorted(set(raw) - set(fields))
    if unknown:
        if len(unknown) == 1:
            raise unknown_name(f"{owner} option", unknown[0], fields)
        known = ", ".join(sorted(fields)) or "none"
        raise PcfbenchError(f"{owner}: unknown option(s) {', '.join(unknown)} (known: {known})")
    hints = typing.get_type_hints(options_cls)
    values = {key: _convert(value, hints[key], f"{owner} option {key}") for key, value in raw.items()}
    for key, value in values.items():
        _check_range(fields[key], value, f"{owner} option {key}")
    try:
        return options_cls(**values)
    except (TypeError, ValueError) as exc:  # a missing required field, or a __post_init__ check
        raise PcfbenchError(f"{owner} options: {exc}") from None


def check_options(options: Any, owner: str) -> Any:
    """``options`` itself when every field is within its declared range (and finite), else
    one ``PcfbenchError`` naming the owner, the option, its range and the value. For options
    built directly (``Options(voxel=...)``) rather than by ``parse_options``."""
    if dataclasses.is_dataclass(options) and not isinstance(options, type):
        for f in dataclasses.fields(options):
            _check_range(f, getattr(options, f.name), f"{owner} option {f.name}")
    return options


def _check_range(f: dataclasses.Field, value: Any, where: str) -> None:
    rng = option_range(f)
    items = value if isinstance(value, tuple) else (value,)
    for item in items:
        problem = rng.problem(item)
        if problem:
            raise PcfbenchError(f"{where} {problem}")


def _convert(value: object, typ: Any, where: str) -> object:
    if not isinstance(value, str):
        return value
    origin = typing.get_origin(typ)
    args = typing.get_args(typ)
    if origin in (typing.Union, types.UnionType):
        if value.lower() in ("none", "null") and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, where)
            except PcfbenchError:
                continue
        raise PcfbenchError(f"{where}: cannot read {value!r} as {type_name(typ)}")
    if origin is typing.Literal:
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
            # "/" separates items in a method spec (where "," separates options); a root
            # query (options separated by "&") may use "," too
            items = value.replace(",", "/").split("/")
            return tuple(_convert(v, args[0], where) for v in items if v)
    except ValueError:
        raise PcfbenchError(f"{where}: cannot read {value!r} as {type_name(typ)}") from None
    raise PcfbenchError(f"{where}: options of type {type_name(typ)} cannot be given on the command line")


def options_dict(options: Any) -> dict[str, Any]:
    """The option values as a plain dict (help texts and other field metadata left out), less
    the ``quiet_default`` options that hold their default."""
    if not dataclasses.is_dataclass(options):
        return {}
    out = dataclasses.asdict(options)
    for f in dataclasses.fields(options):
        if f.metadata.get(QUIET_DEFAULT):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            if getattr(options, f.name) == default:
                del out[f.name]
    return out


def options_hash(options: Any) -> str:
    """A short, stable hash of the option values (canonical JSON of ``options_dict``)."""
    blob = json.dumps(options_dict(options), sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]
