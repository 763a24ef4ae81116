"""The suite's scratch home (cache of generated worlds, config) goes away with the process."""

import subprocess
import sys
from pathlib import Path


def test_scratch_home_is_removed_at_exit():
    here = Path(__file__).parent
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import conftest; "
            "(conftest._HOME / 'cache' / 'x').mkdir(parents=True); print(conftest._HOME)")
    out = subprocess.run([sys.executable, "-c", code, str(here)], capture_output=True, text=True, check=True)
    home = Path(out.stdout.strip())
    assert home.name.startswith("pcfbench-tests-")
    assert not home.exists()


def test_a_forked_child_leaves_it_in_place():
    here = Path(__file__).parent
    code = ("import os, sys; sys.path.insert(0, sys.argv[1]); import conftest; "
            "pid = os.fork()\n"
            "if pid == 0: sys.exit(0)\n"
            "os.waitpid(pid, 0); print(conftest._HOME.exists())")
    out = subprocess.run([sys.executable, "-c", code, str(here)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"
