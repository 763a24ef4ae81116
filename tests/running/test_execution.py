"""The thread budget (pcfbench.execution): shares, pinning, the pool, imports that change
nothing, rows that do not depend on the thread count, and workers that stay within it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.execution import ExecutionContext, applied, available_cpus, current, pool_sizes, thread_limits

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent  # conftest.py, tests_helpers.py


# -- the context -----------------------------------------------------------------------------
@pytest.mark.parametrize("threads, jobs, share", [(2, 2, 1), (2, 1, 2), (16, 3, 5), (1, 4, 1), (3, 2, 1), (8, 8, 1)])
def test_share_is_the_floor_of_the_budget_over_the_jobs_at_least_one(threads, jobs, share):
    assert ExecutionContext(threads).share(jobs) == ExecutionContext(share)


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True, None])
def test_a_bad_thread_count_is_one_clear_error(bad):
    with pytest.raises(PcfbenchError, match=r"threads must be an integer >= 1, not"):
        ExecutionContext(bad)


def test_a_bad_job_count_is_one_clear_error():
    with pytest.raises(PcfbenchError, match=r"number of worker processes must be an integer >= 1, not 0"):
        ExecutionContext(4).share(0)


def test_default_is_every_cpu_the_process_may_use():
    assert ExecutionContext().threads == available_cpus() >= 1
    if hasattr(os, "sched_getaffinity"):
        assert available_cpus() == len(os.sched_getaffinity(0))


def test_map_keeps_order_and_pins_numba_to_one_thread_inside_jobs():
    import numba

    def job(x):
        return x * x, numba.get_num_threads()

    items = list(range(11))
    for threads in (1, 2, 3):
        out = ExecutionContext(threads).map(job, items)
        assert [o[0] for o in out] == [x * x for x in items]
        assert {o[1] for o in out} == {1}
    assert ExecutionContext(2).map(job, []) == []


def test_the_pool_is_made_once_per_size_and_its_workers_run_one_thread_each():
    import numba
    from threadpoolctl import threadpool_info

    ctx = ExecutionContext(2)
    assert ctx.pool() is ctx.pool() is ExecutionContext(2).pool()
    assert ctx.pool()._max_workers == 2 and 2 in pool_sizes()

    def inside(_):
        return numba.get_num_threads(), [i["num_threads"] for i in threadpool_info() if i["user_api"] == "openmp"]

    for numba_threads, openmp in ctx.pool().map(inside, range(8)):
        assert numba_threads == 1 and all(n == 1 for n in openmp)


def test_work_started_inside_a_pool_worker_stays_on_that_thread():
    """Every worker asking the same pool for more work would wait for itself: it runs inline."""
    import threading

    from pcfbench.execution import in_pool_worker
    from pcfbench.metrics import nn

    ctx = ExecutionContext(2)
    rng = np.random.default_rng(3)
    pred_rel, gt_rel = rng.normal(size=(300, 3)) * 20, rng.normal(size=(250, 3)) * 20
    want = nn.nearest_angles(pred_rel, gt_rel, ExecutionContext(1))

    def job(_):
        me = threading.get_ident()
        inner = ctx.map(lambda x: (x, threading.get_ident()), range(5))
        got = nn.nearest_angles(pred_rel, gt_rel, ctx)
        return in_pool_worker(), {t for _, t in inner} == {me}, got

    assert not in_pool_worker()
    for worker, inline, got in ctx.map(job, range(4)):  # 4 jobs on 2 workers: all would block
        assert worker and inline
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_applied_pins_this_process_and_puts_everything_back():
    import numba
    import torch

    before = thread_limits()
    env_before = {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    ctx = ExecutionContext(1)
    with applied(ctx):
        inside = thread_limits()
        assert current() is ctx
        assert os.environ["OMP_NUM_THREADS"] == "1"
    assert inside["numba"] == 1 and inside["torch"] == 1
    assert inside["libraries"] and all(n == 1 for n in inside["libraries"].values())
    after = thread_limits()
    assert after["numba"] == before["numba"] == numba.get_num_threads()
    assert after["torch"] == before["torch"] == torch.get_num_threads()
    assert after["libraries"] == before["libraries"]
    assert {v: os.environ.get(v) for v in env_before} == env_before
    assert current() == ExecutionContext()


def test_method_execution_defaults_to_the_process_and_takes_only_a_context():
    from pcfbench.methods.copy_last import CopyLast

    method = CopyLast()
    assert method.execution == current()
    method.execution = ExecutionContext(1)
    assert method.execution == ExecutionContext(1)
    with pytest.raises(PcfbenchError, match="CopyLast.execution must be an ExecutionContext, not 2"):
        method.execution = 2


# -- importing changes nothing ---------------------------------------------------------------
_SNAPSHOT = """
def snapshot():
    import os, threading
    import numba, torch
    from threadpoolctl import threadpool_info
    return {
        "layer": numba.config.THREADING_LAYER,
        "layer_priority": list(numba.config.THREADING_LAYER_PRIORITY),
        "numba": numba.get_num_threads(),
        "torch": torch.get_num_threads(),
        "libraries": sorted((i["filepath"], i["num_threads"]) for i in threadpool_info()),
        "env": {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                               "NUMBA_NUM_THREADS", "NUMBA_THREADING_LAYER")},
        "threads": sorted(t.name for t in threading.enumerate()),
    }
