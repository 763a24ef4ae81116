"""Ctrl-C that lands in a finalizer is delivered again, not lost.

Python runs a signal's handler at the next bytecode the main thread executes. When that is a
finalizer's (a ``__del__`` or a weakref callback: the garbage collector's, numba's and llvmlite's
run often during a sample), the KeyboardInterrupt it raises cannot propagate: Python prints it as
"Exception ignored in ..." with a traceback and goes on as if Ctrl-C had never been pressed, and
the user has to press it again. :func:`redeliver_swallowed_interrupts` installs a
``sys.unraisablehook`` that says nothing of such an interrupt and raises it again a moment later
(``REDELIVER_S``, SIGALRM), outside the finalizer, until one lands where it propagates (the
interrupted command then says what it kept, :func:`pcfbench.cli.interrupted_note`). Every other
unraisable exception goes to the hook that was there before.

The hook raises nothing itself (an exception in the hook is printed as one, and lost): the
interrupt comes from the alarm's handler, which waits while the hook runs. Whoever catches an
interrupt to say what it stopped calls :func:`handled` first, so that a redelivery still pending
(the same Ctrl-C, lost once and delivered once) does not interrupt the saying. One lost while
the process exits (an exit callback, the interpreter's teardown) is dropped: there is nothing
left to interrupt.
"""

from __future__ import annotations

import atexit
import signal
import sys
from typing import Any, NoReturn

#: seconds from a swallowed interrupt to its redelivery
REDELIVER_S = 0.01

_in_hook = False
_alarm_before: Any = None


def _alarm(signum: int, frame: Any) -> None:
    if _in_hook:  # not inside the hook: later
        signal.setitimer(signal.ITIMER_REAL, REDELIVER_S)
        return
    signal.signal(signal.SIGALRM, _alarm_before)
    raise KeyboardInterrupt


def _redeliver(previous):
    def hook(unraisable: Any) -> None:
        global _in_hook, _alarm_before
        if not (isinstance(unraisable.exc_value, KeyboardInterrupt) and callable(signal.getsignal(signal.SIGINT))):
            previous(unraisable)
            return
        if sys.is_finalizing():  # the process is exiting: nothing left to interrupt, and no alarm may outlive
            return  # the interpreter's signal handlers (SIGALRM would end the process)
        _in_hook = True
        try:
            if signal.getsignal(signal.SIGALRM) is not _alarm:
                _alarm_before = signal.signal(signal.SIGALRM, _alarm)
            signal.setitimer(signal.ITIMER_REAL, REDELIVER_S)
        finally:
            _in_hook = False

    hook.redelivers_interrupts = True
    return hook


def handled() -> None:
    """An interrupt reached its handler: no redelivery is pending after this."""
    if signal.getsignal(signal.SIGALRM) is _alarm:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, _alarm_before)


def exit_interrupted(message: str = "pcfbench: interrupted") -> NoReturn:
    """Where a command answers Ctrl-C: no redelivery pending (:func:`handled`), ``message`` on
    stderr after a line break (the progress bar's line), exit status 130 (128 + SIGINT)."""
    handled()
    print(f"\n{message}", file=sys.stderr, flush=True)
    sys.exit(130)


def redeliver_swallowed_interrupts() -> None:
    """Install the hook in this (the main) thread's process (once: a second call keeps the first)."""
    if not getattr(sys.unraisablehook, "redelivers_interrupts", False):
        sys.unraisablehook = _redeliver(sys.unraisablehook)
        # registered first, so called last at exit: an interrupt one of the other exit callbacks
        # swallowed is not delivered after the interpreter has put SIGALRM's default back
        atexit.register(handled)
