"""raycast-4docc: the ray-tracing baseline exactly as the 4D-Occ reference code computes it.

All past sweeps are concatenated in the reference frame (a static world). For every future
query ray, the past point nearest to it in the reference code's angle space
``(atan2(x, y), atan2(z, y))`` (offsets from the future sensor origin, reference-frame axes,
Euclidean distance, no wrap-around) gives its range ``|p - o|``, and the forecast point is
placed at that range on the query ray. There is no first-hit logic: a far point can win
over a nearer one at almost the same angle, so occluded background shows through; this is
the reference's behaviour and is kept on purpose.

Per view, the angles of all past points and rays come from one vectorised pass
(``fastmath.atan2``, within 2 ulp of the C library, the same function for points and rays)
and the nearest point of every ray from an exact bucket-grid search (``pcfbench.nn2d``; ties go to
the lowest point index, like a brute-force argmin).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import partial

import numba as nb
import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.execution import ExecutionContext, current
from pcfbench.method import Method
from pcfbench.options import option
from pcfbench.methods.raycast.common import aggregate, assemble, map_views, pieces, scratch, views
from pcfbench.methods.raycast.fastmath import atan2
from pcfbench.nn2d import NN2D


#: queries per thread of a view shared by all threads (see ``render_4docc_views``) come in this many pieces
SHARED_PIECES = 2


@dataclass(frozen=True)
class FourDOccOptions:
    constant_velocity: bool = option(False, help="extrapolate the future poses from the last two past poses "
                                                 "instead of using the sample's future poses")


@nb.njit(nogil=True, parallel=True, cache=True)
def angles_into(cols, origin, u, v):
    """The reference angle space ``(atan2(x, y), atan2(z, y))`` of (3, N) points ``cols`` seen
    from ``origin``, into ``u`` and ``v`` (vectorised; ``fastmath.atan2``)."""
    X = cols[0]
    Y = cols[1]
    Z = cols[2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for i in nb.prange(cols.shape[1]):
        y = Y[i] - o1
        u[i] = atan2(X[i] - o0, y)
        v[i] = atan2(Z[i] - o2, y)
    return u, v


def angles(cols: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``angles_into`` new arrays."""
    n = cols.shape[1]
    return angles_into(cols, np.asarray(origin, dtype=np.float64), np.empty(n), np.empty(n))


@nb.njit(nogil=True, cache=True)
def _ranges(cols, origin, idx):
    """``|p - origin|`` of the points ``idx`` (computed as the reference does, in float64)."""
    out = np.empty(idx.shape[0])
    for j in range(idx.shape[0]):
        i = idx[j]
        x = cols[0, i] - origin[0]
        y = cols[1, i] - origin[1]
        z = cols[2, i] - origin[2]
        out[j] = np.sqrt(x * x + y * y + z * z)
    return out


def render_4docc_views(cols: np.ndarray, vws, execution: ExecutionContext | None = None) -> list[np.ndarray]:
    """Depth per ray of each view (``common.View``): the range of the angle-space nearest past
    point among ``cols`` (3, N) (0 with no points). The views go to the threads; each builds
    its view's index in its own reused buffers (``common.scratch``), asks it and drops it.

    Views left over when they do not share out evenly over the threads (the fifth of five on
    two) are shared instead: one thread builds each such view's index first thing (in buffers
    of its own), and its queries go in ``SHARED_PIECES`` pieces per thread after the whole views,
    to whichever thread comes free (5 views on 2 threads: at most 2.5 views' work on one
    thread, not 3)."""
    if cols.shape[1] == 0:
        return [np.zeros(v.dcols.shape[1]) for v in vws]
    n = cols.shape[1]

    def index(v, prefix: str) -> tuple[NN2D, np.ndarray]:
        origin = np.asarray(v.origin, dtype=np.float64)
        u, w = angles_into(cols, origin, scratch(f"{prefix}.u", n), scratch(f"{prefix}.v", n))
        return NN2D((u, w), buffers=lambda name, k, dtype: scratch(f"{prefix}.nn2d.{name}", k, dtype)), origin

    def one(v) -> np.ndarray:
        nn, origin = index(v, "4docc")
        return _ranges(cols, origin, nn.query(angles(v.dcols, np.zeros(3))))

    execution = execution or current()
    threads = execution.threads
    whole = len(vws) - len(vws) % threads if threads > 1 else len(vws)
    if whole == len(vws):
        return map_views(one, vws, execution)
    shared = list(range(whole, len(vws)))
    built = {k: threading.Event() for k in shared}
    indexes: dict = {}
    out = [np.empty(v.dcols.shape[1]) for v in vws]

    def build(k: int) -> None:
        try:
            indexes[k] = index(vws[k], f"4docc.shared{k}")
        finally:
            built[k].set()

    def whole_view(k: int) -> None:
        out[k][:] = one(vws[k])

    def ask(k: int, sl: slice) -> None:
        built[k].wait()  # started before any piece (first in the queue), so this ends
        nn, origin = indexes[k]
        out[k][sl] = _ranges(cols, origin, nn.query(angles(np.ascontiguousarray(vws[k].dcols[:, sl]), np.zeros(3))))

    jobs = [partial(build, k) for k in shared] + [partial(whole_view, k) for k in range(whole)]
    for k in shared:
        m = vws[k].dcols.shape[1]
        jobs += [partial(ask, k, sl) for sl in pieces(m, max(1, -(-m // (SHARED_PIECES * threads))))]
    map_views(lambda job: job(), jobs, execution)
    return out


class RaycastFourDOcc(Method):
    name = "raycast-4docc"
    version = "1"
    Options = FourDOccOptions

    def forecast(self, sample: Sample) -> Forecast:
        agg = sample.derive(aggregate)
        vws = sample.derive(views, self.options.constant_velocity)
        depths = render_4docc_views(agg.cols, vws, self.execution)
        return assemble(sample, vws, depths, self.options.constant_velocity)
