"""Exact nearest neighbours for the metrics: a k-d tree (pykdtree) with float64 distances.

pykdtree was the fastest exact index measured on ray-aligned LiDAR sweeps (against scipy's
cKDTree and open3d's searches: docs/journal/performance-tuning-2026-11.md, tests/benchmarks/test_bench_metrics.py).
Distances are recomputed in float64 from the returned indices (one numba pass), so they are
exact for the chosen neighbour rather than a sqrt/square round trip. The 2D
angle-space searches use the exact bucket grid of pcfbench.nn2d (ties to the lowest index).

Both searches index each distinct point once (``distinct``): a forecast that puts all its
points at one spot (or many on one ray, for the angle spaces) would otherwise fill one leaf or
one grid cell that every query scans, a search quadratic in the point count. Equal points are
equally near to every query, so the answers are unchanged: the first of each set of equal
points stands for the set, kept in index order, so the angle searches' ties still go to the
lowest index. Inputs without repeated points are indexed as before.
"""

from __future__ import annotations

import numba
import numpy as np
from pykdtree.kdtree import KDTree

from pcfbench.execution import ExecutionContext, current, in_pool_worker
from pcfbench.nn2d import NN2D, PER_CELL, _cells

TWO_PI = 2.0 * np.pi
#: points per grid cell of each angle space's search (any value gives the same answers): the
#: fastest measured on the 120k x 120k benchmark pair (docs/journal/performance-tuning-2026-11.md)
PER_CELL_4DOCC = 2.0
PER_CELL_WRAPPED = 4.0


#: rows drawn to look for repeated points before a full pass (see ``distinct``)
SAMPLE = 1024


@numba.njit(cache=True, nogil=True)
def _sets(points: np.ndarray, bits: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, free), each (U,) int64: the first row of each set of equal rows of ``points``
    (increasing), and the first row of each set that ``mask`` (N,) bool leaves, -1 where it
    masks the whole set (an empty ``mask``: no mask, ``free`` is empty).

    One pass over a hash table keyed by the rows' bit patterns ``bits`` (of ``points + 0.0``,
    so that -0.0 and 0.0 agree); rows are compared with ``==`` (a row holding NaN equals no other)."""
    n, d = points.shape
    masked = mask.shape[0] > 0
    size = 16
    while size < 2 * n:
        size *= 2
    table = np.full(size, -1, np.int32)  # a set's number; 4 bytes a slot keep the table in cache
    first = np.empty(n, np.int64)
    free = np.full(n if masked else 0, -1, np.int64)
    u = 0
    for i in range(n):
        h = np.uint64(0x9E3779B97F4A7C15)
        for c in range(d):
            h = (h ^ np.uint64(bits[i, c])) * np.uint64(0xBF58476D1CE4E5B9)
            h ^= h >> np.uint64(31)
        s = np.int64(h & np.uint64(size - 1))
        while True:
            g = table[s]
            if g < 0:
                g = u
                table[s] = g
                first[g] = i
                u += 1
                break
            j = first[g]
            same = True
            for c in range(d):
                if points[i, c] != points[j, c]:
                    same = False
                    break
            if same:
                break
            s = (s + 1) & (size - 1)
        if masked and not mask[i] and free[g] < 0:
            free[g] = i
    return first[:u], free[:u]


def _first_of_sets(points: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``_sets`` of (N, D) float64 C-ordered ``points``."""
    no_mask = np.zeros(0, dtype=bool)
    return _sets(points, (points + 0.0).view(np.int64), no_mask if mask is None else mask)


