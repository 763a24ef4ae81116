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

A driver that starts a Ray of its own records that Ray's processes (its GCS, raylet, the
raylet's agents) in ``<cache>/ray-drivers/<driver pid>.json``; a driver killed with SIGKILL
cannot stop them, and Ray's agents outlive it by minutes (about 175 MB), so the next
``RayExecutor.start`` on this machine stops what a dead driver's record names (each process
known by its pid and its start time, so a reused pid is never touched) and says so, or
prints the ``kill`` command when it may not. A Ray that dies under a run (its raylet, or an
agent the raylet goes down with) is one error saying what died and how to resume.

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
import sys
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


#: Folder (under the cache) of the records of drivers that started a Ray of their own.
RAY_RECORDS = "ray-drivers"
#: Seconds a stale Ray process has to exit after SIGTERM before it gets SIGKILL.
STOP_WAIT_S = 3.0


def _proc_start(pid: int) -> int | None:
    """The start time (clock ticks since boot, /proc/PID/stat) of a running process; None
    when there is none (or only a zombie) or /proc cannot tell. With the pid, it names one
    process: a pid reused by a later process has another start time."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) ": state, ppid, ...
    return None if fields[0] in "ZX" else int(fields[19])


def _ray_name(pid: int) -> str | None:
    """A Ray process's name (``ray::DashboardAgent``, ``raylet``, ``gcs_server``, ``monitor.py``),
    from its command line; None for a process that is not Ray's."""
    try:
        args = [a.decode(errors="replace") for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0") if a]
    except OSError:
        return None
    for a in args[:2]:
        if a.startswith("ray::"):
            return a.split()[0]
        if f"{os.sep}ray{os.sep}" in a:
            return a.rsplit(os.sep, 1)[-1]
    return None


def _proc_rss_mb(pid: int) -> float:
    try:
        return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def _descendants(pid: int) -> list[int]:
    """The pids of every process below ``pid`` (children, theirs, ...), read from /proc."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            children.setdefault(int(stat[stat.rindex(")") + 2:].split()[1]), []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def record_local_ray(records: Path, driver: int | None = None) -> Path | None:
    """Write ``records/<driver pid>.json``: the driver (pid, start time) and every process
    of Ray's below it now (its GCS, raylet, the raylet's agents, workers). None where /proc
    is missing (not Linux)."""
    driver = os.getpid() if driver is None else driver
    start = _proc_start(driver)
    if start is None:
        return None
    procs = []
    for p in _descendants(driver):
        name, t = _ray_name(p), _proc_start(p)
        if name is not None and t is not None:
            procs.append({"pid": p, "start": t, "name": name})
    records.mkdir(parents=True, exist_ok=True)
    path = records / f"{driver}.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps({"driver": {"pid": driver, "start": start}, "processes": procs}))
    os.replace(tmp, path)
    return path


def stop_stale_rays(records: Path, wait_s: float = STOP_WAIT_S) -> list[str]:
    """Stop the Ray processes of every record in ``records`` whose driver is gone (killed
    before it could stop its Ray): SIGTERM, then SIGKILL after ``wait_s``. A process counts
    only with its recorded start time. Returns one line per record acted on, saying what was
    stopped, or the command to run where this user may not stop it; the record is removed
    once nothing of it is left."""
    lines = []
    for path in sorted(records.glob("*.json")) if records.is_dir() else []:
        try:
            rec = json.loads(path.read_text())
            driver = rec["driver"]
            procs = [(int(p["pid"]), int(p["start"]), str(p.get("name", "?"))) for p in rec["processes"]]
        except (OSError, ValueError, KeyError, TypeError):
            path.unlink(missing_ok=True)  # cut short by the kill itself: nothing to go by
            continue
        if _proc_start(int(driver["pid"])) == int(driver["start"]):
            continue  # that driver is running: its Ray is in use
        started = {pid: start for pid, start, _ in procs}
        alive = [(pid, name) for pid, start, name in procs if _proc_start(pid) == start]
        if not alive:
            path.unlink(missing_ok=True)
            continue
        mb = sum(_proc_rss_mb(pid) for pid, _ in alive)
        names = ", ".join(sorted({name for _, name in alive}))
        left, refused = alive, []
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid, name in left:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
                except PermissionError:
                    refused.append((pid, name))
            left = [p for p in left if p not in refused]
            deadline = time.monotonic() + wait_s
            while left and time.monotonic() < deadline:
                time.sleep(0.05)
                left = [(pid, name) for pid, name in left if _proc_start(pid) == started[pid]]
            if not left:
                break
        if refused or left:
            stuck = refused + left
            lines.append(f"Ray processes left running by driver {driver['pid']}, which was killed, could not be stopped: "
                         f"{', '.join(f'{pid} ({name})' for pid, name in stuck)}; stop them with "
                         f"`kill -9 {' '.join(str(pid) for pid, _ in stuck)}` (or `ray stop`, which stops every Ray "
                         "on this machine)")
        else:
            path.unlink(missing_ok=True)
            lines.append(f"stopped {len(alive)} Ray process(es) ({names}; {mb:.0f} MB) left running by driver "
                         f"{driver['pid']}, which was killed before it could stop them")
    return lines


def _records_dir() -> Path:
    from pcfbench.config import cache_dir

    return cache_dir() / RAY_RECORDS


def _note(message: str) -> None:
    print(f"pcfbench: note: {message}", file=sys.stderr)


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
    #: seconds its scoring may run, timed from when the method returned (None: no limit)
    scoring_timeout: float | None = None
    #: per shard run (this process's calls): samples, seconds in the task, worker pid, whether it resolved the cell
    log: list[dict[str, Any]] = field(default_factory=list)
    #: where notes go (a stale Ray stopped at start): stderr
    note: Callable[[str], Any] = field(default=_note, repr=False)
    _task: Any = field(default=None, repr=False)
    _started: bool = field(default=False, repr=False)
    _record_path: Path | None = field(default=None, repr=False)

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
            for line in stop_stale_rays(_records_dir()):
                self.note(line)
            kwargs: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
            if self.address is None and self.num_cpus is not None:
                kwargs["num_cpus"] = self.num_cpus
            try:
                ray.init(address=self.address, **kwargs)
            except ConnectionError as exc:
                raise PcfbenchError(f"--address {self.address}: no Ray cluster there ({exc}); start one with "
                                    "`ray start --head` (docs/cluster.md)") from None
            self._started = True
            self._record()
        # max_calls=0: a worker process runs any number of tasks (Ray's default for GPU tasks
        # is one), so that it keeps the cell it resolved, a trained method's weights included.
        self._task = ray.remote(max_calls=0, retry_exceptions=False)(_run_shard)

    def _record(self) -> None:
        """Name this driver's own Ray's processes in its record (a Ray it joined is not its own)."""
        if self._started and self.address is None:
            self._record_path = record_local_ray(_records_dir())

    def shutdown(self) -> None:
        if self._started:
            _import_ray().shutdown()
            if self._record_path is not None:
                self._record_path.unlink(missing_ok=True)
        self._task, self._started, self._record_path = None, False, None

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
        runs again one task per sample, and such a sample is a failure row. Ray dying under
        it (:class:`RayDied`) is one error saying so and how to resume."""
        self.start()
        ray = _import_ray()
        try:
            return self._run(ray, spec, cell, keys, done, progress)
        except (ray.exceptions.LocalRayletDiedError, ray.exceptions.RaySystemError) as exc:
            raise RayDied(exc, cell.dir) from None

    def _run(self, ray, spec: Any, cell: Any, keys: list[tuple[str, int]], done: set[str],
             progress: Callable[[int], Any]) -> int:
        from pcfbench.plugins import get_plugins
        from pcfbench.training import is_trained

        self._record()  # the raylet's agents and workers as they are now
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
                              self.timeout, self.scoring_timeout)
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
                try:
                    ray.cancel(ref)
                except Exception:  # noqa: BLE001 - a dead Ray cannot cancel; the error that stopped the run is the one to show
                    break
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


