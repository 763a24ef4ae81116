"""Shared fixtures: tiny datasets written in their real on-disk layouts."""

from __future__ import annotations

import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

# The tests import only the installed pcfbench, as a user does: `python -m pytest` from the
# checkout puts its root on sys.path, where bench/, methods/ and datasets/ would import as
# top-level names and resources would resolve from the source folders (a path that breaks once
# installed would pass here). .ci/test runs from a scratch folder; this covers the other ways.
_REPO = Path(__file__).resolve().parent.parent
sys.path[:] = [p for p in sys.path if Path(p or os.getcwd()).resolve() != _REPO]

# Hermetic: no test reads the user's config or dataset roots or writes into their cache.
os.environ["PCFBENCH_NO_PROGRESS"] = "1"
# Reports without figures unless a test asks (re-running samples for them would slow every CLI run).
os.environ["PCFBENCH_FIGURES"] = "0"
# One scratch home per test run, removed when the process that made it exits: left behind,
# a cache of generated worlds per run filled the CI machine's disk. Processes the tests start
# (workers that import this file, and are often killed rather than exit) inherit its path
# and use it rather than make their own; only the maker removes it, so a forked child that
# runs atexit does not pull it away either.
_HOME_VAR = "PCFBENCH_TESTS_HOME"
if os.environ.get(_HOME_VAR) and Path(os.environ[_HOME_VAR]).is_dir():
    _HOME = Path(os.environ[_HOME_VAR])
else:
    _HOME = Path(tempfile.mkdtemp(prefix="pcfbench-tests-"))
    os.environ[_HOME_VAR] = str(_HOME)
    _OWNER = os.getpid()
    atexit.register(lambda: os.getpid() == _OWNER and shutil.rmtree(_HOME, ignore_errors=True))
os.environ["PCFBENCH_CACHE"] = str(_HOME / "cache")
os.environ["XDG_CONFIG_HOME"] = str(_HOME / "config")
os.environ["RAY_TMPDIR"] = str(_HOME / "ray")  # the local Rays' session folders, else left in /tmp/ray
for _var in [v for v in os.environ if v.startswith("PCFBENCH_DATASET_")] + [
    "PCFBENCH_CONFIG", "PCFBENCH_STORE", "PCFBENCH_REPORTS", "PCFBENCH_PLUGINS", "PCFBENCH_BLOCK_PLUGINS",
]:
    os.environ.pop(_var, None)
# Only the built-ins: a third-party plugin installed in the environment (a user's, another
# project's) must not change what the tests see. A test that installs plugins of its own
# opts in with @pytest.mark.third_party_plugins (every allowed, or only the names given);
# processes the tests start inherit the empty allow-list unless they set their own.
os.environ["PCFBENCH_PLUGINS"] = ""


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "third_party_plugins(*names): let third-party pcfbench plugins load (all, or only the entry "
        "points named); without it the tests load the built-ins only",
    )


@pytest.fixture(autouse=True)
def _third_party_plugins(request, monkeypatch):
    """Lift the empty plugin allow-list for a test marked ``third_party_plugins``."""
    marker = request.node.get_closest_marker("third_party_plugins")
    if marker is None:
        return
    if marker.args:
        monkeypatch.setenv("PCFBENCH_PLUGINS", ",".join(marker.args))
    else:
        monkeypatch.delenv("PCFBENCH_PLUGINS", raising=False)


def write_tiny_kitti(root: Path, sequences=("08",), num_sweeps: int = 24, beams: int = 16, azimuths: int = 360) -> Path:
    """A KITTI Odometry tree (velodyne .bin, calib.txt, times.txt, poses/NN.txt) of the toy world."""
    from pcfbench.testing import toy_world_sweeps
    from pcfbench.datasets.kitti import write_kitti_sequence

    for i, name in enumerate(sequences):
        pts, poses, times = toy_world_sweeps(num_sweeps, beams=beams, azimuths=azimuths, seed=i)
        write_kitti_sequence(root, name, pts, poses, times)
    return root


@pytest.fixture
def tiny_kitti(tmp_path: Path) -> Path:
    return write_tiny_kitti(tmp_path / "kitti")


@pytest.fixture
def store(tmp_path: Path) -> Path:
    return tmp_path / "store"
