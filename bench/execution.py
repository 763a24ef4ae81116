"""The thread budget of a process, and the one pool of threads that works within it.

An ``ExecutionContext(threads=n)`` says how many threads the code running under it may keep
busy at once. The runner decides it (``--jobs N`` with a budget of C threads: each worker
gets ``max(1, C // N)``; a serial run all C) and hands it to the method
(``Method.execution``) and to the metrics (``score_sample``). ``apply`` (a worker process,
for good) and ``applied`` (the calling process, for a while) pin numba, torch and the
BLAS/OpenMP libraries to it.

Invariant: under a context of n threads at most n threads are busy. The calling thread either
works itself (numba kernels, torch and BLAS on at most n threads once the context is applied)
or waits while ``map`` or ``pool`` jobs run on the context's pool of n threads, each of which
runs its numba kernels and OpenMP regions on one thread. Pool jobs must not call threaded
BLAS on large arrays: OpenBLAS's thread count is process-wide, not per thread.

Importing a pcfbench module changes no thread setting; before its first parallel work
(``map``, ``pool``, ``apply``) pcfbench asks numba for its OpenMP layer (``_prefer_omp``).

Results must not depend on the number of threads: work is cut into pieces whose answers do
not depend on the cut (tests/running/test_execution.py compares 1, 2 and 3 threads bit for bit).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, TypeVar

from pcfbench.errors import PcfbenchError

_T = TypeVar("_T")
_R = TypeVar("_R")

#: environment variables that libraries loaded after ``apply`` read their default thread count from
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the platform has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


def _check_count(value: object, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise PcfbenchError(f"{what} must be an integer >= 1, not {value!r}")
    return value


@dataclass(frozen=True)
class ExecutionContext:
    """A thread budget: at most ``threads`` (>= 1) threads busy at once (see the module docstring)."""

    threads: int = field(default_factory=available_cpus)

    def __post_init__(self) -> None:
        _check_count(self.threads, "ExecutionContext threads")

    def share(self, jobs: int) -> "ExecutionContext":
        """The budget of each of ``jobs`` processes sharing this one: ``max(1, threads // jobs)``."""
        _check_count(jobs, "number of worker processes")
        return ExecutionContext(max(1, self.threads // jobs))

    def pool(self) -> ThreadPoolExecutor:
        """This process's pool of ``threads`` workers (made on first use, then kept, so that the
        workers' thread-local buffers are too). Each worker runs numba kernels and OpenMP
        regions on one thread. Jobs may wait for jobs submitted before them (the queue is
        first in, first out), never for later ones."""
        _prefer_omp()
        with _POOLS_LOCK:
            pool = _POOLS.get(self.threads)
            if pool is None:
                pool = _POOLS[self.threads] = _Pool(
                    max_workers=self.threads, thread_name_prefix=f"pcfbench-{self.threads}", initializer=_pin_pool_thread
                )
            return pool

    def map(self, fn: Callable[[_T], _R], items: Iterable[_T]) -> list[_R]:
        """``[fn(x) for x in items]``, the items shared out over the pool as its workers come
        free; in this thread, numba on one thread, when there is one thread or one item or
        this thread is itself a pool worker (a job never waits for the pool it runs in)."""
        items = list(items)
        _prefer_omp()  # the jobs run numba's parallel kernels, concurrently
        if self.threads == 1 or len(items) <= 1 or in_pool_worker():
            import numba

            before = numba.get_num_threads()
            numba.set_num_threads(1)
            try:
                return [fn(x) for x in items]
            finally:
                numba.set_num_threads(before)
        return list(self.pool().map(fn, items))


class _Pool(ThreadPoolExecutor):
    """A context's pool: each job first pins its worker again when modules were imported
    since the worker was pinned. A library imported later (torch, open3d: each imported on
    first use) may bring its own OpenMP runtime, which the worker had not pinned."""

    def submit(self, fn, /, *args, **kwargs):
        return super().submit(_repinned, fn, *args, **kwargs)


def _repinned(fn, *args, **kwargs):
    if getattr(_WORKER, "modules", None) != len(sys.modules):
        _pin_pool_thread()
    return fn(*args, **kwargs)


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()
_CURRENT: ExecutionContext | None = None
_WORKER = threading.local()


def in_pool_worker() -> bool:
    """True in a worker thread of a context's pool (work started there stays on that thread)."""
    return getattr(_WORKER, "active", False)


def _forget_pools_in_child() -> None:  # a forked child has the dicts but not the threads
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools_in_child)


def _pin_pool_thread() -> None:
    """Initializer of a pool worker: its numba kernels and OpenMP regions use one thread.

    Both settings are per thread (numba's thread count and OpenMP's nthreads-var), so they
    do not touch the thread that submits the work."""
    import numba
    from threadpoolctl import threadpool_limits

    _WORKER.modules = len(sys.modules)
    numba.set_num_threads(1)
    threadpool_limits(1, user_api="openmp")
    _WORKER.active = True


def pool_sizes() -> list[int]:
    """Worker counts of the pools this process has made (live ones)."""
    with _POOLS_LOCK:
        return sorted(p._max_workers for p in _POOLS.values())


def current() -> ExecutionContext:
    """The context ``apply`` or ``applied`` gave this process, else one of every CPU it may use."""
    return _CURRENT if _CURRENT is not None else ExecutionContext()


def _prefer_omp() -> None:
    """Ask numba for its OpenMP threading layer first, unless numba has chosen one already or
    the user named one: the pool workers launch numba kernels concurrently, which the
    workqueue layer cannot do, and an older TBB than numba wants (open3d ships one) makes
    every process warn. Called before pcfbench's parallel work, never at import."""
    import numba

    try:
        from numba.np.ufunc import parallel
    except ImportError:  # pragma: no cover - numba moved it; keep numba's own choice
        return
    if (getattr(parallel, "_is_initialized", True) or numba.config.THREADING_LAYER != "default"
            or "NUMBA_THREADING_LAYER_PRIORITY" in os.environ):
        return
    order = list(numba.config.THREADING_LAYER_PRIORITY)
    numba.config.THREADING_LAYER_PRIORITY = ["omp"] + [layer for layer in order if layer != "omp"]


def _numba_threads(n: int) -> int:
    import numba

    return max(1, min(n, numba.config.NUMBA_NUM_THREADS))


def apply(context: ExecutionContext) -> None:
    """Pin this whole process to ``context`` for good (a worker process of the runner).

    numba (this thread), torch (intra-op threads; inter-op threads to 1 where torch still
    allows it), the BLAS and OpenMP libraries loaded now (threadpoolctl), and the thread
    environment variables (``THREAD_ENV``) that libraries loaded later start from.
    """
    global _CURRENT
    import numba
    from threadpoolctl import threadpool_limits

    n = context.threads
    _prefer_omp()
    for var in THREAD_ENV:
        os.environ[var] = str(n)
    numba.set_num_threads(_numba_threads(n))
    threadpool_limits(n)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
        with contextlib.suppress(RuntimeError):  # only before torch's first inter-op work
            torch.set_num_interop_threads(1)
    _CURRENT = context


@contextlib.contextmanager
def applied(context: ExecutionContext) -> Iterator[ExecutionContext]:
    """``apply`` for the duration of a ``with`` block in the calling thread, then put back what
    was there (a serial run inside someone else's process). Torch's inter-op threads are
    left alone: they can be set only once per process."""
    global _CURRENT
    import numba
    from threadpoolctl import threadpool_limits

    n = context.threads
    _prefer_omp()
    before_env = {var: os.environ.get(var) for var in THREAD_ENV}
    before_numba = numba.get_num_threads()
    torch = sys.modules.get("torch")
    before_torch = torch.get_num_threads() if torch is not None else None
    before_current = _CURRENT
    try:
        with threadpool_limits(n):
            for var in THREAD_ENV:
                os.environ[var] = str(n)
            numba.set_num_threads(_numba_threads(n))
            if torch is not None:
                torch.set_num_threads(n)
            _CURRENT = context
            yield context
    finally:
        _CURRENT = before_current
        numba.set_num_threads(before_numba)
        if torch is not None:
            torch.set_num_threads(before_torch)
        for var, value in before_env.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def thread_limits() -> dict[str, object]:
    """What this thread and process are pinned to now: numba (this thread), torch (when
    imported), each BLAS/OpenMP library (threadpoolctl; OpenMP's value is this thread's) and
    the pools' worker counts."""
    import numba
    from threadpoolctl import threadpool_info

    torch = sys.modules.get("torch")
    return {
        "numba": numba.get_num_threads(),
        "torch": torch.get_num_threads() if torch is not None else None,
        "libraries": {f"{i['internal_api']}:{os.path.basename(i['filepath'])}": i["num_threads"] for i in threadpool_info()},
        "pools": pool_sizes(),
    }
