"""Speed of the ray-casting baselines on a KITTI-sized sample.

With ``PCFBENCH_BENCH_FULL=1`` the sample has 5 past sweeps of about 127,000 points and 5
future sweeps of about 127,000 query rays (a 64-beam, 2000-step toy LiDAR); otherwise a
16-beam toy sample keeps the default (disabled, run-once) pass quick. Run with

    PCFBENCH_BENCH_FULL=1 .venv/bin/python -m pytest tests/benchmarks/test_bench_raycast.py --benchmark-enable

``render`` times the per-view work of all five views, as ``forecast`` runs it (everything that
depends on a future pose: projections, per-view indexes and images, casts, fallbacks; the
scene built once per sample from the past sweeps alone, aggregate and voxel grid, is outside
it) and reports ``rays_per_s`` in extra_info (the bar: 5 M rays/s); ``ray_queries`` times only
the per-ray part (nearest-neighbour queries, image look-ups, grid casts) with each view's
index, image or grid built beforehand; ``sample`` times ``forecast`` end to end (the bar: 2 s).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.testing import InMemoryDataset
from pcfbench.methods.raycast.common import aggregate, map_views, views
from pcfbench.methods.raycast.fourdocc import RaycastFourDOcc, angles, render_4docc_views
from pcfbench.methods.raycast.freespace import RaycastFreespace, carve
from pcfbench.nn2d import NN2D
from pcfbench.methods.raycast.voxel import RaycastVoxel, build_grid, render_voxel_views
from pcfbench.methods.raycast.zbuffer import RaycastZBuffer, _lookup, build_image, render_zbuffer_views, spherical

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"
METHODS = [RaycastFourDOcc, RaycastZBuffer, RaycastVoxel, RaycastFreespace]


@pytest.fixture(scope="module")
def sample():
    kw = dict(beams=64, azimuths=2000) if FULL else dict(beams=16, azimuths=360)
    ds = InMemoryDataset(num_sweeps=20, **kw)
    s, _ = SampleBuilder(ds, SETTINGS["kitti-1s"]).build("00", 8)
    if FULL:
        assert min(len(p) for p in s.past_points_ref) > 100_000
        assert min(len(q) for q in s.queries) > 100_000
    return s


def _scene(cls, sample):
    """What ``forecast`` builds once per sample from the past alone: (options, aggregate,
    views, grid or None, the points (3, N) and own ranges the renderer reads)."""
    opts = cls.Options()
    agg = aggregate(sample)
    vws = views(sample, False)
    grid = None
    cols, own = agg.cols, agg.own_range
    if cls in (RaycastVoxel, RaycastFreespace):
        grid = build_grid(agg.points, opts)
    if cls is RaycastFreespace:
        grid, keep = carve(grid, agg.origins, agg.points, agg.own_range, opts)
        cols, own = np.ascontiguousarray(cols[:, keep]), own[keep]
    return opts, agg, vws, grid, cols, own


def _renderer(cls, sample):
    """A function rendering every view of ``sample`` from a scene built beforehand."""
    opts, agg, vws, grid, cols, own = _scene(cls, sample)
    if cls is RaycastFourDOcc:
        return lambda: render_4docc_views(cols, vws)
    if cls is RaycastZBuffer:
        return lambda: render_zbuffer_views(cols, own, vws, opts)
    return lambda: render_voxel_views(grid, cols, own, vws, opts)


@pytest.mark.parametrize("cls", METHODS, ids=lambda c: c.name)
def test_render(benchmark, sample, cls):
    render = _renderer(cls, sample)
    render()  # compile outside the timing
    depths = benchmark(render)
    rays = sum(len(q) for q in sample.queries)
    assert sum(len(d) for d in depths) == rays and all(np.isfinite(d).all() for d in depths)
    if benchmark.stats is not None:
        benchmark.extra_info["rays"] = rays
        benchmark.extra_info["rays_per_s"] = rays / benchmark.stats.stats.median


@pytest.mark.parametrize("cls", METHODS, ids=lambda c: c.name)
def test_sample(benchmark, sample, cls):
    method = cls()
    method.forecast(sample)
    forecast = benchmark(method.forecast, sample)
    assert [len(p) for p in forecast.points_ref] == [len(q) for q in sample.queries]


def _ray_queries(cls, sample):
    """Only the per-ray part of every view, its per-view scene (index, image, grid) built beforehand."""
    opts, agg, vws, grid, cols, own = _scene(cls, sample)
    if cls is RaycastFourDOcc:
        jobs = [(NN2D(angles(cols, v.origin)), angles(v.dcols, np.zeros(3))) for v in vws]
        return lambda: map_views(lambda job: job[0].query(job[1]), jobs)
    if cls is RaycastZBuffer:
        jobs = []
        for v in vws:
            R = np.ascontiguousarray(v.T_ref_sensor[:3, :3])
            qaz, qel, _ = spherical(v.dcols, np.zeros(3), R)
            im = build_image(cols, own, v.origin, R, qel, opts.az_res_deg, opts.el_res_deg, opts.splat, opts.max_splat)
            jobs.append((im, qaz, qel))
        return lambda: map_views(
            lambda job: _lookup(job[0].img, job[1], job[2], job[0].el0, job[0].az_res, job[0].el_res, job[0].n_az,
                                job[0].n_el, opts.fill_ring),
            jobs,
        )
    cone = opts.cone_factor * np.deg2rad(opts.el_res_deg)
    return lambda: map_views(lambda v: grid.cast(v.origin, v.directions, cone=cone, max_level=opts.max_level), vws)


@pytest.mark.parametrize("cls", METHODS, ids=lambda c: c.name)
def test_ray_queries(benchmark, sample, cls):
    query = _ray_queries(cls, sample)
    query()
    out = benchmark(query)
    rays = sum(len(q) for q in sample.queries)
    assert sum(len(o) for o in out) == rays
    if benchmark.stats is not None:
        benchmark.extra_info["rays_per_s"] = rays / benchmark.stats.stats.median
