"""Per-sample limits (issue 45): scoring is timed apart from the method, so a forecast that is
slow to score is a scoring failure and not the method's timeout; an optional memory limit; a
forecast over the size cap is refused before it is scored, naming method, sample, sweep, count
and cap."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from pcfbench.data import Forecast
from pcfbench.errors import ForecastError, PcfbenchError
from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.metrics.base import Metric
from pcfbench.plugins import load_plugins
from pcfbench.protocol.validate import FORECAST_FLOOR, check_forecast_size, forecast_cap
from pcfbench.running import workers
from pcfbench.running.runner import RunOptions, _failure_row, run_cell
from pcfbench.running.workers import run_supervised
from pcfbench.store.cells import Cell, CellSpec


def nothing() -> None:
    pass


def two_phases(key: tuple[float, float]) -> str:
    """The method's part (sleep ``key[0]``), then the scoring (sleep ``key[1]``)."""
    method_s, scoring_s = key
    time.sleep(method_s)
    workers.phase(workers.SCORING)
    time.sleep(scoring_s)
    return "ok"


def hog(mib: int) -> int:
    """Hold ``mib`` MiB (touched, so resident) for two seconds; the worker's resident bytes."""
    block = np.ones(mib * 2**20, dtype=np.uint8)
    time.sleep(2.0)
    assert block[-1] == 1
    return workers.resident_bytes(os.getpid())


def _supervise(keys, task, **limits) -> list:
    out: list = []
    t = threading.Thread(target=lambda: out.extend(run_supervised(keys, 1, nothing, (), task,
                                                                  lambda k, kind, msg: ("failed", k, kind, msg),
                                                                  **limits)), daemon=True)
    t.start()
    t.join(60.0)
    assert not t.is_alive(), "run_supervised never returned"
    return out


def test_a_slow_scoring_is_a_scoring_failure_not_the_methods_timeout():
    out = _supervise([(0.0, 30.0)], two_phases, timeout=20.0, scoring_timeout=0.5)
    assert len(out) == 1 and out[0][:3] == ("failed", (0.0, 30.0), "scoring-timeout")
    assert "scoring time limit of 0.5 s" in out[0][3]


def test_the_methods_limit_does_not_count_the_scoring():
    # 1.5 s of method and 1.5 s of scoring: each phase within its 2.5 s limit, together over it
    out = _supervise([(1.5, 1.5)], two_phases, timeout=2.5, scoring_timeout=2.5)
    assert out == ["ok"]
    slow = _supervise([(5.0, 0.0)], two_phases, timeout=0.5, scoring_timeout=30.0)
    assert slow[0][2] == "timeout" and "per-sample time limit of 0.5 s" in slow[0][3]


def test_a_worker_over_the_memory_limit_fails_its_sample_and_the_next_runs():
    (baseline,) = _supervise([1], hog, timeout=30.0)  # a worker's own size with 1 MiB held
    out = _supervise([700, 1], hog, timeout=30.0, max_memory=baseline + 300 * 2**20)
    failed = [o for o in out if isinstance(o, tuple)]
    assert [f[1:3] for f in failed] == [(700, "memory")] and "per-sample memory limit" in failed[0][3]
    assert [o for o in out if isinstance(o, int)], "the next sample ran in a new worker"


def test_failure_rows_name_the_phase_and_the_option():
    scoring = _failure_row(("08", 5), "scoring-timeout", "scoring took too long")[0]
    assert scoring["error"].startswith("ScoringTimeout: sample 08/000005") and "--scoring-timeout" in scoring["traceback"]
    method = _failure_row(("08", 5), "timeout", "too long")[0]
    assert method["error"].startswith("SampleTimeout") and "--timeout" in method["traceback"]
    memory = _failure_row(("08", 5), "memory", "too big")[0]
    assert memory["error"].startswith("SampleMemory") and "--max-memory" in memory["traceback"]
    assert set(scoring) == set(method) == set(memory)  # the store's row format


