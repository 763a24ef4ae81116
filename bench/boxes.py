"""Boxes of the protocol: the ego-vehicle box (docs/protocol.md section 1) and the box
geometry of the ROI (section 3).

The ROI itself is protocol data (``pcfbench.protocol.ROI``, the active protocol's
``roi``): this module is below the protocol and never reads it; every function takes its
box from the caller.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Box:
    """An axis-aligned box, bounds inclusive, in metres. ``None`` bounds are unbounded."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool mask of the (N, 3) points inside the box (inclusive)."""
        inside = np.ones(points.shape[0], dtype=bool)
        for a in range(3):  # column by column: much faster than an (N, 3) mask reduced over axis 1
            col = points[:, a]
            inside &= (col >= self.lo[a]) & (col <= self.hi[a])
        return inside

    def crop(self, points: np.ndarray) -> np.ndarray:
        return points[self.contains(points)]


@dataclass(frozen=True)
class EgoBox:
    """The ego vehicle's footprint in the dataset's own sensor frame; z is unbounded."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float

    def inside(self, points_sensor: np.ndarray) -> np.ndarray:
        x = points_sensor[:, 0]
        y = points_sensor[:, 1]
        return (x >= self.x_min) & (x <= self.x_max) & (y >= self.y_min) & (y <= self.y_max)

    def remove(self, points_sensor: np.ndarray) -> np.ndarray:
        """Drop ego-vehicle returns; apply in the sweep's own sensor frame, before any transform."""
        return points_sensor[~self.inside(points_sensor)]


def ray_box_interval(
    origin: np.ndarray, directions: np.ndarray, box: Box
) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: where rays ``origin + t * d`` (t >= 0) are inside ``box``.

    Returns ``(t_enter, t_exit)`` per ray, float64; ``t_enter`` is 0 for an origin inside the
    box. A ray that misses the box has ``t_enter > t_exit``. Directions need not be unit;
    t is then in units of their length.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    t_enter = np.zeros(d.shape[0])
    t_exit = np.full(d.shape[0], np.inf)
    for a in range(3):  # one slab at a time, on columns
        lo, hi, da = float(box.lo[a]), float(box.hi[a]), d[:, a]
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - o[a]) / da
            t2 = (hi - o[a]) / da
        tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
        # A zero direction component: the ray is parallel to that slab, inside it or never.
        parallel = da == 0
        if parallel.any():
            inside_slab = lo <= o[a] <= hi
            tmin = np.where(parallel, -np.inf if inside_slab else np.inf, tmin)
            tmax = np.where(parallel, np.inf if inside_slab else -np.inf, tmax)
        np.maximum(t_enter, tmin, out=t_enter)
        np.minimum(t_exit, tmax, out=t_exit)
    return t_enter, t_exit


def clamp_ranges_to_box(
    origin: np.ndarray, directions: np.ndarray, ranges: np.ndarray, box: Box
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clamp points ``origin + r * d`` (unit d) to ``box`` along their rays.

    Returns ``(start, end, kept)``: the range where each ray's segment starts (0, or where it
    enters the box when the origin is outside), the clamped range of the point, and a mask of
    rays that meet the box at all. The clamped distance from the clamped origin is
    ``end - start``.
    """
    t_enter, t_exit = ray_box_interval(origin, directions, box)
    kept = t_enter <= t_exit
    end = np.clip(np.asarray(ranges, dtype=np.float64), t_enter, np.maximum(t_exit, t_enter))
    return t_enter, end, kept
