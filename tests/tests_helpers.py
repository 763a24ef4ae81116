"""Helpers importable by test modules (conftest fixtures cover the common cases)."""

import dataclasses
import os

import numpy as np

import pcfbench
from conftest import write_tiny_kitti
from pcfbench.data import Forecast
from pcfbench.method import Method
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins


def write_kitti_tree(root, sequences=("08",), num_sweeps=24):
    return write_tiny_kitti(root, sequences=sequences, num_sweeps=num_sweeps)


class Shifted(Method):
    """The last past sweep moved by ``dx`` metres along x."""

    name = "shifted"

    @dataclasses.dataclass(frozen=True)
    class Options:
        dx: float = pcfbench.option(0.0, help="shift along x (m)")

    def forecast(self, sample):
        last = sample.past_points_ref[-1] + np.array([self.options.dx, 0, 0], dtype=np.float32)
        return Forecast(points_ref=tuple(last for _ in range(sample.num_future)))


def shifted_plugins():
    """The built-in plugins and the test method ``shifted``."""
    plugins = load_plugins()
    if "shifted" not in plugins.methods:
        plugins.methods.add("shifted", Shifted, "test")
    return plugins


#: the sample at which the failing test methods below fail: the tiny KITTI tree's reference
#: index 8 (its first kitti-1s sample)
BAD_INDEX = 8


class Exits(CopyLast):
    """Kills its own process (exit 3) on the sample at ``BAD_INDEX``, copies the last sweep elsewhere."""

    name = "exits"

    def forecast(self, sample):
        if sample.ref_index == BAD_INDEX:
            os._exit(3)
        return super().forecast(sample)


class Raises(CopyLast):
    """Raises on the sample at ``BAD_INDEX``, copies the last sweep elsewhere."""

    name = "raises"

    def forecast(self, sample):
        if sample.ref_index == BAD_INDEX:
            raise RuntimeError("boom")
        return super().forecast(sample)


def chromium() -> str:
    """Debian's chromium for the browser tests: skipped where it is missing, a failure in CI
    (``bash .ci/setup test`` installs it)."""
    import os
    import shutil

    import pytest

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing: bash .ci/setup test installs it (apt-get install chromium)")
        pytest.skip("chromium is not installed (bash .ci/setup test installs it)")
    return exe


def headless(exe: str, *args: str) -> str:
    """Run headless chromium with ``args``; its standard output (a dumped DOM)."""
    import subprocess

    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
           "--hide-scrollbars", "--virtual-time-budget=5000", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout
