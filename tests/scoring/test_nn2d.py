"""pcfbench.nn2d: the one exact 2-D nearest-neighbour kernel (metrics' angle spaces, raycast-4docc,
raycast-zbuffer), against a brute-force float64 argmin (the first of equal minima)."""

from __future__ import annotations

import numpy as np
import pytest

from pcfbench.nn2d import MAX_RINGS, NN2D


def brute(points: np.ndarray, queries: np.ndarray, period: float = 0.0) -> np.ndarray:
    """Slow and obviously right: the argmin over all squared distances, chunked for memory."""
    out = []
    for q in np.array_split(queries, max(1, len(queries) // 256)):
        dx = np.abs(q[:, None, 0] - points[None, :, 0])
        if period > 0:
            dx = np.minimum(dx, period - dx)
        dy = q[:, None, 1] - points[None, :, 1]
        out.append((dx * dx + dy * dy).argmin(axis=1))
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def test_hand_computed_case():
    pts = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 3.0], [2.0, 0.0], [-1.0, -1.0]])
    q = np.array([[1.9, 0.1], [1.0, 0.0], [0.0, 2.0], [-5.0, -5.0], [0.0, 1.5]])
    # (1, 0) is 1 from points 0, 1 and 3: the lowest index; (0, 1.5) is 1.5 from points 0 and 2
    np.testing.assert_array_equal(NN2D(pts).query(q), [1, 0, 2, 4, 0])
    # periodic x with period 8: (3.5, 0) is 0.5 from (-4, 0) around the circle, 1.5 from (2, 0)
    pts = np.array([[2.0, 0.0], [-4.0, 0.0], [4.0, 0.0]])
    np.testing.assert_array_equal(NN2D(pts, period=8.0).query(np.array([[3.5, 0.0], [-3.0, 0.0], [0.0, 0.0]])),
                                  [1, 1, 0])


@pytest.mark.parametrize("period", [0.0, 8.0])
@pytest.mark.parametrize("per_cell", [0.25, 1.0, 4.0, 64.0, 1e6])
def test_exact_ties_within_and_between_cells_match_argmin(period, per_cell):
    """Dyadic lattice coordinates (and a dyadic period): many queries are exactly equidistant
    from several points, which fine cells split over neighbouring cells and coarse cells hold
    together; duplicates sit at scattered indices, before and after their originals."""
    rng = np.random.default_rng(7)
    pts = rng.integers(-16, 16, (3000, 2)) * 0.25
    pts[:, 1] *= 0.5
    dup = rng.choice(len(pts), 400, replace=False)
    pts[dup[:200]] = pts[dup[200:]]
    q = rng.integers(-33, 33, (2500, 2)) * 0.125
    q[:, 1] *= 0.5
    if period:
        pts[:, 0] = np.clip(pts[:, 0], -4.0, 4.0)
        q[:, 0] = np.clip(q[:, 0], -4.0, 4.0)
    else:
        q = np.concatenate([q, rng.integers(-400, 400, (200, 2)) * 0.5])  # far outside the lattice
    got = NN2D(pts, period=period, per_cell=per_cell).query(q)
    np.testing.assert_array_equal(got, brute(pts, q, period))


@pytest.mark.parametrize("period", [0.0, 2 * np.pi])
def test_random_layouts_match_argmin(period):
    rng = np.random.default_rng(3)
    lo, hi = -np.pi, np.pi
    for layout in ("uniform", "clustered", "line", "corner", "one point", "all equal"):
        k = 2000
        if layout == "uniform":
            pts = rng.uniform([lo, -1], [hi, 1], (k, 2))
        elif layout == "clustered":
            pts = np.clip(rng.normal([rng.uniform(lo, hi), 0], 0.02, (k, 2)), lo, hi)
        elif layout == "line":  # zero height: one row of cells
            pts = np.stack([rng.uniform(lo, hi, k), np.full(k, 0.3)], 1)
        elif layout == "corner":  # queries everywhere else: rings, then the coarse grid
            pts = rng.uniform([hi - 0.05, 0.95], [hi, 1.0], (k, 2))
        elif layout == "one point":
            pts = np.array([[0.5, -0.25]])
        else:
            pts = np.full((50, 2), 0.125)
        q = rng.uniform([lo, -3], [hi, 3], (1500, 2))
        q = np.concatenate([q, pts[rng.integers(0, len(pts), 100)]])  # exact hits
        np.testing.assert_array_equal(NN2D(pts, period=period).query(q), brute(pts, q, period), err_msg=layout)


