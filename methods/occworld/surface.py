"""Sub-voxel surfaces for OccWorld's rendering: one offset per voxel beside the occupancy.

Why (measured, docs/occworld.md): rendering a perfect occupancy grid at the middle of the
first occupied voxel along a ray leaves a median depth error of ~0.5 m on the paper grid,
almost all of it rays that come down to the ground: such a ray enters the ground's layer of
voxels (0.5625 m high) a metre or more before its return, in voxels that the other returns
made occupied, and stops there. A plane per voxel fixes it: the ray stops where it crosses
the plane, or passes over the voxel when it stays in front of it.

The plane of an occupied voxel (``surface=front``, or ``mean``):

- its **normal** comes from the occupancy grid itself (:func:`free_normals`): the unit sum of
  the unit directions (in metres) from the voxel to those of its 26 neighbours that are free,
  so it points to the space the rays came through; zero where no neighbour is free (a decoded
  grid weights each neighbour by its free probability: ``occ_copy.decoded_normals``);
- its **offset** is the one extra number per voxel the labels carry (:func:`surface_offsets`):
  the largest signed distance, along that normal, from the voxel's centre to the returns that
  fell in it (the front of the returns, as seen from the free side; inside the voxel, so
  ``|s| <= sum_i |n_i| v_i / 2``). Every return of the sweep then lies on or behind its voxel's
  plane, so none of the sweep's own rays passes its voxel: it stops there or before (except a
  ray lying exactly in a face plane, which the walk may put in the voxel beside its return's). ``mean``
  puts the plane through the mean of the returns instead: half the median error on the
  benchmark's data, but the rays whose return lies in front of the mean pass and run on, which
  costs chamfer_nf several times over (docs/occworld.md).

So the target gains one regression channel per voxel; the occupancy itself is OccWorld's.
:func:`render_surface` walks the ray (the walk of ``occupancy._label``) to the first
occupied voxel (``occupancy >= 0.5``) whose plane it reaches inside the voxel: a ray that
enters the voxel on or behind the plane stops at its entry; one in front stops where it
crosses the plane, if that is inside the voxel, else it goes on; a voxel without a normal
(no free neighbour) stops the ray at its entry, so that no ray passes its own return. A ray
that meets nothing takes the grid's exit.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occupancy import OccGrid, _cell, _face
from pcfbench.methods.raycast.grid import _inverse, _slab

#: ``surface`` option values: ``none`` (OccWorld's occupancy alone), ``front`` and ``mean`` (one
#: plane offset per voxel: the front of its returns, or their mean; :func:`surface_offsets`)
SURFACES = ("none", "front", "mean")


#: the neighbourhoods :func:`free_normals` sums over: the 6 face neighbours, or all 26
NEIGHBOURHOODS = (6, 26)


def free_normals(free: np.ndarray, voxel, neighbours: int = 6) -> np.ndarray:
    """(X, Y, Z, 3) unit normals of every voxel: the normalised sum of the unit directions
    (voxel offsets scaled by ``voxel`` metres) to its free ``neighbours`` (6: the faces' or
    26; ``free``: (X, Y, Z) weights in [0, 1], e.g. ``labels == FREE``); zero where the sum is zero."""
    free = np.asarray(free, np.float64)
    if free.ndim != 3:
        raise PcfbenchError(f"surface normals: expected a (X, Y, Z) free grid, got shape {free.shape}")
    if neighbours not in NEIGHBOURHOODS:
        raise PcfbenchError(f"surface normals: neighbours={neighbours!r}, expected 6 or 26")
    vs = np.asarray(voxel, np.float64)
    nx, ny, nz = free.shape
    pad = np.pad(free, 1)
    if neighbours == 6:  # the face neighbours' unit directions are the axes: the sum is a difference per axis
        acc = np.stack([pad[2:, 1:-1, 1:-1] - pad[:-2, 1:-1, 1:-1], pad[1:-1, 2:, 1:-1] - pad[1:-1, :-2, 1:-1],
                        pad[1:-1, 1:-1, 2:] - pad[1:-1, 1:-1, :-2]], axis=-1)
        return _unit(acc)
    return _unit(_neighbour_sum(pad, vs, (nx, ny, nz)))


def _neighbour_sum(pad: np.ndarray, vs: np.ndarray, shape) -> np.ndarray:
    """The sum over all 26 neighbours of their free weight times their unit direction (the
    slow, obvious form; the 6 face neighbours' sum is its per-axis difference)."""
    nx, ny, nz = shape
    acc = np.zeros((nx, ny, nz, 3))
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if dx == dy == dz == 0:
                    continue
                u = np.array([dx, dy, dz]) * vs
                acc += pad[1 + dx:1 + dx + nx, 1 + dy:1 + dy + ny, 1 + dz:1 + dz + nz, None] * (u / np.linalg.norm(u))
    return acc


def _unit(acc: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(acc, axis=-1, keepdims=True)
    return np.where(length > 1e-12, acc / np.maximum(length, 1e-12), 0.0)


def surface_offsets(grid: OccGrid, points: np.ndarray, normals: np.ndarray, at: str = "front") -> np.ndarray:
    """(X, Y, Z) offsets (m): for each voxel holding returns of ``points`` (N, 3, grid
    frame), ``normal . (p - its centre)`` at the front of its points p (``at="front"``: the
    largest) or their mean (``"mean"``); 0 elsewhere."""
    if at not in ("front", "mean"):
        raise PcfbenchError(f"surface offsets: at={at!r}, expected front or mean")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    dims = np.asarray(grid.dims)
    if normals.shape != (*grid.dims, 3):
        raise PcfbenchError(f"surface offsets: normals of shape {normals.shape}, the grid has {grid.dims} voxels")
    idx = np.floor((pts - np.asarray(grid.lo)) / np.asarray(grid.voxel)).astype(np.int64)
    ok = ((idx >= 0) & (idx < dims)).all(axis=1)
    idx, pts = idx[ok], pts[ok]
    n = normals[idx[:, 0], idx[:, 1], idx[:, 2]]
    s = ((pts - grid.centres()[idx[:, 0], idx[:, 1], idx[:, 2]]) * n).sum(axis=1)
    key = (idx[:, 0], idx[:, 1], idx[:, 2])
    if at == "mean":
        total, count = np.zeros(grid.dims), np.zeros(grid.dims)
        np.add.at(total, key, s)
        np.add.at(count, key, 1.0)
        return total / np.maximum(count, 1.0)
    out = np.full(grid.dims, -np.inf)
    np.maximum.at(out, key, s)
    return np.where(np.isfinite(out), out, 0.0)


@nb.njit(nogil=True, cache=True)
def _render_surface(origin, dirs, prob, normals, offsets, lo, vs):
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
            out[j] = 0.0  # the ray never enters the grid
            continue
        i0, i1, i2 = _inverse(d0), _inverse(d1), _inverse(d2)
        tm = t0 + 1e-9 * max(1.0, t1 - t0) if t1 - t0 > 2e-9 else 0.5 * (t0 + t1)
        a = _cell(o0 + d0 * tm, lo[0], vs[0], nx)
        b = _cell(o1 + d1 * tm, lo[1], vs[1], ny)
        c = _cell(o2 + d2 * tm, lo[2], vs[2], nz)
        t = t0
        depth = t1
        while True:
            f0 = _face(o0, i0, lo[0], vs[0], a)
            f1 = _face(o1, i1, lo[1], vs[1], b)
            f2 = _face(o2, i2, lo[2], vs[2], c)
            f = min(min(f0, min(f1, f2)), t1)
            if prob[a, b, c] >= 0.5:
                n0, n1, n2 = normals[a, b, c, 0], normals[a, b, c, 1], normals[a, b, c, 2]
                if n0 == 0.0 and n1 == 0.0 and n2 == 0.0:
                    depth = t
                    break
                s = offsets[a, b, c]
                m0 = lo[0] + (a + 0.5) * vs[0] + s * n0
                m1 = lo[1] + (b + 0.5) * vs[1] + s * n1
                m2 = lo[2] + (c + 0.5) * vs[2] + s * n2
                # signed distance to the plane where the ray enters the voxel
                se = (o0 + d0 * t - m0) * n0 + (o1 + d1 * t - m1) * n1 + (o2 + d2 * t - m2) * n2
                if se <= 0.0:
                    depth = t
                    break
                dn = d0 * n0 + d1 * n1 + d2 * n2
                if dn < 0.0:
                    ts = t - se / dn
                    if ts <= f:
                        depth = ts
                        break
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
        out[j] = depth
    return out


def render_surface(grid: OccGrid, prob: np.ndarray, normals: np.ndarray, offsets: np.ndarray, origin: np.ndarray,
                   dirs: np.ndarray) -> np.ndarray:
    """(M,) depths (m) along ``dirs`` (M, 3) from ``origin`` (3,) through the occupancy
    ``prob`` (X, Y, Z; occupied where >= 0.5) with one plane per voxel (``normals`` (X, Y, Z, 3),
    ``offsets`` (X, Y, Z)), all in the grid's frame (the rules: module docstring)."""
    prob = np.ascontiguousarray(prob, dtype=np.float64)
    if prob.shape != tuple(grid.dims) or np.shape(offsets) != tuple(grid.dims) or np.shape(normals) != (*grid.dims, 3):
        raise PcfbenchError(f"render_surface: occupancy {prob.shape}, normals {np.shape(normals)} and offsets "
                            f"{np.shape(offsets)}: expected {grid.dims}, {(*grid.dims, 3)} and {grid.dims}")
    dirs = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    return _render_surface(np.asarray(origin, np.float64), dirs, prob, np.ascontiguousarray(normals, np.float64),
                           np.ascontiguousarray(offsets, np.float64), np.asarray(grid.lo, np.float64),
                           np.asarray(grid.voxel, np.float64))
