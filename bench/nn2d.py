"""Exact 2-D nearest neighbours on a uniform bucket grid (numba): the angle-space searches of the
metrics (``pcfbench.metrics.nn``) and of the ray-casting baselines (raycast-4docc, -zbuffer).

Contract. For every query the answer is the index of the data point at the smallest squared
distance ``dx * dx + dy * dy`` (float64), ties to the lowest index: exactly what a brute-force
``argmin`` over those distances gives. With ``period`` > 0, dimension 0 is periodic (an
azimuth): ``dx = min(|x - qx|, period - |x - qx|)``, and points and queries must lie in
``[-period / 2, period / 2]``. A query's answer depends on nothing but the data and the query
(not on the other queries, their order or how they are cut into pieces), so any slice of the
queries can go to another thread.

Method. The points are counting-sorted (stable: a cell keeps its points in index order) into
cells of about ``per_cell`` points, stored as one interleaved (x, y) array with 32-bit cell
starts. A query scans its own cell, then Chebyshev rings of cells, skipping every cell (and
whole ring rows and columns) whose rectangle is farther than the best distance so far, and
stops once the best distance is strictly smaller than the distance to any cell not yet
scanned; so every point at the minimal distance has been seen. Cell gaps and the stopping
bound are taken ``tol`` smaller than computed, so that rounding in a point's cell can never
skip it. On a periodic axis cells are visited at their unwrapped positions; once a ring spans
all columns only the rows bound the search. A cell is scanned without a data-dependent branch
per point: the position of its first minimum is kept with selects (its lowest index at the
minimal distance, as the cell is in index order) and compared with the best so far once per
cell.

Queries not settled within ``MAX_RINGS`` rings (far from all points) get ``FAR_RINGS`` rings,
and those still not settled are asked again on a grid ``COARSE`` times coarser in each
direction, whose ring search runs until it is settled or has covered the whole grid.
``NN2D.near`` is the first pass alone (-1 where not settled) and ``NN2D.settle`` the rest, so
that callers can share the first pass out over threads.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numba as nb
import numpy as np

#: rings of the fine grid scanned by ``NN2D.near`` (the first pass)
MAX_RINGS = 2
#: rings of the fine grid for the queries not settled within ``MAX_RINGS``, before the coarse grid
FAR_RINGS = 16
#: points per cell of the fine grid (on average over the bounding box)
PER_CELL = 4.0
#: the coarse grid's cells are this many fine cells wide in each direction
COARSE = 8

#: ``buffers(name, n, dtype)`` returns an array of ``n`` items of ``dtype`` (contents undefined)
Buffers = Callable[[str, int, type], np.ndarray]


def _empty(name: str, n: int, dtype=np.float64) -> np.ndarray:
    return np.empty(n, dtype)


@nb.njit(nogil=True, cache=True)
def _bbox(px, py):
    """(x0, x1, y0, y1, finite) of the points: their bounding box and whether all are finite."""
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    nan = False
    for i in range(px.shape[0]):
        x0 = min(x0, px[i])
        x1 = max(x1, px[i])
        y0 = min(y0, py[i])
        y1 = max(y1, py[i])
        nan |= (px[i] != px[i]) | (py[i] != py[i])  # (min and max pass NaN over)
    return x0, x1, y0, y1, not nan and -np.inf < x0 and x1 < np.inf and -np.inf < y0 and y1 < np.inf


@nb.njit(nogil=True, cache=True)
def _cells(px, py, x0, y0, hx, hy, nx, ny, keys):
    """Cell of each point into ``keys``, clamped to the grid."""
    ivx = 1.0 / hx
    ivy = 1.0 / hy
    for i in range(px.shape[0]):
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
def _scan(c, starts, sp, sidx, qx, qy, period, best_d, best_i):
    m = np.inf
    ms = -1
    if period is not None:
        for s in range(starts[c], starts[c + 1]):
            dx = abs(sp[s, 0] - qx)
            dx = min(dx, period - dx)
            dy = sp[s, 1] - qy
            d = dx * dx + dy * dy
            lt = d < m
            ms = s if lt else ms
            m = d if lt else m
    else:
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
def _visit(ix, iy, nx, ny, starts, sp, sidx, qx, qy, period, best_d, best_i, x0, y0, hx, hy, tol):
    """Scan cell (ix, iy) unless it is empty or farther than ``best_d``; on a periodic axis
    ``ix`` is the cell's unwrapped position (its gap is taken there)."""
    if iy < 0 or iy >= ny:
        return best_d, best_i
    jx = ix
    if period is not None:
        while jx < 0:  # a ring goes at most a few times around: no integer division
            jx += nx
        while jx >= nx:
            jx -= nx
    elif ix < 0 or ix >= nx:
        return best_d, best_i
    c = jx * ny + iy
    if starts[c] == starts[c + 1]:
        return best_d, best_i
    gx = max(_gap(x0, hx, ix, qx) - tol, 0.0)
    gy = max(_gap(y0, hy, iy, qy) - tol, 0.0)
    if gx * gx + gy * gy > best_d:
        return best_d, best_i
    return _scan(c, starts, sp, sidx, qx, qy, period, best_d, best_i)