def test_queries_far_outside_the_grid():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, (5000, 2))
    far = np.concatenate([rng.uniform(-1e6, 1e6, (300, 2)), [[1e9, 0.0], [0.0, -1e9], [3.0, 3.0], [-2.0, 0.0]]])
    nn = NN2D(pts)
    assert (nn.near(far[:300]) == -1).mean() > 0.9  # beyond the first pass's rings ...
    np.testing.assert_array_equal(nn.query(far), brute(pts, far))  # ... and still exact
    # a periodic axis: queries far above and below the data, all azimuths
    pts = np.stack([rng.uniform(-np.pi, np.pi, 3000), rng.normal(0, 0.01, 3000)], 1)
    q = np.stack([rng.uniform(-np.pi, np.pi, 400), rng.choice([-50.0, 50.0], 400)], 1)
    np.testing.assert_array_equal(NN2D(pts, period=2 * np.pi).query(q), brute(pts, q, 2 * np.pi))


def test_empty_inputs():
    q = np.array([[0.0, 0.0], [1.0, 2.0]])
    assert NN2D(np.zeros((0, 2))).query(q).tolist() == [-1, -1]
    assert NN2D((np.zeros(0), np.zeros(0)), period=2 * np.pi).near(q).tolist() == [-1, -1]
    nn = NN2D(np.array([[0.0, 0.0]]))
    none = np.zeros((0, 2))
    for out in (nn.query(none), nn.near(none), nn.settle(none, np.zeros(0, np.int64))):
        assert out.shape == (0,) and out.dtype == np.int64


def test_pieces_and_query_order_change_no_answer():
    """``near`` on any slice, then ``settle``, gives ``query``'s answers (what the metrics' threads rely on)."""
    rng = np.random.default_rng(4)
    pts = rng.integers(-40, 40, (4000, 2)) * 0.0625
    q = np.concatenate([rng.integers(-90, 90, (3000, 2)) * 0.03125, rng.uniform(-50, 50, (100, 2))])
    nn = NN2D(pts)
    whole = nn.query(q)
    cuts = [0, 1, 17, 1000, 1001, 2500, len(q)]
    idx = np.concatenate([nn.near(q[a:b]) for a, b in zip(cuts[:-1], cuts[1:])])
    assert (idx < 0).any()  # the far queries are left to settle
    np.testing.assert_array_equal(nn.settle(q, idx), whole)
    # the settling's first stage (the far fine rings) on the same slices, then its coarse stage
    idx = np.concatenate([nn._settle_fine(q[a:b, 0].copy(), q[a:b, 1].copy(), nn.near(q[a:b]))
                          for a, b in zip(cuts[:-1], cuts[1:])])
    assert (idx < 0).any()  # the farthest queries are left to the coarse grid
    np.testing.assert_array_equal(nn._settle_coarse(q[:, 0].copy(), q[:, 1].copy(), idx), whole)
    perm = rng.permutation(len(q))
    np.testing.assert_array_equal(nn.query(q[perm]), whole[perm])
    np.testing.assert_array_equal(whole, brute(pts, q))
    assert MAX_RINGS >= 1


