"""Published results as reference rows (``published.toml``): the numbers a paper reports, shown
in their own block under a leaderboard group whose dataset, split and setting (and sample
policy, where the source states one) are the paper's; never ranked, never in an interval or
a comparison: they are text from a paper, not cells of the store.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources
from types import MappingProxyType
from typing import Mapping

from pcfbench.errors import PcfbenchError

PUBLISHED_FILE = "published.toml"
_KEYS = {"method", "source", "dataset", "split", "setting", "policy", "values"}
_REQUIRED = _KEYS - {"policy"}


@dataclass(frozen=True)
class Reported:
    """One published row: ``values`` maps a metric to the text the paper prints, in the unit a
    pcfbench table shows it in (``policy`` None: the source states none)."""

    method: str
    source: str
    dataset: str
    split: str
    setting: str
    policy: str | None
    values: Mapping[str, str]

    def matches(self, dataset: str, split: str, setting: str, policy: str) -> bool:
        return ((self.dataset, self.split, self.setting) == (dataset, split, setting)
                and self.policy in (None, policy))


def parse_published(text: str, source: str) -> tuple[Reported, ...]:
    """The rows of a published-results file; one error naming the file and the row otherwise."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PcfbenchError(f"{source} is not valid TOML: {exc}") from None
    rows = doc.get("reported")
    if set(doc) - {"reported"} or not isinstance(rows, list):
        raise PcfbenchError(f"{source}: expected only [[reported]] tables")
    out = []
    for i, r in enumerate(rows, 1):
        where = f"{source}: reported row {i}"
        if not isinstance(r, dict) or set(r) - _KEYS or _REQUIRED - set(r):
            raise PcfbenchError(f"{where} must have the keys {', '.join(sorted(_REQUIRED))} (and optionally policy), "
                                f"got {sorted(r) if isinstance(r, dict) else r!r}")
        values = r["values"]
        if not isinstance(values, dict) or not values or not all(isinstance(v, str) for v in values.values()):
            raise PcfbenchError(f"{where}: values must map metrics to the printed numbers as strings")
        for v in values.values():
            try:
                float(v)
            except ValueError:
                raise PcfbenchError(f"{where}: value {v!r} is not a number") from None
        fields = [r[k] for k in ("method", "source", "dataset", "split", "setting")]
        if not all(isinstance(v, str) and v for v in fields) or not isinstance(r.get("policy", ""), str):
            raise PcfbenchError(f"{where}: method, source, dataset, split, setting and policy must be strings")
        out.append(Reported(*fields, r.get("policy"), MappingProxyType(dict(values))))
    return tuple(out)


def load_published() -> tuple[Reported, ...]:
    """The shipped published rows."""
    text = resources.files(__package__).joinpath(PUBLISHED_FILE).read_text()
    return parse_published(text, f"pcfbench/reporting/{PUBLISHED_FILE}")


def reported_for(dataset: str, split: str, setting: str, policy: str,
                 rows: tuple[Reported, ...] | None = None) -> list[Reported]:
    """The published rows of a group (dataset, split, setting, policy), in file order."""
    return [r for r in (load_published() if rows is None else rows) if r.matches(dataset, split, setting, policy)]
