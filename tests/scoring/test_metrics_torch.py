"""Issue 48: the metrics' searches in torch (pcfbench.metrics.torch_nn; a GPU's path, run here on the
CPU) give the reference's values, the golden numbers, and the numpy searches' answers."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrics import NAMES, close, make_ctx, slow, suite
from test_metrics_golden import GOLDEN, golden_pair

from pcfbench.errors import PcfbenchError
from pcfbench.metrics import backend
from pcfbench.metrics.backend import TorchSweepContext
from pcfbench.metrics.base import SweepContext
from pcfbench.metrics.torch_nn import TorchSearch
from pcfbench.testing import toy_world_sweeps


def torch_ctx(gt, origin, pred=None, depths=None) -> TorchSweepContext:
    c = make_ctx(gt, origin, pred, depths)
    return TorchSweepContext(c.gt_points, c.query, c._pred_points, c.pred_depths)


def score(ctx) -> dict[str, float]:
    out = {}
    for m in suite():
        out[m.name] = float("nan") if m.needs == "depths" and ctx.pred_depths is None else m(ctx)
    return out


def same(a: float, b: float) -> bool:
    return a == b or (np.isnan(a) and np.isnan(b))


@pytest.mark.parametrize("mode", ["points", "depths"])
def test_the_torch_searches_give_the_golden_numbers(mode):
    gt, origin, pred, depths = golden_pair()
    kw = {"pred": pred} if mode == "points" else {"depths": depths}
    got = score(torch_ctx(gt, origin, **kw))
    col = 1 if mode == "points" else 2
    for name, entry in GOLDEN.items():
        assert close(got[name], entry[col], rel=1e-9), f"{name} ({mode}): {got[name]!r} != golden {entry[col]!r}"


@pytest.mark.parametrize("seed", range(4))
def test_the_torch_searches_equal_the_reference_and_the_numpy_searches_on_random_pairs(seed):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(50, 400, 2)
    origin = rng.normal(0, 2, 3)
    gt = rng.normal(0, 15, (n, 3)) * [2, 2, 0.3]
    pred = gt[rng.integers(0, n, m)] + rng.normal(0, 0.5, (m, 3))
    if seed == 3:  # repeated points: ties everywhere, the search indexes each distinct one once
        pred = np.repeat(pred[: m // 10], 10, axis=0)
    t, c, ref = torch_ctx(gt, origin, pred), make_ctx(gt, origin, pred), slow(gt, origin, pred=pred)
    got, fast = score(t), score(c)
    for name in NAMES:
        assert close(got[name], ref[name], rel=1e-9), f"{name}: {got[name]!r} vs reference {ref[name]!r}"
        assert same(got[name], fast[name]), f"{name}: {got[name]!r} vs numpy {fast[name]!r}"
    np.testing.assert_array_equal(t._angular_nearest[0], c._angular_nearest[0])
    np.testing.assert_array_equal(t._angular_nearest[1], c._angular_nearest[1])
    np.testing.assert_array_equal(t.nn_gt_to_pred[0], c.nn_gt_to_pred[0])


def test_the_torch_searches_equal_the_numpy_searches_on_a_lidar_like_pair():
    """A toy street seen by a spinning LiDAR, the previous sweep as the forecast (copy-last):
    every metric bit for bit, and every angle-space answer."""
    from pcfbench.data import RayQuery
    from pcfbench.geometry import invert, transform_points

    pts, poses, _ = toy_world_sweeps(3, beams=8, azimuths=180)
    gt, pred = pts[2], transform_points(invert(poses[2]) @ poses[1], pts[1]).astype(np.float32)
    rel = gt.astype(np.float64)
    q = RayQuery(np.zeros(3), (rel / np.linalg.norm(rel, axis=1, keepdims=True)).astype(np.float32))
    t, c = TorchSweepContext(gt, q, pred, None), SweepContext(gt, q, pred, None)
    got, fast = score(t), score(c)
    assert all(same(got[n], fast[n]) for n in NAMES), (got, fast)
    for a, b in zip(t._angular_nearest, c._angular_nearest):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("periodic", [False, True])
def test_ties_in_an_angle_space_go_to_the_lowest_index(periodic):
    """A lattice: many points at exactly the nearest distance, more than the float32 pass keeps;
    every answer is the brute-force argmin of nn2d's float64 distance (ties to the lowest index)."""
    rng = np.random.default_rng(5)
    period = 8.0 if periodic else 0.0
    data = rng.integers(-12, 12, (900, 2)) * 0.25
    queries = rng.integers(-26, 26, (700, 2)) * 0.125
    got = TorchSearch("cpu").nearest_2d(data, queries, period)
    dx = np.abs(data[None, :, 0] - queries[:, None, 0])
    if periodic:
        dx = np.minimum(dx, period - dx)
    d2 = dx * dx + (data[None, :, 1] - queries[:, None, 1]) ** 2
    np.testing.assert_array_equal(got, d2.argmin(axis=1))


def test_3d_ties_and_distances_are_the_float64_ones():
    """Points on a 0.5 m lattice (ties) and coordinates that are not float32 values: the squared
    distance is the float64 minimum, the index the lowest at that distance."""
    rng = np.random.default_rng(8)
    points = rng.integers(-6, 6, (500, 3)) * 0.5 + np.array([1e-9, 0.0, 0.0])
    queries = rng.integers(-13, 13, (300, 3)) * 0.25
    d2, idx = TorchSearch("cpu").nearest_3d(queries, points)
    diff = queries[:, None, :] - points[None, :, :]
    full = (diff[..., 0] ** 2 + diff[..., 2] ** 2) + diff[..., 1] ** 2
    np.testing.assert_array_equal(d2, full.min(axis=1))
    np.testing.assert_array_equal(idx, full.argmin(axis=1))


def test_the_backend_is_chosen_by_name_and_by_the_gpu(monkeypatch):
    assert backend.context_class("numpy") is SweepContext
    assert backend.context_class("torch") is TorchSweepContext
    monkeypatch.setattr(backend, "cuda_present", lambda: False)
    assert backend.context_class("auto") is SweepContext
    monkeypatch.setattr(backend, "cuda_present", lambda: True)
    assert backend.context_class("auto") is TorchSweepContext
    with pytest.raises(PcfbenchError, match="metrics backend 'gpu' is not one of auto, numpy, torch"):
        backend.context_class("gpu")