def distinct(points: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray | None:
    """The first of each set of equal rows of (N, D) float64 ``points`` (increasing indices), or
    None when no row repeats another (the common case: the caller indexes them as they are).

    Above ``4 * SAMPLE`` rows, ``SAMPLE`` rows drawn at random (one from each of ``SAMPLE``
    equal blocks) are checked first and the full pass
    (about 2 ms on 120k rows) runs only when two of them are equal. A set of equal rows large
    enough to slow a search (thousands) is then all but sure to be drawn twice; one that is missed
    (or drawn on a normal input) changes the time, never an answer: the searches are exact either
    way. ``rng``: the draw's generator (default: a fresh one, so no input can be shaped to avoid it).
    """
    points = np.asarray(points, dtype=np.float64)  # C-ordered (copied) only for the full pass
    n = points.shape[0]
    if n > 4 * SAMPLE:
        rng = rng if rng is not None else np.random.default_rng()
        block = n // SAMPLE
        rows = np.ascontiguousarray(points[np.arange(SAMPLE) * block + rng.integers(0, block, SAMPLE)])
        if _first_of_sets(rows)[0].shape[0] == rows.shape[0]:
            return None
    first = _first_of_sets(np.ascontiguousarray(points))[0]
    return None if first.shape[0] == n else first


class Index:
    """A k-d tree over (N, D) float64 points (N >= 1); repeated points are indexed once."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if self.points.shape[0] == 0:
            raise ValueError("cannot index an empty point set")
        self._sets = distinct(self.points)
        indexed = self.points if self._sets is None else self.points[self._sets]
        self.tree = KDTree(indexed, leafsize=16)

    def query(self, queries: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(squared distance float64, index int64) of each query's nearest indexed point.

        ``mask``: (N,) bool, True for indexed points that must not be returned.
        """
        q = np.ascontiguousarray(queries, dtype=np.float64)
        if q.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        # (squared distances: the tree's own are dropped, so its square roots are not taken)
        if mask is None:
            _, idx = self.tree.query(q, k=1, sqr_dists=True)
            if self._sets is not None:
                idx = self._sets[idx]
        elif self._sets is None:
            _, idx = self.tree.query(q, k=1, mask=np.ascontiguousarray(mask, dtype=bool), sqr_dists=True)
        else:  # a set is returned through its first member that is not masked
            member = _first_of_sets(self.points, np.ascontiguousarray(mask, dtype=bool))[1]
            _, idx = self.tree.query(q, k=1, mask=member < 0, sqr_dists=True)
            idx = member[idx]
        if q.shape[1] in (2, 3):
            return _sq_dist_to(q, self.points, idx)
        idx = idx.astype(np.int64)
        diff = q - self.points[idx]
        return np.einsum("ij,ij->i", diff, diff), idx


@numba.njit(cache=True, nogil=True)
def _sq_dist_to(queries: np.ndarray, points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(float64 squared distance from each query to ``points[idx]``, idx as int64), in one pass.

    Two or three columns. Three are summed as (dx^2 + dz^2) + dy^2: the order numpy's
    einsum("ij,ij->i") uses for (N, 3) rows, which this replaces (8-12 ms a pass on 120k points
    for the gather, the difference array and einsum; this loop takes under 1 ms), so the
    distances stay bit-identical.
    """
    n = queries.shape[0]
    d2 = np.empty(n, np.float64)
    out = np.empty(n, np.int64)
    for k in range(n):
        j = np.int64(idx[k])
        out[k] = j
        dx = queries[k, 0] - points[j, 0]
        dy = queries[k, 1] - points[j, 1]
        if points.shape[1] == 3:
            dz = queries[k, 2] - points[j, 2]
            d2[k] = (dx * dx + dz * dz) + dy * dy
        else:
            d2[k] = dx * dx + dy * dy
    return d2, out


@numba.njit(cache=True, nogil=True)
def masked_min_sq_dist(queries: np.ndarray, points: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Brute force, for a few queries: squared distance to the nearest of the ``keep`` points,
    each computed as ((x - a)^2 + (y - b)^2) + (z - c)^2 in float64 (numpy's elementwise order)."""
    out = np.full(queries.shape[0], np.inf)
    for i in range(queries.shape[0]):
        x, y, z = queries[i, 0], queries[i, 1], queries[i, 2]
        best = np.inf
        for j in range(points.shape[0]):
            if keep[j]:
                dx, dy, dz = points[j, 0] - x, points[j, 1] - y, points[j, 2] - z
                d = (dx * dx + dy * dy) + dz * dz
                if d < best:
                    best = d
        out[i] = best
    return out


def nn_sq_dist(query: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Squared distance from each query point to its nearest target point (float64)."""
    return Index(target).query(query)[0]


def angles_4docc(rel: np.ndarray) -> np.ndarray:
    """The reference code's angle space ``(atan2(x, y), atan2(z, y))`` of origin-relative points,
    (N, 2) float64 in column order (each column contiguous: the searches take them as they are)."""
    out = np.empty((2, rel.shape[0]))
    np.arctan2(rel[:, 0], rel[:, 1], out=out[0])
    np.arctan2(rel[:, 2], rel[:, 1], out=out[1])
    return out.T


def angles_az_el(rel: np.ndarray) -> np.ndarray:
    """Azimuth ``atan2(y, x)`` in [-pi, pi] and elevation ``atan2(z, hypot(x, y))``, (N, 2) float64
    in column order."""
    out = np.empty((2, rel.shape[0]))
    np.arctan2(rel[:, 1], rel[:, 0], out=out[0])
    np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1]), out=out[1])
    return out.T


#: more points than this in the 3 x 3 cells around a query's, on average over the queries, send
#: a search to the k-d tree (``_Search2D``): the points a grid query scans, about
DENSE_SCAN = 512.0
#: ... as do more than this share of the queries outside the points' box
OUTSIDE_SHARE = 0.25
#: ... when there are at least this many (distinct) points; fewer are searched fast either way
TREE_MIN_POINTS = 1024
#: nearest candidates the k-d tree returns per query
CANDIDATES = 8


class _Search2D:
    """One exact 2D nearest-neighbour search in pieces (grid pass over any slice of the queries,
    then the far queries), so that threads can share the grid pass out (see nearest_angles).

    The bucket grid (pcfbench.nn2d) is fast when its cells hold a few points each and the
    queries lie among the points: the points of one sweep against another's. Points packed in
    the cells where the queries are (a forecast whose points sit around one spot: ``DENSE_SCAN``)
    or queries mostly outside the points' box (a compact cluster seen from the whole sweep) make
    it scan most points per query; those searches take ``CANDIDATES`` nearest from a k-d tree (the periodic axis as three
    copies of the points) and keep the answer where it is provably the grid's: the exact distance
    of nn2d's formula, ties to the lowest index, and the last candidate's tree distance clearly
    beyond the best (so no point left out can tie). The few queries left go to the grid."""

    def __init__(self, data: np.ndarray, queries: np.ndarray, period: float, per_cell: float = PER_CELL) -> None:
        data = np.asarray(data, dtype=np.float64)
        if data.shape[0] == 0:
            raise ValueError("nearest_2d: no data points to search (an empty prediction has no nearest point)")
        self.qx = np.ascontiguousarray(queries[:, 0], dtype=np.float64)
        self.qy = np.ascontiguousarray(queries[:, 1], dtype=np.float64)
        # the (M, 2) float64 queries as given, for _Queries (None: made from qx and qy on demand)
        self.queries = queries if isinstance(queries, np.ndarray) and queries.dtype == np.float64 else None
        self.first = distinct(data)  # None, or the grid holds data[first]
        self.data = data if self.first is None else data[self.first]  # (columns contiguous or not: NN2D takes either)
        self.period = float(period)
        self.grid = NN2D(self.data, period, per_cell)
        self.grid._queries((self.qx, self.qy))  # checked once here (finite, within the period), not per piece
        self.crowded = self._crowded()

    def _crowded(self) -> bool:
        """Whether the grid would scan most points per query (see the class docstring)."""
        n = self.data.shape[0]
        if n < TREE_MIN_POINTS or self.qx.shape[0] == 0:
            return False
        qx, qy = self.qx[::16], self.qy[::16]  # a share: every 16th query tells it well enough
        if self._mean_scan(qx, qy) > DENSE_SCAN:
            return True
        x0, x1, y0, y1, _ = self.grid._box  # the points' box
        outside = (qy < y0) | (qy > y1)
        if self.period == 0.0:
            outside |= (qx < x0) | (qx > x1)
        return int(np.count_nonzero(outside)) > OUTSIDE_SHARE * qx.shape[0]

    def _mean_scan(self, qx: np.ndarray, qy: np.ndarray) -> float:
        """Mean over the queries (qx, qy) of the points in the 3 x 3 fine cells around each one's
        cell: what a grid query scans, about. A few crowded cells among normal ones (a real
        sweep's near ground seen from a moved sensor) keep it low; a forecast packed into a few
        cells where the rays are makes it the point count."""
        starts, _, _, x0, y0, hx, hy, nx, ny, _, period = self.grid.fine
        counts = np.diff(starts).astype(np.int64).reshape(nx, ny)
        padded = np.pad(counts, 1, mode="wrap" if period is not None else "constant")
        if period is not None:  # rows (the plain axis) have no neighbours beyond the edge
            padded[:, 0] = padded[:, -1] = 0
        block = sum(padded[i:i + nx, j:j + ny] for i in range(3) for j in range(3))
        qx, qy = np.ascontiguousarray(qx), np.ascontiguousarray(qy)
        keys = _cells(qx, qy, x0, y0, hx, hy, nx, ny, np.empty(qx.shape[0], np.int32))
        return float(block.reshape(-1)[keys].mean())

    def grid_pass(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Nearest grid index of queries[start:stop]; -1 where the fine grid's rings (out to
        nn2d's ``FAR_RINGS``) leave it (and every query of a crowded search): ``finish``
        answers them. The far rings go in the pieces, so a shared pass has no long last job."""
        if self.crowded:
            return np.full(self.qx[start:stop].shape[0], -1, np.int64)
        qx, qy = self.qx[start:stop], self.qy[start:stop]
        return self.grid._settle_fine(qx, qy, self.grid._near(qx, qy))

    def finish(self, idx: np.ndarray) -> np.ndarray:
        """Answer the queries the grid pass left at -1 (``idx``: the grid passes' answers, in
        place) and return the nearest data index of every query."""
        if self.crowded:
            idx[:] = self._tree_pass()
        if idx.shape != self.qx.shape or idx.dtype != np.int64:
            raise ValueError(f"nearest_2d: finish needs the int64 answers of the grid passes for these "
                             f"{self.qx.shape[0]} queries, got {idx.dtype} {idx.shape}")
        # the grid passes went out to the far rings; the tree's unsure answers have not
        idx = (self.grid._settle if self.crowded else self.grid._settle_coarse)(self.qx, self.qy, idx)
        return idx if self.first is None else self.first[idx]

    def _tree_pass(self) -> np.ndarray:
        """Nearest grid index per query from the k-d tree's candidates; -1 where not sure."""
        d, p = self.data, self.period
        ext = np.ascontiguousarray(d) if p == 0.0 else np.concatenate([d, d + (p, 0.0), d - (p, 0.0)])
        k = min(CANDIDATES, ext.shape[0])
        tree_d2, cand = KDTree(ext, leafsize=16).query(np.stack([self.qx, self.qy], 1), k=k, sqr_dists=True)
        tree_d2, cand = tree_d2.reshape(-1, k), cand.reshape(-1, k).astype(np.int64) % d.shape[0]
        dx = np.abs(d[cand, 0] - self.qx[:, None])
        if p > 0.0:
            dx = np.minimum(dx, p - dx)
        dy = d[cand, 1] - self.qy[:, None]
        d2 = dx * dx + dy * dy  # nn2d's formula, term for term
        best = d2.min(axis=1)
        out = np.where(d2 == best[:, None], cand, d.shape[0]).min(axis=1)
        if k < ext.shape[0]:  # a point beyond the candidates is farther for sure, or the grid decides
            sure = tree_d2[:, -1] > best * (1.0 + 1e-9) + 1e-300
            out[~sure] = -1
        return out


def nearest_2d(data: np.ndarray, queries: np.ndarray, period: float = 0.0, per_cell: float = PER_CELL) -> np.ndarray:
    """Index of the nearest data point for each query (exact, ties to the lowest index)."""
    search = _Search2D(data, queries, period, per_cell)
    return search.finish(search.grid_pass())


def nearest_angle_4docc(pred_rel: np.ndarray, gt_rel: np.ndarray) -> np.ndarray:
    """Index of the predicted point nearest to each ground-truth ray in the 4D-Occ angle space."""
    return nearest_2d(angles_4docc(pred_rel), angles_4docc(gt_rel), per_cell=PER_CELL_4DOCC)


def nearest_angle_wrapped(pred_rel: np.ndarray, gt_rel: np.ndarray) -> np.ndarray:
    """Index of the predicted point nearest to each ground-truth ray in (azimuth, elevation),
    the azimuth difference taken around the circle (min(|da|, 2 pi - |da|))."""
    return nearest_2d(angles_az_el(pred_rel), angles_az_el(gt_rel), period=TWO_PI, per_cell=PER_CELL_WRAPPED)


#: queries per piece of the shared grid pass in nearest_angles, and of a shared k-d tree pass
CHUNK = 8192
#: the two angle spaces: (angles of origin-relative points, period of dimension 0, points per cell)
SPACES = ((angles_4docc, 0.0, PER_CELL_4DOCC), (angles_az_el, TWO_PI, PER_CELL_WRAPPED))


def nearest_angles(pred_rel: np.ndarray, gt_rel: np.ndarray,
                   execution: ExecutionContext | None = None,
                   gt_angles: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """nearest_angle_4docc and nearest_angle_wrapped together, over the threads of
    ``execution`` (default: the process's, ``pcfbench.execution.current()``). ``gt_angles``:
    the ground-truth rays' angles in the two spaces when they are known already (shared by
    every forecast of a sweep), else computed from ``gt_rel``.

    One thread (or called from a pool worker): one search after the other. More: the jobs of
    ``submit_nearest_angles`` on the context's pool; the calling thread only waits, so at
    most ``execution.threads`` threads are busy. The answer of a query does not depend on the
    piece it is in (pcfbench.nn2d), so it is the same as one whole pass's, whatever the thread count.
    """
    execution = execution or current()
    if execution.threads == 1 or in_pool_worker():
        out = []
        for i, (angles, period, per_cell) in enumerate(SPACES):
            queries = gt_angles[i] if gt_angles is not None else angles(gt_rel)
            search = _Search2D(angles(pred_rel), queries, period, per_cell)
            out.append(search.finish(search.grid_pass()))
        return out[0], out[1]
    done, _ = submit_nearest_angles(execution.pool(), pred_rel, gt_rel, gt_angles)
    return done[0].result(), done[1].result()


def submit_nearest_angles(pool, pred_rel: np.ndarray, gt_rel: np.ndarray,
                          gt_angles: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[list, list]:
    """Queue both angle-space searches on ``pool`` (a context's, first in first out) and return
    (answers, queries): each a list of two futures, one per space of ``SPACES``: the nearest
    predicted point per ground-truth ray, and the rays' angles searched (``gt_angles``' or
    computed here).

    The angles and grids of the two spaces are two jobs; then both grid passes are cut into
    CHUNK-query pieces that the pool's threads take as they come free (a thread slowed by other
    load takes fewer), and each space's far queries are answered by a job queued right after
    its pieces."""
    m = gt_rel.shape[0]
    cuts = list(range(0, m, CHUNK)) + [m]

    def make(i: int) -> _Search2D:
        angles, period, per_cell = SPACES[i]
        queries = gt_angles[i] if gt_angles is not None else angles(gt_rel)
        return _Search2D(angles(pred_rel), queries, period, per_cell)

    made = [pool.submit(make, i) for i in range(len(SPACES))]
    done = []
    for f in made:
        pieces = [pool.submit(lambda f=f, a=a, b=b: f.result().grid_pass(a, b)) for a, b in zip(cuts[:-1], cuts[1:])]
        # queued after its pieces: when a thread takes it, every piece has been taken (FIFO)
        done.append(pool.submit(lambda f=f, pieces=pieces: _finish(f.result(), pieces)))
    return done, [_Queries(f) for f in made]


class _Queries:
    """The (M, 2) query angles of a search future, as a future-like ``result()``."""

    def __init__(self, search) -> None:
        self._search = search

    def result(self) -> np.ndarray:
        s = self._search.result()
        return np.stack([s.qx, s.qy], axis=1) if s.queries is None else s.queries


def _finish(search: _Search2D, pieces: list) -> np.ndarray:
    idx = np.concatenate([f.result() for f in pieces]) if pieces else np.zeros(0, dtype=np.int64)
    return search.finish(idx)


def submit_query(pool, index, queries: np.ndarray) -> "_Joined":
    """``index().query(queries)`` as CHUNK-query jobs of ``pool`` (``index``: a callable that
    returns the :class:`Index`, called in each job: a future's ``result`` or a cached
    property). A query's answer does not depend on its chunk, so the joined answer is the
    whole pass's."""
    q = np.ascontiguousarray(queries, dtype=np.float64)
    cuts = list(range(0, q.shape[0], CHUNK)) + [q.shape[0]]
    return _Joined([pool.submit(lambda a=a, b=b: index().query(q[a:b])) for a, b in zip(cuts[:-1], cuts[1:])])


class _Joined:
    """The chunks of a shared k-d tree pass, joined on ``result()``: (squared distance, index)."""

    def __init__(self, parts: list) -> None:
        self.parts = parts

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.parts:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        out = [f.result() for f in self.parts]
        return np.concatenate([d for d, _ in out]), np.concatenate([i for _, i in out])
