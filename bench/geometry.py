"""SE(3) helpers. A transform ``T_a_b`` is a (4, 4) float64 matrix mapping frame b to frame a;
a twist (6,) = (rho, omega) is its logarithm (``se3_log``, ``se3_exp``)."""

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


# ---------------------------------------------------------------- SO(3) / SE(3) exponential and logarithm
# A twist xi = (rho, omega) (6,) float64: omega the rotation vector (axis times angle, radians),
# rho the translation part; se3_exp(xi) = expm of the 4x4 matrix [[hat(omega), rho], [0, 0]].

#: below this rotation angle (radians) the left Jacobian's coefficients come from their Taylor
#: series (truncation under 1e-16 here): the closed form (1 - cos t) / t^2 loses about
#: eps / t^2 of its value to cancellation (all of it by t ~ 1e-8)
_SERIES_ANGLE = 1e-2
#: within this of pi (radians) so3_log takes the axis from the symmetric part of R and the
#: angle from atan2: there the antisymmetric part (2 sin(angle) axis) shrinks to 0 and an angle
#: from arccos loses about eps / (pi - angle)^2 (4e-10 at 1e-3 from pi)
_NEAR_PI = 0.5


def hat(w: np.ndarray) -> np.ndarray:
    """(3,) vector to the (3, 3) skew-symmetric matrix of its cross product: hat(w) @ v = w x v."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) (axis times angle, radians) to a (3, 3) rotation matrix (Rodrigues)."""
    th = float(np.linalg.norm(w))
    K = hat(w)
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix to its rotation vector (3,), angle in [0, pi] (at exactly pi
    either of the two opposite vectors)."""
    R = np.asarray(R, dtype=np.float64)
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(th) axis
    if th < 1e-9:
        return 0.5 * v
    if np.pi - th < _NEAR_PI:
        # (R + R^T) / 2 = cos(th) I + (1 - cos(th)) a a^T: the axis up to sign from its largest
        # column, the sign from v, the angle from atan2 (accurate where arccos is not)
        B = ((R + R.T) / 2.0 - c * np.eye(3)) / (1.0 - c)
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(B[i, i])
        axis /= np.linalg.norm(axis)
        if axis @ v < 0:
            axis = -axis
        return float(np.arctan2(np.linalg.norm(v) / 2.0, c)) * axis
    return th / (2.0 * np.sin(th)) * v


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """J(w) = I + (1 - cos t) / t^2 hat(w) + (t - sin t) / t^3 hat(w)^2, t = |w|: the
    translation of se3_exp(rho, w) is J(w) @ rho."""
    th = float(np.linalg.norm(w))
    K = hat(w)
    if th < _SERIES_ANGLE:
        t2 = th * th
        return np.eye(3) + (0.5 - t2 / 24.0 + t2 * t2 / 720.0) * K + (1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0) * K @ K
    return np.eye(3) + (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Twist (6,) = (rho, omega) to a (4, 4) rigid transform."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, w = xi[:3], xi[3:]
    T = np.eye(4)
    T[:3, :3] = so3_exp(w)
    T[:3, 3] = _left_jacobian(w) @ rho
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform to its twist (6,) = (rho, omega), rotation angle in [0, pi]:
    se3_exp(se3_log(T)) == T."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[:3, :3])
    rho = np.linalg.solve(_left_jacobian(w), T[:3, 3])
    return np.concatenate([rho, w])


def constant_velocity_poses(
    past_T_ref_sensor: np.ndarray, past_t_ns: np.ndarray, future_t_ns: np.ndarray
) -> np.ndarray:
    """Future poses ``T_ref_sensor`` (F, 4, 4) extrapolated from the last two past poses at
    constant SE(3) velocity: ``T(t) = T_0 se3_exp(s se3_log(T_-1^-1 T_0))`` with
    ``s = (t - t_0) / (t_0 - t_-1)`` (a turning vehicle follows an arc).

    With a single past pose (or equal timestamps) the vehicle is taken as standing still.
    """
    past_T = np.asarray(past_T_ref_sensor, dtype=np.float64)
    T0 = past_T[-1]
    out = np.repeat(T0[None], len(future_t_ns), axis=0)
    if len(past_T) < 2:
        return out
    dt = float(past_t_ns[-1] - past_t_ns[-2])
    if dt <= 0:
        return out
    xi = se3_log(invert(past_T[-2]) @ T0)
    for k, t in enumerate(future_t_ns):
        s = float(t - past_t_ns[-1]) / dt
        out[k] = T0 @ se3_exp(s * xi)
    return out
