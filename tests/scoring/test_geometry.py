import numpy as np
import pytest

from pcfbench.geometry import (
    constant_velocity_poses, hat, invert, is_se3, quat_wxyz_to_rotation, rotate_vectors, rotation_to_quat_wxyz, se3,
    se3_exp, se3_log, so3_exp, so3_log, transform_points, yaw_transform,
)
from pcfbench.protocol import ROI
from pcfbench.boxes import Box, EgoBox, clamp_ranges_to_box, ray_box_interval


def random_se3(rng):
    q = rng.normal(size=4)
    return se3(quat_wxyz_to_rotation(q), rng.normal(size=3) * 10)


def test_invert_matches_numpy_inverse():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = random_se3(rng)
        assert np.allclose(invert(T), np.linalg.inv(T), atol=1e-12)
        assert is_se3(T)


def test_transform_points_hand_computed():
    T_a_b = yaw_transform(np.pi / 2, (1.0, 2.0, 3.0))  # b's x axis is a's y axis
    pts_b = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=np.float32)
    pts_a = transform_points(T_a_b, pts_b)
    assert pts_a.dtype == np.float32
    assert np.allclose(pts_a, [[1.0, 3.0, 3.0], [0.0, 2.0, 3.0]], atol=1e-6)
    assert np.allclose(rotate_vectors(T_a_b, pts_b), [[0, 1, 0], [-1, 0, 0]], atol=1e-6)


