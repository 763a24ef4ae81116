"""Compile a run's numba kernels on the idle core while its data is being generated.

The ray casters and the metrics are numba kernels cached on disk (``cache=True``, next to
their source files). On a fresh install the first cell that uses one compiles it, in each of
its worker processes at once: about a minute of the default run went to compiling while
both cores were meant to forecast. Generating the embedded dataset keeps about one core
busy, so ``pcfbench run`` registers a warm-up (:func:`warm_while_preparing`) and a dataset
that is about to generate data for a while calls :func:`preparing_data`: the warm-up then
starts, in one child process on one thread, forecasts a toy sample with each of the run's
methods that need no checkpoint and scores it with the run's metrics. That compiles (or
loads) their kernels into numba's on-disk cache, where the workers find them. The run waits
for it before its first cell, so the two never compete for the cores; when no data is
generated it never starts. Once the data is ready the core the generation used is free too,
so a second child joins in for what is left: each takes the next method nobody has claimed
(a claim is a file created exclusively in a folder the two share), the first in registry
order, the second from the end; from cold the warm-up takes about 71 s of one core and the
default run's test split 35 s (journal/performance-tuning-2026-11.md).

It changes no result: the kernels are the same functions, compiled from the same source, and
numba checks its cache against the source file. A warm-up that fails (a method that cannot
forecast the toy sample) only leaves that kernel to be compiled by the cell, as before; the
cell then reports any real error.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
from typing import Iterator

#: the warm-up ``preparing_data`` starts (one at a time: the CLI's run)
_pending: "KernelWarmup | None" = None


class KernelWarmup:
    """The warm-up of ``methods`` (``NAME`` / ``NAME:k=v`` strings; None: every registered
    method that needs no checkpoint) and ``metrics`` (names), started at most once, helped
    once by a second child when the run stops preparing data (``join``).

    It runs as ``python -c`` in child processes, not through ``multiprocessing``: a script
    that calls the CLI without a ``__main__`` guard is then not imported again."""

    def __init__(self, methods: tuple[str, ...] | None, metrics: tuple[str, ...]) -> None:
        self.methods = None if methods is None else tuple(methods)
        self.metrics = tuple(metrics)
        self.process: subprocess.Popen | None = None
        self.helper: subprocess.Popen | None = None
        self._claims: tempfile.TemporaryDirectory | None = None

    def _spawn(self, reverse: bool) -> subprocess.Popen:
        assert self._claims is not None
        code = "import json, sys; from pcfbench.running.warmup import warm; warm(*json.loads(sys.argv[1]))"
        args = json.dumps([None if self.methods is None else list(self.methods), list(self.metrics),
                           self._claims.name, reverse])
        return subprocess.Popen([sys.executable, "-c", code, args], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def start(self) -> None:
        if self.process is None:
            self._claims = tempfile.TemporaryDirectory(prefix="pcfbench-warmup-")
            self.process = self._spawn(reverse=False)

    def join(self) -> None:
        """Wait for the warm-up: the data is ready, so while the first child is still at it a
        second one takes the methods it has not claimed yet, from the end."""
        if self.process is None:
            return
        if self.helper is None and self.process.poll() is None:
            self.helper = self._spawn(reverse=True)
        for p in (self.process, self.helper):
            if p is not None:
                p.wait()
        self._cleanup()

    def stop(self) -> None:
        """End it now (the run failed or was interrupted: its error should not wait for this)."""
        for p in (self.process, self.helper):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        self._cleanup()

    def _cleanup(self) -> None:
        if self._claims is not None:
            self._claims.cleanup()
            self._claims = None


@contextlib.contextmanager
def warm_while_preparing(methods: tuple[str, ...] | None, metrics: tuple[str, ...]) -> Iterator[KernelWarmup]:
    """Within the block, :func:`preparing_data` starts the warm-up of ``methods`` and
    ``metrics``; leaving the block waits for it (when it started), or ends it when the block
    raised."""
    global _pending
    warmup = KernelWarmup(methods, metrics)
    _pending = warmup
    try:
        yield warmup
    except BaseException:
        warmup.stop()
        raise
    else:
        warmup.join()
    finally:
        _pending = None


def preparing_data() -> None:
    """Say that this process is about to prepare data for a while (generate a split): a
    registered warm-up starts now, on the core that leaves idle."""
    if _pending is not None:
        _pending.start()


def warm(methods: "list[str] | tuple[str, ...] | None", metrics: "list[str] | tuple[str, ...]",
         claims: str | None = None, reverse: bool = False) -> list[str]:
    """Forecast and score the toy sample with each method on one thread; returns the names of
    the methods that ran (the process's exit status says nothing: failures are left to the cells).

    ``claims``: a folder shared with another warm-up: a method is warmed only by the one that
    creates its claim file there first. ``reverse``: take the methods from the last."""
    from pcfbench.execution import ExecutionContext, applied
    from pcfbench.method import resolve_method
    from pcfbench.metrics.base import score_sample
    from pcfbench.plugins import get_plugins
    from pcfbench.testing import toy_sample
    from pcfbench.training import is_trained
    from pcfbench.protocol.validate import validate_forecast

    plugins = get_plugins()
    if methods is None:
        methods = tuple(n for n in plugins.methods.names() if not is_trained(plugins.methods.get(n)))
    done = []
    one = ExecutionContext(1)
    with applied(one):
        try:
            scorers = [plugins.metrics.get(m) for m in metrics]
            sample, truth = toy_sample("kitti-1s")
        except Exception:  # noqa: BLE001 - nothing to warm; the run reports its own errors
            return done
        for i, m in (reversed(list(enumerate(methods))) if reverse else enumerate(methods)):
            if claims is not None and not _claim(claims, i):
                continue
            try:
                spec = resolve_method(m, plugins)
                if is_trained(spec.cls):
                    continue  # its weights load in the cell; its kernels are few
                method = spec.create()
                method.execution = one
                forecast = validate_forecast(sample, method.forecast(sample.for_method()))
                score_sample(sample, truth, forecast, scorers, one)
                done.append(spec.name)
            except Exception:  # noqa: BLE001 - the cell compiles what was not warmed, and reports errors
                continue
    return done


def _claim(folder: str, i: int) -> bool:
    """Whether this process is the first to claim item ``i`` in ``folder``."""
    try:
        os.close(os.open(os.path.join(folder, f"{i}.claim"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    return True


if __name__ == "__main__":  # pragma: no cover - by hand: python -m pcfbench.running.warmup
    print(warm(None, tuple(sys.argv[1:]) or ()))
