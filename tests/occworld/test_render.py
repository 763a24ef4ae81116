"""Rendering depths through an occupancy-probability grid (methods/occworld/render.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occupancy import OccGrid
from pcfbench.methods.occworld.render import render_depths

GRID = OccGrid.over((0.0, 0.0, 0.0), (10.0, 1.0, 1.0), (10, 1, 1))
ORIGIN = np.array([0.5, 0.5, 0.5])
X = np.array([[1.0, 0.0, 0.0]])


def _prob(*p):
    out = np.zeros((10, 1, 1))
    out[:len(p), 0, 0] = p
    return out


def test_a_certain_wall():
    prob = _prob(0, 0, 0, 1.0)  # voxel 3: [3, 4] m, from x = 0.5: t in [2.5, 3.5]
    assert render_depths(GRID, prob, ORIGIN, X)[0] == pytest.approx(3.0)
    assert render_depths(GRID, prob, ORIGIN, X, "threshold")[0] == pytest.approx(3.0)


def test_expected_depth_by_hand():
    # voxel 1 (t 0.5..1.5, middle 1.0) p = 0.5, voxel 3 (middle 3.0) p = 0.5: weights 0.5 and 0.25,
    # the 0.25 left at the exit (t = 9.5): 0.5 * 1 + 0.25 * 3 + 0.25 * 9.5 = 3.625
    prob = _prob(0, 0.5, 0, 0.5)
    assert render_depths(GRID, prob, ORIGIN, X)[0] == pytest.approx(3.625)
    assert render_depths(GRID, prob, ORIGIN, X, "threshold")[0] == pytest.approx(1.0)
    # the first voxel is crossed from the origin only: t 0..0.5, middle 0.25
    assert render_depths(GRID, _prob(1.0), ORIGIN, X)[0] == pytest.approx(0.25)


def test_empty_space_reads_the_exit():
    assert render_depths(GRID, _prob(), ORIGIN, X)[0] == pytest.approx(9.5)
    assert render_depths(GRID, _prob(0.4, 0.4), ORIGIN, X, "threshold")[0] == pytest.approx(9.5)
    backwards = render_depths(GRID, _prob(), ORIGIN, -X)[0]
    assert backwards == pytest.approx(0.5)


def test_oblique_rays_agree_with_dense_sampling():
    rng = np.random.default_rng(0)
    grid = OccGrid.over((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), (8, 8, 4))
    prob = rng.uniform(0, 0.3, grid.dims)
    o = np.array([0.1, 0.2, 0.05])
    dirs = rng.normal(size=(20, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    got = render_depths(grid, prob, o, dirs)
    lo, vs = np.array(grid.lo), np.array(grid.voxel)
    for d, g in zip(dirs, got):
        # slow: samples every 1e-4 m; a voxel's run of samples is its segment
        t = np.arange(0, 10, 1e-4)
        q = np.floor((o + t[:, None] * d - lo) / vs).astype(int)
        inside = ((q >= 0) & (q < np.array(grid.dims))).all(axis=1)
        t, q = t[inside], q[inside]
        breaks = np.flatnonzero((np.diff(q, axis=0) != 0).any(axis=1)) + 1
        acc, trans = 0.0, 1.0
        for seg_t, seg_q in zip(np.split(t, breaks), np.split(q, breaks)):
            p = prob[tuple(seg_q[0])]
            acc += trans * p * 0.5 * (seg_t[0] + seg_t[-1])
            trans *= 1 - p
        assert g == pytest.approx(acc + trans * t[-1], abs=2e-3)


def test_bad_input():
    with pytest.raises(PcfbenchError, match="readout"):
        render_depths(GRID, _prob(), ORIGIN, X, "median")
    with pytest.raises(PcfbenchError, match="shape"):
        render_depths(GRID, np.zeros((3, 3, 3)), ORIGIN, X)
