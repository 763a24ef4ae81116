"""Property tests: the fast metrics agree with the brute-force float64 references."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_metrics import NAMES, close, fast, slow

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _cloud(rng: np.random.Generator, n: int, spread: float, origin: np.ndarray) -> np.ndarray:
    """Points around ``origin`` out to ``spread`` metres, some beyond the ROI, some behind the seam."""
    kind = rng.integers(3)
    if kind == 0:  # uniform box
        pts = rng.uniform([-spread, -spread, -spread / 8], [spread, spread, spread / 8], (n, 3))
    elif kind == 1:  # ray-aligned: ranges along random directions, as a LiDAR sees them
        az = rng.uniform(-np.pi, np.pi, n)
        el = rng.uniform(-0.4, 0.1, n)
        r = rng.uniform(0.5, spread, n)
        pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    else:  # clustered near the +-pi azimuth seam
        pts = np.stack([-rng.uniform(1, spread, n), rng.normal(0, 1.0, n), rng.normal(0, 1.0, n)], 1)
    return (origin + pts).astype(np.float32)


def _case(seed: int, n_gt: int, n_pred: int, spread: float, outside: bool):
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-5, 5, 3) + (np.array([-85.0, 0, 0]) if outside else 0.0)
    gt = _cloud(rng, n_gt, spread, origin)
    pred = _cloud(rng, n_pred, spread, origin)
    return rng, origin, gt, pred


def _assert_agree(f: dict, s: dict) -> None:
    for name in NAMES:
        assert close(f[name], s[name], rel=1e-6, abs_=1e-9), f"{name}: fast {f[name]!r} vs reference {s[name]!r}"


case = dict(
    seed=st.integers(0, 2**32 - 1),
    n_gt=st.integers(1, 80),
    n_pred=st.integers(0, 80),
    spread=st.sampled_from([3.0, 40.0, 120.0]),
    outside=st.booleans(),
)


@SETTINGS
@given(**case)
def test_point_forecasts_match_reference(seed, n_gt, n_pred, spread, outside):
    _, origin, gt, pred = _case(seed, n_gt, n_pred, spread, outside)
    _assert_agree(fast(gt, origin, pred=pred), slow(gt, origin, pred=pred))


@SETTINGS
@given(**case)
def test_depth_forecasts_match_reference(seed, n_gt, n_pred, spread, outside):
    rng, origin, gt, _ = _case(seed, n_gt, n_pred, spread, outside)
    depths = rng.uniform(0, 1.5 * spread, n_gt).astype(np.float32)
    _assert_agree(fast(gt, origin, depths=depths), slow(gt, origin, depths=depths))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 400))
def test_larger_ray_aligned_clouds_match_reference(seed, n):
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-2, 2, 3)
    gt, pred = _cloud(rng, n, 90.0, origin), _cloud(rng, n + 7, 90.0, origin)
    _assert_agree(fast(gt, origin, pred=pred), slow(gt, origin, pred=pred))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 300), m=st.integers(1, 120), periodic=st.booleans(),
       layout=st.sampled_from(["uniform", "clustered", "line", "far"]))
def test_nearest_2d_matches_brute_force(seed, k, m, periodic, layout):
    """The grid (with its k-d tree fallback) finds the brute-force nearest distance, wrap included."""
    from pcfbench.metrics.nn import nearest_2d

    rng = np.random.default_rng(seed)
    lo, hi = (-np.pi, np.pi)
    if layout == "uniform":
        data = rng.uniform([lo, -1], [hi, 1], (k, 2))
    elif layout == "clustered":
        data = np.clip(rng.normal([rng.uniform(lo, hi), 0], 0.05, (k, 2)), lo, hi)
    elif layout == "line":  # degenerate: all on one elevation
        data = np.stack([rng.uniform(lo, hi, k), np.full(k, 0.3)], 1)
    else:  # data in a corner, queries everywhere: most need many rings or the fallback
        data = rng.uniform([hi - 0.2, 0.9], [hi, 1.0], (k, 2))
    queries = rng.uniform([lo, -1.5], [hi, 1.5], (m, 2))
    idx = nearest_2d(data, queries, period=2 * np.pi if periodic else 0.0)
    dx = np.abs(queries[:, None, 0] - data[None, :, 0])
    if periodic:
        dx = np.minimum(dx, 2 * np.pi - dx)
    d2 = dx**2 + (queries[:, None, 1] - data[None, :, 1]) ** 2
    got = d2[np.arange(m), idx]
    np.testing.assert_allclose(got, d2.min(axis=1), rtol=1e-12, atol=0)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 50))
def test_ray_box_interval_matches_scalar_slab_walk(seed, n):
    from pcfbench.metrics.reference import segment_in_box
    from pcfbench.protocol import ROI
    from pcfbench.boxes import ray_box_interval

    rng = np.random.default_rng(seed)
    o = rng.uniform(-100, 100, 3) * rng.integers(0, 2, 3)  # some coordinates exactly 0
    d = rng.normal(size=(n, 3)) * rng.integers(0, 2, (n, 3))  # some components exactly 0
    d[~d.any(axis=1), 0] = 1.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t0, t1 = ray_box_interval(o, d, ROI)
    for i in range(n):
        seg = segment_in_box(o, d[i], ROI)
        if seg is None:
            assert not t0[i] <= t1[i]
        else:
            np.testing.assert_allclose([t0[i], t1[i]], seg, rtol=1e-12, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 300), chunk=st.integers(1, 50))
def test_nearest_angles_in_pieces_match_whole_searches(seed, n, chunk):
    """Sharing the grid passes out in pieces changes no answer (index, ties included)."""
    from pcfbench.metrics import nn

    rng = np.random.default_rng(seed)
    origin = rng.uniform(-2, 2, 3)
    gt, pred = _cloud(rng, n, 60.0, origin), _cloud(rng, n + 3, 60.0, origin)
    gt_rel, pred_rel = gt.astype(np.float64) - origin, pred.astype(np.float64) - origin
    old = nn.CHUNK
    nn.CHUNK = chunk
    try:
        a, b = nn.nearest_angles(pred_rel, gt_rel)
    finally:
        nn.CHUNK = old
    np.testing.assert_array_equal(a, nn.nearest_angle_4docc(pred_rel, gt_rel))
    np.testing.assert_array_equal(b, nn.nearest_angle_wrapped(pred_rel, gt_rel))


def test_nearest_2d_ties_go_to_the_lowest_index():
    """Exact ties on a lattice (coordinates exact in binary): the brute-force argmin's index."""
    from pcfbench.metrics.nn import nearest_2d

    rng = np.random.default_rng(3)
    data = rng.integers(-8, 8, (400, 2)) * 0.25
    queries = rng.integers(-20, 20, (500, 2)) * 0.125
    idx = nearest_2d(data, queries)
    d2 = ((queries[:, None, :] - data[None, :, :]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(idx, d2.argmin(axis=1))
