"""Ray-casting baselines: re-render the aggregated past from the future sensor poses.

One module per baseline (``fourdocc``, ``zbuffer``, ``voxel``, ``freespace``); shared pieces
in ``common`` (aggregation, viewpoints, forecast assembly) and ``grid`` (voxel occupancy and
ray traversal); exact angle-space nearest neighbours come from ``pcfbench.nn2d``.

Their threads come from the method's execution context (``pcfbench.execution``); importing
them sets no thread or threading-layer setting.
"""