"""


def test_importing_every_builtin_plugin_module_changes_no_thread_setting():
    script = _SNAPSHOT + textwrap.dedent("""
        import importlib, json, pkgutil, sys
        import numba, torch, threadpoolctl  # the libraries themselves, before any pcfbench module
        before = snapshot()
        import pcfbench, pcfbench.methods, pcfbench.datasets, pcfbench.metrics
        names = []
        for pkg in (pcfbench, pcfbench.methods, pcfbench.datasets, pcfbench.metrics):
            for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
                if info.name.rsplit(".", 1)[-1] != "__main__":
                    importlib.import_module(info.name)
                    names.append(info.name)
        from pcfbench.plugins import load_plugins
        plugins = load_plugins()
        for registry in (plugins.methods, plugins.datasets, plugins.metrics):
            for name in registry.names():
                registry.get(name)
        after = snapshot()
        print(json.dumps({"before": before, "after": after, "modules": names}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    modules = set(got["modules"])
    for expected in ("pcfbench.methods.raycast.common", "pcfbench.methods.raycast.fourdocc", "pcfbench.metrics.nn",
                     "pcfbench.running.runner", "pcfbench.execution", "pcfbench.methods.copilot4d.plugin"):
        assert expected in modules
    before, after = got["before"], got["after"]
    # libraries loaded by the imports (scipy's BLAS, ...) come in at their own defaults; those
    # loaded before must keep their settings
    libs_before, libs_after = dict(map(tuple, before.pop("libraries"))), dict(map(tuple, after.pop("libraries")))
    assert libs_before and {k: libs_after.get(k) for k in libs_before} == libs_before
    assert after == before


# -- outputs do not depend on the thread count -----------------------------------------------
def _rows(sample, truth, forecast, metrics, threads):
    from pcfbench.metrics.base import score_sample

    return score_sample(sample, truth, forecast, metrics, ExecutionContext(threads))


def test_metric_rows_are_bit_identical_for_one_two_and_three_threads(monkeypatch):
    from pcfbench.metrics import nn
    from pcfbench.methods.copy_last import CopyLast
    from pcfbench.plugins import load_plugins
    from pcfbench.testing import toy_sample

    plugins = load_plugins()
    metrics = [plugins.metrics.get(name) for name in plugins.metrics.names()]
    sample, truth = toy_sample("kitti-1s")
    forecast = CopyLast().forecast(sample)  # points only: the metrics search the angle spaces
    assert forecast.depths is None
    monkeypatch.setattr(nn, "CHUNK", 701)  # several pieces per grid pass
    rows = {t: _rows(sample, truth, forecast, metrics, t) for t in (1, 2, 3)}
    names = [m.name for m in metrics]
    assert {"l1@4docc", "l1_mean", "chamfer"} <= set(names)  # both angle spaces and the 3D search
    ref = rows[1]
    scored = [m.name for m in metrics if m.needs != "depths"]  # the others skip a points-only forecast
    assert len(ref) == sample.num_future and all(np.isfinite(r[m]) for r in ref for m in scored)
    for t in (2, 3):
        for a, b in zip(ref, rows[t]):
            assert a.keys() == b.keys()
            for key in a:  # bit for bit, NaN included
                assert np.array_equal(np.float64(a[key]), np.float64(b[key]), equal_nan=True), (t, key)


@pytest.mark.parametrize("method_name", ["raycast-4docc", "raycast-zbuffer"])
def test_raycast_forecasts_are_bit_identical_for_one_two_and_three_threads(method_name):
    from pcfbench.plugins import load_plugins
    from pcfbench.testing import toy_sample

    cls = load_plugins().methods.get(method_name)
    sample, _ = toy_sample("kitti-1s")
    out = {}
    for threads in (1, 2, 3):  # 5 views on 3 threads: 4docc shares the last two out in pieces
        method = cls()
        method.execution = ExecutionContext(threads)
        out[threads] = method.forecast(sample)
    for threads in (2, 3):
        for a, b in zip(out[1].depths, out[threads].depths):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
        for a, b in zip(out[1].points_ref, out[threads].points_ref):
            assert np.array_equal(a, b)
    assert sum(int(np.count_nonzero(d > 0)) for d in out[1].depths) > 0


# -- the workers of --jobs N stay within the budget --------------------------------------------
_PROBE = _SNAPSHOT + textwrap.dedent('''
    import json, os
    import numba
    from pcfbench.data import Forecast
    from pcfbench.execution import current, pool_sizes, thread_limits
    from pcfbench.hookspecs import hookimpl
    from pcfbench.methods.raycast.zbuffer import RaycastZBuffer


    def _inside(_):
        from threadpoolctl import threadpool_info
        return numba.get_num_threads(), [i["num_threads"] for i in threadpool_info() if i["user_api"] == "openmp"]


    class ThreadProbe(RaycastZBuffer):
        """raycast-zbuffer, as points only (so the metrics search angles too), recording the
        thread settings of the worker it runs in before each sample."""
        name = "thread-probe"

        def forecast(self, sample):
            import torch  # first imported here, after the worker was pinned
            import multiprocessing
            record = {"pid": os.getpid(), "worker": multiprocessing.parent_process() is not None,
                      "context": self.execution.threads, "current": current().threads,
                      **thread_limits(), "torch": torch.get_num_threads(),
                      "pool_jobs": self.execution.map(_inside, range(4 * self.execution.threads))}
            with open(os.path.join(os.environ["THREAD_PROBE_OUT"], f"{os.getpid()}.jsonl"), "a") as f:
                f.write(json.dumps(record) + "\\n")
            return Forecast(points_ref=super().forecast(sample).points_ref)


    @hookimpl
    def register_methods(register):
        register("thread-probe", ThreadProbe, "records the thread settings of its worker")
''')


def _probe_env(tmp_path: Path) -> dict[str, str]:
    site = tmp_path / "site"
    (site / "thread_probe-0.dist-info").mkdir(parents=True)
    (site / "thread_probe-0.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: thread-probe\nVersion: 0\n")
    (site / "thread_probe-0.dist-info" / "entry_points.txt").write_text("[pcfbench]\nthread-probe = thread_probe_plugin\n")
    (site / "thread_probe_plugin.py").write_text(_PROBE)
    out = tmp_path / "records"
    out.mkdir()
    path = [str(site), str(HERE), str(TESTS)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path), PCFBENCH_PLUGINS="thread-probe",
               THREAD_PROBE_OUT=str(out), PCFBENCH_NO_PROGRESS="1")
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env.pop(var, None)
    return env


@pytest.mark.parametrize("threads", [None, 4])
def test_jobs_2_workers_stay_within_the_thread_budget(tmp_path, threads):
    from tests_helpers import write_kitti_tree

    root = write_kitti_tree(tmp_path / "kitti", num_sweeps=28)
    env = _probe_env(tmp_path)
    cmd = [sys.executable, "-m", "pcfbench", "run", "--dataset", f"kitti={root}", "--setting", "kitti-1s",
           "--method", "thread-probe", "--jobs", "2", "--limit", "8", "--store", str(tmp_path / "store"),
           "--reports", str(tmp_path / "reports"), "--no-report", "--quiet"]
    if threads is not None:
        cmd += ["--threads", str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "8 samples (8 now, 0 failed)" in out.stdout, out.stdout
    records = [json.loads(line) for f in (tmp_path / "records").glob("*.jsonl") for line in f.read_text().splitlines()]
    assert len(records) == 8
    budget = threads or available_cpus()
    share = max(1, budget // 2)
    assert 2 * share <= max(budget, 2)  # two workers never hold more than the budget (or 1 each)
    for r in records:
        assert r["context"] == r["current"] == share
        assert 1 <= r["numba"] <= share
        assert 1 <= r["torch"] <= share
        assert r["libraries"] and all(n <= share for n in r["libraries"].values()), r["libraries"]
        assert sum(r["pools"]) <= share  # the render and metric threads are one pool of the share
        assert r["pools"] in ([], [share])
        assert all(numba_threads == 1 and all(n == 1 for n in openmp) for numba_threads, openmp in r["pool_jobs"])
    if share > 1:  # after a worker's first sample its method and metrics have used the one pool
        firsts = {}
        for r in records:
            firsts.setdefault(r["pid"], r)
        assert any(r["pools"] == [share] for r in records if r is not firsts[r["pid"]])
    assert all(r["worker"] for r in records)


def test_parallel_work_outside_the_runner_asks_numba_for_openmp_first():
    """No context applied (a notebook, a test): the first map still gets numba's OpenMP layer,
    so the TBB that open3d ships (older than numba wants) is never tried and never warned about."""
    script = textwrap.dedent("""
        import json, warnings
        import open3d  # noqa: F401 - loads its own TBB
        import numba
        from pcfbench.methods.raycast.zbuffer import RaycastZBuffer
        from pcfbench.testing import toy_sample
        sample, _ = toy_sample()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            RaycastZBuffer().forecast(sample)
        print(json.dumps({"layer": numba.threading_layer(), "warnings": [str(w.message) for w in caught]}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env={k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")})
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["layer"] == "omp"
    assert not [w for w in got["warnings"] if "TBB" in w], got["warnings"]


def test_a_library_imported_after_the_pool_is_pinned_before_the_next_job():
    """A library imported after a pool was made may bring its own OpenMP runtime (torch and
    open3d are imported on first use; pykdtree's wheel bundles one, under its own name, so
    it stands for them here): each worker pins it to one thread before its next job."""
    import subprocess
    import sys

    code = """
import sys
from threadpoolctl import threadpool_info
from pcfbench.execution import ExecutionContext
assert "pykdtree" not in sys.modules
ctx = ExecutionContext(2)
omp = lambda _: sorted((i["filepath"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "openmp")
before = list(ctx.pool().map(omp, range(4)))
import pykdtree.kdtree
after = list(ctx.pool().map(omp, range(8)))
assert len(after[0]) > len(before[0]), (before[0], after[0])
assert all(n == 1 for libs in after for _, n in libs), after
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "ok", out.stderr[-2000:]
