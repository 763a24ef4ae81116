"""Which cells of the store a report shows: ``pcfbench report --dataset/--setting/--method``.

Each option takes shell-style patterns (:mod:`fnmatch`, case-sensitive: ``raycast-*``,
``kitti-?s``), repeatable; a cell is shown when, for every option given, its name matches one
of that option's patterns. The selection is applied to the cells read from the store before
any number, table or figure is made, so a filtered report is the report of a store holding
only those cells, and every page it writes says which filters made it.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from fnmatch import fnmatchcase

from pcfbench.errors import PcfbenchError, close_names

#: (option, CellSpec field) of each filter, in the order they are printed
FIELDS = (("dataset", "dataset"), ("setting", "setting"), ("method", "method"))


@dataclass(frozen=True)
class Selection:
    """Patterns per field; an empty tuple selects everything of that field."""

    datasets: tuple[str, ...] = ()
    settings: tuple[str, ...] = ()
    methods: tuple[str, ...] = ()

    def patterns(self, field: str) -> tuple[str, ...]:
        return getattr(self, f"{field}s")

    @property
    def active(self) -> bool:
        return any(self.patterns(f) for f, _ in FIELDS)

    def matches(self, spec) -> bool:
        """Whether cell ``spec`` (a ``CellSpec``) is selected."""
        return all(not self.patterns(f) or any(fnmatchcase(getattr(spec, attr), p) for p in self.patterns(f))
                   for f, attr in FIELDS)

    def describe(self) -> str:
        """The options that made this selection, as typed: ``--dataset kitti --method 'raycast-*'``."""
        return " ".join(f"--{f} {shlex.quote(p)}" for f, _ in FIELDS for p in self.patterns(f))

    def check(self, held: list) -> None:
        """One error when a pattern matches no cell of ``held`` (the ``CellSpec`` of every cell
        the report reads), or when every pattern matches some cell but no cell matches them
        all; the error lists the names the store holds."""
        if not self.active:
            return
        names = {f: sorted({getattr(s, attr) for s in held}) for f, attr in FIELDS}
        unmatched = [(f, p) for f, _ in FIELDS for p in self.patterns(f)
                     if not any(fnmatchcase(n, p) for n in names[f])]
        if not unmatched and any(self.matches(s) for s in held):
            return
        where = "\n".join(f"  {f}s: {', '.join(names[f]) or 'none'}" for f, _ in FIELDS)
        if unmatched:
            what = "; ".join(f"--{f} {shlex.quote(p)} matches no {f}{_did_you_mean(p, names[f])}" for f, p in unmatched)
        else:
            what = f"no cell matches {self.describe()} together"
        raise PcfbenchError(f"{what} of the store's {len(held)} complete cell(s), which hold:\n{where}\n"
                            "patterns are shell-style (fnmatch, case-sensitive): `--method 'raycast-*'`")


def _did_you_mean(pattern: str, names: list[str]) -> str:
    close = close_names(pattern, names)
    return f" (did you mean {' or '.join(shlex.quote(c) for c in close)}?)" if close else ""
