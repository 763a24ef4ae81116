"""The Ray executor's task times a sample's two phases apart, as the local executor does: the
method (loading and forecasting) under ``timeout``, the scoring under ``scoring_timeout`` from
when the method returned (``workers.phase``). The task runs in a child process here (its
watchdog kills the process it runs in, as it kills a Ray worker), with a stand-in for
``process_sample``; no Ray is needed."""

from __future__ import annotations

import multiprocessing
import time

import pandas as pd


def _fake_sample(method_s: float, scoring_s: float):
    def process_sample(res, key):
        from pcfbench.running import workers

        time.sleep(method_s)
        workers.phase(workers.SCORING)
        time.sleep(scoring_s)
        seq, i = key
        return [{"sample_id": f"{seq}/{i:06d}", "sequence": seq, "ref_index": i, "step": 0, "status": "ok",
                 "error": None, "traceback": None, "t_load": 0.0}]
    return process_sample


def _task(cell_dir: str, method_s: float, scoring_s: float, timeout: float, scoring_timeout: float) -> None:
    import pcfbench.running.ray_executor as rx
    import pcfbench.running.runner as runner

    runner.process_sample = _fake_sample(method_s, scoring_s)
    rx._resolved = lambda spec, threads: (None, False)
    rx._run_shard(None, cell_dir, 0, 2, [0, 1], [("08", 9), ("08", 10)], 1, timeout, scoring_timeout)


def _run(tmp_path, *args) -> pd.DataFrame:
    ctx = multiprocessing.get_context("spawn")
    p = ctx.Process(target=_task, args=(str(tmp_path), *args))
    p.start()
    p.join(120)
    assert not p.is_alive()
    return pd.concat([pd.read_parquet(f) for f in sorted((tmp_path / "rows").glob("*.parquet"))], ignore_index=True)


def test_a_slow_scoring_is_a_scoring_timeout_not_the_methods(tmp_path):
    rows = _run(tmp_path, 0.0, 60.0, 30.0, 1.0)  # the method is quick; scoring hangs past its 1 s
    assert list(rows["sample_id"]) == ["08/000009"] and list(rows["status"]) == ["failed"]
    assert rows["error"].iloc[0] == ("ScoringTimeout: sample 08/000009: it ran past the scoring time limit of 1 s "
                                     "on its Ray worker")


def test_the_methods_time_is_not_held_to_the_scoring_limit(tmp_path):
    rows = _run(tmp_path, 1.5, 0.0, 30.0, 1.0)  # 1.5 s of method, under its 30 s; the scoring's 1 s starts after
    assert list(rows["status"]) == ["ok", "ok"]


def test_a_slow_method_is_the_methods_timeout(tmp_path):
    rows = _run(tmp_path, 60.0, 0.0, 1.0, 30.0)
    assert list(rows["status"]) == ["failed"]
    assert rows["error"].iloc[0] == "SampleTimeout: sample 08/000009: it ran past the time limit of 1 s on its Ray worker"
