"""SE(3) helpers. A transform ``T_a_b`` is a (4, 4) float64 matrix mapping frame b to frame a."""

from __future__ import annotations

import numpy as np


def invert(T_a_b: np.ndarray) -> np.ndarray:
    """Return ``T_b_a`` for a rigid transform (uses R^T, exact for rotations)."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    R = T_a_b[..., :3, :3]
    t = T_a_b[..., :3, 3]
    T_b_a = np.zeros_like(T_a_b)
    Rt = np.swapaxes(R, -1, -2)
    T_b_a[..., :3, :3] = Rt
    T_b_a[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    T_b_a[..., 3, 3] = 1.0
    return T_b_a


def _affine(M: np.ndarray, t: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """out = points @ M.T + t in float64, column by column.

    (N, 3) @ (3, 3) goes through BLAS, whose threads make it ~10x slower than this on a
    loaded 2-core machine; three fused multiply-adds per column are memory-bound and exact.
    """
    q = points.astype(np.float64, copy=False)
    out = np.empty((q.shape[0], 3), dtype=np.float64)
    for i in range(3):
        col = out[:, i]
        np.multiply(q[:, 0], M[i, 0], out=col)
        col += q[:, 1] * M[i, 1]
        col += q[:, 2] * M[i, 2]
        if t is not None:
            col += t[i]
    return out


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame b to frame a; float64 arithmetic, float input dtype kept."""
    points_b = np.asarray(points_b)
    T = np.asarray(T_a_b, dtype=np.float64)
    out = _affine(T[:3, :3], T[:3, 3], points_b.reshape(-1, 3))
    return out.astype(points_b.dtype if points_b.dtype.kind == "f" else np.float64, copy=False)


def rotate_vectors(T_a_b: np.ndarray, vectors_b: np.ndarray) -> np.ndarray:
    """Rotate (N, 3) direction vectors from frame b to frame a (no translation)."""
    vectors_b = np.asarray(vectors_b)
    R = np.asarray(T_a_b, dtype=np.float64)[:3, :3]
    out = _affine(R, None, vectors_b.reshape(-1, 3))
    return out.astype(vectors_b.dtype if vectors_b.dtype.kind == "f" else np.float64, copy=False)


def quat_wxyz_to_rotation(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions [w, x, y, z] to (..., 3, 3) rotation matrices.

    Raises ValueError on a quaternion of (near) zero norm; others are normalised.
    """
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise ValueError("quaternion of zero norm")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotation_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix to a unit quaternion [w, x, y, z] with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    tr = m00 + m11 + m22
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif m00 > m11 and m00 > m22:
        s = 2.0 * np.sqrt(1.0 + m00 - m11 - m22)
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif m11 > m22:
        s = 2.0 * np.sqrt(1.0 + m11 - m00 - m22)
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m22 - m00 - m11)
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Assemble a (4, 4) transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def is_se3(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True when T is a finite (4, 4) rigid transform (orthonormal R, det +1, last row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (
        np.allclose(R @ R.T, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
        and np.allclose(T[3], [0, 0, 0, 1], atol=atol)
    )


def yaw_transform(yaw: float, t: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """A rotation about +z by ``yaw`` radians followed by translation t."""
    c, s = np.cos(yaw), np.sin(yaw)
    return se3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.asarray(t, dtype=float))
