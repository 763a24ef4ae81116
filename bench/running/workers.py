"""Supervised worker processes: one sample at a time each, with a time limit, crash isolation
and no orphans.

A method runs a sample in a worker process, never in the driver, so that what it does to its
process cannot take the run down: a worker that dies (a native crash, ``os._exit``, the
kernel's out-of-memory killer), exceeds a time limit or the memory limit is killed and
replaced, and only the sample it held is recorded failed (``on_failure``). The driver hands
out one sample per message, so it always knows which sample a dead worker held.

A sample has two timed phases: the task's own work (loading and the method's forecast), under
``timeout``, and from the task's :func:`phase` ``"scoring"`` message on, the scoring, under
``scoring_timeout``; each phase's clock starts when it does, and a sample over the scoring
limit is a scoring failure, not the method's timeout.

Workers die with the driver, even one SIGKILLed: they start from the ``forkserver``, which
exits when the driver does, and each worker asks the kernel for SIGKILL when its parent (the
forkserver) exits (``PR_SET_PDEATHSIG``, Linux), and watches its pipe to the driver for a
hang-up from a thread (:func:`_die_with_driver`).
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import select
import signal
import sys
import threading
import time
from collections import deque
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as wait_ready
from typing import Any, Callable, Iterator

from pcfbench.errors import PcfbenchError

#: seconds a worker gets to finish its last sample and exit after the driver says stop
STOP_GRACE_S = 5.0
#: seconds a timed-out worker gets to exit on SIGTERM before it is killed (the run waits meanwhile)
TERM_GRACE_S = 1.0
_PR_SET_PDEATHSIG = 1
#: seconds between two looks at the busy workers' resident memory (with a memory limit)
MEMORY_POLL_S = 0.25
#: the phase a task reports when the method's work is done and its scoring begins
SCORING = "scoring"

#: this process's pipe to the driver, in a worker (None elsewhere): :func:`phase` writes to it
_CONN: Connection | None = None
#: in a process another executor runs tasks in (a Ray worker), what :func:`phase` calls instead
_HOOK: Callable[[str], None] | None = None


def phase(name: str) -> None:
    """Tell the driver that the task in this worker entered phase ``name`` (``SCORING``): its
    clock restarts under that phase's limit. In a Ray task, the task's own watchdog is told
    (:func:`phase_hook`). Elsewhere it does nothing."""
    if _CONN is not None:
        _CONN.send(("phase", name))
    elif _HOOK is not None:
        _HOOK(name)


@contextlib.contextmanager
def phase_hook(hook: Callable[[str], None]):
    """Within the block, :func:`phase` calls ``hook`` (the Ray executor's watchdog of a task)."""
    global _HOOK
    before, _HOOK = _HOOK, hook
    try:
        yield
    finally:
        _HOOK = before


def resident_bytes(pid: int) -> int | None:
    """Resident memory of process ``pid`` in bytes (Linux ``/proc``), None when unknown."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def _context() -> multiprocessing.context.BaseContext:
    # forkserver, not fork: metric and method libraries run threads (numba, OpenMP k-d trees,
    # torch), and a child forked while one of them holds a lock deadlocks. Preloading the
    # runner makes each worker a cheap fork of a process that has imported it once.
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["pcfbench.running.runner"])
    _start_helpers_ignoring_sigint()
    return ctx


def _start_helpers_ignoring_sigint() -> None:
    """Start multiprocessing's resource tracker and the forkserver (each once per driver) with
    SIGINT ignored, a disposition a started program keeps, and the forkserver hands on to every
    worker it forks. Ctrl-C at a terminal goes to the whole foreground process group, and it is
    the driver's to answer (it stops the workers through their own exit and says what it kept,
    ``pcfbench.cli.interrupted_note``): a helper still starting Python or importing the runner,
    or a worker setting up, would otherwise die of it with a KeyboardInterrupt traceback (or a
    fatal error) over the driver's message, and a dead forkserver fails the run.
    The driver ignores SIGINT only while it forks and execs them (milliseconds; a Ctrl-C in that
    window is lost, a second one is answered). Off the main thread (where a handler cannot be set)
    they start as multiprocessing starts them."""
    from multiprocessing import forkserver, resource_tracker

    if threading.current_thread() is not threading.main_thread():
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        resource_tracker.ensure_running()
        forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, before)


def _die_with_driver(conn: Connection) -> None:
    """Exit when the driver does. The kernel sends SIGKILL when the parent (the forkserver,
    which exits with the driver) exits (``PR_SET_PDEATHSIG``, Linux), even while native code
    holds the GIL; a watcher thread exits when the driver's end of ``conn`` hangs up, which
    also covers a driver that died before this process got to ask the kernel."""
    parent = os.getppid()
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no libc prctl
            pass
    hangup = getattr(select, "POLLRDHUP", 0x2000) | select.POLLHUP | select.POLLERR | select.POLLNVAL
    poller = select.poll()
    poller.register(conn.fileno(), hangup)  # not POLLIN: the tasks are the main thread's to read

    def watch() -> None:
        while True:
            if os.getppid() != parent or any(event & hangup for _, event in poller.poll(500)):
                os._exit(70)

    threading.Thread(target=watch, name="pcfbench-driver-watch", daemon=True).start()


#: seconds between the repeats of a stop that a worker's finalizer swallowed (:func:`_exit_on_term`)
STOP_REPEAT_S = 0.2


def _exit_on_term(signum: int, frame: Any) -> None:
    """SIGTERM: exit through Python (SystemExit). One raised while the worker runs a finalizer
    (a ``__del__`` or weakref callback: numba's and llvmlite's run often) cannot propagate:
    Python prints it as "Exception ignored in ..." on the stderr the worker shares with the
    driver, and goes on with the sample. So a stopped worker's stderr goes to /dev/null first
    (the driver says why the run stopped; nothing a stopped worker says is wanted), and the stop
    repeats every ``STOP_REPEAT_S`` (SIGALRM) until one lands where it propagates; the worker's
    exit ends the repeats (:func:`_stopped`)."""
    _silence_stderr()
    signal.signal(signal.SIGALRM, _exit_on_term)
    signal.setitimer(signal.ITIMER_REAL, STOP_REPEAT_S)
    raise SystemExit(128 + signal.SIGTERM)


def _silence_stderr() -> None:
    try:
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
    except OSError:  # pragma: no cover - no /dev/null
        pass


def _stopped() -> None:
    """The stop propagated: no more repeats, so that the worker's exit (its finalizers: the
    named semaphore) runs to the end."""
    signal.setitimer(signal.ITIMER_REAL, 0)


def _worker_main(conn: Connection, init: Callable[..., None], init_args: tuple, task: Callable[[Any], Any]) -> None:
    """A worker's life: set up (``init(*init_args)``), then answer one task per message until
    told to stop (``None``) or the driver's end of the pipe closes.

    SIGTERM (the driver stopping a busy worker, :func:`_stop`) exits through Python, so that the
    process's finalizers run: a named semaphore the worker made (a ``multiprocessing`` lock) is
    registered with the resource tracker the driver shares, and one a killed worker leaves
    behind is what the tracker warns about ("leaked semaphore") at the driver's exit."""
    signal.signal(signal.SIGTERM, _exit_on_term)
    # Ctrl-C is the driver's to answer (it stops this worker with SIGTERM): ignored from the fork on
    # (_start_helpers_ignoring_sigint); again here for a forkserver that another module started.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # A process this worker starts is spawned, never forked (a fork of a process running numba,
    # OpenMP or torch threads can deadlock). numba reads it: it makes its init lock a named
    # semaphore only under a fork start method, so a worker killed after all (a hang past the
    # grace, a crash) leaves none behind.
    multiprocessing.set_start_method("spawn", force=True)
    _die_with_driver(conn)
    global _CONN
    _CONN = conn
    try:
        init(*init_args)
    except SystemExit:  # told to stop while setting up
        _stopped()
        return
    except BaseException as exc:  # noqa: BLE001 - every setup failure goes back to the driver
        _send_error(conn, "init-error", exc)
        return
    conn.send(("ready", None))
    while True:
        try:
            key = conn.recv()
        except (EOFError, OSError):  # the driver is gone
            return
        if key is None:
            return
        try:
            result = task(key)
        except SystemExit:  # told to stop mid-sample: its result is not wanted
            _stopped()
            return
        except BaseException as exc:  # noqa: BLE001 - data errors stop the run: the driver raises them
            _send_error(conn, "error", exc)
            return
        conn.send(("done", result))