def test_quaternion_round_trip_and_hand_case():
    # 90 degrees about z: w = cos(45), z = sin(45)
    R = quat_wxyz_to_rotation([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        assert np.allclose(rotation_to_quat_wxyz(quat_wxyz_to_rotation(q)), q, atol=1e-9)
    with pytest.raises(ValueError, match="zero norm"):
        quat_wxyz_to_rotation([0, 0, 0, 0])


def test_is_se3_rejects_scaled_and_nan():
    T = np.eye(4)
    T[0, 0] = 2
    assert not is_se3(T)
    T = np.eye(4)
    T[0, 3] = np.nan
    assert not is_se3(T)


def test_ego_box_inclusive():
    box = EgoBox(-2.0, 3.5, -1.55, 1.55)
    pts = np.array([[-2.0, 0, 0], [3.5, 1.55, 5], [3.51, 0, 0], [0, -1.56, 0]], dtype=np.float32)
    assert box.inside(pts).tolist() == [True, True, False, False]
    assert len(box.remove(pts)) == 2


def test_roi_contains_is_inclusive():
    pts = np.array([[70, -70, 4.5], [70.001, 0, 0], [0, 0, -4.6]])
    assert ROI.contains(pts).tolist() == [True, False, False]


def test_ray_box_interval_hand_cases():
    box = Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    d = np.array([[1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    # origin inside: enter at 0, leave at 1
    t0, t1 = ray_box_interval(np.zeros(3), d[:2], box)
    assert np.allclose(t0, 0) and np.allclose(t1, 1)
    # origin outside, looking at the box: enters at 2, leaves at 4
    t0, t1 = ray_box_interval(np.array([-3.0, 0, 0]), d[2:], box)
    assert np.allclose(t0, 2) and np.allclose(t1, 4)
    # origin outside, looking away: misses
    t0, t1 = ray_box_interval(np.array([3.0, 0, 0]), d[2:], box)
    assert t0[0] > t1[0]
    # parallel ray outside a slab misses
    t0, t1 = ray_box_interval(np.array([0, 5.0, 0]), d[:1], box)
    assert t0[0] > t1[0]


def test_clamp_ranges_to_box():
    box = Box((-10.0, -10.0, -10.0), (10.0, 10.0, 10.0))
    d = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    start, end, kept = clamp_ranges_to_box(np.zeros(3), d, np.array([5.0, 25.0]), box)
    assert kept.all() and np.allclose(start, 0) and np.allclose(end, [5.0, 10.0])
    # origin outside at x=-20: a point at range 5 (x=-15) is before the box -> zero length
    start, end, kept = clamp_ranges_to_box(np.array([-20.0, 0, 0]), d, np.array([5.0, 25.0]), box)
    assert np.allclose(start, 10) and np.allclose(end, [10.0, 25.0]) and kept.all()


# ---------------------------------------------------------------- SE(3) exponential and logarithm


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    """The 4x4 matrix [[hat(omega), rho], [0, 0]] whose matrix exponential se3_exp is."""
    M = np.zeros((4, 4))
    M[:3, :3] = hat(xi[3:])
    M[:3, 3] = xi[:3]
    return M


#: rotation angles (radians) across every branch and its edges: zero, tiny (where 1 - cos has
#: no digits left), the series threshold, ordinary, and up to pi from below
ANGLES = [0.0, 1e-13, 1e-10, 1e-8, 1e-6, 1e-4, 0.9999e-2, 1.0001e-2, 0.05, 0.7, 2.0, 2.6, 2.7, 3.0,
          np.pi - 1e-3, np.pi - 1e-5, np.pi - 1e-7, np.pi - 1e-9, np.pi - 1e-12, np.pi]


def random_twists(rng, angles=ANGLES, n=4):
    for th in angles:
        for _ in range(n):
            axis = rng.normal(size=3)
            yield np.concatenate([rng.normal(0, 5, 3), th * axis / np.linalg.norm(axis)])


def test_se3_hand_computed_quarter_turn():
    """A quarter turn about z at unit body speed along x: a quarter circle of radius 1 about
    (0, 1) from the origin to (1, 1), plus 1 m up. By hand, J(omega) restricted to xy is
    (2 / pi) [[1, -1], [1, 1]], so t = J rho = (1, 1, 1) for rho = (pi / 2, 0, 1)."""
    T = yaw_transform(np.pi / 2, (1.0, 1.0, 1.0))
    xi = np.array([np.pi / 2, 0.0, 1.0, 0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(se3_log(T), xi, rtol=0, atol=1e-15)
    np.testing.assert_allclose(se3_exp(xi), T, rtol=0, atol=1e-15)
    np.testing.assert_allclose(so3_exp([0.0, 0.0, np.pi / 2]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=2e-16)
    np.testing.assert_array_equal(se3_exp(np.zeros(6)), np.eye(4))
    np.testing.assert_array_equal(se3_log(np.eye(4)), np.zeros(6))


def test_se3_exp_matches_scipy_expm_of_the_twist_matrix():
    from scipy.linalg import expm

    rng = np.random.default_rng(2)
    for xi in random_twists(rng):
        scale = 1 + np.linalg.norm(xi[:3])
        np.testing.assert_allclose(se3_exp(xi), expm(twist_matrix(xi)), rtol=0, atol=1e-14 * scale, err_msg=str(xi))


def test_se3_log_matches_scipy_logm_away_from_pi():
    from scipy.linalg import logm

    rng = np.random.default_rng(3)
    for xi in random_twists(rng, [a for a in ANGLES if a < 3.0]):
        T = se3_exp(xi)
        ref = np.real(logm(T))
        np.testing.assert_allclose(twist_matrix(se3_log(T)), ref, rtol=0, atol=1e-13 * (1 + np.linalg.norm(xi[:3])),
                                   err_msg=str(xi))


def test_se3_round_trips_near_zero_and_near_pi():
    rng = np.random.default_rng(4)
    for xi in random_twists(rng, n=10):
        T = se3_exp(xi)
        back = se3_log(T)
        scale = 1 + np.linalg.norm(xi[:3])
        # exp(log(T)) = T everywhere, pi included (where log picks one of two opposite axes)
        np.testing.assert_allclose(se3_exp(back), T, rtol=0, atol=1e-14 * scale, err_msg=str(xi))
        if np.linalg.norm(xi[3:]) < np.pi - 1e-9:  # below pi the twist is unique: log(exp(xi)) = xi
            np.testing.assert_allclose(back, xi, rtol=0, atol=1e-14 * scale, err_msg=str(xi))
        np.testing.assert_allclose(so3_exp(so3_log(T[:3, :3])), T[:3, :3], rtol=0, atol=1e-14)
    for _ in range(50):  # random rigid transforms (any rotation): exp(log(T)) = T
        T = random_se3(rng)
        np.testing.assert_allclose(se3_exp(se3_log(T)), T, rtol=0, atol=1e-14 * (1 + np.abs(T).max()))
        assert np.linalg.norm(se3_log(T)[3:]) <= np.pi


def test_se3_log_exp_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        xi = np.concatenate([rng.normal(0, 3, 3), rng.normal(0, 0.8, 3)])
        np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)
    np.testing.assert_allclose(se3_exp(np.zeros(6)), np.eye(4))


def test_constant_velocity_follows_an_arc_with_uneven_timestamps():
    xi = np.array([8.0, 0.2, 0.0, 0.0, 0.01, 0.3])  # per second: forward, turning
    t_past = np.array([-0.81, -0.6, -0.39, -0.2, 0.0])
    t_fut = np.array([0.2, 0.41, 0.6, 1.0, 3.0])
    past = np.stack([se3_exp(t * xi) for t in t_past])
    got = constant_velocity_poses(past, (t_past * 1e9).astype(np.int64), (t_fut * 1e9).astype(np.int64))
    for g, t in zip(got, t_fut):
        np.testing.assert_allclose(g, se3_exp(t * xi), atol=1e-9)
    # a single past pose: standing still
    still = constant_velocity_poses(past[-1:], np.array([0]), np.array([10**8]))
    np.testing.assert_allclose(still[0], past[-1])
