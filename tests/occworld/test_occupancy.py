"""Occupancy labelling from LiDAR rays (methods/occworld/occupancy.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occupancy import FREE, OCCUPIED, UNKNOWN, OccGrid, label_occupancy


def _wall_scene():
    """A 20 x 4 x 2 m grid of 0.5 m voxels, the sensor at x = 0.25; a wall of returns at
    x = 5.25 (voxel 10) facing it; a box at x = 8.25 (voxel 16) behind the wall."""
    grid = OccGrid.over((0.0, 0.0, 0.0), (20.0, 4.0, 2.0), (40, 8, 4))
    origin = np.array([0.25, 2.0, 1.0])
    ys, zs = np.meshgrid(np.arange(8) * 0.5 + 0.25, np.arange(4) * 0.5 + 0.25, indexing="ij")
    wall = np.stack([np.full(ys.size, 5.25), ys.ravel(), zs.ravel()], axis=1)
    return grid, origin, wall


def test_wall_hides_the_box_behind_it():
    grid, origin, wall = _wall_scene()
    lab = label_occupancy(grid, wall, origin)
    assert (lab[10] == OCCUPIED).all()  # every wall voxel has a return
    # the sensor's rays fan out from (0, 4, 2) to every wall voxel: the voxels they cross are free
    assert lab[0, 4, 2] == FREE and lab[9, 4, 2] == FREE and lab[5, 3, 1] == FREE
    # nothing behind the wall was seen: the box's voxels (16, 3..4, 1..2), whose returns the wall
    # hides from the sensor, stay unknown, as does everything else past the wall
    assert (lab[16, 3:5, 1:3] == UNKNOWN).all() and (lab[11:] == UNKNOWN).all()
    # occupied wins: a return on the box (as if seen through a gap) frees the voxels its ray
    # crosses, and the wall voxel it passes through stays occupied (other rays ended there)
    box = np.array([[8.25, 2.25, 1.25]])
    both = label_occupancy(grid, np.concatenate([wall, box]), origin)
    assert both[16, 4, 2] == OCCUPIED and both[13, 4, 2] == FREE and (both[10] == OCCUPIED).all()


def test_free_and_occupied_on_one_axis_ray():
    grid = OccGrid.over((0.0, 0.0, 0.0), (10.0, 1.0, 1.0), (10, 1, 1))
    lab = label_occupancy(grid, np.array([[6.5, 0.5, 0.5]]), np.array([0.5, 0.5, 0.5]))
    assert lab[:, 0, 0].tolist() == [FREE] * 6 + [OCCUPIED] + [UNKNOWN] * 3


def test_ray_from_outside_and_past_the_grid():
    grid = OccGrid.over((0.0, 0.0, 0.0), (10.0, 1.0, 1.0), (10, 1, 1))
    # from x = -5 to x = 20: crosses the whole grid, ends outside: all free, nothing occupied
    lab = label_occupancy(grid, np.array([[20.0, 0.5, 0.5]]), np.array([-5.0, 0.5, 0.5]))
    assert (lab == FREE).all()


def _reference(grid: OccGrid, points, origin, step: float) -> tuple[set, set]:
    """Slow and obviously correct: the voxels of points sampled every ``step`` metres along each
    ray (free), and the voxels of the points (occupied)."""
    lo, vs, n = np.array(grid.lo), np.array(grid.voxel), np.array(grid.dims)
    free, occ = set(), set()
    for p in points:
        r = np.linalg.norm(p - origin)
        t = np.arange(0.0, r, step)
        q = np.floor((origin + (p - origin)[None] * (t / r)[:, None] - lo) / vs).astype(int)
        q = q[((q >= 0) & (q < n)).all(axis=1)]
        free.update(map(tuple, q))
        k = np.floor((p - lo) / vs).astype(int)
        if ((k >= 0) & (k < n)).all():
            occ.add(tuple(k))
    return free - occ, occ


def _segment_length_in(grid: OccGrid, origin, p, key) -> float:
    lo = np.array(grid.lo) + np.array(key) * np.array(grid.voxel)
    hi = lo + np.array(grid.voxel)
    d = p - origin
    t0, t1 = 0.0, 1.0
    for a in range(3):
        if d[a] == 0:
            if not lo[a] <= origin[a] <= hi[a]:
                return 0.0
            continue
        ta, tb = (lo[a] - origin[a]) / d[a], (hi[a] - origin[a]) / d[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return max(0.0, t1 - t0) * float(np.linalg.norm(d))


def test_agrees_with_dense_sampling_on_random_rays():
    rng = np.random.default_rng(3)
    grid = OccGrid.over((-3.0, -3.0, -1.0), (3.0, 3.0, 1.0), (12, 12, 5))  # anisotropic: 0.5 x 0.5 x 0.4
    origin = np.array([0.1, -0.2, 0.05])
    points = rng.uniform(-4.0, 4.0, (150, 3)) * np.array([1.0, 1.0, 0.4])
    step = 1e-3
    lab = label_occupancy(grid, points, origin)
    free_ref, occ_ref = _reference(grid, points, origin, step)
    occ = set(map(tuple, np.argwhere(lab == OCCUPIED)))
    free = set(map(tuple, np.argwhere(lab == FREE)))
    assert occ == occ_ref
    assert free_ref <= free
    # what sampling missed, the rays only clip: some ray crosses it for less than the sampling step
    for key in free - free_ref:
        assert min(_segment_length_in(grid, origin, p, key) for p in points) < 2 * step, key
    assert len(free) > 100  # the test exercises many voxels


def test_per_point_origins():
    grid = OccGrid.over((0.0, 0.0, 0.0), (10.0, 1.0, 1.0), (10, 1, 1))
    pts = np.array([[2.5, 0.5, 0.5], [7.5, 0.5, 0.5]])
    lab = label_occupancy(grid, pts, np.array([[0.5, 0.5, 0.5], [9.5, 0.5, 0.5]]))
    assert lab[:, 0, 0].tolist() == [FREE, FREE, OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED, FREE, FREE]


def test_bad_input_is_one_error():
    grid = OccGrid.over((0.0, 0.0, 0.0), (10.0, 1.0, 1.0), (10, 1, 1))
    with pytest.raises(PcfbenchError, match="origins"):
        label_occupancy(grid, np.zeros((4, 3)), np.zeros((2, 3)))
    with pytest.raises(PcfbenchError, match="finite"):
        label_occupancy(grid, np.full((1, 3), np.nan), np.zeros(3))