def _send_error(conn: Connection, kind: str, exc: BaseException) -> None:
    try:
        conn.send((kind, exc))
    except Exception:  # an exception that does not pickle: its type and message
        conn.send((kind, PcfbenchError(f"{type(exc).__name__}: {exc}")))


def exit_description(code: int | None) -> str:
    """``-11`` -> ``signal SIGSEGV``; ``3`` -> ``exit code 3``."""
    if code is None:
        return "an unknown status"
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


class _Worker:
    def __init__(self, ctx, init, init_args, task) -> None:
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_worker_main, args=(child, init, init_args, task), daemon=True,
                                   name="pcfbench-worker")
        try:
            self.process.start()
        finally:
            child.close()
        self.ready = False
        self.stopping = False  # told to exit (None sent)
        self.exiting = False  # sent an error and exits on its own
        self.key: Any = None
        self.started = 0.0  # when the key's current phase began (time.monotonic)
        self.phase: str | None = None  # None: the task's own work; SCORING once it says so
        self.kind: Any = None  # the affinity of its last key (run_supervised)

    def kill(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join()
        self.conn.close()


def run_supervised(
    keys: list[Any],
    jobs: int,
    init: Callable[..., None],
    init_args: tuple,
    task: Callable[[Any], Any],
    on_failure: Callable[[Any, str, str], Any],
    timeout: float | None = None,
    scoring_timeout: float | None = None,
    max_memory: int | None = None,
    affinity: Callable[[Any], Any] | None = None,
) -> Iterator[Any]:
    """Yield ``task(key)`` for every key (in completion order) from ``jobs`` worker processes.

    Each worker runs ``init(*init_args)`` once, then one key at a time. A key whose worker dies,
    runs past ``timeout`` seconds before it reports :func:`phase` ``SCORING`` or past
    ``scoring_timeout`` seconds after, or whose process holds more than ``max_memory`` bytes of
    resident memory, yields ``on_failure(key, kind, message)`` (``kind``: ``"crash"``,
    ``"timeout"``, ``"scoring-timeout"`` or ``"memory"``) instead, and a new worker takes over
    the remaining keys. An exception raised by ``init`` or ``task`` in a worker is raised here
    (the run stops), as is a worker dying during ``init`` (it would die again in every replacement).

    ``affinity(key)``: keys with the same value go to one worker in turn where it can be (a
    worker that finished one takes the next of its kind; one whose kind is done takes the first
    kind no other worker had last), so that it reuses what it kept of the last (a sample's tasks,
    one per method). Near the end, when every kind left is another worker's, a free worker
    helps with one rather than wait. Without it, keys go out in order.

    ``init``, ``init_args`` and ``task`` are sent to the workers (picklable, importable).
    """
    ctx = _context()
    todo = _Todo(keys, affinity)
    workers: list[_Worker] = []

    def spawn() -> None:
        workers.append(_Worker(ctx, init, init_args, task))

    try:
        for _ in range(max(1, min(jobs, len(todo)))):
            spawn()
        while workers:
            for w in workers:
                if w.ready and w.key is None and not w.stopping:
                    if todo:
                        held = {x.kind for x in workers if x is not w}  # a free one takes its own kind next
                        w.key, w.started, w.phase = todo.take(w.kind, held), time.monotonic(), None
                        w.kind = todo.kind(w.key)
                        w.conn.send(w.key)
                    else:  # nothing left for it (also one that got ready after the others took every key)
                        w.stopping = True
                        w.conn.send(None)
            busy = [w for w in workers if w.key is not None]
            ends = [w.started + limit for w in busy if (limit := _limit(w, timeout, scoring_timeout)) is not None]
            wait_s = max(0.0, min(ends) - time.monotonic()) if ends else None
            if max_memory is not None and busy:
                wait_s = MEMORY_POLL_S if wait_s is None else min(wait_s, MEMORY_POLL_S)
            ready = set(wait_ready([w.conn for w in workers] + [w.process.sentinel for w in workers], wait_s))
            for w in list(workers):
                message = None
                if w.conn in ready or w.process.sentinel in ready:
                    try:
                        message = w.conn.recv() if w.conn.poll() else None
                    except (EOFError, OSError):
                        message = None
                if message is not None:
                    kind, value = message
                    if kind in ("error", "init-error"):
                        w.exiting = True
                        raise value
                    if kind == "ready":
                        w.ready = True
                    elif kind == "phase":
                        w.phase, w.started = value, time.monotonic()
                    else:
                        w.key = None
                        yield value
                    continue
                if w.process.sentinel in ready or not w.process.is_alive():
                    w.process.join()
                    code = w.process.exitcode
                    workers.remove(w)
                    w.conn.close()
                    if w.key is None and not w.ready:
                        raise PcfbenchError(f"a worker process died with {exit_description(code)} while setting up "
                                            "(resolving the method, dataset and metrics)")
                    if w.key is not None:
                        yield on_failure(w.key, "crash", f"its worker process died with {exit_description(code)}")
                    if todo:
                        spawn()
                    continue
                if w.key is None:
                    continue
                limit = _limit(w, timeout, scoring_timeout)
                failure = None
                if limit is not None and time.monotonic() - w.started > limit:
                    failure = (("timeout", f"it ran longer than the per-sample time limit of {limit:g} s")
                               if w.phase is None else
                               ("scoring-timeout", f"scoring its forecast took longer than the scoring time limit of "
                                                   f"{limit:g} s (the method's forecast was done)"))
                elif max_memory is not None:
                    used = resident_bytes(w.process.pid)
                    if used is not None and used > max_memory:
                        failure = ("memory", f"its worker process held {used / 2**30:.2f} GiB of memory, over the "
                                             f"per-sample memory limit of {max_memory / 2**30:g} GiB"
                                             + (" (while scoring)" if w.phase == SCORING else ""))
                if failure is not None:
                    workers.remove(w)
                    w.process.terminate()  # a sample hung in Python exits through its finalizers (_stop)
                    w.process.join(TERM_GRACE_S)
                    w.kill()
                    yield on_failure(w.key, *failure)
                    if todo:
                        spawn()
    finally:
        _stop(workers)


class _Todo:
    """The keys still to hand out, by affinity (``run_supervised``), in order within each kind
    and kinds in order of their first key."""

    def __init__(self, keys: list[Any], affinity: Callable[[Any], Any] | None) -> None:
        self.affinity = affinity
        self.kinds: dict[Any, deque] = {}
        for key in keys:
            self.kinds.setdefault(self.kind(key), deque()).append(key)

    def kind(self, key: Any) -> Any:
        return None if self.affinity is None else self.affinity(key)

    def __bool__(self) -> bool:
        return bool(self.kinds)

    def __len__(self) -> int:
        return sum(len(q) for q in self.kinds.values())

    def take(self, prefer: Any, held: set) -> Any:
        """The next key: of kind ``prefer`` if any is left, else of the first kind not ``held``,
        else of the first kind."""
        kind = prefer if prefer in self.kinds else next((k for k in self.kinds if k not in held), next(iter(self.kinds)))
        queue = self.kinds[kind]
        key = queue.popleft()
        if not queue:
            del self.kinds[kind]
        return key


def _limit(w: _Worker, timeout: float | None, scoring_timeout: float | None) -> float | None:
    """The time limit of the phase worker ``w``'s key is in (None: none)."""
    return timeout if w.phase is None else scoring_timeout


def _stop(workers: list[_Worker]) -> None:
    """Stop every worker after an error or an interrupt, each through its own exit (so its
    finalizers run, :func:`_worker_main`): an idle one is told to exit, a busy one (a sample
    whose result nobody will read) or one setting up gets SIGTERM, and one that sent an error
    is already exiting. Whatever is left after ``STOP_GRACE_S`` (native code that does not
    return to Python) is killed."""
    for w in workers:
        if w.exiting or w.stopping:
            continue
        if w.ready and w.key is None:
            try:
                w.conn.send(None)
                w.stopping = True
                continue
            except (OSError, ValueError):
                pass
        if w.process.is_alive():
            w.process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for w in workers:
        w.process.join(max(0.0, deadline - time.monotonic()))
        w.kill()
