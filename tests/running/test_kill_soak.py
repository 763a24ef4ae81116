"""Issue 15: the kill -9 soak. A pooled run SIGKILLed at random moments, again and again, then
completed, has exactly the rows of an uninterrupted run: every (sample, step) once, the
same values bit for bit, and no worker process outlives a killed driver."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.store.cells import Cell, CellSpec
from tests_helpers import write_kitti_tree
from test_isolation import _alive, _descendants

#: kills per soak (PCFBENCH_SOAK_KILLS=10 for the issue's closing note)
KILLS = int(os.environ.get("PCFBENCH_SOAK_KILLS", 5))
METRICS = ("chamfer", "chamfer_nf", "l1_mean")


class Dawdles(CopyLast):
    """copy-last at about 20 samples per second per worker: a run long enough to kill."""

    name = "dawdles"

    def forecast(self, sample):
        time.sleep(0.05)
        return super().forecast(sample)


def plugins():
    p = load_plugins()
    p.methods.add("dawdles", Dawdles, "test")
    return p


_RUN = """
import sys
sys.path[:0] = {tests!r}
import pcfbench.plugins
from test_kill_soak import plugins
pcfbench.plugins._PLUGINS = plugins()
from pcfbench.cli import main
sys.argv = ["pcfbench", "run", "-d", "kitti={root}", "-s", "kitti-1s", "-m", "dawdles", "-j", "2", "--store", {store!r},
            "--no-report", "-q", *{metrics!r}]
main()
"""


def _start(root, store):
    code = textwrap.dedent(_RUN).format(tests=[str(Path(__file__).parent), str(Path(__file__).parents[1])], root=root, store=str(store),
                                        metrics=[a for m in METRICS for a in ("--metric", m)])
    env = {**os.environ, "PCFBENCH_CHUNK_SAMPLES": "3", "PCFBENCH_NO_PROGRESS": "1"}
    return subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _raw_rows(store, spec):
    return pd.concat([pd.read_parquet(p) for p in Cell(store, spec).chunk_paths()], ignore_index=True)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_soak_gives_the_rows_of_an_uninterrupted_run(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("08", "09"), num_sweeps=60)
    spec = CellSpec("dawdles", {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None,
                    METRICS)
    rng = np.random.default_rng(15)
    kills, attempts, sizes = 0, 0, []
    while kills < KILLS and attempts < 4 * KILLS:
        attempts += 1
        before = len(Cell(tmp_path / "store", spec).chunk_paths())
        proc = _start(root, tmp_path / "store")
        # at a random moment after this run's first new chunk: mid-computation, mid-write, ...
        deadline = time.monotonic() + 120
        while (len(Cell(tmp_path / "store", spec).chunk_paths()) <= before and proc.poll() is None
               and time.monotonic() < deadline):
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 0.6))
        family = _descendants(proc.pid)
        if proc.poll() is not None:  # finished before the kill: start over from a clean store
            assert proc.returncode == 0, proc.communicate()
            Cell(tmp_path / "store", spec).clear()
            continue
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
        kills += 1
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and any(_alive(p) for p in family):
            time.sleep(0.1)
        assert not [p for p in family if _alive(p)], f"kill {kills}: orphans outlived the driver"
        chunks = Cell(tmp_path / "store", spec).chunk_paths()
        sizes.append(len(_raw_rows(tmp_path / "store", spec)) if chunks else 0)
    assert kills == KILLS, f"only {kills} kills landed in {attempts} runs"
    assert len(set(sizes)) == len(sizes) and sizes[-1] < 2 * (60 - 18) * 5, sizes  # each kill mid-run, at another point
    final = _start(root, tmp_path / "store")
    out, err = final.communicate(timeout=300)
    assert final.returncode == 0, err
    clean = _start(root, tmp_path / "clean")
    out_c, err_c = clean.communicate(timeout=300)
    assert clean.returncode == 0, err_c

    key = ["sample_id", "step"]
    raw = _raw_rows(tmp_path / "store", spec)
    assert not raw.duplicated(key).any(), "a (sample, step) was written twice"
    ref = _raw_rows(tmp_path / "clean", spec)
    a = raw.sort_values(key).reset_index(drop=True)
    b = ref.sort_values(key).reset_index(drop=True)
    assert len(a) == len(b) == 2 * (60 - 18) * 5
    assert (a["status"] == "ok").all()
    assert a[key].values.tolist() == b[key].values.tolist()
    for col in METRICS:  # bit for bit
        assert a[col].to_numpy(np.float64).tobytes() == b[col].to_numpy(np.float64).tobytes(), col
    meta = Cell(tmp_path / "store", spec).read_meta()
    assert meta["status"] == "complete" and meta["counts"] == {**meta["counts"], "failed": 0, "ok": 84}
