"""Runs a cell's samples as Ray tasks, one task per shard, against a store every node sees.

``pcfbench run/sweep --executor ray`` hands each cell to :class:`RayExecutor` through
``pcfbench.running.runner.run_cell``, which keeps everything else of a cell on the driver: its identity
check, ``cell.json``, what is already done, completion. The executor cuts the cell's sample
list into shards of ``shard_samples`` consecutive samples (fixed by the list, not by what is
left to do) and submits one Ray task per shard that has samples left. A task computes them
and publishes their rows itself as one chunk, ``rows/shard-START-STOP.parquet``
(``pcfbench.store.cells.write_shard``: a temporary file renamed into place), so:

- a finished shard is never recomputed: a rerun of a killed driver finds its rows;
- a task that Ray retries after its worker died (``max_retries``) replaces the same file, so
  its rows are never there twice;
- the rows travel from the worker to the store, not through the driver;
- a shard whose worker dies on every try runs again one task per sample, and a sample whose
  worker dies on every try is one failure row (``SampleCrash``), as the local executor
  records a crash: the cell goes on;
- a sample running past ``timeout`` is a failure row (``SampleTimeout``) too: the task
  publishes what it finished, kills its worker, and Ray's retry does the rest of the shard.

A worker process keeps the last cell it resolved (the dataset adapter, the metrics, the
method, a trained method with its checkpoint loaded), so a worker loads a checkpoint once
for all the shards of a cell it runs, not once per sample or per shard. Trained methods'
tasks ask Ray for ``gpus_per_task`` GPUs. Ray is imported only when an executor starts:
``import pcfbench`` never imports it. docs/cluster.md tells how to run it on a cluster.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import pandas as pd

from pcfbench.errors import PcfbenchError
from pcfbench.store.cells import write_shard

#: Samples per task unless told otherwise: enough that a task's overhead (a few ms) is
#: small against its samples (~0.1-1 s each), few enough to share a cell over many workers.
SHARD_SAMPLES = 16


def shards(n: int, size: int) -> list[tuple[int, int]]:
    """The ``[start, stop)`` ranges that cut a list of ``n`` samples into shards of ``size``."""
    if size < 1:
        raise PcfbenchError(f"a shard must hold at least 1 sample, not {size}")
    return [(a, min(a + size, n)) for a in range(0, n, size)]


def check_gpus(wanted: float, available: float, label: str) -> None:
    """Refuse GPU tasks that no node of the cluster could run (Ray would keep them waiting)."""
    if wanted > available:
        raise PcfbenchError(f"{label}: --gpus-per-task {wanted:g}, and the Ray cluster has {available:g} GPU(s): its "
                            "tasks would wait for ever; add GPU nodes (`ray start --num-gpus N`) or pass --gpus-per-task 0")


def _import_ray():
    try:
        import ray
    except ImportError:
        raise PcfbenchError("--executor ray needs Ray, which is not installed: pip install 'pcfbench[ray]'") from None
    return ray


@dataclass
class RayExecutor:
    """Computes cells' samples as Ray tasks (see the module docstring).

    ``address``: a running cluster (``auto``: the one this machine belongs to, or
    ``HOST:PORT``); None starts a Ray on this machine only, of ``num_cpus`` CPUs (default:
    all). ``cpus_per_task``: the CPUs Ray reserves for a task, and its thread budget.
    ``gpus_per_task``: GPUs reserved for each task of a trained method's cell (0: none).
    ``max_retries``: how often Ray reruns a task whose worker process died. ``timeout``:
    seconds a sample may run (``pcfbench run --timeout``) before it is a failure row.
    """

    address: str | None = None
    shard_samples: int = SHARD_SAMPLES
    cpus_per_task: int = 1
    gpus_per_task: float = 0.0
    max_retries: int = 3
    num_cpus: int | None = None
    #: seconds a sample may run before it is recorded as timed out (None: no limit)
    timeout: float | None = None
    #: per shard run (this process's calls): samples, seconds in the task, worker pid, whether it resolved the cell
    log: list[dict[str, Any]] = field(default_factory=list)
    _task: Any = field(default=None, repr=False)
    _started: bool = field(default=False, repr=False)

    def __post_init__(self) -> None:
        if self.shard_samples < 1 or self.cpus_per_task < 1 or self.gpus_per_task < 0 or self.max_retries < 0:
            raise PcfbenchError(f"Ray executor: shard_samples and cpus_per_task must be >= 1, gpus_per_task and "
                                f"max_retries >= 0 (got {self.shard_samples}, {self.cpus_per_task}, "
                                f"{self.gpus_per_task}, {self.max_retries})")

    def start(self) -> None:
        """Connect to the cluster (or start a local Ray) once; later calls do nothing."""
        if self._task is not None:
            return
        ray = _import_ray()
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
            if self.address is None and self.num_cpus is not None:
                kwargs["num_cpus"] = self.num_cpus
            try:
                ray.init(address=self.address, **kwargs)
            except ConnectionError as exc:
                raise PcfbenchError(f"--address {self.address}: no Ray cluster there ({exc}); start one with "
                                    "`ray start --head` (docs/cluster.md)") from None
            self._started = True
        # max_calls=0: a worker process runs any number of tasks (Ray's default for GPU tasks
        # is one), so that it keeps the cell it resolved, a trained method's weights included.
        self._task = ray.remote(max_calls=0, retry_exceptions=False)(_run_shard)

    def shutdown(self) -> None:
        if self._started:
            _import_ray().shutdown()
        self._task, self._started = None, False

    def __enter__(self) -> "RayExecutor":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def run(self, spec: Any, cell: Any, keys: list[tuple[str, int]], done: set[str],
            progress: Callable[[int], Any] = lambda n: None) -> int:
        """Compute every sample of ``keys`` (the cell's whole list) not in ``done`` as shard
        tasks; each writes its rows to ``cell.dir``. Returns how many samples failed. Bad
        data in a task stops the run with its error; a shard whose worker died on every try
        runs again one task per sample, and such a sample is a failure row."""
        from pcfbench.plugins import get_plugins
        from pcfbench.training import is_trained

        self.start()
        ray = _import_ray()
        ids = [f"{s}/{i:06d}" for s, i in keys]
        trained = is_trained(get_plugins().methods.get(spec.method))
        gpus = self.gpus_per_task if trained else 0
        if gpus:
            check_gpus(gpus, ray.cluster_resources().get("GPU", 0), spec.label)
        task = self._task.options(num_cpus=self.cpus_per_task, num_gpus=gpus, max_retries=self.max_retries)
        spec_ref = ray.put(spec)
        pending: dict[Any, tuple[int, int, list[int]]] = {}

        def submit(start: int, stop: int, todo: list[int]) -> None:
            ref = task.remote(spec_ref, str(cell.dir), start, stop, todo, [keys[i] for i in todo], self.cpus_per_task,
                              self.timeout)
            pending[ref] = (start, stop, todo)

        for start, stop in shards(len(keys), self.shard_samples):
            todo = [i for i in range(start, stop) if ids[i] not in done]
            if todo:
                submit(start, stop, todo)
        failed = 0
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    start, stop, todo = pending.pop(ref)
                    try:
                        result = self._result(ray, ref, cell, start, stop)
                    except _WorkerLost as lost:
                        if len(todo) > 1:  # find the sample that kills its worker: one task per sample
                            for i in todo:
                                submit(i, i + 1, [i])
                            continue
                        # that one sample is a failure row, as the local executor records a crash
                        from pcfbench.running.runner import _failure_row

                        reason = (f"its Ray worker process died on each of {self.max_retries + 1} tries "
                                  f"({lost.kind})")
                        write_shard(cell.dir, start, stop, _failure_row(keys[todo[0]], "crash", reason))
                        result = {"start": start, "stop": stop, "samples": 1, "failed": 1, "crashed": True}
                    self.log.append(result)
                    failed += result["failed"]
                    progress(result["samples"])
        except KeyboardInterrupt:
            raise  # the driver exits, and Ray ends its tasks with it
        except BaseException:
            for ref in pending:  # stopped by an error: what is left is not wanted now
                ray.cancel(ref)
            raise
        return failed

    def _result(self, ray, ref, cell, start: int, stop: int) -> dict[str, Any]:
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, PcfbenchError):
                raise cause from None
            raise PcfbenchError(f"cell {cell.dir}: the task of samples {start}-{stop - 1} raised "
                                f"{type(cause).__name__ if cause else 'an error'}: {cause or exc}") from None
        except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError, ray.exceptions.ObjectLostError) as exc:
            raise _WorkerLost(type(exc).__name__) from None


class _WorkerLost(Exception):
    """A task's worker process died on every try (Ray's retries included)."""

    def __init__(self, kind: str) -> None:
        super().__init__(kind)
        self.kind = kind


# -- in the worker process --------------------------------------------------------------------
_CACHED: tuple[str, Any] | None = None


def _resolved(spec: Any, threads: int) -> tuple[Any, bool]:
    """This worker's resolved cell (built on its first shard of the cell, then kept; one cell
    at a time, so a worker holds one method's weights). Returns it and whether it was built now."""
    global _CACHED
    from pcfbench.execution import ExecutionContext, apply
    from pcfbench.running.runner import resolve
    from pcfbench.store.cells import spec_to_meta

    key = json.dumps([spec_to_meta(spec), threads], sort_keys=True, default=str)
    if _CACHED is not None and _CACHED[0] == key:
        return _CACHED[1], False
    _CACHED = None  # let go of the previous cell's method before loading the next
    execution = ExecutionContext(threads)
    apply(execution)  # before the method is built, so that what it imports starts within the budget
    res = resolve(spec)
    res.bind(execution)
    _CACHED = (key, res)
    return res, True


