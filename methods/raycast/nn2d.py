"""Exact 2-D nearest neighbours on an adaptive grid (numba), for angle-space look-ups.

The grid's cell edges are quantiles of each coordinate, so strongly non-uniform angle
distributions (the 4D-Occ angle space bunches points near +-pi/2) still put a few points in
each cell. A query visits rings of cells around its own and stops once the best squared
distance is no larger than the distance to the outside of the rings visited, which makes the
answer exact (ties go to the lower point index).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _lut(e, nbins):
    """Cell index at the start of each of ``nbins`` uniform bins spanning the edges."""
    lo = e[0]
    w = (e[-1] - e[0]) / nbins
    lut = np.empty(nbins + 1, np.int64)
    c = 0
    for b in range(nbins + 1):
        x = lo + b * w
        while c + 1 < e.shape[0] - 1 and e[c + 1] <= x:
            c += 1
        lut[b] = c
    return lut


@nb.njit(inline="always")
def _locate(x, e, lut, inv_w):
    """The cell of ``x`` (edges ``e``, clamped to the grid): a LUT jump then a short walk."""
    g = e.shape[0] - 1
    b = int((x - e[0]) * inv_w)
    if b <= 0:
        c = 0
    elif b >= lut.shape[0]:
        c = g - 1
    else:
        c = lut[b]
    while c + 1 < g and e[c + 1] <= x:
        c += 1
    while c > 0 and e[c] > x:
        c -= 1
    return c


@nb.njit(parallel=True, cache=True)
def _cells(px, py, ex, ey, lx, ly, ix, iy):
    gy = ey.shape[0] - 1
    n = px.shape[0]
    cell = np.empty(n, np.int64)
    for i in nb.prange(n):
        cell[i] = _locate(px[i], ex, lx, ix) * gy + _locate(py[i], ey, ly, iy)
    return cell


@nb.njit(cache=True)
def _build(cell, ncells):
    n = cell.shape[0]
    start = np.zeros(ncells + 1, np.int64)
    for i in range(n):
        start[cell[i] + 1] += 1
    for c in range(ncells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        c = cell[i]
        order[fill[c]] = i
        fill[c] += 1
    return start, order


@nb.njit(parallel=True, cache=True)
def _query(px, py, ex, ey, start, order, qx, qy, qcell, qorder):
    gx = ex.shape[0] - 1
    gy = ey.shape[0] - 1
    m = qx.shape[0]
    out = np.full(m, -1, np.int64)
    for jj in nb.prange(m):
        j = qorder[jj]  # queries in cell order, for memory locality
        x = qx[j]
        y = qy[j]
        cx = qcell[j] // gy
        cy = qcell[j] - cx * gy
        best = np.inf
        besti = -1
        r = 0
        while True:
            x0 = cx - r
            x1 = cx + r
            y0 = cy - r
            y1 = cy + r
            for ix in range(max(x0, 0), min(x1, gx - 1) + 1):
                on_x_edge = ix == x0 or ix == x1
                iy = max(y0, 0)
                while iy <= min(y1, gy - 1):
                    c = ix * gy + iy
                    for k in range(start[c], start[c + 1]):
                        dx = px[k] - x
                        dy = py[k] - y
                        d = dx * dx + dy * dy
                        if d < best or (d == best and order[k] < besti):
                            best = d
                            besti = order[k]
                    if on_x_edge or iy == y1:
                        iy += 1
                    else:
                        iy = y1  # interior columns: only the ring's top and bottom cells
            # distance from the query to the outside of the visited block of cells
            bound = np.inf
            if x0 > 0:
                bound = min(bound, x - ex[x0])
            if x1 < gx - 1:
                bound = min(bound, ex[x1 + 1] - x)
            if y0 > 0:
                bound = min(bound, y - ey[y0])
            if y1 < gy - 1:
                bound = min(bound, ey[y1 + 1] - y)
            if bound == np.inf:
                break  # the whole grid was visited
            if besti >= 0 and bound > 0 and best <= bound * bound:
                break
            r += 1
        out[j] = besti
    return out


def _edges(v: np.ndarray, g: int) -> np.ndarray:
    q = np.quantile(v, np.linspace(0.0, 1.0, g + 1))
    q = np.unique(q)
    if q.shape[0] < 2:
        q = np.array([v.min() - 1.0, v.max() + 1.0])
    return q.astype(np.float64)


class NN2D:
    """Index (N, 2) points once, then find the nearest one to each of many (M, 2) queries."""

    def __init__(self, points: np.ndarray | tuple[np.ndarray, np.ndarray], points_per_cell: float = 2.0) -> None:
        if isinstance(points, tuple):  # (x, y) columns
            px, py = points
        else:
            points = np.asarray(points, dtype=np.float64)
            px, py = points[:, 0], points[:, 1]
        self.n = int(px.shape[0])
        self.px = np.ascontiguousarray(px, dtype=np.float64)
        self.py = np.ascontiguousarray(py, dtype=np.float64)
        if self.n == 0:
            return
        g = max(1, int(np.sqrt(self.n / points_per_cell)))
        # subsample for the quantiles: edges need not be exact quantiles to keep answers exact
        sub = slice(None, None, max(1, self.n // 50_000))
        self.ex = _edges(self.px[sub], g)
        self.ey = _edges(self.py[sub], g)
        nbx, nby = 4 * (len(self.ex) - 1), 4 * (len(self.ey) - 1)
        self.lx, self.ly = _lut(self.ex, nbx), _lut(self.ey, nby)
        self.ix = nbx / max(self.ex[-1] - self.ex[0], 1e-300)
        self.iy = nby / max(self.ey[-1] - self.ey[0], 1e-300)
        self.ncells = (len(self.ex) - 1) * (len(self.ey) - 1)
        cell = _cells(self.px, self.py, self.ex, self.ey, self.lx, self.ly, self.ix, self.iy)
        self.start, self.order = _build(cell, self.ncells)
        # points stored cell by cell, so that a query scans contiguous memory
        self.sx = self.px[self.order]
        self.sy = self.py[self.order]

    def query(self, queries: np.ndarray) -> np.ndarray:
        """Index of the nearest point per query (-1 when there are no points)."""
        queries = np.asarray(queries, dtype=np.float64)
        if self.n == 0:
            return np.full(queries.shape[0], -1, np.int64)
        qx = np.ascontiguousarray(queries[:, 0])
        qy = np.ascontiguousarray(queries[:, 1])
        qcell = _cells(qx, qy, self.ex, self.ey, self.lx, self.ly, self.ix, self.iy)
        _, qorder = _build(qcell, self.ncells)
        return _query(self.sx, self.sy, self.ex, self.ey, self.start, self.order, qx, qy, qcell, qorder)
