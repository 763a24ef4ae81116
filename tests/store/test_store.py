"""Issue 15: the results store. A damaged chunk, a cut-short cell.json, a read-only store and
a full disk are each one error naming the file and what to do; two runs on one store compute
each cell once."""

import errno
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
from click.testing import CliRunner

from pcfbench.cli import cli
from pcfbench.errors import PcfbenchError
from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.reporting.report import collect
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellLocked, CellSpec

METRICS = ("chamfer",)


class Naps(CopyLast):
    """copy-last, slowly: long enough for a second run to meet the first one's lock."""

    name = "naps"

    def forecast(self, sample):
        time.sleep(0.5)
        return super().forecast(sample)


def plugins():
    p = load_plugins()
    p.methods.add("naps", Naps, "test")
    return p


def _spec(root, method="copy-last"):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


def _cli(store, root, *extra):
    return CliRunner().invoke(cli, ["run", "-d", f"kitti={root}", "-m", "copy-last", "-s", "kitti-1s", "--metric",
                                    "chamfer", "--store", str(store), "--no-report", "-q", *extra])


def _one_line_error(res, *parts):
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and isinstance(res.exception, SystemExit), res.output
    lines = [line for line in res.stderr.splitlines() if line.startswith("pcfbench: error:")]
    assert len(lines) == 1, res.stderr
    for part in parts:
        assert part in lines[0], lines[0]


def test_a_damaged_chunk_is_one_error_naming_it(tiny_kitti, store):
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    before = collect(store).table
    chunk = Cell(store, _spec(tiny_kitti)).chunk_paths()[0]
    chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])  # cut short
    for read in (lambda: collect(store), lambda: run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))):
        with pytest.raises(PcfbenchError, match=rf"rows file {chunk} is damaged or cut short .*delete that file"):
            read()
    res = CliRunner().invoke(cli, ["report", "--store", str(store), "--reports", str(store.parent / "rep")])
    _one_line_error(res, str(chunk), "delete that file")
    # the fix the message gives: its samples are recomputed, the leaderboard is the same
    chunk.unlink()
    assert run_cell(_spec(tiny_kitti), store, RunOptions(progress=False)).processed == 6
    pd.testing.assert_series_equal(collect(store).table.chamfer, before.chamfer)


def test_a_parquet_file_without_row_columns_is_refused(tiny_kitti, store):
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    chunk = Cell(store, _spec(tiny_kitti)).chunk_paths()[0]
    pd.DataFrame({"x": [1.0]}).to_parquet(chunk)
    with pytest.raises(PcfbenchError, match=rf"rows file {chunk} has no column sample_id, step, status"):
        collect(store)


@pytest.mark.parametrize("content, message", [
    (None, r"is not valid JSON .*cut short\?\): delete the folder"),
    ("[1, 2]", r"is not a complete cell.json \(not a JSON object\)"),
    ('{"status": "complete", "spec": {"method": "copy-last"}}',
     r"is not a complete cell.json \(spec without options, options_hash, dataset, split, setting\)"),
])
def test_a_cut_short_cell_json_is_one_error_not_a_vanished_cell(tiny_kitti, store, content, message):
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    path = Cell(store, _spec(tiny_kitti)).dir / "cell.json"
    path.write_text(path.read_text()[:200] if content is None else content)
    with pytest.raises(PcfbenchError, match=rf"{path} {message}"):
        collect(store)
    with pytest.raises(PcfbenchError, match=rf"{path} {message}"):
        run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    _one_line_error(CliRunner().invoke(cli, ["report", "--store", str(store), "--reports", str(store.parent / "r")]),
                    str(path))
    # --force, as the message says, recomputes it
    assert run_cell(_spec(tiny_kitti), store, RunOptions(progress=False, force=True)).processed == 6
    assert len(collect(store).table) == 1


def test_a_read_only_store_is_one_error(tiny_kitti, tmp_path, monkeypatch):
    store = tmp_path / "store"
    store.mkdir()
    if os.geteuid() != 0:
        store.chmod(0o555)
    else:  # root writes anywhere: the file system says read-only instead
        def read_only(self, *a, **k):
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        monkeypatch.setattr(Path, "mkdir", read_only)
    try:
        _one_line_error(_cli(store, tiny_kitti), f"cannot write {store}", "the results store is not writable",
                        "pass a writable --store")
    finally:
        store.chmod(0o755)


