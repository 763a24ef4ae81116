"""Depth along query rays through an occupancy-probability grid (OccWorld's forecast, rendered).

A ray from its sensor origin walks the grid voxel by voxel (the walk of ``occupancy._label``:
clipped to the grid with the slab test, stepping across the face it leaves first). Voxel i,
crossed over ``[t_in, t_out]`` with occupancy probability ``p_i`` (1 - p(free)), is where the
ray ends with probability ``w_i = p_i * prod_{j < i} (1 - p_j)``, at the middle of its segment
(a return falls anywhere in its voxel). Readouts (``READOUTS``):

- ``expected``: ``sum_i w_i d_i + (1 - sum_i w_i) t_exit``: the expected depth, the mass left
  when the ray leaves the grid put at the grid's exit;
- ``threshold``: the middle of the first voxel with ``p_i >= 0.5`` (the grid's exit if none).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occupancy import OccGrid, _cell, _face
from pcfbench.methods.raycast.grid import _inverse, _slab

READOUTS = ("expected", "threshold")


@nb.njit(nogil=True, cache=True)
def _render(origin, dirs, prob, lo, vs, threshold_mode):
    nx, ny, nz = prob.shape
    hi0, hi1, hi2 = lo[0] + nx * vs[0], lo[1] + ny * vs[1], lo[2] + nz * vs[2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    out = np.empty(dirs.shape[0])
    for j in range(dirs.shape[0]):
        d0, d1, d2 = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        n = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        d0, d1, d2 = d0 / n, d1 / n, d2 / n
        t0, t1 = _slab(o0, d0, lo[0], hi0, 0.0, np.inf)
        t0, t1 = _slab(o1, d1, lo[1], hi1, t0, t1)
        t0, t1 = _slab(o2, d2, lo[2], hi2, t0, t1)
        if not t0 < t1:
            out[j] = 0.0  # the ray never enters the grid (its origin is outside, looking away)
            continue
        i0, i1, i2 = _inverse(d0), _inverse(d1), _inverse(d2)
        tm = t0 + 1e-9 * max(1.0, t1 - t0) if t1 - t0 > 2e-9 else 0.5 * (t0 + t1)
        a = _cell(o0 + d0 * tm, lo[0], vs[0], nx)
        b = _cell(o1 + d1 * tm, lo[1], vs[1], ny)
        c = _cell(o2 + d2 * tm, lo[2], vs[2], nz)
        t = t0
        trans = 1.0
        acc = 0.0
        found = False
        while True:
            f0 = _face(o0, i0, lo[0], vs[0], a)
            f1 = _face(o1, i1, lo[1], vs[1], b)
            f2 = _face(o2, i2, lo[2], vs[2], c)
            f = min(min(f0, min(f1, f2)), t1)
            p = prob[a, b, c]
            mid = 0.5 * (t + f)
            if threshold_mode:
                if p >= 0.5:
                    out[j] = mid
                    found = True
                    break
            else:
                acc += trans * p * mid
                trans *= 1.0 - p
            if f >= t1:
                break
            t = f
            if f0 == f:
                a += 1 if i0 > 0 else -1
            elif f1 == f:
                b += 1 if i1 > 0 else -1
            else:
                c += 1 if i2 > 0 else -1
            if a < 0 or a >= nx or b < 0 or b >= ny or c < 0 or c >= nz:
                break
        if threshold_mode:
            if not found:
                out[j] = t1
        else:
            out[j] = acc + trans * t1
    return out


def render_depths(grid: OccGrid, prob: np.ndarray, origin: np.ndarray, dirs: np.ndarray,
                  readout: str = "expected") -> np.ndarray:
    """(M,) depths (m) along ``dirs`` (M, 3) from ``origin`` (3,) through ``prob`` (nx, ny, nz),
    the occupancy probability of ``grid``'s voxels, all in the grid's frame (``READOUTS``)."""
    if readout not in READOUTS:
        raise PcfbenchError(f"readout={readout!r}: expected one of {', '.join(READOUTS)}")
    prob = np.ascontiguousarray(prob, dtype=np.float64)
    if prob.shape != tuple(grid.dims):
        raise PcfbenchError(f"render: occupancy of shape {prob.shape}, the grid has {grid.dims} voxels")
    dirs = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    return _render(np.asarray(origin, np.float64), dirs, prob, np.asarray(grid.lo, np.float64),
                   np.asarray(grid.voxel, np.float64), readout == "threshold")
