"""raycast-voxel: first hit in a voxel occupancy grid of the aggregated past.

The past sweeps, concatenated in the reference frame, fill a ``voxel`` (0.2 m) occupancy grid
over the ROI; every query ray is cast from the future origin to its first occupied voxel
(see ``pcfbench.methods.raycast.grid`` for the traversal).

Sparsity policy (documented, tested): far from the sensor consecutive beams are metres apart,
so a thin ray from a new origin slips between occupied voxels. The ray is therefore a cone:
at range ``t`` it stops at occupied space at the resolution ``t * cone_factor * el_res``
(``cone_factor`` times the beam spacing, on the pyramid level at least that coarse, at most
``max_level``), and a coarse hit is refined at 0.2 m where the surface is dense enough.
``cone_center=past`` measures the range from the t=0 sensor instead (the gaps of the past
beams); the future origin is the default (the choice of both defaults: docs/baselines.md).

Depth at the hit (``surface``, version 2): where the ray crosses the hit voxel's fitted
surface (the plane through the mean of its points, normal from the flat points around it),
following it up to 3 m past the voxel for grazing rays (see ``pcfbench.methods.raycast.grid``);
``surface=mean`` keeps version 1's projection of the voxel's mean on the ray (results of
both versions: docs/baselines.md).

Grid phase (``align_ground``): the grid is shifted down (by less than 3.2 m) so that every
level has a face half a voxel above the ground under the sensor (``ground_height``: the median
height of the most common 2 cm height band within 20 m). The ground then sits in the middle
of its voxels, and the cells above it are free of its noise: fewer, longer steps for the rays
coming down to it (speed, see docs/journal/performance-tuning-2026-11.md; the surfaces keep the depth independent of
the phase).

Rays that hit nothing: a ray that leaves the grid (the ROI) without meeting occupied space,
or starts outside it and misses it, takes the z-buffer depth of ``raycast-zbuffer`` (the
nearest range among past points in its angular bin, else the nearest filled bin or the
angular nearest neighbour),
which also covers surfaces beyond the ROI.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.execution import ExecutionContext
from pcfbench.method import Method
from pcfbench.options import option
from pcfbench.protocol import ROI
from pcfbench.boxes import Box
from pcfbench.methods.raycast.common import aggregate, assemble, map_views, pieces, views
from pcfbench.methods.raycast.grid import VoxelGrid
from pcfbench.methods.raycast.zbuffer import ZBufferOptions, render_zbuffer


#: levels of the occupancy pyramid above the voxels (0.2 m * 2**4 = 3.2 m cells): with 4
#: instead of 3 a ray over open ground skips 3.2 m at a step, 11.4 instead of 15.1 steps a ray
#: on the KITTI-sized benchmark sample (the same depths there; a cone's hit can in principle
#: move where its width crosses a level inside a skipped cell, see pcfbench.methods.raycast.grid)
PYRAMID = 4

#: horizontal radius (m) around the reference sensor whose points give the ground's height
GROUND_RADIUS = 20.0
#: height bins (m) of the ground's mode
GROUND_BIN = 0.02
#: the ground's points are those within this (m) of the mode
GROUND_BAND = 0.15


def ground_height(points: np.ndarray, box: Box = ROI) -> float | None:
    """The height of the ground under the reference sensor: among the points within
    ``GROUND_RADIUS`` of it horizontally and inside ``box``, the median height of those within
    ``GROUND_BAND`` of the most common height (``GROUND_BIN`` bins, the lowest of equal ones).
    None without such points."""
    lo, hi = float(box.lo[2]), float(box.hi[2])
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    z = z[(x * x + y * y < GROUND_RADIUS**2) & (z >= lo) & (z < hi)]
    if len(z) == 0:
        return None
    mode = lo + (int(np.argmax(np.bincount(np.floor((z - lo) / GROUND_BIN).astype(np.int64)))) + 0.5) * GROUND_BIN
    return float(np.median(z[np.abs(z - mode) <= GROUND_BAND]))


def build_grid(points: np.ndarray, opts) -> VoxelGrid:
    """The occupancy grid of ``points`` for the options of raycast-voxel (or -freespace); with
    ``align_ground``, every level has a face half a voxel above the ground (``ground_height``)."""
    return _grid(points, opts.voxel, max(opts.max_level, PYRAMID), opts.align_ground)


def _grid(points: np.ndarray, voxel: float, levels: int, align_ground: bool) -> VoxelGrid:
    ground = ground_height(points) if align_ground else None
    anchor = None if ground is None else ground + 0.5 * voxel
    return VoxelGrid(points, voxel=voxel, levels=levels, anchor_z=anchor)


def _past_grid(sample: Sample, voxel: float, levels: int, align_ground: bool) -> VoxelGrid:
    return _grid(sample.derive(aggregate).points, voxel, levels, align_ground).freeze()


def past_grid(sample: Sample, opts) -> VoxelGrid:
    """``build_grid`` of the sample's aggregated past, read-only: built once for every method on
    the sample that asks with the same voxel, levels and ground alignment (``Sample.derive``)."""
    return sample.derive(_past_grid, float(opts.voxel), max(opts.max_level, PYRAMID), bool(opts.align_ground))


@dataclass(frozen=True)
class VoxelOptions:
    voxel: float = option(0.2, help="voxel edge of the occupancy grid, metres", gt=0, max=10)
    cone_factor: float = option(1.0, help="ray thickness in units of the beam spacing el_res_deg (0: thin rays)",
                                min=0, max=100)
    max_level: int = option(3, help="coarsest pyramid level a cone may stop on (voxel * 2**level: 1.6 m at 3)",
                            min=0, max=10)
    cone_center: Literal["future", "past"] = option(
        "future", help="the cone widens with the range from the future sensor, or from the t=0 sensor (past)")
    az_res_deg: float = option(0.2, help="azimuth bin width of the z-buffer fallback (as raycast-zbuffer), degrees",
                                gt=0, max=360)
    el_res_deg: float = option(0.4, help="beam spacing: elevation bins of the z-buffer fallback and the cone width, "
                                         "degrees", gt=0, max=180)
    surface: Literal["plane", "mean"] = option(
        "plane", help="depth in a hit voxel: where the ray crosses its fitted surface, or its mean projected on the ray")
    align_ground: bool = option(True, help="shift the grid so a face lies half a voxel above the ground (speed only)")
    constant_velocity: bool = option(False, help="extrapolate the future poses from the last two past poses "
                                                 "instead of using the sample's future poses")


def render_voxel_views(grid: VoxelGrid, cols, own_range, vws, opts,
                       execution: ExecutionContext | None = None) -> list[np.ndarray]:
    """Depth per query ray of each view of ``vws``; ``cols`` (3, N) and ``own_range`` are the
    past points of the z-buffer fallback (see ``render_zbuffer``). The casts go to the threads
    of ``execution`` (default: the process's) in pieces of ``PIECE`` rays (finer than views,
    so that the threads finish together), then the fallback of each view with escaped rays."""
    cone = opts.cone_factor * np.deg2rad(opts.el_res_deg)
    center = None if opts.cone_center == "future" else np.zeros(3)
    jobs = [(v, sl) for v in vws for sl in pieces(len(v.directions))]
    parts = iter(map_views(
        lambda job: grid.cast(job[0].origin, job[0].directions[job[1]], cone=cone, max_level=opts.max_level,
                              cone_center=center, surface=opts.surface == "plane"),
        jobs,
        execution,
    ))
    depths = [np.concatenate([next(parts) for _ in pieces(len(v.directions))]) for v in vws]
    zb = ZBufferOptions(az_res_deg=opts.az_res_deg, el_res_deg=opts.el_res_deg)

    def fallback(k: int) -> None:
        miss = np.isnan(depths[k])
        depths[k][miss] = render_zbuffer(cols, own_range, vws[k].subset(miss), zb)

    map_views(fallback, [k for k, d in enumerate(depths) if np.isnan(d).any()], execution)
    return depths


class RaycastVoxel(Method):
    name = "raycast-voxel"
    version = "2"
    Options = VoxelOptions

    def forecast(self, sample: Sample) -> Forecast:
        agg = sample.derive(aggregate)
        grid = past_grid(sample, self.options)
        vws = sample.derive(views, self.options.constant_velocity)
        depths = render_voxel_views(grid, agg.cols, agg.own_range, vws, self.options, self.execution)
        return assemble(sample, vws, depths, self.options.constant_velocity)