def _published(cell_dir: Path, start: int, stop: int) -> dict[str, bool]:
    """Samples of shard [start, stop) already in the store, in files of this shard's range
    (one that a timed-out try of this task published before its worker was killed), and
    whether each failed."""
    from pcfbench.store.cells import ROWS_DIR

    out: dict[str, bool] = {}
    for path in sorted((Path(cell_dir) / ROWS_DIR).glob("shard-*.parquet")):
        a, b = (int(x) for x in path.stem.split("-")[1:3])
        if start <= a and b <= stop:
            df = pd.read_parquet(path, columns=["sample_id", "status"])
            for sid, status in zip(df["sample_id"], df["status"]):
                out[sid] = out.get(sid, False) or status == "failed"
    return out


def _run_shard(spec: Any, cell_dir: str, start: int, stop: int, todo: list[int], keys: list[tuple[str, int]],
               threads: int, timeout: float | None = None) -> dict[str, Any]:
    """One task: the rows of ``keys`` (samples ``todo`` of shard [start, stop), not done when
    it was submitted), published as one chunk. A data error propagates (it stops the run).

    With a ``timeout``, a watchdog thread ends a sample running past it the way the local
    executor does: it publishes the rows done so far and a ``SampleTimeout`` row for that
    sample (``shard-FIRST-HUNG+1``), then kills this worker process; Ray's retry of the task
    skips what is published and writes the rest (``shard-HUNG+1-STOP``)."""
    from pcfbench.running.runner import _failure_row, process_sample

    t0 = time.perf_counter()
    published = _published(Path(cell_dir), start, stop)
    ids = [f"{s}/{i:06d}" for s, i in keys]
    remaining = [(i, k) for i, k, sid in zip(todo, keys, ids) if sid not in published]
    failed = sum(published[sid] for sid in ids if sid in published)
    result = {"start": start, "stop": stop, "samples": len(keys), "failed": failed, "pid": os.getpid(),
              "resolved": False, "t_resolve": 0.0, "t_samples": 0.0, "t_write": 0.0}
    if not remaining:
        return {**result, "t_task": time.perf_counter() - t0}
    res, built = _resolved(spec, threads)
    t1 = time.perf_counter()
    first = remaining[0][0]
    rows: list[dict[str, Any]] = []
    lock = threading.Lock()
    current: list[Any] = [None]  # (index, key, start time) of the sample running now
    finished = threading.Event()

    def watchdog() -> None:
        while not finished.wait(min(1.0, timeout / 10)):
            with lock:
                if current[0] is not None and time.monotonic() - current[0][2] > timeout:
                    i, key, _ = current[0]
                    reason = f"it ran past the time limit of {timeout:g} s on its Ray worker"
                    write_shard(Path(cell_dir), first, i + 1, rows + _failure_row(key, "timeout", reason))
                    os.kill(os.getpid(), signal.SIGKILL)  # the only way to stop a hung method; Ray retries the task

    if timeout:
        threading.Thread(target=watchdog, name="pcfbench-timeout", daemon=True).start()
    try:
        for i, key in remaining:
            with lock:
                current[0] = (i, key, time.monotonic())
            sample_rows = process_sample(res, key)
            with lock:
                rows.extend(sample_rows)
                current[0] = None
            failed += sample_rows[0]["status"] == "failed"
    finally:
        finished.set()
    t2 = time.perf_counter()
    write_shard(Path(cell_dir), first, stop, rows)
    return {**result, "failed": failed, "resolved": built, "t_resolve": t1 - t0, "t_samples": t2 - t1,
            "t_write": time.perf_counter() - t2, "t_task": time.perf_counter() - t0}
