"""raycast-4docc: the ray-tracing baseline exactly as the 4D-Occ reference code computes it.

All past sweeps are concatenated in the reference frame (a static world). For every future
query ray, the past point nearest to it in the reference code's angle space
``(atan2(x, y), atan2(z, y))`` (offsets from the future sensor origin, reference-frame axes,
Euclidean distance, no wrap-around) gives its range ``|p - o|``, and the forecast point is
placed at that range on the query ray. There is no first-hit logic: a far point can win
over a nearer one at almost the same angle, so occluded background shows through; this is
the reference's behaviour and is kept on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from bench.data import Forecast, Sample
from bench.method import Method
from bench.metrics.nn import angles_4docc
from methods.raycast.common import aggregate, assemble, views
from methods.raycast.nn2d import NN2D


@dataclass(frozen=True)
class FourDOccOptions:
    constant_velocity: bool = False  # extrapolate future poses from the last two past poses


@nb.njit(parallel=True, cache=True)
def _angles_ranges(points, origin):
    """The reference angle space and the range of every point seen from ``origin``."""
    n = points.shape[0]
    u = np.empty(n)
    v = np.empty(n)
    r = np.empty(n)
    for i in nb.prange(n):
        x = points[i, 0] - origin[0]
        y = points[i, 1] - origin[1]
        z = points[i, 2] - origin[2]
        u[i] = np.arctan2(x, y)
        v[i] = np.arctan2(z, y)
        r[i] = np.sqrt(x * x + y * y + z * z)
    return u, v, r


def render_4docc(points: np.ndarray, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Depth per ray: the range of the angle-space nearest past point (0 with no points)."""
    if len(points) == 0:
        return np.zeros(len(directions))
    u, v, r = _angles_ranges(np.ascontiguousarray(points, dtype=np.float64), np.asarray(origin, dtype=np.float64))
    index = NN2D((u, v))
    nearest = index.query(angles_4docc(np.asarray(directions, dtype=np.float64)))
    return r[nearest]


class RaycastFourDOcc(Method):
    name = "raycast-4docc"
    version = "1"
    Options = FourDOccOptions

    def forecast(self, sample: Sample) -> Forecast:
        agg = aggregate(sample)
        vws = views(sample, self.options.constant_velocity)
        depths = [render_4docc(agg.points, v.origin, v.directions) for v in vws]
        return assemble(sample, vws, depths, self.options.constant_velocity)
