"""The closed sets of words the harness reads from metrics, table presets and the protocol file.

Each is a ``StrEnum``: a member *is* its string (``Needs.DEPTHS == "depths"``), so cell.json,
the TOML files and the docs hold the same bytes as when these were bare strings, and plugin
code may keep passing strings. :func:`parse` turns a string from a file or a plugin into a
member, or raises one error that lists the valid values.
"""

from __future__ import annotations

from enum import StrEnum
from typing import TypeVar

from pcfbench.errors import PcfbenchError


class Needs(StrEnum):
    """What a forecast must carry for a metric to score it (``Metric.needs``)."""

    POINTS = "points"
    DEPTHS = "depths"
    EITHER = "either"


class Better(StrEnum):
    """Which way a metric improves: its table arrow, ranking and bold best value."""

    LOWER = "lower"
    HIGHER = "higher"

    @classmethod
    def of(cls, higher_is_better: bool) -> "Better":
        return cls.HIGHER if higher_is_better else cls.LOWER


class PolicyKind(StrEnum):
    """The anchor rule of a sample policy (``kind`` of ``[policies.NAME]`` in protocol.toml)."""

    FULL_CONTEXT = "full-context"
    EVERY_FRAME = "every-frame"
    SUBSAMPLE = "subsample"


E = TypeVar("E", bound=StrEnum)


def parse(kind: type[E], value: object, what: str) -> E:
    """``value`` as a member of ``kind``; a :class:`PcfbenchError` naming ``what`` (where the
    value came from) and the valid values otherwise."""
    if isinstance(value, kind):
        return value
    if isinstance(value, str):
        try:
            return kind(value)
        except ValueError:
            pass
    valid = ", ".join(f'"{m.value}"' for m in kind)
    raise PcfbenchError(f"{what} must be one of {valid}, got {value!r}")