def test_a_full_disk_is_one_error_and_the_run_resumes(tiny_kitti, tmp_path, monkeypatch):
    store = tmp_path / "store"
    real_fsync, calls = os.fsync, []

    def fsync(fd):  # cell.json is written, then the disk is full
        calls.append(fd)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setenv("PCFBENCH_CHUNK_SAMPLES", "64")
    res = _cli(store, tiny_kitti)
    chunk = Cell(store, _spec(tiny_kitti)).dir / "rows" / "chunk-000000.parquet"
    _one_line_error(res, f"cannot write {chunk}: no space left on the device", "free some space",
                    "the run resumes from the rows already written")
    assert not list(store.rglob("*.tmp")), "the temporary file is removed"
    monkeypatch.setattr(os, "fsync", real_fsync)
    again = _cli(store, tiny_kitti)
    assert again.exit_code == 0, again.output
    rows = Cell(store, _spec(tiny_kitti)).read_rows()
    assert len(rows) == 6 * 5 and not rows.duplicated(["sample_id", "step"]).any()


def test_a_locked_cell_is_refused_or_waited_for(tiny_kitti, store):
    holder = Cell(store, _spec(tiny_kitti))
    with holder:
        with pytest.raises(CellLocked, match="is being computed by another pcfbench process"):
            run_cell(_spec(tiny_kitti), store, RunOptions(progress=False, wait=False))
    assert run_cell(_spec(tiny_kitti), store, RunOptions(progress=False, wait=True)).processed == 6


_RUN = """
import sys
sys.path[:0] = {tests!r}
import pcfbench.plugins
from test_store import plugins
pcfbench.plugins._PLUGINS = plugins()
from pcfbench.cli import main
sys.argv = ["pcfbench", "run", "-d", "kitti={root}", "-s", "kitti-1s", "--metric", "chamfer", "--store", {store!r},
            "--no-report", "-q", "-j", "1", *{methods!r}]
main()
"""


@pytest.mark.slow
def test_two_runs_on_one_store_compute_each_cell_once(tiny_kitti, tmp_path):
    store = str(tmp_path / "store")

    def start(*methods):
        code = textwrap.dedent(_RUN).format(tests=[str(Path(__file__).parent), str(Path(__file__).parents[1])], root=tiny_kitti, store=store,
                                            methods=[a for m in methods for a in ("-m", m)])
        return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    first = start("naps")
    meta = Cell(store, _spec(tiny_kitti, "naps")).dir / "cell.json"
    deadline = time.monotonic() + 60
    while not meta.exists() and time.monotonic() < deadline and first.poll() is None:
        time.sleep(0.05)
    assert meta.exists(), first.communicate()
    second = start("naps", "copy-last")
    out2, err2 = second.communicate(timeout=120)
    out1, err1 = first.communicate(timeout=120)
    assert first.returncode == 0 and second.returncode == 0, (err1, err2)

    def line(text, *parts):  # the one line holding every part (whatever the cell's label looks like)
        found = [ln for ln in text.splitlines() if all(p in ln for p in parts)]
        assert len(found) == 1, (parts, text)

    line(err2, "naps", "another pcfbench process is computing it; doing the other cells first")
    line(err2, "naps", "waiting for the other pcfbench process computing it")
    # the second run did copy-last, then found naps complete: its rows are the first run's
    line(out2, "copy-last", "6 samples (6 now, 0 failed)")
    line(out2, "naps", "complete, nothing to do (6 samples)")
    line(out1, "naps", "6 samples (6 now, 0 failed)")
    raw = pd.concat([pd.read_parquet(p) for p in Cell(store, _spec(tiny_kitti, "naps")).chunk_paths()])
    assert len(raw) == 6 * 5 and not raw.duplicated(["sample_id", "step"]).any()
    assert json.loads(meta.read_text())["status"] == "complete"
