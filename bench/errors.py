"""Errors the harness raises on purpose: each names the file, sample or name at fault."""

from __future__ import annotations

from typing import Iterable


class PcfbenchError(Exception):
    """Base class: a clear, user-facing error (the CLI prints it without a traceback)."""


class DataError(PcfbenchError):
    """A dataset file or table is missing, truncated or malformed."""


class ForecastError(PcfbenchError):
    """A method returned a forecast that breaks the contract (shape, dtype, NaN, range)."""


class UnknownNameError(PcfbenchError, KeyError):
    """An unknown method, dataset, metric or setting name."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class PluginError(PcfbenchError):
    """A plugin failed to import or registered something invalid."""


def unknown_name(kind: str, name: str, known: Iterable[str], note: str = "") -> UnknownNameError:
    """The one "unknown X 'y'; did you mean ...? (known: ...)" error, for every kind of name.

    ``note`` is appended after the list of known names (e.g. plugins that failed to load).
    """
    known = sorted(known)
    msg = f"unknown {kind} {name!r}"
    close = close_names(name, known)
    if close:
        msg += f"; did you mean {' or '.join(repr(c) for c in close)}?"
    msg += f" (known: {', '.join(known) or 'none'})"
    if note:
        msg += f"; {note}"
    return UnknownNameError(msg)


def close_names(name: str, known: Iterable[str]) -> list[str]:
    """The (at most three) names of ``known`` close to ``name``: what a "did you mean" offers."""
    import difflib

    return difflib.get_close_matches(str(name), list(known), n=3, cutoff=0.5)