@nb.njit(nogil=True, cache=True)
def _query(qx_all, qy_all, which, starts, sp, sidx, x0, y0, hx, hy, nx, ny, tol, period, max_rings, out):
    """Nearest point of the queries ``which`` (indices into qx_all/qy_all) into ``out``; -1
    where not settled within ``max_rings`` rings (``max_rings`` < 0: no limit)."""
    ivx = 1.0 / hx
    ivy = 1.0 / hy
    periodic = period is not None
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
                best_d, best_i = _visit(cx, cy, nx, ny, starts, sp, sidx, qx, qy, period, best_d, best_i,
                                        x0, y0, hx, hy, tol)
            else:
                # a periodic axis has no edges: its cells are visited at every unwrapped position
                ix_lo = cx - r if periodic else max(cx - r, 0)
                ix_hi = cx + r if periodic else min(cx + r, nx - 1)
                for iy in (cy - r, cy + r):  # top and bottom rows of the ring
                    g = max(_gap(y0, hy, iy, qy) - tol, 0.0)
                    if iy < 0 or iy >= ny or g * g > best_d:
                        continue
                    for ix in range(ix_lo, ix_hi + 1):
                        best_d, best_i = _visit(ix, iy, nx, ny, starts, sp, sidx, qx, qy, period, best_d, best_i,
                                                x0, y0, hx, hy, tol)
                for ix in (cx - r, cx + r):  # the side columns
                    g = max(_gap(x0, hx, ix, qx) - tol, 0.0)
                    if (not periodic and (ix < 0 or ix >= nx)) or g * g > best_d:
                        continue
                    for iy in range(max(cy - r + 1, 0), min(cy + r - 1, ny - 1) + 1):
                        best_d, best_i = _visit(ix, iy, nx, ny, starts, sp, sidx, qx, qy, period, best_d, best_i,
                                                x0, y0, hx, hy, tol)
            # distance from the query to the nearest cell outside the scanned block
            bound = np.inf
            if cy - r > 0:
                bound = min(bound, max(qy - (y0 + (cy - r) * hy), 0.0))
            if cy + r < ny - 1:
                bound = min(bound, max(y0 + (cy + r + 1) * hy - qy, 0.0))
            if periodic:
                if 2 * r + 1 < nx:  # some columns not scanned yet, at either side
                    bound = min(bound, max(qx - (x0 + (cx - r) * hx), 0.0))
                    bound = min(bound, max(x0 + (cx + r + 1) * hx - qx, 0.0))
            else:
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


