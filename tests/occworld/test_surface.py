"""Sub-voxel planes for OccWorld's rendering (methods/occworld/surface.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occupancy import FREE, OCCUPIED, UNKNOWN, OccGrid
from pcfbench.methods.occworld.render import render_depths
from pcfbench.methods.occworld.surface import free_normals, render_surface, surface_offsets

# a 4 m long strip of two layers of 1 m voxels: z in [0, 1] the ground's layer, [1, 2] above it
STRIP = OccGrid.over((0.0, 0.0, 0.0), (4.0, 1.0, 2.0), (4, 1, 2))
UP = np.zeros((4, 1, 2, 3))
UP[..., 2] = 1.0


def _ground(offset: float):
    prob = np.zeros((4, 1, 2))
    prob[:, 0, 0] = 1.0  # the whole lower layer occupied (other rays' returns)
    return prob, UP, np.full((4, 1, 2), offset)


def test_a_grazing_ray_by_hand():
    # from (0.5, 0.5, 1.5) along (1, 0, -0.5)/|.|: x = 0.5 + u, z = 1.5 - u / 2 (depth = u * sqrt(1.25)).
    # It enters the lower layer at u = 1 (x = 1.5, voxel 1 of x [1, 2]), stays there until u = 1.5 (x = 2).
    o, d = np.array([0.5, 0.5, 1.5]), np.array([[1.0, 0.0, -0.5]])
    k = np.sqrt(1.25)
    # plane z = 0.5 + 0.3 = 0.8 in every voxel: crossed at u = 1.4 (x = 1.9, still in voxel 1)
    assert render_surface(STRIP, *_ground(0.3), o, d)[0] == pytest.approx(1.4 * k)
    # the old readout stops in the middle of voxel 1's segment, u = 1.25
    assert render_depths(STRIP, _ground(0.3)[0], o, d)[0] == pytest.approx(1.25 * k)
    # plane z = 0.2: the ray passes over voxels 1 and 2 and meets it at u = 2.6 (x = 3.1, voxel 3)
    assert render_surface(STRIP, *_ground(-0.3), o, d)[0] == pytest.approx(2.6 * k)
    # plane z = 0.1: u = 2.8 (x = 3.3, voxel 3)
    assert render_surface(STRIP, *_ground(-0.4), o, d)[0] == pytest.approx(2.8 * k)
    # level with the origin: it never comes down to the planes and leaves the grid at x = 4 (u = 3.5)
    assert render_surface(STRIP, *_ground(0.3), np.array([0.5, 0.5, 0.9]), np.array([[1.0, 0.0, 0.0]]))[0] == \
        pytest.approx(3.5)


def test_a_wall_and_the_voxel_rules_by_hand():
    grid = OccGrid.over((0.0, 0.0, 0.0), (10.0, 1.0, 1.0), (10, 1, 1))
    prob = np.zeros((10, 1, 1))
    prob[3] = 1.0
    normals = np.zeros((10, 1, 1, 3))
    offsets = np.zeros((10, 1, 1))
    o, x = np.array([0.5, 0.5, 0.5]), np.array([[1.0, 0.0, 0.0]])
    # no normal: the voxel's entry, x = 3 (depth 2.5)
    assert render_surface(grid, prob, normals, offsets, o, x)[0] == pytest.approx(2.5)
    # a wall facing the sensor, 0.25 m in front of the centre: x = 3.25
    normals[3, 0, 0] = (-1.0, 0.0, 0.0)
    offsets[3] = 0.25
    assert render_surface(grid, prob, normals, offsets, o, x)[0] == pytest.approx(2.75)
    # the ray enters behind a plane facing away (normal +x, plane x = 3.5): stops at the entry, 2.5
    normals[3, 0, 0] = (1.0, 0.0, 0.0)
    offsets[3] = 0.0
    assert render_surface(grid, prob, normals, offsets, o, x)[0] == pytest.approx(2.5)
    # seen from behind (origin x = 9.5, looking -x), that plane is in front: 9.5 - 3.5 = 6
    assert render_surface(grid, prob, normals, offsets, np.array([9.5, 0.5, 0.5]), -x)[0] == pytest.approx(6.0)
    # a probability below 0.5 is not occupied: the exit
    assert render_surface(grid, prob * 0.4, normals, offsets, o, x)[0] == pytest.approx(9.5)


def test_oblique_rays_agree_with_dense_sampling():
    """Random planes in a random grid: the first sample (every 1e-4 m) that lies in an occupied
    voxel on or behind its plane is the depth (1e-3 m; a voxel entered behind its plane stops the
    ray at its entry, which the dense samples also find)."""
    rng = np.random.default_rng(1)
    grid = OccGrid.over((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0), (8, 8, 4))
    prob = (rng.uniform(size=grid.dims) < 0.25) * 1.0
    normals = rng.normal(size=(*grid.dims, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    offsets = rng.uniform(-0.2, 0.2, grid.dims)
    o = np.array([0.1, 0.2, 0.05])
    prob[tuple(np.floor((o - np.array(grid.lo)) / np.array(grid.voxel)).astype(int))] = 0.0
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    got = render_surface(grid, prob, normals, offsets, o, dirs)
    lo, vs = np.array(grid.lo), np.array(grid.voxel)
    centres = grid.centres()
    for d, g in zip(dirs, got):
        t = np.arange(0, 10, 1e-4)
        p = o + t[:, None] * d
        q = np.floor((p - lo) / vs).astype(int)
        inside = ((q >= 0) & (q < np.array(grid.dims))).all(axis=1)
        t, p, q = t[inside], p[inside], q[inside]
        n = normals[q[:, 0], q[:, 1], q[:, 2]]
        m = centres[q[:, 0], q[:, 1], q[:, 2]] + offsets[q[:, 0], q[:, 1], q[:, 2], None] * n
        hit = (prob[q[:, 0], q[:, 1], q[:, 2]] >= 0.5) & (((p - m) * n).sum(axis=1) <= 0)
        want = t[hit][0] if hit.any() else t[-1]
        assert g == pytest.approx(want, abs=1e-3)


def test_normals_point_to_free_space():
    grid = OccGrid.over((0.0, 0.0, 0.0), (3.0, 3.0, 3.0), (3, 3, 3))
    labels = np.full((3, 3, 3), UNKNOWN)
    labels[:, :, 2] = FREE  # free above, ground in the middle layer, unknown under it
    labels[:, :, 1] = OCCUPIED
    n = free_normals(labels == FREE, grid.voxel)
    assert np.allclose(n[1, 1, 1], (0, 0, 1))  # free above only (the unknown below does not count)
    assert np.allclose(n[1, 1, 0], 0)  # no free neighbour: no normal
    # a corner: free above and on the -x side (x = 0 column free): tilted to (-1, 0, 1) / sqrt 2
    labels[0, :, :] = FREE
    n = free_normals(labels == FREE, grid.voxel)
    assert np.allclose(n[1, 1, 1], np.array([-1.0, 0.0, 1.0]) / np.sqrt(2))
    # under the ground, (1, 1, 0)'s one free face neighbour is (0, 1, 0): -x; with all 26 the free
    # (0, 1, 1), (0, 0, 0), ... tilt it upwards
    assert np.allclose(n[1, 1, 0], (-1.0, 0.0, 0.0))
    n26 = free_normals(labels == FREE, grid.voxel, 26)
    assert n26[1, 1, 0, 0] < 0 and n26[1, 1, 0, 2] > 0.1 and n26[1, 1, 0, 1] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(PcfbenchError, match="neighbours=8"):
        free_normals(labels == FREE, grid.voxel, 8)
    with pytest.raises(PcfbenchError, match=r"\(X, Y, Z\) free grid"):
        free_normals(np.zeros((3, 3)), grid.voxel)


def test_normals_equal_a_voxel_by_voxel_sum_of_neighbour_directions():
    """The per-axis difference (6 face neighbours) and the shifted sums (26) against a plain loop
    over every voxel and neighbour, on random free weights and anisotropic voxels."""
    rng = np.random.default_rng(3)
    free = rng.random((5, 4, 3)) * (rng.random((5, 4, 3)) < 0.6)
    voxel = (0.7, 0.5, 0.5625)
    for neighbours in (6, 26):
        want = np.zeros(free.shape + (3,))
        for x, y, z in np.ndindex(free.shape):
            acc = np.zeros(3)
            for d in np.ndindex(3, 3, 3):
                d = np.array(d) - 1
                if not d.any() or (neighbours == 6 and np.abs(d).sum() > 1):
                    continue
                i = np.array([x, y, z]) + d
                if (i < 0).any() or (i >= free.shape).any():
                    continue
                u = d * voxel
                acc += free[tuple(i)] * u / np.linalg.norm(u)
            n = np.linalg.norm(acc)
            want[x, y, z] = acc / n if n > 1e-12 else 0.0
        got = free_normals(free, voxel, neighbours)
        assert np.allclose(got, want, rtol=0, atol=1e-12), neighbours
        assert (np.linalg.norm(got, axis=-1) > 0).sum() > 30


def test_offsets_are_the_front_of_the_returns_along_the_normal():
    grid = OccGrid.over((0.0, 0.0, 0.0), (2.0, 1.0, 1.0), (2, 1, 1))
    normals = np.zeros((2, 1, 1, 3))
    normals[..., 2] = 1.0
    normals[1, 0, 0] = (0.6, 0.0, 0.8)
    pts = np.array([[0.2, 0.5, 0.7], [0.4, 0.5, 0.9],  # voxel 0: the highest z 0.9, centre 0.5: +0.4
                    [1.5, 0.5, 0.5], [1.9, 0.5, 0.2]])  # voxel 1: 0; 0.6 * 0.4 + 0.8 * -0.3 = 0
    s = surface_offsets(grid, pts, normals)
    assert s[0, 0, 0] == pytest.approx(0.4) and s[1, 0, 0] == pytest.approx(0.0, abs=1e-12)
    moved = normals.copy()
    moved[0, 0, 0] = (0.0, 0.0, -1.0)  # seen from below, the front is the lowest: -(0.7 - 0.5)
    assert surface_offsets(grid, pts, moved)[0, 0, 0] == pytest.approx(-0.2)
    assert surface_offsets(grid, pts[:1], normals)[1, 0, 0] == 0.0  # no return: 0
    # their mean instead: voxel 0 (0.7 + 0.9) / 2 - 0.5 = 0.3; voxel 1: (0 + 0) / 2
    s = surface_offsets(grid, pts, normals, "mean")
    assert s[0, 0, 0] == pytest.approx(0.3) and s[1, 0, 0] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(PcfbenchError, match="normals of shape"):
        surface_offsets(grid, pts, normals[:1])
    with pytest.raises(PcfbenchError, match="at='median'"):
        surface_offsets(grid, pts, normals, "median")


def test_no_ray_of_the_sweep_passes_its_own_return():
    """A perfect grid of a sweep (its labels, normals and offsets) stops every one of its rays
    at or before its return: a noisy ground seen at grazing angles, a box and a pole (the mean of
    the returns instead of their front lets the rays whose return lies in front of it run on)."""
    from pcfbench.methods.occworld.occupancy import label_occupancy

    rng = np.random.default_rng(3)
    grid = OccGrid.over((-30.0, -30.0, -3.0), (30.0, 30.0, 3.0), (60, 60, 8))
    az = rng.uniform(-np.pi, np.pi, 20000)
    el = rng.uniform(np.radians(-20), np.radians(-1.5), 20000)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    r = (-1.73 + rng.normal(0, 0.04, len(d))) / d[:, 2]  # the ground at z = -1.73, 4 cm of noise
    pts = d * r[:, None]
    box = (pts[:, 0] > 8) & (pts[:, 0] < 10) & (np.abs(pts[:, 1]) < 1.5)
    r[box] = (8 + rng.normal(0, 0.03, box.sum())) / d[box, 0]  # a wall facing the sensor at x = 8
    pts = d * r[:, None]
    keep = (np.abs(pts) < [29.9, 29.9, 2.9]).all(axis=1) & (r < 40)
    pts, d, r = pts[keep], d[keep], r[keep]
    labels = label_occupancy(grid, pts, np.zeros(3))
    normals = free_normals(labels == FREE, grid.voxel)
    offsets = surface_offsets(grid, pts, normals)
    depth = render_surface(grid, (labels == OCCUPIED) * 1.0, normals, offsets, np.zeros(3), d)
    assert (depth <= r + 1e-9).all(), (depth - r).max()
    mean = render_surface(grid, (labels == OCCUPIED) * 1.0, normals, surface_offsets(grid, pts, normals, "mean"),
                          np.zeros(3), d)
    assert (mean > r + 0.1).mean() > 0.1  # the mean's planes let many run on
    # and closer than the middle of the first occupied voxel
    old = render_depths(grid, (labels == OCCUPIED) * 1.0, np.zeros(3), d, "threshold")
    assert np.median(np.abs(depth - r)) < 0.8 * np.median(np.abs(old - r))


def test_a_decoded_grid_renders_through_its_planes():
    """``occ_copy.render_grid`` with ``readout="surface"``: a decoded occupancy probability and
    its decoded offsets render as ``render_surface`` with the normals weighted by the neighbours'
    free probability (here those of the voxels below 0.5: the side neighbours cancel); the same
    grid without offsets (a tokenizer trained with surface=none) is one error."""
    from pcfbench.methods.occworld.config import TokenizerConfig
    from pcfbench.methods.occworld.occ_copy import render_grid

    cfg = TokenizerConfig("strip", dims=(4, 1, 2), box_lo=(0.0, 0.0, 0.0), box_hi=(4.0, 1.0, 2.0), ch_mult=(1,))
    prob = np.full((4, 1, 2), 0.2)
    prob[:, 0, 0] = 0.9
    o, d = np.array([0.5, 0.5, 1.5]), np.array([[1.0, 0.0, -0.5]])
    got = render_grid(cfg, (prob, np.full((4, 1, 2), 0.3)), o, d, "surface")
    assert got[0] == pytest.approx(1.4 * np.sqrt(1.25))  # the plane z = 0.8, as test_a_grazing_ray_by_hand
    assert got == pytest.approx(render_surface(STRIP, *_ground(0.3), o, d))
    # normals given (render_sample computes them once for a grid all sweeps share): the same depths
    given = free_normals(prob < 0.5, STRIP.voxel)
    assert render_grid(cfg, (prob, np.full((4, 1, 2), 0.3)), o, d, "surface", given) == pytest.approx(got)
    assert render_grid(cfg, (prob, None), o, d, "threshold") == pytest.approx(render_depths(STRIP, prob, o, d, "threshold"))
    with pytest.raises(PcfbenchError, match="no offset head"):
        render_grid(cfg, (prob, None), o, d, "surface")


def test_decoded_normals_weight_each_neighbour_by_its_free_probability():
    """A ground voxel with a free voxel above it and a neighbour beside it decoded at 0.45 (free
    by the 0.5 threshold): counted whole, the neighbour tilts the normal by 45 degrees; weighted
    by 1 - p = 0.55, by atan(0.55) = 28.8. A grazing ray that the 45-degree plane stops in front
    of the voxel's return passes over the weighted one and reaches its ground plane."""
    from pcfbench.methods.occworld.occ_copy import decoded_normals

    grid = OccGrid.over((0.0, 0.0, 0.0), (3.0, 1.0, 2.0), (3, 1, 2))  # 1 m voxels
    prob = np.ones((3, 1, 2))
    prob[:, 0, 1] = 0.0  # the upper layer free
    prob[0, 0, 0] = 0.45  # the lower layer's first voxel: decoded just free
    soft, hard = decoded_normals(prob, grid.voxel), free_normals(prob < 0.5, grid.voxel)
    np.testing.assert_allclose(hard[1, 0, 0], np.array([-1.0, 0.0, 1.0]) / np.sqrt(2))
    np.testing.assert_allclose(soft[1, 0, 0], np.array([-0.55, 0.0, 1.0]) / np.hypot(0.55, 1.0))
    # certain grids: the same normals either way
    certain = (prob >= 0.5) * 1.0
    np.testing.assert_allclose(decoded_normals(certain, grid.voxel), free_normals(certain < 0.5, grid.voxel))
    # a grazing ray (0.1 m down per m) entering voxel 1 from above at x = 1.3, towards a return on
    # the ground farther on: each tilted plane (through the centre + 0.4 m along its normal) stops
    # it where the ray crosses it, the weighted one 0.11 m later, nearer the return
    offsets = np.zeros((3, 1, 2))
    offsets[:, 0, 0] = 0.4
    occupied = prob.copy()
    occupied[0, 0, 0] = 0.0  # decoded free
    o, d = np.array([0.0, 0.5, 1.13]), np.array([1.0, 0.0, -0.1])
    depths = {}
    for name, normals in (("hard", hard), ("soft", soft)):
        n = normals[1, 0, 0]
        m = np.array([1.5, 0.5, 0.5]) + 0.4 * n
        t = (m - o) @ n / (d / np.linalg.norm(d) @ n)  # where the ray crosses voxel 1's plane
        assert 1.3 < o[0] + t * d[0] / np.linalg.norm(d) < 2.0  # inside voxel 1
        depths[name] = render_surface(grid, occupied, normals, offsets, o, d[None])[0]
        assert depths[name] == pytest.approx(t)
    assert depths["soft"] - depths["hard"] == pytest.approx(0.11, abs=0.01)
