"""pcfbench.running.workers.run_supervised: every key answered once, and no worker left waiting."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from pcfbench.running.workers import run_supervised

_FIRST: list[bool] = []


def slow_unless_first(marker: str) -> None:
    """Worker set-up: the first worker to start is ready at once, every other one 1.5 s later."""
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        os.close(fd)
    except FileExistsError:
        time.sleep(1.5)


def double(key: int) -> int:
    return 2 * key


def _run_in_thread(keys, jobs, init_args, timeout_s=60.0):
    out: list = []
    t = threading.Thread(target=lambda: out.extend(run_supervised(keys, jobs, slow_unless_first, init_args, double,
                                                                  lambda k, kind, msg: ("failed", k, kind))),
                         daemon=True)
    t.start()
    t.join(timeout_s)
    return t.is_alive(), out


def test_a_worker_ready_after_the_others_took_every_key_is_told_to_stop(tmp_path: Path):
    # The first worker answers all three keys while the second is still setting up; the second
    # then reports ready with nothing left to do. It used to be left waiting for a key while
    # the driver waited for it: a hang (seen in CI with --jobs 2 on 8 quick samples).
    hung, out = _run_in_thread([1, 2, 3], 2, (str(tmp_path / "first"),))
    assert not hung, "run_supervised never returned"
    assert sorted(out) == [2, 4, 6]


def test_every_key_once_with_more_workers_than_keys(tmp_path: Path):
    hung, out = _run_in_thread(list(range(5)), 3, (str(tmp_path / "first"),))
    assert not hung and sorted(out) == [0, 2, 4, 6, 8]
