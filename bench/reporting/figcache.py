"""Figures drawn again only when what they plot changed.

Each leaderboard figure is keyed on a sha256 of exactly the data it plots (the frame of values
in plotting order, the columns' labels and units, the title), the figure code (the bytes of
``pcfbench/reporting/figures.py``) and the matplotlib version. The reports folder keeps a
manifest, ``figures/.figures.json``: per figure stem its key and the sha256 of each file
written for it. A report draws a figure only when the manifest lacks its key, or a file of it
is missing or is not the file the manifest recorded (replaced or edited since, or a report
killed between publishing the figure and the manifest); otherwise the file in place is kept.
The manifest is written last, after the figures it describes are in place.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

MANIFEST = ".figures.json"
MANIFEST_VERSION = 1


@functools.cache
def code_version() -> str:
    """What draws the figures: the sha256 of figures.py and the matplotlib version (any change
    to either draws every figure again)."""
    from importlib.metadata import version

    drawer = Path(__file__).with_name("figures.py")  # read beside this module: figures imports this one
    return hashlib.sha256(drawer.read_bytes()).hexdigest()[:16] + f"/matplotlib {version('matplotlib')}"


def _plain(value: Any) -> Any:
    """``value`` as JSON can hold it, floats exact (repr round-trips; NaN and inf spelled out)."""
    if isinstance(value, pd.DataFrame):
        return {"columns": [str(c) for c in value.columns],
                "rows": [[_plain(v) for v in row] for row in value.itertuples(index=False, name=None)]}
    if isinstance(value, dict):  # in order: the variants' order is the order their lines are drawn in
        return [[str(k), _plain(v)] for k, v in value.items()]
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else {"float": repr(value)}
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


def figure_key(kind: str, **data: Any) -> str:
    """The key of a figure of ``kind`` drawn from ``data`` (everything it plots)."""
    payload = json.dumps({"kind": kind, "code": code_version(), "data": _plain(data)}, sort_keys=True,
                         allow_nan=False)
    return hashlib.sha256(payload.encode()).hexdigest()


def _sha256(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


class FigureCache:
    """The figures already in ``figures_dir`` (a reports folder's ``figures/``), by key.

    :meth:`fresh` says whether a figure is there as drawn from the same key; :meth:`record`
    notes a figure drawn now (its files, possibly staged elsewhere); :meth:`write` replaces the
    manifest with the entries of this report's figures."""

    def __init__(self, figures_dir: Path):
        self.dir = Path(figures_dir)
        self.entries: dict[str, dict] = {}  # this report's figures: stem -> {"key", "files"}
        self.drawn: list[str] = []
        self.kept: list[str] = []
        try:
            old = json.loads((self.dir / MANIFEST).read_text())
            self.old = old["figures"] if old.get("version") == MANIFEST_VERSION else {}
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            self.old = {}

    def fresh(self, stem: str, key: str) -> dict[str, Path] | None:
        """The paths of figure ``stem`` in place when drawn from ``key`` and unchanged since; else None."""
        entry = self.old.get(stem)
        if not isinstance(entry, dict) or entry.get("key") != key or not entry.get("files"):
            return None
        files = entry["files"]
        if any(_sha256(self.dir / name) != digest for name, digest in files.items()):
            return None
        self.entries[stem] = entry
        self.kept.append(stem)
        return {name: self.dir / name for name in files}

    def record(self, stem: str, key: str, paths: dict[str, Path]) -> None:
        """Figure ``stem`` was drawn from ``key`` into ``paths`` (file name -> where it is now)."""
        self.entries[stem] = {"key": key, "files": {name: _sha256(Path(p)) for name, p in paths.items()}}
        self.drawn.append(stem)

    def write(self) -> None:
        """Replace the manifest (temporary file, rename): this report's figures only."""
        from pcfbench.store.cells import atomic_write_json

        self.dir.mkdir(parents=True, exist_ok=True)
        atomic_write_json(self.dir / MANIFEST, {"version": MANIFEST_VERSION, "figures": self.entries})
