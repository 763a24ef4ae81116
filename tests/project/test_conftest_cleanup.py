"""The suite's scratch home (cache of generated worlds, config) goes away with the process that
made it, and the processes the tests start use it rather than leave homes of their own."""

import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]  # conftest.py
IMPORT = "import os, sys; sys.path.insert(0, sys.argv[1]); import conftest\n"


def _run(code: str, env: dict) -> str:
    return subprocess.run([sys.executable, "-c", IMPORT + code, str(HERE)], capture_output=True, text=True,
                          check=True, env=env).stdout.strip()


def _fresh_env() -> dict:
    return {k: v for k, v in os.environ.items() if k != "PCFBENCH_TESTS_HOME"}


def test_scratch_home_is_removed_at_exit():
    home = Path(_run("(conftest._HOME / 'cache' / 'x').mkdir(parents=True); print(conftest._HOME)", _fresh_env()))
    assert home.name.startswith("pcfbench-tests-")
    assert not home.exists()


def test_a_forked_child_leaves_it_in_place():
    code = ("pid = os.fork()\n"
            "if pid == 0: sys.exit(0)\n"
            "os.waitpid(pid, 0); print(conftest._HOME.exists())")
    assert _run(code, _fresh_env()) == "True"


def test_a_started_process_uses_the_home_it_inherits_and_leaves_it(tmp_path):
    home = tmp_path / "inherited"
    home.mkdir()
    env = dict(_fresh_env(), PCFBENCH_TESTS_HOME=str(home))
    assert _run("print(conftest._HOME, os.environ['PCFBENCH_CACHE'])", env) == f"{home} {home / 'cache'}"
    assert home.is_dir()  # not its maker: left for the process that made it


def test_this_run_passes_its_home_on():
    import conftest

    assert os.environ["PCFBENCH_TESTS_HOME"] == str(conftest._HOME)
