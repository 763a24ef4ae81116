"""The linter's rules (``[tool.ruff]`` in pyproject.toml) hold over the code: CI runs ruff
through this test, with the version the ``test`` extra pins."""

import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PATHS = ("bench", "methods", "datasets", "tests")


def test_ruff_finds_nothing():
    if importlib.util.find_spec("ruff") is None:
        pytest.skip("ruff is not installed: pip install -e '.[test]' installs the pinned version")
    res = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", *PATHS],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, f"ruff check {' '.join(PATHS)} (from {ROOT}):\n{res.stdout}{res.stderr}"


def test_the_test_extra_pins_ruff():
    """One ruff version everywhere: a newer one may bring rules the code was never checked with."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    pins = [r for r in project["project"]["optional-dependencies"]["test"] if r.startswith("ruff")]
    assert len(pins) == 1 and "==" in pins[0], pins
    if importlib.util.find_spec("ruff") is not None:
        out = subprocess.run([sys.executable, "-m", "ruff", "--version"], capture_output=True, text=True, check=True)
        assert out.stdout.split()[-1] == pins[0].split("==")[1], (out.stdout, pins[0])