class RayDied(PcfbenchError):
    """Ray itself failed under a run: its raylet died (or an agent it goes down with)."""

    def __init__(self, exc: BaseException, cell_dir: Path) -> None:
        what = "its raylet (the process that runs tasks on this node) died"
        if not isinstance(exc, _import_ray().exceptions.LocalRayletDiedError):
            what = "it failed"
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        super().__init__(
            f"Ray stopped the run: {what} ({type(exc).__name__}{': ' + detail if detail else ''}). The samples "
            f"finished so far are kept in {cell_dir}: run the same command again to resume, and only the rest is "
            "computed. If Ray processes are left over, the next run stops them (or `ray stop` does now)"
        )


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
               threads: int, timeout: float | None = None, scoring_timeout: float | None = None) -> dict[str, Any]:
    """One task: the rows of ``keys`` (samples ``todo`` of shard [start, stop), not done when
    it was submitted), published as one chunk. A data error propagates (it stops the run).

    With a ``timeout`` or a ``scoring_timeout``, a watchdog thread ends a sample running past
    the limit of its phase the way the local executor does (``timeout`` for loading and the
    method's forecast; ``scoring_timeout`` from when the method returned, told by
    :func:`pcfbench.running.workers.phase`): it publishes the rows done so far and a
    ``SampleTimeout`` (or ``ScoringTimeout``) row for that sample (``shard-FIRST-HUNG+1``),
    then kills this worker process; Ray's retry of the task skips what is published and writes
    the rest (``shard-HUNG+1-STOP``)."""
    from pcfbench.running import workers
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
    current: list[Any] = [None]  # (index, key, start time of its phase, phase) of the sample running now
    finished = threading.Event()
    limits = [t for t in (timeout, scoring_timeout) if t]

    def scoring(name: str) -> None:  # workers.phase: the method returned; the scoring's clock starts
        with lock:
            if current[0] is not None:
                current[0] = (*current[0][:2], time.monotonic(), name)

    def watchdog() -> None:
        while not finished.wait(min(1.0, min(limits) / 10)):
            with lock:
                if current[0] is None:
                    continue
                i, key, began, ph = current[0]
                limit = timeout if ph is None else scoring_timeout
                if limit and time.monotonic() - began > limit:
                    what = "time limit" if ph is None else "scoring time limit"
                    reason = f"it ran past the {what} of {limit:g} s on its Ray worker"
                    kind = "timeout" if ph is None else "scoring-timeout"
                    write_shard(Path(cell_dir), first, i + 1, rows + _failure_row(key, kind, reason))
                    os.kill(os.getpid(), signal.SIGKILL)  # the only way to stop a hung method; Ray retries the task

    if limits:
        threading.Thread(target=watchdog, name="pcfbench-timeout", daemon=True).start()
    try:
        with workers.phase_hook(scoring):
            for i, key in remaining:
                with lock:
                    current[0] = (i, key, time.monotonic(), None)
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