def _columns(a, what: str, period: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) contiguous float64 columns of an (N, 2) array or an (x, y) tuple, checked."""
    if isinstance(a, tuple):
        x, y = a
    else:
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"nn2d: {what} must be an (N, 2) array or an (x, y) tuple, got shape {a.shape}")
        x, y = a[:, 0], a[:, 1]
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"nn2d: {what} columns must be two 1-D arrays of one length, got {x.shape} and {y.shape}")
    if x.shape[0] >= 2**31 - 1:
        raise ValueError(f"nn2d: {x.shape[0]:,} {what}, more than 32-bit indices hold")
    return x, y


def _check(x0, x1, finite, what: str, period: float) -> None:
    if not finite:
        raise ValueError(f"nn2d: {what} contain NaN or infinite coordinates")
    if period > 0.0 and (x0 < -period / 2 or x1 > period / 2):
        raise ValueError(f"nn2d: {what} have x in [{x0}, {x1}], outside [-period / 2, period / 2] = "
                         f"[{-period / 2}, {period / 2}] of the periodic axis")


class NN2D:
    """Index (N, 2) points once, then find the nearest one to each of many (M, 2) queries.

    ``points`` and queries may be (N, 2) arrays or (x, y) tuples of columns. ``period`` > 0
    makes dimension 0 periodic (see the module docstring). ``buffers``, when given, supplies the
    fine grid's arrays (for example a thread's reused scratch buffers: the index is then valid
    only as long as they are not handed out again)."""

    def __init__(self, points, period: float = 0.0, per_cell: float = PER_CELL,
                 buffers: Buffers | None = None) -> None:
        self.period = float(period)
        if not self.period >= 0.0 or math.isinf(self.period):
            raise ValueError(f"nn2d: period must be 0 (no periodic axis) or positive and finite, got {period}")
        if not per_cell > 0.0:
            raise ValueError(f"nn2d: per_cell must be positive, got {per_cell}")
        self.px, self.py = _columns(points, "points", self.period)
        self.n = int(self.px.shape[0])
        self.per_cell = float(per_cell)
        self._coarse = None
        if self.n == 0:
            return
        self._box = _bbox(self.px, self.py)
        _check(self._box[0], self._box[1], self._box[4], "points", self.period)
        self.fine = self._grid(self.per_cell, buffers or _empty)

    def _grid(self, per_cell: float, buffers: Buffers):
        x0, x1, y0, y1, _ = self._box
        if self.period > 0.0:
            x0, x1 = -self.period / 2, self.period / 2
        wx = max(x1 - x0, 1e-9)
        wy = max(y1 - y0, 1e-9)
        cells = max(1.0, min(self.n / per_cell, 2.0**30))
        nx = int(min(max(round(math.sqrt(cells * wx / wy)), 1), cells))
        ny = int(min(max(round(cells / nx), 1), cells))
        # cells a hair wider than the box, so that its far edge lies inside the last cell (not on
        # a periodic axis: there the columns must tile the period exactly, and points on its far
        # edge are clamped into the last column, within ``tol`` of it)
        hx = wx / nx if self.period > 0.0 else wx / nx * (1 + 1e-9)
        hy = wy / ny * (1 + 1e-9)
        n = self.n
        keys = buffers("keys", n, np.int32)
        starts = buffers("starts", nx * ny + 1, np.int32)
        sp = buffers("sp", 2 * n, np.float64).reshape(n, 2)
        sidx = buffers("sidx", n, np.int32)
        _cells(self.px, self.py, x0, y0, hx, hy, nx, ny, keys)
        _build(self.px, self.py, keys, starts, sp, sidx)
        tol = 1e-12 * (1.0 + max(abs(x0), abs(x1), abs(y0), abs(y1)))
        # the period goes to the kernels as None on a plain axis: numba then compiles them without
        # the periodic branches
        return starts, sp, sidx, x0, y0, hx, hy, nx, ny, tol, (self.period if self.period > 0.0 else None)

    def _queries(self, queries) -> tuple[np.ndarray, np.ndarray]:
        qx, qy = _columns(queries, "queries", self.period)
        if qx.shape[0]:
            x0, x1, _, _, finite = _bbox(qx, qy)
            _check(x0, x1, finite, "queries", self.period)
        return qx, qy

    def _near(self, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
        out = np.full(qx.shape[0], -1, np.int64)
        if self.n and qx.shape[0]:
            _query(qx, qy, np.arange(qx.shape[0]), *self.fine, MAX_RINGS, out)
        return out

    def _settle(self, qx: np.ndarray, qy: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return self._settle_coarse(qx, qy, self._settle_fine(qx, qy, idx))

    def _settle_fine(self, qx: np.ndarray, qy: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``_settle``'s first stage, in place: the queries ``_near`` left at -1 searched out to
        ``FAR_RINGS`` rings of fine cells (a few stray queries: more fine rings cost far less than
        a coarse grid). Each query's answer is its own: any slice of the queries may go alone."""
        left = np.flatnonzero(idx < 0) if self.n else np.zeros(0, np.int64)
        if left.size:
            _query(qx, qy, left, *self.fine, FAR_RINGS, idx)
        return idx

    def _settle_coarse(self, qx: np.ndarray, qy: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``_settle``'s second stage, in place: the queries still at -1 after ``_settle_fine``
        answered on a coarse grid (made on first use)."""
        left = np.flatnonzero(idx < 0) if self.n else np.zeros(0, np.int64)
        if left.size:
            if self._coarse is None:
                self._coarse = self._grid(self.per_cell * COARSE * COARSE, _empty)
            _query(qx, qy, left, *self._coarse, -1, idx)
        return idx

    def near(self, queries) -> np.ndarray:
        """Index (int64) of each query's nearest point where it lies within ``MAX_RINGS`` rings of
        cells, -1 elsewhere (and everywhere when there are no points): ``settle`` those."""
        return self._near(*self._queries(queries))

    def settle(self, queries, idx: np.ndarray) -> np.ndarray:
        """Answer, in place in ``idx`` (the int64 answers of ``near`` for the same queries), the
        queries it leaves at -1, and return it. With no points every answer stays -1."""
        qx, qy = self._queries(queries)
        if idx.shape != qx.shape or idx.dtype != np.int64:
            raise ValueError(f"nn2d: settle needs the int64 answers of near for these {qx.shape[0]} queries, "
                             f"got {idx.dtype} {idx.shape}")
        return self._settle(qx, qy, idx)

    def query(self, queries) -> np.ndarray:
        """Index (int64) of the nearest point per query (-1 when there are no points)."""
        qx, qy = self._queries(queries)
        return self._settle(qx, qy, self._near(qx, qy))
