"""raycast-voxel: first hit in a voxel occupancy grid of the aggregated past.

The past sweeps, concatenated in the reference frame, fill a ``voxel`` (0.2 m) occupancy grid
over the ROI; every query ray is cast from the future origin to its first occupied voxel
(see ``methods.raycast.grid`` for the traversal).

Sparsity policy (documented, tested): far from the sensor consecutive beams are metres apart,
so a thin ray from a new origin slips between occupied voxels. The ray is therefore a cone:
at range ``t`` it stops at occupied space at the resolution ``t * cone_factor * el_res``
(``cone_factor`` times the beam spacing; 1 scored better than 2 and 0 on the synthetic-town
val split, on the pyramid level at least that coarse, at most
``max_level``), and a coarse hit is refined at 0.2 m where the surface is dense enough.
``cone_center=past`` measures the range from the t=0 sensor instead (the gaps of the past
beams); on synthetic-town it scored worse at 3 s, so the future origin is the default.

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

from bench.data import Forecast, Sample
from bench.method import Method
from methods.raycast.common import aggregate, assemble, map_views, pieces, views
from methods.raycast.grid import VoxelGrid
from methods.raycast.zbuffer import ZBufferOptions, render_zbuffer


#: levels of the occupancy pyramid above the voxels (0.2 m * 2**4 = 3.2 m cells): with 4
#: instead of 3 a ray over open ground skips 3.2 m at a step, 11.4 instead of 15.1 steps a ray
#: on the KITTI-sized benchmark sample (the same depths there; a cone's hit can in principle
#: move where its width crosses a level inside a skipped cell, see methods.raycast.grid)
PYRAMID = 4


@dataclass(frozen=True)
class VoxelOptions:
    voxel: float = 0.2  # voxel edge, metres
    cone_factor: float = 1.0  # ray thickness in units of the beam spacing (0: thin rays)
    max_level: int = 3  # coarsest level a cone may use (0.2 * 2**3 = 1.6 m)
    cone_center: Literal["future", "past"] = "future"  # cone width grows with range from the future or the t=0 sensor
    az_res_deg: float = 0.2  # z-buffer fallback bins (see raycast-zbuffer)
    el_res_deg: float = 0.4  # beam spacing: z-buffer fallback bins and cone width
    constant_velocity: bool = False  # extrapolate future poses from the last two past poses


def render_voxel_views(grid: VoxelGrid, cols, own_range, vws, opts) -> list[np.ndarray]:
    """Depth per query ray of each view of ``vws``; ``cols`` (3, N) and ``own_range`` are the
    past points of the z-buffer fallback (see ``render_zbuffer``). The casts go to the threads
    in pieces of ``PIECE`` rays (finer than views, so that the threads finish together), then
    the fallback of each view with escaped rays."""
    cone = opts.cone_factor * np.deg2rad(opts.el_res_deg)
    center = None if opts.cone_center == "future" else np.zeros(3)
    jobs = [(v, sl) for v in vws for sl in pieces(len(v.directions))]
    parts = iter(map_views(
        lambda job: grid.cast(job[0].origin, job[0].directions[job[1]], cone=cone, max_level=opts.max_level,
                              cone_center=center),
        jobs,
    ))
    depths = [np.concatenate([next(parts) for _ in pieces(len(v.directions))]) for v in vws]
    zb = ZBufferOptions(az_res_deg=opts.az_res_deg, el_res_deg=opts.el_res_deg)

    def fallback(k: int) -> None:
        miss = np.isnan(depths[k])
        depths[k][miss] = render_zbuffer(cols, own_range, vws[k].subset(miss), zb)

    map_views(fallback, [k for k, d in enumerate(depths) if np.isnan(d).any()])
    return depths


class RaycastVoxel(Method):
    name = "raycast-voxel"
    version = "1"
    Options = VoxelOptions

    def forecast(self, sample: Sample) -> Forecast:
        agg = aggregate(sample)
        grid = VoxelGrid(agg.points, voxel=self.options.voxel, levels=max(self.options.max_level, PYRAMID))
        vws = views(sample, self.options.constant_velocity)
        depths = render_voxel_views(grid, agg.cols, agg.own_range, vws, self.options)
        return assemble(sample, vws, depths, self.options.constant_velocity)
