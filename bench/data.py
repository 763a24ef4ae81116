"""The data model: plain frozen dataclasses over NumPy arrays.

Frames are in the names: ``*_ref`` arrays are in the sample's reference (t=0) sensor frame,
``*_sensor`` arrays in a sweep's own sensor frame, ``T_a_b`` maps frame b to frame a.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any, Callable, Hashable, TypeVar

import numpy as np

_T = TypeVar("_T")

FLOAT32_MAX = float(np.finfo(np.float32).max)


def read_only_copy(arr: np.ndarray) -> np.ndarray:
    """A copy of ``arr`` that cannot be written: a read-only view of a read-only copy, so the
    view's ``writeable`` flag cannot be turned back on either."""
    owner = np.array(arr, copy=True)
    owner.flags.writeable = False
    view = owner.view()
    view.flags.writeable = False
    return view


def frozen(value: Any) -> Any:
    """``value`` with every NumPy array in it (itself, the items of its tuples and lists, the
    fields of its dataclasses, the values of its dicts) made read-only, in place; returns it."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, (tuple, list)):
        for item in value:
            frozen(item)
    elif isinstance(value, dict):
        for item in value.values():
            frozen(item)
    elif is_dataclass(value) and not isinstance(value, type):
        for f in fields(value):
            frozen(getattr(value, f.name))
    return value


@dataclass(frozen=True, eq=False)
class Sweep:
    """One LiDAR sweep as an adapter loads it.

    points_sensor: (N, 3) float32, sensor frame, metres.
    T_world_sensor: (4, 4) float64 pose of the sensor in the dataset's world frame.
    """

    points_sensor: np.ndarray
    T_world_sensor: np.ndarray
    timestamp_ns: int
    intensity: np.ndarray | None = None
    source: str = ""


@dataclass(frozen=True, eq=False)
class RayQuery:
    """The rays of one future sweep: every ground-truth return, seen from the sweep's origin.

    origin_ref: (3,) float64, the future sensor position in the reference frame.
    directions_ref: (M, 3) float32 unit vectors, one per ground-truth point.
    """

    origin_ref: np.ndarray
    directions_ref: np.ndarray

    def __len__(self) -> int:
        return int(self.directions_ref.shape[0])


@dataclass(frozen=True, eq=False)
class Sample:
    """What a method sees: the past in the reference frame, the future poses and query rays.

    past_points_ref: P arrays (N_k, 3) float32, oldest first, the last one is t=0.
    past_T_ref_sensor: (P, 4, 4) float64; future_T_ref_sensor: (F, 4, 4) float64.
    queries: F RayQuery, one per future sweep. Ground-truth points are not here.
    """

    sample_id: str
    dataset: str
    sequence: str
    ref_index: int
    past_points_ref: tuple[np.ndarray, ...]
    past_T_ref_sensor: np.ndarray
    past_timestamps_ns: np.ndarray
    future_T_ref_sensor: np.ndarray
    future_timestamps_ns: np.ndarray
    queries: tuple[RayQuery, ...]
    T_world_ref: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def num_future(self) -> int:
        return len(self.queries)

    def derive(self, fn: Callable[..., _T], *args: Hashable) -> _T:
        """``fn(self, *args)``, computed once for every method run on this sample in this process.

        When a run scores several methods on a sample (``pcfbench.running.group``), each gets its
        own :meth:`for_method` copy of it; what those copies derive is kept in one place, so a
        structure that several methods build from the same inputs (the ray casters' aggregate of
        the past sweeps) is built by the first of them only. ``fn`` must be a module-level
        function of the sample's inputs and ``args`` alone (hashable; options, not objects): the
        key is its module, name and ``args``. The value's arrays are made read-only (what one
        method derives cannot be changed under the next); the first method's ``t_method``
        includes computing it."""
        if "<" in fn.__qualname__:  # a lambda or a nested function: its name is not a key
            raise ValueError(f"Sample.derive: {fn.__qualname__!r} of {fn.__module__} is not a module-level function; "
                             "two such functions could share a name, and so one's value")
        derived = _DERIVED.setdefault(self, {})
        key = (fn.__module__, fn.__qualname__, args)
        try:
            return derived[key]
        except KeyError:
            pass
        value = frozen(fn(self, *args))
        derived[key] = value
        return value

    def for_method(self) -> "Sample":
        """What a method receives: a copy whose every array (points, poses, timestamps, query
        origins and directions) is read-only, so a method writing into its input gets a
        ``ValueError`` and, whatever it does to the copy, the sample it is scored against (this
        one, kept by the runner) is untouched. The copies share what :meth:`derive` computes."""
        copy = replace(
            self,
            past_points_ref=tuple(read_only_copy(p) for p in self.past_points_ref),
            past_T_ref_sensor=read_only_copy(self.past_T_ref_sensor),
            past_timestamps_ns=read_only_copy(self.past_timestamps_ns),
            future_T_ref_sensor=read_only_copy(self.future_T_ref_sensor),
            future_timestamps_ns=read_only_copy(self.future_timestamps_ns),
            queries=tuple(RayQuery(read_only_copy(q.origin_ref), read_only_copy(q.directions_ref)) for q in self.queries),
            T_world_ref=read_only_copy(self.T_world_ref),
        )
        _DERIVED[copy] = _DERIVED.setdefault(self, {})
        return copy


#: what ``Sample.derive`` computed, per sample: one dict shared by a sample and its
#: ``for_method`` copies only (a sample made any other way, ``replace`` or ``Sample(**...)``,
#: may have other inputs and starts empty); kept outside the samples, so neither their fields
#: nor their pickles carry it
_DERIVED: weakref.WeakKeyDictionary[Sample, dict] = weakref.WeakKeyDictionary()


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Held back from methods: the future points (F arrays (M_k, 3) float32, reference frame)."""

    sample_id: str
    future_points_ref: tuple[np.ndarray, ...]


@dataclass(frozen=True, eq=False)
class Forecast:
    """A method's answer for one sample, one entry per future sweep.

    points_ref: F arrays (K, 3) in the reference frame, or None.
    depths: F arrays (M_k,), one depth in metres along each query ray, or None.
    At least one of the two is given; both may be.
    """

    points_ref: tuple[np.ndarray, ...] | None = None
    depths: tuple[np.ndarray, ...] | None = None

    @staticmethod
    def from_depths(sample: Sample, depths: list[np.ndarray] | tuple[np.ndarray, ...]) -> "Forecast":
        """Answer per-ray depths and the points they place along the query rays."""
        depths = tuple(np.asarray(d, dtype=np.float32) for d in depths)
        points = tuple(
            (q.origin_ref + q.directions_ref.astype(np.float64) * d[:, None].astype(np.float64)).astype(np.float32)
            for q, d in zip(sample.queries, depths)
        )
        return Forecast(points_ref=points, depths=depths)
