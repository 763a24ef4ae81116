"""Degenerate forecasts (repeated points, every point at one spot) are searched as fast as any
other and give exactly the answers of the plain searches (pcfbench.metrics.nn, ``distinct``)."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrics import NAMES, close, fast, slow


def _street(rng: np.random.Generator, n: int) -> np.ndarray:
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(-0.4, 0.1, n)
    r = rng.uniform(2.0, 60.0, n)
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1).astype(np.float32)


def test_points_at_one_spot_are_indexed_once():
    """3,000 copies of one point: the k-d tree and both angle grids hold one point, so a query
    scans one point instead of all of them (the quadratic search the old code did)."""
    from pcfbench.metrics.nn import Index, _Search2D, angles_4docc

    rng = np.random.default_rng(0)
    spot = np.tile(rng.normal(size=(1, 3)) * 10, (3000, 1))
    assert Index(spot).tree.n == 1
    assert _Search2D(angles_4docc(spot), angles_4docc(rng.normal(size=(50, 3))), 0.0).grid.n == 1
    on_a_ray = spot * rng.uniform(0.5, 2.0, (3000, 1))  # distinct points, one direction: one angle
    assert _Search2D(angles_4docc(on_a_ray), angles_4docc(spot[:5]), 0.0).grid.n <= 4


def test_distinct_points_are_indexed_as_they_are():
    from pcfbench.metrics.nn import Index, distinct

    pts = np.random.default_rng(1).normal(size=(40_000, 3))
    assert distinct(pts) is None
    assert Index(pts).tree.n == 40_000


@pytest.mark.parametrize("n", [300, 40_000])  # the full pass, and the random draw before it
def test_distinct_finds_the_first_of_each_set(n):
    from pcfbench.metrics.nn import distinct

    rng = np.random.default_rng(n)
    pts = rng.normal(size=(n, 3))
    pts[rng.integers(0, n, n // 2)] = pts[7]  # a large set
    pts[n - 5:] = pts[n - 6]  # a small one at the end
    pts[3, 0] = -0.0
    pts[4] = pts[3] * (1, 1, 1)
    pts[4, 0] = 0.0  # -0.0 and 0.0 are the same coordinate
    first = distinct(pts, np.random.default_rng(0))
    _, want = np.unique(pts + 0.0, axis=0, return_index=True)
    np.testing.assert_array_equal(first, np.sort(want))


def test_index_answers_match_brute_force_with_repeated_points():
    """Distances bit-identical to the plain tree's; the returned point is at that distance; a
    mask that hides the first of a set still returns the set through an unmasked member."""
    from pcfbench.metrics import nn

    rng = np.random.default_rng(2)
    pts = np.repeat(rng.normal(size=(60, 3)), 50, axis=0)[rng.permutation(3000)]
    queries = rng.normal(size=(500, 3))
    d2, idx = nn.Index(pts).query(queries)
    np.testing.assert_array_equal(d2, ((queries - pts[idx]) ** 2)[:, [0, 2, 1]].sum(axis=1))
    brute = ((queries[:, None, :] - pts[None]) ** 2).sum(axis=2).min(axis=1)
    np.testing.assert_allclose(d2, brute, rtol=1e-12, atol=0)
    mask = rng.random(3000) < 0.7
    d2m, idxm = nn.Index(pts).query(queries, mask=mask)
    assert not mask[idxm].any()
    np.testing.assert_allclose(d2m, ((queries[:, None, :] - pts[None][:, ~mask]) ** 2).sum(axis=2).min(axis=1),
                               rtol=1e-12, atol=0)


def test_nearest_2d_with_repeated_points_keeps_ties_at_the_lowest_index():
    from pcfbench.metrics.nn import nearest_2d

    rng = np.random.default_rng(3)
    data = np.repeat(rng.integers(-8, 8, (40, 2)) * 0.25, 30, axis=0)[rng.permutation(1200)]
    queries = rng.integers(-20, 20, (400, 2)) * 0.125
    for period in (0.0, 8.0):
        dx = np.abs(queries[:, None, 0] - data[None, :, 0])
        if period:
            dx = np.minimum(dx, period - dx)
        d2 = dx**2 + (queries[:, None, 1] - data[None, :, 1]) ** 2
        np.testing.assert_array_equal(nearest_2d(data, queries, period=period), d2.argmin(axis=1))


@pytest.mark.parametrize("layout", ["one spot", "repeated", "one ray"])
def test_degenerate_forecasts_score_as_the_plain_searches_and_the_reference(layout, monkeypatch):
    """Every metric: bit-identical to the searches without set detection (``distinct`` forced to
    None, the old code path) and within rounding of the brute-force reference."""
    from pcfbench.metrics import nn

    rng = np.random.default_rng(4)
    origin = np.array([0.5, -0.3, 1.7])
    gt = origin.astype(np.float32) + _street(rng, 2000)
    if layout == "one spot":
        pred = np.tile(gt[:1] + 0.25, (2000, 1))
    elif layout == "repeated":
        pred = np.repeat(gt[::40] + 0.1, 40, axis=0)
    else:
        pred = (origin + (gt[:1] - origin) * rng.uniform(0.2, 3.0, (2000, 1))).astype(np.float32)
    new = fast(gt, origin, pred=pred)
    monkeypatch.setattr(nn, "distinct", lambda points, rng=None: None)
    old = fast(gt, origin, pred=pred)
    ref = slow(gt, origin, pred=pred)
    for name in NAMES:
        assert new[name] == old[name] or (np.isnan(new[name]) and np.isnan(old[name])), name
        assert close(new[name], ref[name], rel=1e-6, abs_=1e-9), f"{name}: {new[name]!r} vs reference {ref[name]!r}"


@pytest.mark.parametrize("periodic", [False, True])
@pytest.mark.parametrize("layout", ["lattice", "cluster", "few"])
def test_the_tree_path_of_crowded_angle_searches_is_the_brute_force_argmin(periodic, layout, monkeypatch):
    """Forced onto the k-d tree path, every answer is the brute-force argmin of nn2d's
    distance, ties (a lattice has many) to the lowest index; wrap-around included."""
    from pcfbench.metrics import nn

    monkeypatch.setattr(nn, "TREE_MIN_POINTS", 1)
    monkeypatch.setattr(nn, "DENSE_SCAN", -1.0)
    rng = np.random.default_rng(5)
    period = (8.0 if layout == "lattice" else 2 * np.pi) if periodic else 0.0  # 8: exact in binary, as the lattice
    if layout == "lattice":
        data = rng.integers(-12, 12, (900, 2)) * 0.25
        queries = rng.integers(-26, 26, (700, 2)) * 0.125
    elif layout == "cluster":
        data = np.clip(rng.normal([3.1, 0.2], 1e-4, (900, 2)), -np.pi, np.pi)
        queries = rng.uniform([-np.pi, -1.5], [np.pi, 1.5], (700, 2))
    else:  # fewer points than candidates
        data = rng.uniform([-np.pi, -1], [np.pi, 1], (5, 2))
        queries = rng.uniform([-np.pi, -1.5], [np.pi, 1.5], (300, 2))
    search = nn._Search2D(data, queries, period)
    assert search.crowded
    dx = np.abs(data[None, :, 0] - queries[:, None, 0])
    if periodic:
        dx = np.minimum(dx, period - dx)
    d2 = dx * dx + (data[None, :, 1] - queries[:, None, 1]) ** 2
    np.testing.assert_array_equal(search.finish(search.grid_pass()), d2.argmin(axis=1))


def test_a_tight_cluster_far_from_the_queries_takes_the_tree_path():
    """Distinct forecast points within a millimetre of one spot: the grid would scan them all for
    every ray (seconds on a few thousand points); the search is marked crowded instead."""
    from pcfbench.metrics.nn import _Search2D, angles_4docc, angles_az_el

    rng = np.random.default_rng(6)
    pred = np.array([[10.0, 5.0, -1.0]]) + rng.normal(0, 1e-3, (3000, 3))
    gt = _street(rng, 3000).astype(np.float64)
    assert _Search2D(angles_4docc(pred), angles_4docc(gt), 0.0).crowded
    assert _Search2D(angles_az_el(pred), angles_az_el(gt), 2 * np.pi).crowded
    assert not _Search2D(angles_4docc(gt[::-1] * 1.01), angles_4docc(gt), 0.0).crowded  # a normal pair


def test_a_few_crowded_cells_among_normal_ones_keep_the_grid():
    """A real sweep's forecast seen from a moved sensor packs some of its points into a few
    cells (hundreds in one, on KITTI) while most of the queries lie among normal ones: the grid
    scans few points per query there, so the search stays on the grid (the k-d tree path took
    5-6x its time on real KITTI pairs), with the same answers."""
    from pcfbench.metrics import nn

    rng = np.random.default_rng(9)
    data = rng.uniform([-1.0, -1.0], [1.0, 1.0], (6000, 2))
    data[:800] = rng.normal([0.2, 0.3], 1e-3, (800, 2))  # 800 points in one or two cells
    queries = rng.uniform([-1.0, -1.0], [1.0, 1.0], (4000, 2))
    search = nn._Search2D(data, queries, 0.0)
    assert int(np.diff(search.grid.fine[0]).max()) > 256  # the old rule sent this to the tree
    assert not search.crowded
    d2 = ((data[None] - queries[:, None]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(search.finish(search.grid_pass()), d2.argmin(axis=1))


def test_more_ties_than_candidates_go_to_the_grid(monkeypatch):
    """Twelve points at exactly 5 from the query (3-4-5 triangles): the tree's eight candidates
    cannot show the lowest index among them, so the grid answers that query."""
    from pcfbench.metrics import nn

    monkeypatch.setattr(nn, "TREE_MIN_POINTS", 1)
    monkeypatch.setattr(nn, "DENSE_SCAN", -1.0)
    ring = [(a * sa, b * sb) for a, b in ((3, 4), (4, 3)) for sa in (1, -1) for sb in (1, -1)]
    ring += [(5, 0), (-5, 0), (0, 5), (0, -5)]
    rng = np.random.default_rng(7)
    far = rng.uniform(6, 9, (40, 2)) * rng.choice([-1, 1], (40, 2))
    order = rng.permutation(52)
    data = np.concatenate([far, np.array(ring, float)])[order] * 0.25
    queries = np.array([[0.0, 0.0], [0.25, 0.0]])
    search = nn._Search2D(data, queries, 0.0)
    assert search.crowded and search._tree_pass()[0] == -1
    d2 = ((data[None] - queries[:, None]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(search.finish(search.grid_pass()), d2.argmin(axis=1))
