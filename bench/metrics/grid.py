"""Exact 2D nearest neighbours on a uniform grid (numba), for the angle-space searches.

On ray-aligned LiDAR sweeps a k-d tree query in a 2D angle space costs about as much as one
in 3D (~0.1 s per 120k queries with pykdtree on the shared 2-core machine). A bucket grid
with about two points per cell, scanned with the GIL released, was measured side by side at
0.57-0.59x the time of pykdtree's exact 2D search (both angle spaces, one thread, the same
answers; 9 interleaved runs on the 120k pair, loaded machine). Queries are answered one by
one, so any slice of them can go to another thread (pcfbench.metrics.nn.nearest_angles).

Exactness: cells are scanned in Chebyshev rings around the query's cell (at most MAX_RINGS,
then the query is handed back unanswered, index -1); cells whose rectangle is farther than
the best distance so far are skipped, and after each ring the search stops once the best
distance is smaller than the distance from the query to any cell not yet scanned (computed
from the block's geometry, so a query outside the grid is handled too). Strictly smaller: every
point at the minimal distance has then been scanned, so the tie rule below holds and a query's
answer does not depend on its starting candidate or on which queries are asked together.
Each query starts
from the previous query's answer (a real data point; consecutive LiDAR rays are neighbours).
Ties go to the lowest data index, like a brute-force argmin. Dimension 0 may be periodic
(azimuth, period 2 pi): differences are then taken around the circle.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_TARGET_PER_CELL = 2.0
#: rings scanned before a query is left to the caller's fallback (returned index -1)
MAX_RINGS = 2
# No numba parallelism inside a query pass: numba's OpenMP threads made the queries 2-3x slower
# on the shared 2-core reference machine; nearest_angles shares pieces out over Python threads.


@numba.njit(cache=True, nogil=True)
def _build(xs, ys, x0, y0, hx, hy, nx, ny):
    n = xs.shape[0]
    keys = np.empty(n, np.int64)
    for i in range(n):
        cx = min(max(int(math.floor((xs[i] - x0) / hx)), 0), nx - 1)
        cy = min(max(int(math.floor((ys[i] - y0) / hy)), 0), ny - 1)
        keys[i] = cx * ny + cy
    starts = np.zeros(nx * ny + 1, np.int64)
    for i in range(n):
        starts[keys[i] + 1] += 1
    for c in range(nx * ny):
        starts[c + 1] += starts[c]
    order = np.empty(n, np.int64)  # counting sort, stable: a cell keeps its points in index order
    fill = starts[:-1].copy()
    for i in range(n):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    return order, starts


@numba.njit(cache=True, nogil=True)
def _scan_cell(c, starts, order, sx, sy, qx, qy, period, best_d, best_i):
    for s in range(starts[c], starts[c + 1]):
        dx = abs(sx[s] - qx)
        if period > 0.0:
            dx = min(dx, period - dx)
        dy = sy[s] - qy
        d = dx * dx + dy * dy
        if d < best_d:
            best_d = d
            best_i = order[s]
        elif d == best_d and order[s] < best_i:
            best_i = order[s]
    return best_d, best_i


@numba.njit(cache=True, nogil=True)
def _scan(ix, iy, nx, ny, starts, order, sx, sy, qx, qy, period, best_d, best_i, x0, y0, hx, hy):
    if iy < 0 or iy >= ny:
        return best_d, best_i
    jx = ix  # the cell's column in the grid (ix is its unwrapped position)
    if period > 0.0:
        while jx < 0:  # (a ring never goes more than a few periods around: no integer division)
            jx += nx
        while jx >= nx:
            jx -= nx
    elif ix < 0 or ix >= nx:
        return best_d, best_i
    c = jx * ny + iy
    if starts[c] == starts[c + 1]:  # empty: most cells of a clustered cloud
        return best_d, best_i
    # skip a cell whose rectangle (at this unwrapped position) is farther than the best so far
    gx = max(x0 + ix * hx - qx, qx - (x0 + (ix + 1) * hx), 0.0)
    gy = max(y0 + iy * hy - qy, qy - (y0 + (iy + 1) * hy), 0.0)
    if gx * gx + gy * gy > best_d:
        return best_d, best_i
    return _scan_cell(c, starts, order, sx, sy, qx, qy, period, best_d, best_i)


@numba.njit(cache=True, nogil=True)
def _query(qxs, qys, xs, ys, sx, sy, order, starts, x0, y0, hx, hy, nx, ny, period, max_rings, out_i, out_d):
    m = qxs.shape[0]
    warm = -1  # the previous query's answer: a real data point, so a valid first candidate
    for q in range(m):
        qx, qy = qxs[q], qys[q]
        cx = min(max(int(math.floor((qx - x0) / hx)), 0), nx - 1)
        cy = min(max(int(math.floor((qy - y0) / hy)), 0), ny - 1)
        best_d, best_i = np.inf, -1
        if warm >= 0:
            dx = abs(xs[warm] - qx)
            if period > 0.0:
                dx = min(dx, period - dx)
            dy = ys[warm] - qy
            best_d, best_i = dx * dx + dy * dy, warm
        found = False
        for r in range(max_rings + 1):
            if r == 0:
                best_d, best_i = _scan(cx, cy, nx, ny, starts, order, sx, sy, qx, qy, period, best_d, best_i,
                                          x0, y0, hx, hy)
            else:  # the ring's perimeter only: top and bottom rows, then the two side columns
                # a whole row (column) is skipped when its band is farther than the best so far
                for iy in (cy - r, cy + r):
                    g = max(y0 + iy * hy - qy, qy - (y0 + (iy + 1) * hy), 0.0)
                    if iy < 0 or iy >= ny or g * g > best_d:
                        continue
                    for ix in range(cx - r, cx + r + 1):
                        best_d, best_i = _scan(ix, iy, nx, ny, starts, order, sx, sy, qx, qy, period, best_d,
                                               best_i, x0, y0, hx, hy)
                for ix in (cx - r, cx + r):
                    g = max(x0 + ix * hx - qx, qx - (x0 + (ix + 1) * hx), 0.0)
                    if g * g > best_d:
                        continue
                    for iy in range(cy - r + 1, cy + r):
                        best_d, best_i = _scan(ix, iy, nx, ny, starts, order, sx, sy, qx, qy, period, best_d,
                                               best_i, x0, y0, hx, hy)
            # distance from the query to the nearest cell outside the scanned block
            bound = np.inf
            if cy - r > 0:
                bound = min(bound, max(qy - (y0 + (cy - r) * hy), 0.0))
            if cy + r < ny - 1:
                bound = min(bound, max(y0 + (cy + r + 1) * hy - qy, 0.0))
            if period > 0.0:
                if 2 * r + 1 < nx:
                    bound = min(bound, max(qx - (x0 + (cx - r) * hx), 0.0))
                    bound = min(bound, max(x0 + (cx + r + 1) * hx - qx, 0.0))
            else:
                if cx - r > 0:
                    bound = min(bound, max(qx - (x0 + (cx - r) * hx), 0.0))
                if cx + r < nx - 1:
                    bound = min(bound, max(x0 + (cx + r + 1) * hx - qx, 0.0))
            if best_i >= 0 and best_d < bound * bound:
                found = True
                break
        out_i[q] = best_i if found else -1
        out_d[q] = best_d
        warm = best_i


class Grid2D:
    """Nearest neighbours among (K, 2) float64 points; dimension 0 periodic if ``period`` > 0
    (its values must then lie in [-period / 2, period / 2])."""

    def __init__(self, points: np.ndarray, period: float = 0.0, per_cell: float = _TARGET_PER_CELL) -> None:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] == 0:
            raise ValueError(f"need a non-empty (K, 2) array, got {pts.shape}")
        k = pts.shape[0]
        self.period = float(period)
        if self.period > 0:
            x0, wx = -self.period / 2, self.period
        else:
            x0, wx = float(pts[:, 0].min()), float(np.ptp(pts[:, 0]))
        y0, wy = float(pts[:, 1].min()), float(np.ptp(pts[:, 1]))
        wx, wy = max(wx, 1e-9), max(wy, 1e-9)
        xs, ys = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
        cells = max(1.0, k / per_cell)
        nx = int(min(max(round(math.sqrt(cells * wx / wy)), 1), cells))
        ny = int(min(max(round(cells / nx), 1), cells))
        self.x0, self.y0, self.nx, self.ny = x0, y0, nx, ny
        self.hx, self.hy = wx / nx, wy / ny
        self.order, self.starts = _build(xs, ys, x0, y0, self.hx, self.hy, nx, ny)
        self.xs, self.ys = xs, ys
        self.sx, self.sy = xs[self.order], ys[self.order]

    def query(self, queries: np.ndarray, max_rings: int = MAX_RINGS) -> tuple[np.ndarray, np.ndarray]:
        """(squared distance, index) of each query's nearest point; index -1 where the nearest
        point is not proven within ``max_rings`` rings of cells (far from all data): those
        queries need another search (pcfbench.metrics.nn falls back to a k-d tree)."""
        q = np.asarray(queries, dtype=np.float64)
        out_i = np.empty(q.shape[0], np.int64)
        out_d = np.empty(q.shape[0], np.float64)
        if q.shape[0]:
            _query(np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), self.xs, self.ys, self.sx, self.sy, self.order,
                   self.starts, self.x0, self.y0, self.hx, self.hy, self.nx, self.ny, self.period, max_rings,
                   out_i, out_d)
        return out_d, out_i
