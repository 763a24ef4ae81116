"""Speed of the one exact 2-D nearest-neighbour kernel (pcfbench.nn2d) on both of its workloads,
index build and every query, on one thread:

- ``metrics-4docc`` / ``metrics-wrapped``: the metrics' two angle-space searches (4D-Occ space;
  azimuth/elevation with the azimuth periodic) of the ray-aligned pair of
  test_bench_metrics.py (~120k predicted points, ~120k ground-truth rays), each space with the
  cell density pcfbench.metrics.nn uses;
- ``raycast-4docc``: raycast-4docc's per-view searches on the sample of test_bench_raycast.py
  (5 views of ~636k past points and ~127k rays in the 4D-Occ space of each view's origin).

    PCFBENCH_BENCH_FULL=1 .venv/bin/python -m pytest tests/benchmarks/test_bench_nn2d.py --benchmark-enable

Without PCFBENCH_BENCH_FULL the inputs are 16-beam toys, so the default (disabled) pass stays
quick. The side-by-side ratios against the two kernels it replaced are in docs/journal/performance-tuning-2026-11.md.
"""

from __future__ import annotations

import os

import numba
import numpy as np
import pytest

from pcfbench.geometry import invert, transform_points
from pcfbench.methods.raycast.common import aggregate, views
from pcfbench.methods.raycast.fourdocc import angles
from pcfbench.metrics.nn import PER_CELL_4DOCC, PER_CELL_WRAPPED, TWO_PI, angles_4docc, angles_az_el
from pcfbench.nn2d import NN2D
from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.testing import InMemoryDataset, toy_world_sweeps

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"


def _metrics_jobs():
    beams, azimuths = (64, 1900) if FULL else (16, 360)
    pts, poses, _ = toy_world_sweeps(6, beams=beams, azimuths=azimuths)
    gt = pts[5].astype(np.float64)
    pred = transform_points(invert(poses[5]) @ poses[4], pts[4]).astype(np.float32).astype(np.float64)
    return {"metrics-4docc": [(angles_4docc(pred), angles_4docc(gt), 0.0, PER_CELL_4DOCC)],
            "metrics-wrapped": [(angles_az_el(pred), angles_az_el(gt), TWO_PI, PER_CELL_WRAPPED)]}


def _raycast_jobs():
    kw = dict(beams=64, azimuths=2000) if FULL else dict(beams=16, azimuths=360)
    sample, _ = SampleBuilder(InMemoryDataset(num_sweeps=20, **kw), SETTINGS["kitti-1s"]).build("00", 8)
    cols = aggregate(sample).cols
    return {"raycast-4docc": [(angles(cols, v.origin), angles(v.dcols, np.zeros(3)), 0.0, 4.0)
                              for v in views(sample, False)]}


def _rows(a) -> np.ndarray:
    """(N, 2) rows of an (N, 2) array or an (x, y) tuple of columns."""
    return np.stack(a, 1) if isinstance(a, tuple) else a


@pytest.fixture(scope="module")
def workloads():
    return {**_metrics_jobs(), **_raycast_jobs()}


@pytest.mark.parametrize("workload", ["metrics-4docc", "metrics-wrapped", "raycast-4docc"])
def test_nn2d(benchmark, workloads, workload):
    jobs = workloads[workload]

    def run():
        return [NN2D(data, period, per_cell).query(queries) for data, queries, period, per_cell in jobs]

    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        out = run()  # compile outside the timing
        benchmark(run)
    finally:
        numba.set_num_threads(before)
    data, queries, period, _ = jobs[0]
    d, q = _rows(data), _rows(queries)
    sub = q[:: max(1, len(q) // 200)]  # spot check against a brute-force argmin
    dx = np.abs(sub[:, None, 0] - d[None, :, 0])
    if period:
        dx = np.minimum(dx, period - dx)
    want = (dx * dx + (sub[:, None, 1] - d[None, :, 1]) ** 2).argmin(1)
    np.testing.assert_array_equal(out[0][:: max(1, len(q) // 200)], want)
    if benchmark.stats is not None:
        n_queries = sum(len(_rows(j[1])) for j in jobs)
        benchmark.extra_info["queries"] = n_queries
        benchmark.extra_info["queries_per_s"] = n_queries / benchmark.stats.stats.median
