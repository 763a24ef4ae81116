"""A report whose figures' data did not change vs one that draws every figure (the baseline:
what every report did before figures were keyed on their data, ``pcfbench.reporting.figcache``).

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_report.py --benchmark-enable
The store: copy-last and raycast-voxel on a tiny KITTI sequence, kitti-1s and kitti-3s (two
groups, four figures); the ratio of the two medians is the saving.
"""

import shutil

import pytest

from conftest import write_tiny_kitti
from pcfbench.method import options_hash, parse_options
from pcfbench.plugins import load_plugins
from pcfbench.reporting.report import ReportOptions, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1_median", "absrel_mean", "absrel_median")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bench-report")
    root = write_tiny_kitti(tmp / "kitti", num_sweeps=64)
    for setting in ("kitti-1s", "kitti-3s"):
        for method in ("copy-last", "raycast-voxel"):
            opts = parse_options(load_plugins().methods.get(method).Options, {}, method)
            spec = CellSpec(method, {}, options_hash(opts), "kitti", str(root), "test", setting, "full-context", None,
                            METRICS)
            run_cell(spec, tmp / "store", RunOptions(progress=False))
    return tmp / "store"


def test_report_drawing_every_figure(benchmark, store, tmp_path):
    """The baseline: a fresh reports folder each round, so every figure is drawn."""
    out = tmp_path / "rep"

    def fresh():
        shutil.rmtree(out, ignore_errors=True)
        return write_reports(store, out, ReportOptions(figures=True))

    paths = benchmark.pedantic(fresh, rounds=3, iterations=1, warmup_rounds=1)
    assert paths.kept_figures == ()


def test_report_with_unchanged_figures(benchmark, store, tmp_path):
    """The same report again: every figure's key matches, none is drawn."""
    out = tmp_path / "rep"
    write_reports(store, out, ReportOptions(figures=True))
    paths = benchmark.pedantic(write_reports, args=(store, out, ReportOptions(figures=True)), rounds=3, iterations=1)
    assert len(paths.kept_figures) == 4
