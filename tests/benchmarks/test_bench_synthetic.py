"""Synthetic generation speed: sweeps per second per domain (world build + ray casting + writing).

Default run: 3-sweep sequences (each benchmark runs once). ``PCFBENCH_BENCH_FULL=1``: 30
sweeps, closer to the steady state of a real generation.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from pcfbench.datasets.synthetic.domains import get_domain
from pcfbench.datasets.synthetic.generate import simulate_sequence, write_kitti

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"
SWEEPS = 30 if FULL else 3


@pytest.mark.parametrize("name", ["synthetic-town", "synthetic-suburb", "synthetic-town-realistic"])
def test_bench_generate_sequence(benchmark, name, tmp_path):
    dom = dataclasses.replace(get_domain(name), splits={"test": (("05", SWEEPS),)})
    counter = iter(range(10**6))

    def run():
        seq = simulate_sequence(dom, "05")
        write_kitti(tmp_path / str(next(counter)), seq)
        return seq

    seq = benchmark.pedantic(run, rounds=1 if not FULL else 2, iterations=1)
    assert len(seq.points) == SWEEPS and all(len(p) > 10_000 for p in seq.points)
    stats = getattr(benchmark, "stats", None)
    if stats is not None and stats.stats.mean:
        benchmark.extra_info["sweeps_per_s"] = SWEEPS / stats.stats.mean
        benchmark.extra_info["points_per_sweep"] = float(np.mean([len(p) for p in seq.points]))


def test_bench_baseline_toy_world(benchmark):
    """Side-by-side baseline: pcfbench.testing's analytic toy street (a few planes and posts, no
    agents, no files) ray-cast with the town's ray count (64 beams x 512 columns)."""
    from pcfbench.testing import toy_world_sweeps

    points, poses, _ = benchmark.pedantic(
        lambda: toy_world_sweeps(SWEEPS, beams=64, azimuths=512), rounds=1 if not FULL else 2, iterations=1)
    assert len(points) == SWEEPS and len(points[0]) > 1000
    stats = getattr(benchmark, "stats", None)
    if stats is not None and stats.stats.mean:
        benchmark.extra_info["sweeps_per_s"] = SWEEPS / stats.stats.mean
