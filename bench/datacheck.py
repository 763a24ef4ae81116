"""What a sweep read from a dataset must be: finite float points of shape (N, 3) and a rigid
pose. ``pcfbench run`` (through ``Sequence.checked_sweep``) and ``pcfbench datasets check``
(``DatasetAdapter.check``) call these same functions, so a check that passes means a run
does not refuse the data; a method's forecast goes through :func:`check_points` too
(``pcfbench.protocol.validate``)."""

from __future__ import annotations

import numpy as np

from pcfbench.data import FLOAT32_MAX, Sweep
from pcfbench.errors import DataError
from pcfbench.geometry import is_se3

#: How far a sweep's pose may be from rigid (orthonormal rotation, determinant +1).
POSE_ATOL = 1e-4


def check_points(arr, where: str, err: type[Exception] = DataError) -> np.ndarray:
    """``arr`` as (N, 3) float32 when it is finite floating point, else one ``err`` naming ``where``."""
    arr = np.asarray(arr)
    if arr.dtype.kind != "f":
        raise err(f"{where}: points must be floating point, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise err(f"{where}: points must have shape (N, 3), got {arr.shape}")
    finite = np.isfinite(arr)
    if not finite.all():
        bad = int((~finite.all(axis=1)).sum())
        raise err(f"{where}: {bad} point(s) with NaN or inf coordinates")
    if arr.dtype.itemsize > 4 and arr.size and np.abs(arr).max() > FLOAT32_MAX:  # finite float32 always fits
        raise err(f"{where}: coordinates outside float32 range")
    return arr.astype(np.float32, copy=False)


def check_rigid(T: np.ndarray, where: str, atol: float = 1e-3) -> np.ndarray:
    """``T`` when it is a finite rigid 4x4 transform (rotation orthonormal within ``atol``,
    determinant +1, last row 0 0 0 1), else one ``DataError`` naming ``where`` and what is off
    (a scaled or sheared transform would move every point silently)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DataError(f"{where}: expected a finite 4x4 transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise DataError(f"{where}: expected a finite 4x4 transform, got NaN or inf values")
    if not is_se3(T, atol=atol):
        R = T[:3, :3]
        scales = np.linalg.svd(R, compute_uv=False)
        raise DataError(f"{where}: not a rigid transform (rotation singular values {', '.join(f'{s:.6g}' for s in scales)}, "
                        f"determinant {np.linalg.det(R):.6g}, last row {', '.join(f'{v:g}' for v in T[3])}; "
                        f"expected 1, 1, 1, +1 and 0, 0, 0, 1 within {atol:g})")
    return T


def pose_is_rigid(T: np.ndarray) -> bool:
    """Whether a sweep's pose passes :func:`validate_sweep` (no message built)."""
    return is_se3(T, atol=POSE_ATOL)


def validate_sweep(sweep: Sweep, where: str | None = None, pose_where: str | None = None) -> Sweep:
    """The sweep with float32 points, or one ``DataError``: points not finite (x, y, z) float,
    named by ``where`` (default: the sweep's source, the file it was read from), or a pose
    that is not rigid within ``POSE_ATOL``, named by ``pose_where`` (default: ``where``)."""
    where = where or sweep.source or "sweep"
    pts = check_points(sweep.points_sensor, where)
    check_rigid(sweep.T_world_sensor, pose_where or f"{where} (its pose)", atol=POSE_ATOL)
    return sweep if pts is sweep.points_sensor else Sweep(pts, sweep.T_world_sensor, sweep.timestamp_ns, sweep.intensity, sweep.source)
