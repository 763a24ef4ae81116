"""pcfbench.metrics.rays: each fused kernel against the numpy chain it replaced in SweepTruth /
SweepContext, on LiDAR-like, random and edge inputs: equal values everywhere, and bit for bit (the
sign of zeros too) in what reaches a metric, the kept rays. (numpy's own maximum and minimum
return either zero for -0.0 against 0.0, depending on where the element falls in its SIMD loop.)"""

from __future__ import annotations

import numpy as np
import pytest

from pcfbench.boxes import Box, ray_box_interval
from pcfbench.metrics import rays
from pcfbench.protocol import ROI
from pcfbench.testing import toy_world_sweeps


def numpy_chain(points, origin, box, min_range, depth):
    """The expressions SweepTruth and SweepContext evaluated before the kernels."""
    p64 = np.ascontiguousarray(points, dtype=np.float64)
    inside = box.contains(p64)
    rel = p64 - origin
    r = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    with np.errstate(divide="ignore", invalid="ignore"):
        dirs = np.where(r[:, None] > 0, rel / r[:, None], 0.0)
    t_enter, t_exit = ray_box_interval(origin, dirs, box)
    meets = (t_enter <= t_exit) & (r > 0)
    clamped = np.clip(r, t_enter, np.maximum(t_exit, t_enter))
    with np.errstate(invalid="ignore"):
        kept = meets & (clamped - t_enter > min_range)
    p_c = np.clip(depth[kept], t_enter[kept], t_exit[kept])
    g_c = clamped[kept]
    err = np.abs(g_c - p_c)
    return p64, rel, r, inside, t_enter, t_exit, meets, clamped, kept, err, err / (g_c - t_enter[kept])


def kernels(points, origin, box, min_range, depth):
    lo, hi = np.asarray(box.lo, dtype=np.float64), np.asarray(box.hi, dtype=np.float64)
    p64, rel, r, inside = rays.lift(points, origin, lo, hi)
    t_enter, t_exit, meets, clamped, kept = rays.clamp_rays(rel, r, origin, lo, hi, min_range)
    return (p64, rel, r, inside, t_enter, t_exit, meets, clamped, kept) + rays.ray_errors(depth, t_enter, t_exit,
                                                                                          clamped, kept)


def _cases():
    rng = np.random.default_rng(0)
    pts, poses, _ = toy_world_sweeps(2, beams=16, azimuths=360)
    yield "lidar", pts[1], poses[1][:3, 3].astype(np.float64), ROI
    odd = rng.normal(0, 40, (20000, 3)).astype(np.float32)
    odd[:50] = 0.0  # zero range at the origin
    odd[50:100, 2] = 0.0  # directions parallel to a slab
    odd[100:150, :2] = 0.0
    odd[150:200] = odd[150:200] * 1e-4  # within the minimum range
    yield "origin at zero", odd, np.zeros(3), ROI
    yield "origin on a face", odd, np.array([float(ROI.lo[0]), 0.0, 0.0]), ROI
    yield "origin outside", odd, np.array([150.0, -3.0, 0.5]), ROI
    box = Box((-10.0, -5.0, -2.0), (30.0, 5.0, 4.0))
    wide = rng.uniform(-80, 80, (20000, 3))
    wide[:300] = rng.uniform(-10, 30, (300, 3))
    wide[:100, 0], wide[100:200, 1], wide[200:300, 2] = -10.0, 5.0, 4.0  # on the box's faces: inside
    yield "float64, other box", wide, np.array([1.25, 2.5, -1.0]), box
    yield "empty", np.zeros((0, 3), np.float32), np.zeros(3), ROI


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: c[0])
def test_kernels_equal_the_numpy_chain_bit_for_bit(case):
    _, points, origin, box = case
    depth = np.random.default_rng(1).uniform(0, 120, points.shape[0])
    depth[::7] = 0.0
    want = numpy_chain(points, origin, box, 0.01, depth)
    got = kernels(points, origin, box, 0.01, depth)
    names = ("p64", "rel", "ranges", "inside", "t_enter", "t_exit", "meets", "clamped", "kept", "err", "relerr")
    for name, a, b in zip(names, want, got):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(b, a, err_msg=name)
    kept = want[8]
    for name, a, b in [("t_enter", want[4][kept], got[4][kept]), ("t_exit", want[5][kept], got[5][kept]),
                       ("clamped", want[7][kept], got[7][kept]), ("err", want[9], got[9]), ("relerr", want[10], got[10])]:
        assert np.array_equal(np.signbit(a), np.signbit(b)), name


def test_kept_range_groups_hand_computed():
    """Rays at 0.5, 12, 3 and 25 m straight ahead inside the ROI, one of them too short to keep
    (under the minimum range): bins of 10 m hold the kept rays' positions in order."""
    from pcfbench.data import RayQuery
    from pcfbench.metrics.base import SweepTruth

    gt = np.array([[0.5, 0, 0], [12, 0, 0], [3, 0, 0], [25, 0, 0], [9.5, 0, 0]], np.float32)
    dirs = (gt / np.linalg.norm(gt, axis=1, keepdims=True)).astype(np.float32)
    truth = SweepTruth(gt, RayQuery(np.zeros(3), dirs), min_range_m=1.0)
    assert truth.ray_kept.tolist() == [False, True, True, True, True]
    groups = truth.kept_range_groups(10.0)
    # kept rays: 12, 3, 25, 9.5 m at positions 0, 1, 2, 3
    assert [(k, p.tolist()) for k, p in groups] == [(0, [1, 3]), (1, [0]), (2, [2])]
    assert truth.kept_range_groups(10.0) is groups  # computed once per width
    assert [k for k, _ in truth.kept_range_groups(20.0)] == [0, 1]


@pytest.mark.parametrize("index", [8, 14])
def test_kept_range_groups_select_what_the_bin_masks_select(index):
    """Against the masks ``ranges.sweep_bins`` used before: the same rays in the same order per
    bin, so the stored sums are bit for bit what they were."""
    from pcfbench.metrics.base import SweepTruth
    from pcfbench.testing import toy_sample

    sample, truth_ = toy_sample("kitti-1s", index)
    for gt, query in zip(truth_.future_points_ref, sample.queries):
        truth = SweepTruth(gt, query)
        b = np.floor(truth.gt_ranges[truth.ray_kept] / 10.0).astype(np.int64)
        assert len(np.unique(b)) >= 4
        errors = np.random.default_rng(index).random(len(b))
        got = truth.kept_range_groups(10.0)
        assert [k for k, _ in got] == np.unique(b).tolist()
        for k, positions in got:
            np.testing.assert_array_equal(errors[positions], errors[b == k])
            assert np.sum(errors[positions]) == np.sum(errors[b == k])