def test_bad_input_is_one_clear_error():
    with pytest.raises(ValueError, match="points contain NaN or infinite"):
        NN2D(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    with pytest.raises(ValueError, match="queries contain NaN or infinite"):
        NN2D(np.array([[0.0, 0.0]])).query(np.array([[np.inf, 0.0]]))
    with pytest.raises(ValueError, match=r"points have x in \[-4.0, 3.5\], outside \[-period / 2, period / 2\]"):
        NN2D(np.array([[-4.0, 0.0], [3.5, 0.0]]), period=2 * np.pi)
    with pytest.raises(ValueError, match="queries have x in"):
        NN2D(np.array([[0.0, 0.0]]), period=2 * np.pi).query(np.array([[4.0, 0.0]]))
    with pytest.raises(ValueError, match=r"points must be an \(N, 2\) array"):
        NN2D(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="period must be 0"):
        NN2D(np.zeros((5, 2)), period=-1.0)
    with pytest.raises(ValueError, match="settle needs the int64 answers of near"):
        NN2D(np.zeros((5, 2))).settle(np.zeros((3, 2)), np.zeros(2, np.int64))


def test_exact_on_clustered_data_with_duplicates():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(0, 0.01, (3000, 2)), rng.uniform(-3, 3, (2000, 2)), np.zeros((50, 2)),
                          np.stack([np.full(500, 1.0), rng.uniform(-1, 1, 500)], 1)])
    q = np.concatenate([rng.uniform(-4, 4, (1500, 2)), rng.normal(0, 0.02, (500, 2)), [[10.0, 10.0], [-9.0, 0.0]]])
    got = NN2D(pts).query(q)
    dist = ((q[:, None, :] - pts[None]) ** 2).sum(-1)
    np.testing.assert_allclose(dist[np.arange(len(q)), got], dist.min(1), rtol=0, atol=0)
    assert (NN2D(np.zeros((0, 2))).query(q) == -1).all()


def test_ties_go_to_the_lowest_index_and_far_queries_are_exact():
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1, 1, (4000, 2))
    pts[100:110] = pts[3000]  # duplicates of a later point: the lowest index must win
    grid_pts = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2) + 10.0
    pts = np.concatenate([pts, grid_pts])  # a lattice far away: queries between lattice points tie
    q = np.concatenate([pts[3000:3001], [[10.5, 10.5], [12.5, 11.0]], rng.uniform(-30, 30, (300, 2))])
    got = NN2D(pts).query(q)
    dist = ((q[:, None, :] - pts[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(got, dist.argmin(1))  # argmin: the first of equal minima
    assert got[0] == 100


def test_matches_argmin_on_banded_data_with_ties_across_cells():
    # like the 4D-Occ angle space: most points in thin dense bands, a sparse rest; exact
    # duplicates at scattered indices and queries equidistant from two points, so ties are
    # decided between cells (a cell's branch-free scan must still give the lowest index)
    rng = np.random.default_rng(11)
    bands = [np.stack([rng.uniform(-3, 3, 3000), rng.normal(c, 0.01, 3000)], 1) for c in (-3.0, -0.1, 0.0)]
    pts = np.concatenate(bands + [rng.uniform(-3.1, 3.1, (1500, 2))])
    pts = pts[rng.permutation(len(pts))]
    src = rng.choice(len(pts), 300, replace=False)
    dst = rng.choice(len(pts), 300, replace=False)
    pts[dst] = pts[src]  # duplicates, the copy sometimes before and sometimes after the original
    # exact ties between cells: pairs 2 * 2**-7 apart (dyadic, so both distances are exactly
    # equal) in a sparse stretch, the query halfway, the pair's points at random indices
    x = rng.integers(-180, 180, 200) / 64.0
    y = 1.5 + rng.integers(0, 2, 200) / 64.0
    d = 2.0**-7
    left = np.stack([x - d, y], 1)
    right = np.stack([x + d, y], 1)
    slots = rng.choice(len(pts), 400, replace=False)
    pts[slots[:200]], pts[slots[200:]] = left, right
    a, b = rng.choice(len(pts), 400), rng.choice(len(pts), 400)
    q = np.concatenate([np.stack([x, y], 1), pts[rng.choice(len(pts), 400)], (pts[a] + pts[b]) / 2,
                        np.stack([rng.uniform(-3, 3, 600), rng.normal(0, 0.05, 600)], 1),
                        rng.uniform(-4, 4, (200, 2))])
    expect = np.concatenate([((c[:, None, :] - pts[None]) ** 2).sum(-1).argmin(1) for c in np.array_split(q, 8)])
    for per_cell in (0.5, 4.0, 64.0):
        np.testing.assert_array_equal(NN2D(pts, per_cell=per_cell).query(q), expect)

