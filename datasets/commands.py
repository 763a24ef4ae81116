"""``pcfbench export`` and ``pcfbench convert`` (added through the register_commands hook)."""

from __future__ import annotations


def add_commands(cli) -> None:
    pass
