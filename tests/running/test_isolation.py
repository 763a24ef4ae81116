"""Issue 15: a method that hangs or kills its process costs one sample, not the run; workers
die with a driver killed by SIGKILL."""

import ctypes
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec
from tests_helpers import BAD_INDEX, Exits

METRICS = ("chamfer",)


class Hangs(CopyLast):
    name = "hangs"

    def forecast(self, sample):
        if sample.ref_index == BAD_INDEX:
            while True:  # a busy loop: no signal-based limit inside the process would stop a native one either
                time.sleep(0.05)
        return super().forecast(sample)


class Segfaults(CopyLast):
    name = "segfaults"

    def forecast(self, sample):
        if sample.ref_index == BAD_INDEX:
            ctypes.string_at(0)  # reads address 0: SIGSEGV
        return super().forecast(sample)


class Slow(CopyLast):
    name = "slow"

    def forecast(self, sample):
        time.sleep(30)
        return super().forecast(sample)


def plugins():
    p = load_plugins()
    for cls in (Hangs, Exits, Segfaults, Slow):
        p.methods.add(cls.name, cls, "test")
    return p


def _spec(root, method):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


def _rows(store, root, method):
    return Cell(store, _spec(root, method)).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)


@pytest.mark.parametrize("method, jobs, error", [
    ("exits", 1, "SampleCrash: sample 08/000008: its worker process died with exit code 3"),
    ("segfaults", 2, "SampleCrash: sample 08/000008: its worker process died with signal SIGSEGV"),
])
def test_a_crashing_sample_is_one_failure_and_the_cell_completes(tiny_kitti, tmp_path, method, error, jobs):
    p = plugins()
    run_cell(_spec(tiny_kitti, "copy-last"), tmp_path / "ref", RunOptions(progress=False), plugins=p)
    result = run_cell(_spec(tiny_kitti, method), tmp_path / "s", RunOptions(progress=False, jobs=jobs, isolate=True), plugins=p)
    assert result.status == "complete" and result.samples == 6 and result.failed == 1
    rows = _rows(tmp_path / "s", tiny_kitti, method)
    failed = rows[rows.status == "failed"]
    assert list(failed.sample_id) == ["08/000008"] and failed.error.iloc[0] == error
    # every other sample scored exactly as copy-last scores it
    ref = _rows(tmp_path / "ref", tiny_kitti, "copy-last")
    ok = rows[rows.status == "ok"].reset_index(drop=True)
    pd.testing.assert_frame_equal(ok[["sample_id", "step", "chamfer"]],
                                  ref[ref.sample_id != "08/000008"].reset_index(drop=True)[["sample_id", "step", "chamfer"]])
    meta = Cell(tmp_path / "s", _spec(tiny_kitti, method)).read_meta()
    assert meta["status"] == "complete" and meta["counts"]["failed"] == 1


def test_a_hanging_sample_times_out_and_the_cell_completes(tiny_kitti, store):
    t0 = time.monotonic()
    # (a worker's first sample includes its warm-up, numba's compilation: seconds on a loaded machine)
    result = run_cell(_spec(tiny_kitti, "hangs"), store, RunOptions(progress=False, timeout=5), plugins=plugins())
    assert time.monotonic() - t0 < 60
    assert result.failed == 1 and result.samples == 6
    rows = _rows(store, tiny_kitti, "hangs")
    failed = rows[rows.status == "failed"]
    assert list(failed.sample_id) == ["08/000008"]
    assert failed.error.iloc[0] == "SampleTimeout: sample 08/000008: it ran longer than the per-sample time limit of 5 s"
    assert "--timeout" in failed.traceback.iloc[0]
    assert (rows.status == "ok").sum() == 5 * 5


def test_the_timeout_must_be_positive(tiny_kitti, store):
    for bad in (0, -1, float("nan"), True):
        with pytest.raises(PcfbenchError, match="per-sample time limit must be a number of seconds > 0"):
            run_cell(_spec(tiny_kitti, "copy-last"), store, RunOptions(progress=False, timeout=bad))


