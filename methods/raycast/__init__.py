"""Ray-casting baselines: re-render the aggregated past from the future sensor poses.

One module per baseline (``fourdocc``, ``zbuffer``, ``voxel``, ``freespace``); shared pieces
in ``common`` (aggregation, poses, angle spaces), ``nn2d`` (exact angle-space nearest
neighbours) and ``grid`` (voxel occupancy and ray traversal).
"""

import numba

# numba tries TBB first; the TBB found here is too old and every process warns about it.
# OpenMP ships with numba's wheels and serves the prange kernels just as well.
numba.config.THREADING_LAYER = "omp"
