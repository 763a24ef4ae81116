"""Exact 2-D nearest neighbours on a uniform bucket grid (numba), for angle-space look-ups.

Built per view from ~640k points and asked ~127k queries, so both halves are single passes
without Python in between: the points' cells are counted, prefix-summed and scattered (a
counting sort, stable, so a cell keeps its points in index order) into one interleaved
(x, y) array with 32-bit cell starts, which keeps a query's candidates in few cache lines.

A query scans its own cell and then Chebyshev rings of cells, skipping every cell (and whole
ring rows and columns) whose rectangle is farther than the best distance so far, and stops
once the best distance is strictly smaller than the distance to any cell not yet scanned; so
every point at the minimal distance has been seen and ties go to the lowest point index,
exactly like a brute-force ``argmin``. Queries not settled within ``MAX_RINGS`` rings (far
from all points) get ``FAR_RINGS`` rings, and those still not settled are asked again on a
grid 8x coarser in each direction, whose ring search runs until it is settled or has covered
the whole grid. (On the benchmark sample 0 to 4 rays of a view's 127k need more than 2 rings
and none more than 16; building the coarse grid for them had cost a pass over all points.)

A cell is scanned without a data-dependent branch per point: the position of its first
minimum is kept with selects (a cell holds its points in index order, so that is its lowest
index at the minimal distance) and compared with the best so far once per cell. On the
KITTI-sized benchmark view (635,702 points, 127,154 rays; angle space very unevenly
filled: 41 points in a point's cell on average) the per-point branch (``if d < best``, taken
at random places) cost more than the distances: the queries took 17.5 ms against 22.9 ms
(thread CPU time, medians, same process). Measured and dropped: starting each query from the
previous query's answer (a random read of the unsorted points and a looser first bound: 10%
slower than without), finer cells (0.125 to 1 point per cell), cells 4x to 32x finer along
one axis scanned column by column outward, a direct scan of the block of cells within the
first candidate's distance, a two-pass min-then-index scan, and asking the queries in the
order of their cells (24.2 ms against 24.2 ms unsorted plus a 1.3 ms counting sort): none
faster. With the
branch-free scan 2 to 4 points per cell are equally fast; 4 halves the cell table to build.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from pcfbench.methods.raycast.common import scratch

#: rings of the fine grid scanned before a query goes to the coarse grid
MAX_RINGS = 2
#: rings of the fine grid for the queries not settled within ``MAX_RINGS``, before the coarse grid
FAR_RINGS = 16
#: points per cell of the fine grid (on average over the bounding box)
PER_CELL = 4.0
#: the coarse grid's cells are this many fine cells wide in each direction
COARSE = 8


@nb.njit(nogil=True, cache=True)
def _bbox(px, py):
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    for i in range(px.shape[0]):
        x0 = min(x0, px[i])
        x1 = max(x1, px[i])
        y0 = min(y0, py[i])
        y1 = max(y1, py[i])
    return x0, x1, y0, y1


@nb.njit(nogil=True, parallel=True, cache=True)
def _cells(px, py, x0, y0, hx, hy, nx, ny, keys):
    """Cell of each point into ``keys``, clamped to the grid (prange: numba vectorises it)."""
    n = px.shape[0]
    ivx = 1.0 / hx
    ivy = 1.0 / hy
    for i in nb.prange(n):
        cx = min(max(int(math.floor((px[i] - x0) * ivx)), 0), nx - 1)
        cy = min(max(int(math.floor((py[i] - y0) * ivy)), 0), ny - 1)
        keys[i] = cx * ny + cy
    return keys


@nb.njit(nogil=True, cache=True)
def _build(px, py, keys, starts, sp, sidx):
    """Counting sort of the points into their cells ``keys``: fills ``starts`` (ncell+1,)
    int32, ``sp`` (K, 2) float64 interleaved x, y and ``sidx`` (K,) int32, the sorted index."""
    n = px.shape[0]
    ncell = starts.shape[0] - 1
    starts[:] = 0
    for i in range(n):
        starts[keys[i] + 1] += 1
    for c in range(ncell):
        starts[c + 1] += starts[c]
    for i in range(n):
        k = keys[i]
        s = starts[k]
        starts[k] = s + 1
        sp[s, 0] = px[i]
        sp[s, 1] = py[i]
        sidx[s] = i
    for c in range(ncell, 0, -1):  # the fill advanced every start to the next one: undo
        starts[c] = starts[c - 1]
    starts[0] = 0


@nb.njit(inline="always")
def _gap(lo, h, i, q):
    """Distance from ``q`` to the interval of cell ``i`` along one axis (0 inside)."""
    return max(lo + i * h - q, q - (lo + (i + 1) * h), 0.0)


@nb.njit(inline="always")
def _scan(c, starts, sp, sidx, qx, qy, best_d, best_i):
    m = np.inf
    ms = -1
    for s in range(starts[c], starts[c + 1]):
        dx = sp[s, 0] - qx
        dy = sp[s, 1] - qy
        d = dx * dx + dy * dy
        lt = d < m
        ms = s if lt else ms
        m = d if lt else m
    if ms >= 0:
        i = sidx[ms]
        if m < best_d or (m == best_d and i < best_i):
            best_d = m
            best_i = i
    return best_d, best_i


@nb.njit(inline="always")
def _visit(ix, iy, nx, ny, starts, sp, sidx, qx, qy, best_d, best_i, x0, y0, hx, hy, tol):
    if ix < 0 or ix >= nx or iy < 0 or iy >= ny:
        return best_d, best_i
    c = ix * ny + iy
    if starts[c] == starts[c + 1]:
        return best_d, best_i
    gx = max(_gap(x0, hx, ix, qx) - tol, 0.0)
    gy = max(_gap(y0, hy, iy, qy) - tol, 0.0)
    if gx * gx + gy * gy > best_d:
        return best_d, best_i
    return _scan(c, starts, sp, sidx, qx, qy, best_d, best_i)


@nb.njit(nogil=True, cache=True)
def _query(qx_all, qy_all, which, starts, sp, sidx, x0, y0, hx, hy, nx, ny, tol, max_rings, out):
    """Nearest point of the queries ``which`` (indices into qx_all/qy_all) into ``out``; -1
    where not settled within ``max_rings`` rings (``max_rings`` < 0: no limit). Cell gaps and
    the stopping bound are taken ``tol`` smaller than computed, so that rounding in a point's
    cell can never skip it (it only costs a rare extra ring)."""
    ivx = 1.0 / hx
    ivy = 1.0 / hy
    for k in range(which.shape[0]):
        q = which[k]
        qx = qx_all[q]
        qy = qy_all[q]
        cx = min(max(int(math.floor((qx - x0) * ivx)), 0), nx - 1)
        cy = min(max(int(math.floor((qy - y0) * ivy)), 0), ny - 1)
        best_d = np.inf
        best_i = -1
        found = False
        r = 0
        while max_rings < 0 or r <= max_rings:
            if r == 0:
                best_d, best_i = _visit(cx, cy, nx, ny, starts, sp, sidx, qx, qy, best_d, best_i, x0, y0, hx, hy, tol)
            else:
                for iy in (cy - r, cy + r):  # top and bottom rows of the ring
                    g = max(_gap(y0, hy, iy, qy) - tol, 0.0)
                    if iy < 0 or iy >= ny or g * g > best_d:
                        continue
                    for ix in range(max(cx - r, 0), min(cx + r, nx - 1) + 1):
                        best_d, best_i = _visit(ix, iy, nx, ny, starts, sp, sidx, qx, qy, best_d, best_i,
                                                x0, y0, hx, hy, tol)
                for ix in (cx - r, cx + r):  # the side columns
                    g = max(_gap(x0, hx, ix, qx) - tol, 0.0)
                    if ix < 0 or ix >= nx or g * g > best_d:
                        continue
                    for iy in range(max(cy - r + 1, 0), min(cy + r - 1, ny - 1) + 1):
                        best_d, best_i = _visit(ix, iy, nx, ny, starts, sp, sidx, qx, qy, best_d, best_i,
                                                x0, y0, hx, hy, tol)
            # distance from the query to the nearest cell outside the scanned block
            bound = np.inf
            if cy - r > 0:
                bound = min(bound, max(qy - (y0 + (cy - r) * hy), 0.0))
            if cy + r < ny - 1:
                bound = min(bound, max(y0 + (cy + r + 1) * hy - qy, 0.0))
            if cx - r > 0:
                bound = min(bound, max(qx - (x0 + (cx - r) * hx), 0.0))
            if cx + r < nx - 1:
                bound = min(bound, max(x0 + (cx + r + 1) * hx - qx, 0.0))
            bound = max(bound - tol, 0.0)
            if best_i >= 0 and (best_d < bound * bound or bound == np.inf):
                found = True
                break
            if bound == np.inf:  # the whole grid was scanned and it is empty
                break
            r += 1
        out[q] = best_i if found else -1
    return out


class NN2D:
    """Index (N, 2) points once, then find the nearest one to each of many (M, 2) queries.

    ``points`` may be an (N, 2) array or an (x, y) tuple of columns."""

    def __init__(self, points: np.ndarray | tuple[np.ndarray, np.ndarray], per_cell: float = PER_CELL,
                 reuse: bool | str = False) -> None:
        """``reuse``: build the index in this thread's ``common.scratch`` buffers (no allocation;
        the index is then only valid until this thread builds another one in the same buffers;
        a string names its own set of them)."""
        if isinstance(points, tuple):
            px, py = points
        else:
            points = np.asarray(points, dtype=np.float64)
            px, py = points[:, 0], points[:, 1]
        self.px = np.ascontiguousarray(px, dtype=np.float64)
        self.py = np.ascontiguousarray(py, dtype=np.float64)
        self.n = int(self.px.shape[0])
        self.per_cell = float(per_cell)
        self.reuse = bool(reuse)
        self.prefix = reuse if isinstance(reuse, str) else "nn2d"
        self._coarse = None
        if self.n == 0:
            return
        self.fine = self._grid(self.per_cell)

    def _grid(self, per_cell: float):
        x0, x1, y0, y1 = _bbox(self.px, self.py)
        wx = max(x1 - x0, 1e-9)
        wy = max(y1 - y0, 1e-9)
        cells = max(1.0, min(self.n / per_cell, 2.0**30))
        nx = int(min(max(round(math.sqrt(cells * wx / wy)), 1), cells))
        ny = int(min(max(round(cells / nx), 1), cells))
        # cells a hair wider than the box, so that its far edge lies inside the last cell
        hx = wx / nx * (1 + 1e-9)
        hy = wy / ny * (1 + 1e-9)
        n = self.n
        if self.reuse and per_cell == self.per_cell:
            keys = scratch(f"{self.prefix}.keys", n, np.int32)
            starts = scratch(f"{self.prefix}.starts", nx * ny + 1, np.int32)
            sp = scratch(f"{self.prefix}.sp", 2 * n).reshape(n, 2)
            sidx = scratch(f"{self.prefix}.sidx", n, np.int32)
        else:
            keys = np.empty(n, np.int32)
            starts = np.empty(nx * ny + 1, np.int32)
            sp = np.empty((n, 2))
            sidx = np.empty(n, np.int32)
        _cells(self.px, self.py, x0, y0, hx, hy, nx, ny, keys)
        _build(self.px, self.py, keys, starts, sp, sidx)
        tol = 1e-12 * (1.0 + max(abs(x0), abs(x1), abs(y0), abs(y1)))
        return starts, sp, sidx, x0, y0, hx, hy, nx, ny, tol

    def query(self, queries: np.ndarray | tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Index of the nearest point per query (-1 when there are no points)."""
        if isinstance(queries, tuple):
            qx, qy = queries
        else:
            queries = np.asarray(queries, dtype=np.float64)
            qx, qy = queries[:, 0], queries[:, 1]
        qx = np.ascontiguousarray(qx, dtype=np.float64)
        qy = np.ascontiguousarray(qy, dtype=np.float64)
        m = qx.shape[0]
        out = np.full(m, -1, np.int64)
        if self.n == 0 or m == 0:
            return out
        _query(qx, qy, np.arange(m), *self.fine, MAX_RINGS, out)
        left = np.flatnonzero(out < 0)
        if left.size:  # a few stray queries: more fine rings cost far less than a coarse grid
            _query(qx, qy, left, *self.fine, FAR_RINGS, out)
            left = left[out[left] < 0]
        if left.size:
            if self._coarse is None:
                self._coarse = self._grid(self.per_cell * COARSE * COARSE)
            _query(qx, qy, left, *self._coarse, -1, out)
        return out
