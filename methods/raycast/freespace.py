"""raycast-freespace: raycast-voxel on a grid whose free space was carved by the past rays.

Every past return is a ray from its own sensor origin to the point. The occupied voxels it
crosses before ``range - margin`` (``margin = max(carve_margin_m, carve_margin_frac *
range)``, so that rays grazing the ground near their own return do not erode it) count as
seen free once; the voxels its points fall in count as seen occupied once per point. A voxel
stays occupied when its log-odds ``hits * l_hit - free * l_miss`` is positive (OctoMap's
default increments), so the ghosts that moving objects leave in the aggregate, which later
or earlier rays pass through, are carved away and only stably occupied space stops a ray.
Past points in carved voxels are also removed from the z-buffer fallback of the voxel caster.
With ``renderer=zbuffer`` the surviving points are rendered by ``raycast-zbuffer`` instead of
casting the carved grid. Version 2 casts as ``raycast-voxel`` version 2 (fitted surfaces,
ground-aligned grid; carving refits the surfaces of the voxels it keeps; results of both
versions: docs/baselines.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.method import Method
from pcfbench.options import option
from pcfbench.methods.raycast.common import aggregate, assemble, views
from pcfbench.methods.raycast.grid import VoxelGrid
from pcfbench.methods.raycast.voxel import VoxelOptions, past_grid, render_voxel_views
from pcfbench.methods.raycast.zbuffer import render_zbuffer_views


@dataclass(frozen=True)
class FreespaceOptions(VoxelOptions):
    """raycast-voxel's options (the caster of the carved grid), and the carving's."""

    l_hit: float = option(0.85, help="log-odds added to a voxel per past return in it", gt=0, max=100)
    l_miss: float = option(0.4, help="log-odds removed from a voxel per past ray passing through it", min=0, max=100)
    carve_margin_m: float = option(0.5, help="a ray carves up to this far before its return, metres, or "
                                             "carve_margin_frac of its range if that is more", min=0, max=1000)
    carve_margin_frac: float = option(0.15, help="a ray carves up to this fraction of its range before its return, "
                                                 "or carve_margin_m if that is more", min=0, max=1)
    renderer: Literal["voxel", "zbuffer"] = option(
        "voxel", help="cast the carved grid (voxel), or z-buffer the points that survive the carving (zbuffer)")
    splat: float = option(1.0, help="zbuffer renderer: splat diameter, as raycast-zbuffer's", min=0, max=100)
    max_splat: int = option(4, help="zbuffer renderer: largest splat half-width, bins, as raycast-zbuffer's",
                            min=0, max=256)
    fill_ring: int = option(8, help="zbuffer renderer: empty-bin fill radius, bins, as raycast-zbuffer's",
                            min=0, max=1800)


def carve(grid: VoxelGrid, origins, points, own_range, opts) -> tuple[VoxelGrid, np.ndarray]:
    """(the carved grid, the mask of points whose voxel survived or that lie outside); ``grid``
    is left as it is."""
    t_end = own_range - np.maximum(opts.carve_margin_m, opts.carve_margin_frac * own_range)
    free = grid.free_counts(origins, points, t_end)
    keep = grid.hits * opts.l_hit - free * opts.l_miss > 0
    slot = grid.point_slot
    point_keep = np.ones(len(points), bool)
    point_keep[slot >= 0] = keep[slot[slot >= 0]]
    return grid.kept(keep), point_keep


class RaycastFreespace(Method):
    name = "raycast-freespace"
    version = "2"
    Options = FreespaceOptions

    def forecast(self, sample: Sample) -> Forecast:
        agg = sample.derive(aggregate)
        grid, keep = carve(past_grid(sample, self.options), agg.origins, agg.points, agg.own_range, self.options)
        cols, own = np.ascontiguousarray(agg.cols[:, keep]), agg.own_range[keep]
        vws = sample.derive(views, self.options.constant_velocity)
        if self.options.renderer == "zbuffer":
            depths = render_zbuffer_views(cols, own, vws, self.options, self.execution)
        else:
            depths = render_voxel_views(grid, cols, own, vws, self.options, self.execution)
        return assemble(sample, vws, depths, self.options.constant_velocity)