def test_run_options_refuse_bad_limits():
    for bad in ({"scoring_timeout": 0}, {"max_memory_gb": -1.0}, {"forecast_ratio": float("nan")}):
        with pytest.raises(PcfbenchError, match="must be"):
            RunOptions(**bad)


# -- the forecast size cap ----------------------------------------------------------------------
class _Sample:
    sample_id = "08/000005"


class _Truth:
    future_points_ref = (np.zeros((100, 3), np.float32), np.zeros((30_000, 3), np.float32))


def test_a_forecast_over_the_cap_is_refused_naming_method_sample_sweep_count_and_cap():
    ok = np.zeros((FORECAST_FLOOR, 3), np.float32)
    big = np.zeros((30_000 * 8 + 1, 3), np.float32)
    check_forecast_size(_Sample(), _Truth(), Forecast(points_ref=(ok, big[:-1])), "m")  # at the caps: accepted
    with pytest.raises(ForecastError) as exc:
        check_forecast_size(_Sample(), _Truth(), Forecast(points_ref=(ok, big)), "spray")
    msg = str(exc.value)
    for part in ("method spray", "sample 08/000005", "future sweep 1", "240,001 points", "cap of 240,000",
                 "8 x the ground truth's 30,000 points", "--max-forecast-ratio"):
        assert part in msg, (part, msg)
    check_forecast_size(_Sample(), _Truth(), Forecast(points_ref=(ok, big)), "spray", ratio=None)  # no cap
    check_forecast_size(_Sample(), _Truth(), Forecast(points_ref=(ok, big)), "spray", ratio=9.0)
    assert forecast_cap(10) == FORECAST_FLOOR and forecast_cap(10**6, 2.0) == 2 * 10**6


class Spray(CopyLast):
    """copy-last's points repeated to one more than the cap's floor in every sweep."""

    name = "spray"

    def forecast(self, sample):
        f = super().forecast(sample)
        return Forecast(points_ref=tuple(np.resize(p, (FORECAST_FLOOR + 1, 3)) for p in f.points_ref))


def sleepy(ctx) -> float:
    time.sleep(5.0)
    return 0.0


SLEEPY = Metric(name="sleepy", version="1", fn=sleepy, description="sleeps 5 s a sweep", higher_is_better=False)


def _spec(root, method, metrics=("chamfer",)):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", 1, metrics)


def _rows(store, spec):
    return Cell(store, spec).read_rows()


def test_run_cell_refuses_a_forecast_over_the_cap_as_the_methods_failure(tiny_kitti, store):
    plugins = load_plugins()
    plugins.methods.add("spray", Spray, "test")
    spec = _spec(tiny_kitti, "spray")
    result = run_cell(spec, store, RunOptions(progress=False), plugins=plugins)  # the default cap
    assert result.failed == 1
    row = _rows(store, spec).iloc[0]
    assert row.status == "failed" and row.error.startswith("ForecastError: method spray, sample ")
    assert f"{FORECAST_FLOOR + 1:,} points, over the cap of {FORECAST_FLOOR:,}" in row.error
    again = run_cell(spec, store, RunOptions(progress=False, forecast_ratio=None, force=True), plugins=plugins)
    assert again.failed == 0  # uncapped: scored


def test_run_cell_records_a_stalled_scoring_as_a_scoring_failure(tiny_kitti, store):
    plugins = load_plugins()
    plugins.metrics.add("sleepy", SLEEPY, "test")
    spec = _spec(tiny_kitti, "copy-last", ("sleepy",))
    result = run_cell(spec, store, RunOptions(progress=False, timeout=60.0, scoring_timeout=1.0, isolate=True),
                      plugins=plugins)
    assert result.failed == 1
    row = _rows(store, spec).iloc[0]
    assert row.error.startswith("ScoringTimeout: sample ") and "scoring time limit of 1 s" in row.error
