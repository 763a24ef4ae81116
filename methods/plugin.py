"""Registers the built-in methods through the same hook as third-party plugins."""

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_methods(register):
    register("copy-last", "pcfbench.methods.copy_last:CopyLast", "the t=0 sweep as every future sweep (static world)")
    register("raycast-4docc", "pcfbench.methods.raycast.fourdocc:RaycastFourDOcc", "4D-Occ reference ray tracing: angle-space nearest past point, no occlusion")
    register("raycast-zbuffer", "pcfbench.methods.raycast.zbuffer:RaycastZBuffer", "spherical z-buffer of the aggregated past from the future pose")
    register("raycast-voxel", "pcfbench.methods.raycast.voxel:RaycastVoxel", "first hit in a 0.2 m occupancy grid, range-growing cone rays")
    register("raycast-freespace", "pcfbench.methods.raycast.freespace:RaycastFreespace", "raycast-voxel with past free space carved (moving ghosts removed)")
    register("submission", "pcfbench.exchange.method:Submission", "forecasts made elsewhere, read from a file (pcfbench score)")
