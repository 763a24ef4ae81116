"""What produced a result, beyond its inputs: the code's git commit and the environment.

A leaf of the import graph: the runner records both in a cell, training in a checkpoint's
manifest.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["environment", "git_commit"]


def git_commit() -> str | None:
    """The commit of the git checkout this package's files lie in (editable, or a wheel in a
    virtual environment inside the checkout), else None."""
    here = Path(__file__).resolve().parent  # git looks upwards from any folder of a work tree
    try:
        out = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def environment() -> dict[str, Any]:
    import pandas
    import pyarrow

    env = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "numpy": np.__version__,
        "pandas": pandas.__version__,
        "pyarrow": pyarrow.__version__,
        "cpus": os.cpu_count(),
    }
    if "torch" in sys.modules:
        env["torch"] = sys.modules["torch"].__version__
    return env
