"""The benchmark protocol as versioned data (docs/protocol.md 2): settings, sample policies, the
ROI and the minimum range.

Protocol file and versioning
----------------------------
The protocol's values live in ``protocol.toml``, shipped inside the package and read once
by :func:`load_protocol` into a frozen :class:`Protocol`: its ``version``, the named
:class:`Setting` s, the ROI box, the minimum range and the named :class:`SamplePolicy` s.
:func:`active_protocol` is the protocol every run uses; the module-level names
``SETTINGS``, ``SAMPLE_POLICIES``, ``MIN_RANGE_M`` and ``ROI`` are views of it, never
separate copies; what scores a sweep is handed the ROI and minimum range it uses
(:class:`~pcfbench.metrics.base.SweepContext`), and the box geometry below the protocol
(:mod:`pcfbench.boxes`) takes its box from the caller.

- Changing any value in the file changes what cells compute: bump ``version`` with it.
- A malformed file is one :class:`~pcfbench.errors.PcfbenchError` naming the file, the key
  and what was expected; no value falls back to a default silently.
- Dataset plugins add settings through the ``register_settings`` hook; those names may not
  collide with the file's or with each other. :func:`pcfbench.plugins.get_setting` looks in
  the protocol first, then in the loaded plugins (the protocol is below the plugins and
  never imports them).
- Every cell records the protocol version, the setting's parameters, the sample policy, the
  ROI and the minimum range in its ``cell.json`` identity (:meth:`SampleBuilder.identity`);
  a rerun under different values stops with an error naming the field rather than mixing
  rows.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

from pcfbench.dataset import DatasetAdapter
from pcfbench.errors import PcfbenchError, unknown_name
from pcfbench.kinds import PolicyKind, parse
from pcfbench.boxes import Box

#: The protocol file shipped in the package.
PROTOCOL_FILE = "protocol.toml"


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


@dataclass(frozen=True)
class Setting:
    """How many past / future sweeps a sample has and how far apart (in source sweeps).

    ``rate_hz`` > 0 is the source sweep rate; ``past`` >= 1 counts t=0; ``future`` >= 1;
    ``stride`` >= 1 source sweeps between used sweeps.
    """

    name: str
    rate_hz: float
    past: int  # including t=0
    future: int
    stride: int
    description: str = ""

    def __post_init__(self) -> None:
        where = f"setting {self.name!r}"
        if not isinstance(self.name, str) or not self.name or any(c.isspace() for c in self.name):
            raise PcfbenchError(f"setting name {self.name!r} must be a non-empty string without spaces")
        if isinstance(self.rate_hz, bool) or not isinstance(self.rate_hz, (int, float)) or not (
            math.isfinite(self.rate_hz) and self.rate_hz > 0
        ):
            raise PcfbenchError(f"{where}: rate_hz must be a positive number of Hz, got {self.rate_hz!r}")
        for key in ("past", "future", "stride"):
            value = getattr(self, key)
            if not _is_int(value) or value < 1:
                raise PcfbenchError(f"{where}: {key} must be an integer >= 1, got {value!r}")
        if not isinstance(self.description, str):
            raise PcfbenchError(f"{where}: description must be a string, got {self.description!r}")

    @property
    def horizon_s(self) -> float:
        return self.future * self.stride / self.rate_hz

    def step_seconds(self, step: int) -> float:
        """Time of future sweep ``step`` (0-based) after t=0, in seconds."""
        return (step + 1) * self.stride / self.rate_hz

    def params(self) -> dict[str, Any]:
        """What the setting computes with (its cell identity): everything but the description."""
        return {"rate_hz": float(self.rate_hz), "past": self.past, "future": self.future, "stride": self.stride}


#: The anchor rules a policy can use; ``subsample`` thins another policy's anchors.
POLICY_KINDS = tuple(k.value for k in PolicyKind)
#: the kinds whose anchors a ``subsample`` policy can thin
_ANCHOR_RULES = (PolicyKind.FULL_CONTEXT, PolicyKind.EVERY_FRAME)


@dataclass(frozen=True)
class SamplePolicy:
    """Which reference sweeps of a split count as samples.

    ``full-context``: anchors with every past and future sweep inside the sequence.
    ``every-frame``: every sweep (past and future sweeps outside the sequence are empty).
    ``subsample``: policy ``of``'s anchors thinned over the whole split in its stable order:
    either ``n`` of them evenly spaced (see :func:`evenly_spaced`; every anchor when there are
    ``n`` or fewer), or ``every``-th one from the first (candidates 0, k, 2k, ...: a share of
    every split and setting, however many anchors it has).
    """

    name: str
    kind: PolicyKind
    n: int | None = None
    of: str | None = None
    description: str = ""
    #: the anchor rule of the candidates: ``kind``, or for ``subsample`` the kind of ``of``
    rule: PolicyKind | str = ""
    every: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", parse(PolicyKind, self.kind, f"sample policy {self.name!r}: kind"))
        if not self.rule:
            object.__setattr__(self, "rule", self.kind)
        if self.rule not in _ANCHOR_RULES:
            raise PcfbenchError(f"sample policy {self.name!r}: candidates must follow full-context or every-frame, not {self.rule!r}")
        object.__setattr__(self, "rule", PolicyKind(self.rule))

    def params(self) -> dict[str, Any]:
        """What the policy selects with (its cell identity): everything but the description.
        The kind is its plain string, as cell.json has always held it."""
        out: dict[str, Any] = {"name": self.name, "kind": self.kind.value}
        if self.kind == PolicyKind.SUBSAMPLE:  # an n policy's identity stays as it was before ``every``
            out.update({"every": self.every} if self.every is not None else {"n": self.n}, of=self.of)
        return out

    def thin(self, count: int) -> list[int]:
        """Indices of the kept candidates among ``count`` (a subsample policy's thinning)."""
        if self.every is not None:
            return list(range(0, count, self.every))
        return evenly_spaced(count, self.n)


def evenly_spaced(count: int, n: int) -> list[int]:
    """Indices of ``n`` of ``count`` candidates spread evenly: ``i * count // n`` for i < n.

    Exact integer arithmetic: the first candidate is always kept and consecutive picks are
    ``count // n`` or ``count // n + 1`` apart. With ``count <= n`` every candidate is kept.
    """
    if n < 1:
        raise PcfbenchError(f"evenly_spaced: n must be >= 1, got {n}")
    if count <= n:
        return list(range(count))
    return [i * count // n for i in range(n)]


@dataclass(frozen=True)
class Protocol:
    """The benchmark protocol: version, settings, ROI, minimum range and sample policies."""

    version: str
    settings: Mapping[str, Setting]
    roi: Box
    min_range_m: float
    policies: Mapping[str, SamplePolicy]
    default_policy: str = "full-context"
    source: str = field(default="", compare=False)

    def setting(self, name: str) -> Setting:
        if name not in self.settings:
            raise unknown_name("setting", name, self.settings)
        return self.settings[name]

    def policy(self, name: str) -> SamplePolicy:
        if name not in self.policies:
            raise unknown_name("sample policy", name, self.policies)
        return self.policies[name]

    def identity(self) -> dict[str, Any]:
        """The protocol-wide part of a cell's identity (JSON-ready)."""
        return {
            "protocol_version": self.version,
            "roi": {"lo": list(self.roi.lo), "hi": list(self.roi.hi)},
            "min_range_m": self.min_range_m,
        }


_TOP_KEYS = {"version", "min_range_m", "roi", "policies", "settings"}
_SETTING_KEYS = {"rate_hz", "past", "future", "stride", "description"}
_POLICY_KEYS = {"kind", "n", "every", "of", "description"}


def _table(value: object, where: str) -> dict:
    if not isinstance(value, dict):
        raise PcfbenchError(f"{where} must be a table, got {value!r}")
    return value


def _no_extra(table: dict, allowed: set[str], where: str) -> None:
    extra = sorted(set(table) - allowed)
    if extra:
        raise PcfbenchError(f"{where} has unknown key(s) {', '.join(extra)} (allowed: {', '.join(sorted(allowed))})")


def _require(table: dict, key: str, where: str) -> Any:
    if key not in table:
        raise PcfbenchError(f"{where} is missing {key!r}")
    return table[key]


def _vector3(value: object, where: str) -> tuple[float, float, float]:
    if not (isinstance(value, list) and len(value) == 3 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
    )):
        raise PcfbenchError(f"{where} must be 3 finite numbers [x, y, z], got {value!r}")
    return tuple(float(v) for v in value)  # type: ignore[return-value]


def parse_protocol(data: dict, source: str) -> Protocol:
    """Validate a protocol table (as read from TOML) into a :class:`Protocol`; errors name ``source``."""
    _no_extra(data, _TOP_KEYS, f"protocol file {source}")
    version = _require(data, "version", f"protocol file {source}")
    if not isinstance(version, str) or not version:
        raise PcfbenchError(f"protocol file {source}: version must be a non-empty string, got {version!r}")
    min_range = _require(data, "min_range_m", f"protocol file {source}")
    if isinstance(min_range, bool) or not isinstance(min_range, (int, float)) or not (math.isfinite(min_range) and min_range >= 0):
        raise PcfbenchError(f"protocol file {source}: min_range_m must be a number of metres >= 0, got {min_range!r}")

    roi_t = _table(_require(data, "roi", f"protocol file {source}"), f"protocol file {source} [roi]")
    _no_extra(roi_t, {"lo", "hi"}, f"protocol file {source} [roi]")
    lo = _vector3(_require(roi_t, "lo", f"protocol file {source} [roi]"), f"protocol file {source} roi.lo")
    hi = _vector3(_require(roi_t, "hi", f"protocol file {source} [roi]"), f"protocol file {source} roi.hi")
    if not all(a < b for a, b in zip(lo, hi)):
        raise PcfbenchError(f"protocol file {source}: roi.lo {list(lo)} must be below roi.hi {list(hi)} on every axis")

    settings: dict[str, Setting] = {}
    for name, raw in _table(_require(data, "settings", f"protocol file {source}"), f"protocol file {source} [settings]").items():
        where = f"protocol file {source} [settings.{name}]"
        raw = _table(raw, where)
        _no_extra(raw, _SETTING_KEYS, where)
        args = {k: _require(raw, k, where) for k in ("rate_hz", "past", "future", "stride")}
        try:
            settings[name] = Setting(name, description=raw.get("description", ""), **args)
        except PcfbenchError as exc:
            raise PcfbenchError(f"{where}: {exc}") from None

    policies: dict[str, SamplePolicy] = {}
    raw_policies = _table(_require(data, "policies", f"protocol file {source}"), f"protocol file {source} [policies]")
    for name, raw in raw_policies.items():
        where = f"protocol file {source} [policies.{name}]"
        raw = _table(raw, where)
        _no_extra(raw, _POLICY_KEYS, where)
        kind = parse(PolicyKind, _require(raw, "kind", where), f"{where}: kind")
        n, of, every = raw.get("n"), raw.get("of"), raw.get("every")
        if kind == PolicyKind.SUBSAMPLE:
            if (n is None) == (every is None):
                raise PcfbenchError(f"{where}: a subsample policy needs one of n (how many anchors) and every "
                                    f"(every k-th anchor), got n={n!r}, every={every!r}")
            if n is not None and (not _is_int(n) or n < 1):
                raise PcfbenchError(f"{where}: a subsample policy's n must be an integer >= 1, got {n!r}")
            if every is not None and (not _is_int(every) or every < 1):
                raise PcfbenchError(f"{where}: a subsample policy's every must be an integer >= 1, got {every!r}")
            base = raw_policies.get(of) if isinstance(of, str) else None
            if not isinstance(base, dict) or base.get("kind") not in _ANCHOR_RULES:
                raise PcfbenchError(
                    f"{where}: of must name a full-context or every-frame policy of the file, got {of!r}"
                )
        elif n is not None or of is not None or every is not None:
            raise PcfbenchError(f"{where}: only a subsample policy takes n, every and of")
        rule = raw_policies[of]["kind"] if kind == "subsample" else kind
        policies[name] = SamplePolicy(name, kind, n, of, raw.get("description", ""), rule, every)
    if "full-context" not in policies:
        raise PcfbenchError(f"protocol file {source} has no [policies.full-context] (the default sample policy)")

    return Protocol(
        version=version,
        settings=MappingProxyType(settings),
        roi=Box(lo=lo, hi=hi),
        min_range_m=float(min_range),
        policies=MappingProxyType(policies),
        source=source,
    )


def load_protocol(path: str | Path | None = None) -> Protocol:
    """Read and validate a protocol file; ``None`` reads the one shipped in the package."""
    if path is None:
        resource = resources.files(__package__).joinpath(PROTOCOL_FILE)
        source, text = str(resource), resource.read_text(encoding="utf-8")
    else:
        source = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise PcfbenchError(f"cannot read protocol file {source}: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PcfbenchError(f"protocol file {source} is not valid TOML: {exc}") from None
    return parse_protocol(data, source)


_ACTIVE = load_protocol()


def active_protocol() -> Protocol:
    """The protocol every run uses: the file shipped in the package, loaded once."""
    return _ACTIVE


#: Views of the active protocol (read-only), kept for the code that imports them.
SETTINGS: Mapping[str, Setting] = _ACTIVE.settings
SAMPLE_POLICIES: tuple[str, ...] = tuple(_ACTIVE.policies)
#: Ground-truth points closer than this to their sensor are ignored by the metrics.
MIN_RANGE_M: float = _ACTIVE.min_range_m
#: The region of interest: the metrics' near-field crop and the clamp of depths along rays.
ROI: Box = _ACTIVE.roi


def check_compatible(setting: Setting, adapter: DatasetAdapter) -> None:
    if abs(setting.rate_hz - adapter.rate_hz) > 1e-6:
        raise PcfbenchError(
            f"setting {setting.name!r} expects {setting.rate_hz:g} Hz sweeps but dataset {adapter.name!r} "
            f"has {adapter.rate_hz:g} Hz (its settings: {', '.join(adapter.default_settings) or 'none'})"
        )


