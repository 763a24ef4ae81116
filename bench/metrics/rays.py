"""The per-ray and per-point arithmetic of the metrics in single numba passes.

Each kernel computes what a chain of numpy expressions in ``SweepContext`` and ``SweepTruth``
computed (named in its docstring), element by element with the same float64 operations in the
same order, so the values are equal to the numpy chain's (tests/scoring/test_metrics_rays.py);
they replace 3-10 passes over the arrays and their temporaries (16.5 ms of numpy on the real
KITTI benchmark sweep against 4.4 ms, docs/journal/performance-tuning-2026-11.md). Where numpy's
``maximum``, ``minimum`` and ``clip`` meet a NaN they return it, and so do these. Of -0.0 and
0.0 numpy returns either, depending on where the element falls in its SIMD loop; these return
the first, so a zero's sign may differ from numpy's where neither matters (on no kept ray).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(inline="always")
def _max(a, b):
    """np.maximum of two floats (NaN if either is)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@numba.njit(inline="always")
def _min(a, b):
    """np.minimum of two floats (NaN if either is)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@numba.njit(cache=True, nogil=True)
def lift(points: np.ndarray, origin: np.ndarray, lo: np.ndarray,
         hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(p64, rel, ranges, inside) of (N, 3) ``points``: ``np.ascontiguousarray(points, np.float64)``,
    ``p64 - origin``, ``np.sqrt(np.einsum("ij,ij->i", rel, rel))`` (the sum taken as einsum takes
    it for (N, 3) rows, ``(x^2 + z^2) + y^2``, as ``nn._sq_dist_to``) and ``Box(lo, hi).contains(p64)``."""
    n = points.shape[0]
    p64 = np.empty((n, 3), np.float64)
    rel = np.empty((n, 3), np.float64)
    ranges = np.empty(n, np.float64)
    inside = np.empty(n, np.bool_)
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for i in range(n):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        p64[i, 0] = x
        p64[i, 1] = y
        p64[i, 2] = z
        rx = x - o0
        ry = y - o1
        rz = z - o2
        rel[i, 0] = rx
        rel[i, 1] = ry
        rel[i, 2] = rz
        ranges[i] = np.sqrt((rx * rx + rz * rz) + ry * ry)
        inside[i] = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])
    return p64, rel, ranges, inside


@numba.njit(cache=True, nogil=True)
def clamp_rays(rel: np.ndarray, ranges: np.ndarray, origin: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               min_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_enter, t_exit, meets, clamped, kept) of the rays o -> o + rel (``ranges`` their
    lengths) against the box [lo, hi]: ``SweepTruth.ray_clamp`` (the unit directions
    ``np.where(r > 0, rel / r, 0)``, then ``pcfbench.boxes.ray_box_interval``'s slabs axis by
    axis), ``gt_clamped`` (``np.clip(r, t_enter, np.maximum(t_exit, t_enter))``) and
    ``ray_kept`` (``meets & (clamped - t_enter > min_range)``)."""
    n = rel.shape[0]
    t_enter = np.empty(n, np.float64)
    t_exit = np.empty(n, np.float64)
    meets = np.empty(n, np.bool_)
    clamped = np.empty(n, np.float64)
    kept = np.empty(n, np.bool_)
    a_lo = np.empty(3, np.float64)
    a_hi = np.empty(3, np.float64)
    inside = np.empty(3, np.bool_)
    for a in range(3):
        a_lo[a] = lo[a] - origin[a]
        a_hi[a] = hi[a] - origin[a]
        inside[a] = lo[a] <= origin[a] and origin[a] <= hi[a]
    for i in range(n):
        r = ranges[i]
        te = 0.0
        tx = np.inf
        for a in range(3):
            d = rel[i, a] / r if r > 0 else 0.0
            if d == 0:  # parallel to the slab: inside it or never
                tmin = -np.inf if inside[a] else np.inf
                tmax = np.inf if inside[a] else -np.inf
            else:
                t1 = a_lo[a] / d
                t2 = a_hi[a] / d
                tmin = _min(t1, t2)
                tmax = _max(t1, t2)
            te = _max(te, tmin)
            tx = _min(tx, tmax)
        t_enter[i] = te
        t_exit[i] = tx
        m = te <= tx and r > 0
        meets[i] = m
        c = _min(_max(r, te), _max(tx, te))
        clamped[i] = c
        kept[i] = m and c - te > min_range
    return t_enter, t_exit, meets, clamped, kept


@numba.njit(cache=True, nogil=True)
def ray_errors(depth: np.ndarray, t_enter: np.ndarray, t_exit: np.ndarray, clamped: np.ndarray,
               kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(|g_c - p_c|, |g_c - p_c| / (g_c - t_enter)) on the kept rays, in ray order, with
    ``p_c = np.clip(depth, t_enter, t_exit)`` and ``g_c = clamped``: ``SweepContext.ray_errors``."""
    n = 0
    for i in range(kept.shape[0]):
        n += kept[i]
    err = np.empty(n, np.float64)
    rel = np.empty(n, np.float64)
    k = 0
    for i in range(kept.shape[0]):
        if kept[i]:
            p = _min(_max(depth[i], t_enter[i]), t_exit[i])
            g = clamped[i]
            e = abs(g - p)
            err[k] = e
            rel[k] = e / (g - t_enter[i])
            k += 1
    return err, rel
