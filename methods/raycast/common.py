"""Shared pieces of the ray-casting baselines: past-sweep aggregation, future viewpoints
(given or extrapolated at constant velocity), angle spaces and the forecast assembly.

Constant velocity. With ``constant_velocity=True`` a baseline ignores the given future
poses (and the query origins, which are their positions): each future sensor pose is
extrapolated from the last two past poses, ``T(t) = T_0 exp(s log(T_-1^-1 T_0))`` with
``s = (t - t_0) / (t_0 - t_-1)`` from the timestamps (SE(3) exponential map, so a turning
vehicle follows an arc: ``pcfbench.geometry.constant_velocity_poses``). The query directions
are cast from the extrapolated origin, and the forecast carries points only (depths along the
given query rays would need the true origin), so the metrics read it as a point cloud, as the
reference code's ``--assume-constant-velocity`` results are read.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import threading
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.execution import ExecutionContext, current
from pcfbench.geometry import constant_velocity_poses


@dataclass(frozen=True)
class Aggregate:
    """All past points in the reference frame, with each point's own sensor origin and range."""

    points: np.ndarray  # (N, 3) float64
    origins: np.ndarray  # (N, 3) float64, the sensor position of the sweep each point came from
    own_range: np.ndarray  # (N,) float64, the range from that sensor
    sweep: np.ndarray  # (N,) int16, the index of the past sweep (0 is the oldest)
    cols: np.ndarray  # (3, N) float64, ``points`` column by column (the projection kernels vectorise on it)


def soa(points: np.ndarray) -> np.ndarray:
    """(N, 3) to (3, N) contiguous float64: x, y and z each contiguous, so that numba vectorises
    the per-point projections (about 5x faster than reading the (N, 3) rows)."""
    return np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)


def aggregate(sample: Sample) -> Aggregate:
    pts = [np.asarray(p, dtype=np.float64) for p in sample.past_points_ref]
    counts = [len(p) for p in pts]
    if sum(counts) == 0:
        z = np.zeros((0, 3))
        return Aggregate(z, z, np.zeros(0), np.zeros(0, np.int16), np.zeros((3, 0)))
    points = np.concatenate(pts)
    sweep = np.repeat(np.arange(len(pts), dtype=np.int16), counts)
    origins = np.asarray(sample.past_T_ref_sensor, dtype=np.float64)[sweep, :3, 3]
    own_range = np.linalg.norm(points - origins, axis=1)
    return Aggregate(points, origins, own_range, sweep, soa(points))


@dataclass(frozen=True)
class View:
    """One future sweep to render: the pose it is rendered from and the rays to answer."""

    T_ref_sensor: np.ndarray  # (4, 4)
    origin: np.ndarray  # (3,) float64
    directions: np.ndarray  # (M, 3) float64 unit, reference frame
    dcols: np.ndarray  # (3, M) float64, ``directions`` column by column

    def subset(self, which: np.ndarray) -> View:
        """The same viewpoint with only the rays ``which`` (a mask or indices)."""
        return View(self.T_ref_sensor, self.origin, self.directions[which], np.ascontiguousarray(self.dcols[:, which]))


def views(sample: Sample, constant_velocity: bool) -> list[View]:
    if constant_velocity:
        poses = constant_velocity_poses(sample.past_T_ref_sensor, sample.past_timestamps_ns, sample.future_timestamps_ns)
    else:
        poses = np.asarray(sample.future_T_ref_sensor, dtype=np.float64)
    out = []
    for T, q in zip(poses, sample.queries):
        origin = T[:3, 3].copy() if constant_velocity else np.asarray(q.origin_ref, dtype=np.float64)
        d = np.asarray(q.directions_ref, dtype=np.float64)
        out.append(View(T, origin, d, soa(d)))
    return out


_T = TypeVar("_T")
_R = TypeVar("_R")


def map_views(fn: Callable[[_T], _R], items: Sequence[_T], execution: ExecutionContext | None = None) -> list[_R]:
    """``[fn(x) for x in items]`` with the items shared out over the threads of ``execution``
    (default: the process's, ``pcfbench.execution.current()``) as they come free; each runs
    its numba kernels on one thread (``ExecutionContext.map``).

    Views (or pieces of views: ``pieces``), not rays, are the unit of parallel work: numba's
    ``prange`` joins all its threads at the end of every kernel, so one thread waiting for a
    core would hold the others up, while here a slowed thread just takes fewer views. The
    kernels keep ``prange`` loops where numba's parallel lowering is what makes LLVM
    vectorise them; with one numba thread they run inline.
    """
    return (execution or current()).map(fn, items)


_LOCAL = threading.local()


def scratch(name: str, n: int, dtype=np.float64) -> np.ndarray:
    """A buffer of ``n`` items of this thread's, reused by its next request for ``name`` (so
    only for temporaries that do not outlive one view's work; contents undefined).

    A view's temporaries are tens of MB (4docc: angles, cell keys and the sorted copy of
    ~640k points); fresh ones each view came as new pages from the kernel, zero-filled on
    first touch, and two threads faulting them in waited on each other."""
    bufs = getattr(_LOCAL, "bufs", None)
    if bufs is None:
        bufs = _LOCAL.bufs = {}
    dtype = np.dtype(dtype)
    buf = bufs.get(name)
    if buf is None or buf.dtype != dtype or buf.shape[0] < n:
        buf = bufs[name] = np.empty(max(n, 1), dtype)
    return buf[:n]


#: rays per piece of work when a view's rays are shared out over threads (see map_views)
PIECE = 32_768


def pieces(n: int, size: int = PIECE) -> list[slice]:
    """``range(n)`` cut into consecutive slices of at most ``size`` (at least one slice)."""
    return [slice(a, min(a + size, n)) for a in range(0, max(n, 1), size)]


def assemble(sample: Sample, vws: list[View], depths: list[np.ndarray], constant_velocity: bool) -> Forecast:
    """Per-ray depths to a forecast: depths and points on the query rays, or points only
    (cast from the extrapolated origins) under constant velocity."""
    depths = [np.maximum(np.nan_to_num(np.asarray(d, np.float64), nan=0.0, posinf=0.0), 0.0) for d in depths]
    if not constant_velocity:
        return Forecast.from_depths(sample, depths)
    pts = tuple((v.origin + v.directions * d[:, None]).astype(np.float32) for v, d in zip(vws, depths))
    return Forecast(points_ref=pts)
