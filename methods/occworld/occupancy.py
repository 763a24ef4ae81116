"""Occupancy from LiDAR: a 3-class voxel grid (free, occupied, unknown) per sweep.

Every return is a ray from its sensor origin to the point. The voxels the segment passes
through are **free**, the voxel the point falls in is **occupied** (occupied wins where a
voxel is both: another ray ended in it), every voxel no ray reached is **unknown**. Rays that
end outside the grid still free the voxels they cross inside it.

The traversal is an exact voxel walk (Amanatides and Woo): the ray is clipped to the grid's
box with ``pcfbench.methods.raycast.grid``'s slab test (``_slab``, the arithmetic of
``pcfbench.boxes.ray_box_interval``), then steps to the neighbouring voxel across whichever
face it leaves first; each face's crossing ``t`` is recomputed from the voxel index (no
accumulated increments), so the visited voxels are those whose interior the segment crosses,
plus, where it passes exactly through an edge or corner, the ones it only touches there. The
point's voxel comes from ``floor((p - lo) / voxel)``, as ``grid._voxel_keys`` computes it.

Voxels may be anisotropic (``voxel`` per axis): the protocol's ROI, 140 x 140 x 9 m, is
covered by the paper's 200 x 200 x 16 grid with 0.7 x 0.7 x 0.5625 m voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from pcfbench.errors import PcfbenchError
from pcfbench.methods.raycast.grid import _inverse, _slab

FREE = 0
OCCUPIED = 1
UNKNOWN = 2
#: the classes, in label order
CLASSES = ("free", "occupied", "unknown")


@dataclass(frozen=True)
class OccGrid:
    """A voxel grid: ``dims`` voxels (nx, ny, nz) from corner ``lo``, each ``voxel`` (vx, vy, vz) metres."""

    lo: tuple[float, float, float]
    dims: tuple[int, int, int]
    voxel: tuple[float, float, float]

    @staticmethod
    def over(box_lo, box_hi, dims) -> "OccGrid":
        """The grid of ``dims`` voxels that exactly covers the box ``box_lo .. box_hi``."""
        lo = tuple(float(v) for v in box_lo)
        hi = tuple(float(v) for v in box_hi)
        dims = tuple(int(n) for n in dims)
        if len(lo) != 3 or len(hi) != 3 or len(dims) != 3 or any(n < 1 for n in dims) or any(h <= v for v, h in zip(lo, hi)):
            raise PcfbenchError(f"occupancy grid: expected a box lo < hi and 3 positive sizes, got {lo}, {hi}, {dims}")
        return OccGrid(lo, dims, tuple((h - v) / n for v, h, n in zip(lo, hi, dims)))

    @property
    def hi(self) -> tuple[float, float, float]:
        return tuple(v + n * s for v, n, s in zip(self.lo, self.dims, self.voxel))

    def centres(self) -> np.ndarray:
        """(nx, ny, nz, 3) voxel centres."""
        axes = [lo + (np.arange(n) + 0.5) * s for lo, n, s in zip(self.lo, self.dims, self.voxel)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


@nb.njit(inline="always")
def _cell(q, lo, vs, n):
    """The voxel index of coordinate ``q`` along one axis, clamped into the grid."""
    return min(max(int(np.floor((q - lo) / vs)), 0), n - 1)


@nb.njit(inline="always")
def _face(o, iv, lo, vs, i):
    """The ray's ``t`` at the face it leaves voxel ``i`` through along one axis (inf if parallel)."""
    if iv > 0:
        return (lo + (i + 1) * vs - o) * iv
    if iv < 0:
        return (lo + i * vs - o) * iv
    return np.inf


@nb.njit(cache=True)
def _label(origins, points, lo, vs, dims, out):
    nx, ny, nz = dims[0], dims[1], dims[2]
    hi0, hi1, hi2 = lo[0] + nx * vs[0], lo[1] + ny * vs[1], lo[2] + nz * vs[2]
    one = origins.shape[0] == 1
    for i in range(points.shape[0]):
        k = 0 if one else i
        o0, o1, o2 = origins[k, 0], origins[k, 1], origins[k, 2]
        e0, e1, e2 = points[i, 0] - o0, points[i, 1] - o1, points[i, 2] - o2
        r = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if r <= 0.0:
            continue
        d0, d1, d2 = e0 / r, e1 / r, e2 / r
        t0, t1 = _slab(o0, d0, lo[0], hi0, 0.0, r)
        t0, t1 = _slab(o1, d1, lo[1], hi1, t0, t1)
        t0, t1 = _slab(o2, d2, lo[2], hi2, t0, t1)
        if not t0 < t1:
            continue
        i0, i1, i2 = _inverse(d0), _inverse(d1), _inverse(d2)
        # the voxel the clipped segment starts in: that of its midpoint's side of any face it
        # starts on (a start exactly on a face belongs to the voxel the ray enters)
        tm = t0 + 1e-9 * max(1.0, t1 - t0) if t1 - t0 > 2e-9 else 0.5 * (t0 + t1)
        a = _cell(o0 + d0 * tm, lo[0], vs[0], nx)
        b = _cell(o1 + d1 * tm, lo[1], vs[1], ny)
        c = _cell(o2 + d2 * tm, lo[2], vs[2], nz)
        while True:
            out[a, b, c] = FREE
            f0 = _face(o0, i0, lo[0], vs[0], a)
            f1 = _face(o1, i1, lo[1], vs[1], b)
            f2 = _face(o2, i2, lo[2], vs[2], c)
            f = min(f0, min(f1, f2))
            if f >= t1:
                break
            if f0 == f:
                a += 1 if i0 > 0 else -1
            elif f1 == f:
                b += 1 if i1 > 0 else -1
            else:
                c += 1 if i2 > 0 else -1
            if a < 0 or a >= nx or b < 0 or b >= ny or c < 0 or c >= nz:
                break
    for i in range(points.shape[0]):  # occupied wins: the end voxels after every ray has freed its path
        fa = np.floor((points[i, 0] - lo[0]) / vs[0])
        fb = np.floor((points[i, 1] - lo[1]) / vs[1])
        fc = np.floor((points[i, 2] - lo[2]) / vs[2])
        if 0 <= fa < nx and 0 <= fb < ny and 0 <= fc < nz:
            out[int(fa), int(fb), int(fc)] = OCCUPIED


def label_occupancy(grid: OccGrid, points: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """(nx, ny, nz) uint8 labels (``FREE``, ``OCCUPIED``, ``UNKNOWN``) of ``points`` (N, 3) seen
    from ``origins`` ((3,) one sensor, or (N, 3) one per point), all in the grid's frame."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    org = np.ascontiguousarray(np.atleast_2d(origins), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PcfbenchError(f"occupancy: expected points of shape (N, 3), got {points.shape}")
    if org.shape[1] != 3 or org.shape[0] not in (1, len(pts)):
        raise PcfbenchError(f"occupancy: expected origins of shape (3,) or ({len(pts)}, 3), got {np.shape(origins)}")
    if not (np.isfinite(pts).all() and np.isfinite(org).all()):
        raise PcfbenchError("occupancy: points and origins must be finite")
    out = np.full(grid.dims, UNKNOWN, np.uint8)
    _label(org, pts, np.asarray(grid.lo, np.float64), np.asarray(grid.voxel, np.float64),
           np.asarray(grid.dims, np.int64), out)
    return out
