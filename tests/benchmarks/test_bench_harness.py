"""Harness overhead per sample (everything but the method and the metrics) vs a copy-last sample.

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_harness.py --benchmark-enable
With PCFBENCH_BENCH_FULL=1 the sweeps are KITTI-sized (about 120,000 points).
"""

import os

import pytest

from pcfbench.method import options_hash
from pcfbench.plugins import get_plugins
from pcfbench.running.runner import Resolved, process_sample
from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.store.cells import Cell, CellSpec
from conftest import write_tiny_kitti
from pcfbench.datasets.kitti import KittiOdometry
from pcfbench.methods.copy_last import CopyLast

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"
SAMPLES = 8


@pytest.fixture(scope="module")
def kitti_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti")
    beams, az = (64, 2100) if FULL else (16, 360)
    write_tiny_kitti(root, num_sweeps=8 + SAMPLES + 10, beams=beams, azimuths=az)
    return root


def _pass(root, metrics, store):
    """Process SAMPLES consecutive samples as the runner does, rows written as one chunk."""
    res = Resolved(SampleBuilder(KittiOdometry(root), SETTINGS["kitti-1s"]), CopyLast(), metrics)
    rows = []
    for ref in range(8, 8 + SAMPLES):
        rows.extend(process_sample(res, ("08", ref)))
    spec = CellSpec("copy-last", {}, options_hash(None), "kitti", str(root), "test", "kitti-1s")
    with Cell(store, spec) as cell:
        cell.append_rows(rows)
    return rows


def test_harness_overhead_per_sample(benchmark, kitti_root, tmp_path):
    """Loading, ego removal, frame changes, query rays, forecast validation, Parquet rows."""
    rows = benchmark.pedantic(_pass, args=(kitti_root, [], tmp_path), rounds=5 if FULL else 1, iterations=1)
    benchmark.extra_info["samples_per_round"] = SAMPLES
    benchmark.extra_info["points_per_sweep"] = int(rows[0]["n_gt"])


def test_copy_last_sample_with_metrics(benchmark, kitti_root, tmp_path):
    """The whole copy-last sample: the same harness work plus the method and every registered metric."""
    plugins = get_plugins()
    metrics = [plugins.metrics.get(n) for n in plugins.metrics.names()]
    benchmark.pedantic(_pass, args=(kitti_root, metrics, tmp_path), rounds=5 if FULL else 1, iterations=1)
    benchmark.extra_info["samples_per_round"] = SAMPLES
    benchmark.extra_info["metrics"] = [m.name for m in metrics]