def test_isolated_rows_equal_in_process_rows(tiny_kitti, tmp_path):
    run_cell(_spec(tiny_kitti, "copy-last"), tmp_path / "a", RunOptions(progress=False))
    run_cell(_spec(tiny_kitti, "copy-last"), tmp_path / "b", RunOptions(progress=False, timeout=60))
    cols = ["sample_id", "step", "status", "chamfer"]
    pd.testing.assert_frame_equal(_rows(tmp_path / "a", tiny_kitti, "copy-last")[cols],
                                  _rows(tmp_path / "b", tiny_kitti, "copy-last")[cols])


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), ()):
            out.add(c)
            todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_no_orphan_workers_after_the_driver_is_sigkilled(tiny_kitti, tmp_path):
    script = textwrap.dedent(f"""
        import sys
        sys.path[:0] = {[str(Path(__file__).parent), str(Path(__file__).parents[1])]!r}
        from test_isolation import plugins, _spec
        from pcfbench.running.runner import RunOptions, run_cell
        run_cell(_spec({str(tiny_kitti)!r}, "slow"), {str(tmp_path / "store")!r},
                 RunOptions(progress=False, jobs=2, timeout=600), plugins=plugins())
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        workers: set[int] = set()
        while time.monotonic() < deadline and proc.poll() is None:
            kids = _descendants(proc.pid)
            # forkserver, resource tracker and the two workers, all started
            named = [Path(f"/proc/{k}/cmdline").read_bytes() for k in kids if _alive(k)]
            if len(kids) >= 4 and sum(b"forkserver" in n for n in named) >= 1:
                workers = kids
                time.sleep(1.0)  # the workers are in their first sample
                workers |= _descendants(proc.pid)
                break
            time.sleep(0.2)
        assert workers, f"no workers started: {proc.poll()} {proc.stderr.read() if proc.poll() is not None else ''}"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 30  # seconds at most: a loaded machine is slow to reap
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.2)
        left = [p for p in workers if _alive(p)]
        assert not left, f"orphans left alive: {left}"
    finally:
        for p in _descendants(proc.pid):
            os.kill(p, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()


def test_run_timeout_option_records_the_hung_sample_and_exits_1(tiny_kitti, tmp_path, monkeypatch):
    import pcfbench.plugins
    from click.testing import CliRunner

    from pcfbench.cli import cli

    monkeypatch.setattr(pcfbench.plugins, "_PLUGINS", plugins())
    args = ["run", "-d", f"kitti={tiny_kitti}", "-m", "hangs", "-s", "kitti-1s", "--metric", "chamfer", "--store",
            str(tmp_path / "store"), "--no-report", "-q"]
    res = CliRunner().invoke(cli, [*args, "--timeout", "5"])
    assert res.exit_code == 1, res.output
    assert "6 samples (6 now, 1 failed)" in res.stdout and "1 sample(s) failed in 1 cell(s)" in res.stderr
    rows = _rows(tmp_path / "store", tiny_kitti, "hangs")
    assert rows[rows.status == "failed"].error.tolist() == [
        "SampleTimeout: sample 08/000008: it ran longer than the per-sample time limit of 5 s"]
    bad = CliRunner().invoke(cli, [*args, "--timeout", "-1"])
    assert bad.exit_code == 2 and "-1" in bad.output


def test_sweep_timeout_option_records_the_hung_sample(tiny_kitti, tmp_path, monkeypatch):
    import pcfbench.plugins
    from click.testing import CliRunner

    from pcfbench.cli import cli

    monkeypatch.setattr(pcfbench.plugins, "_PLUGINS", plugins())
    exp = tmp_path / "hang.toml"
    exp.write_text(f"datasets = ['kitti={tiny_kitti}']\nsettings = ['kitti-1s']\nmetrics = ['chamfer']\n"
                   "[[methods]]\nname = 'hangs'\n")
    res = CliRunner().invoke(cli, ["sweep", str(exp), "--store", str(tmp_path / "store"), "--reports",
                                   str(tmp_path / "r"), "-q", "--timeout", "5"])
    assert res.exit_code == 1, res.output  # failed samples: exit 1, as run
    assert "1 sample(s) failed" in res.stderr
    again = CliRunner().invoke(cli, ["sweep", str(exp), "--store", str(tmp_path / "store2"), "--reports",
                                     str(tmp_path / "r2"), "-q", "--timeout", "5", "--keep-going"])
    assert again.exit_code == 0 and "1 sample(s) failed" in again.stderr, again.output
    rows = _rows(tmp_path / "store", tiny_kitti, "hangs")
    assert rows[rows.status == "failed"].error.tolist() == [
        "SampleTimeout: sample 08/000008: it ran longer than the per-sample time limit of 5 s"]
