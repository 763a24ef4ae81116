import numpy as np
import pytest

from pcfbench.geometry import (
    invert, is_se3, quat_wxyz_to_rotation, rotate_vectors, rotation_to_quat_wxyz, se3, transform_points, yaw_transform,
)
from pcfbench.roi import ROI, Box, EgoBox, clamp_ranges_to_box, ray_box_interval


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
