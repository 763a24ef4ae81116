"""Registers the built-in methods through the same hook as third-party plugins."""

from bench.hookspecs import hookimpl


@hookimpl
def register_methods(register):
    register("copy-last", "methods.copy_last:CopyLast", "the t=0 sweep as every future sweep (static world)")
    register("raycast-4docc", "methods.raycast.fourdocc:RaycastFourDOcc", "4D-Occ reference ray tracing: angle-space nearest past point, no occlusion")
    register("raycast-zbuffer", "methods.raycast.zbuffer:RaycastZBuffer", "spherical z-buffer of the aggregated past from the future pose")
    register("raycast-voxel", "methods.raycast.voxel:RaycastVoxel", "first hit in a 0.2 m occupancy grid, range-growing cone rays")
    register("raycast-freespace", "methods.raycast.freespace:RaycastFreespace", "raycast-voxel with past free space carved (moving ghosts removed)")
