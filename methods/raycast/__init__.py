"""Ray-casting baselines: re-render the aggregated past from the future sensor poses.

One module per baseline (``fourdocc``, ``zbuffer``, ``voxel``, ``freespace``); shared pieces
in ``common`` (aggregation, poses, angle spaces), ``nn2d`` (exact angle-space nearest
neighbours) and ``grid`` (voxel occupancy and ray traversal).

Their threads come from the method's execution context (``pcfbench.execution``); importing
them sets no thread or threading-layer setting.
"""
