"""Issue 48: cells that differ only in the method share one pass over their samples (each sample
loaded and its ground truth's structures built once), with the rows, resume and failure
semantics of separate runs."""

import os
import time

import pandas as pd
import pytest

from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.protocol import SampleBuilder
from pcfbench.running import workers
from pcfbench.running.group import groups, run_group
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec
from tests_helpers import Exits, Raises

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1@4docc", "absrel_median")
#: where Interrupts stops the run: the third sample
STOP_INDEX = 10
TIMINGS = ["t_load", "t_method", "t_metrics"]


class Interrupts(CopyLast):
    """Stops the run (Ctrl-C) at STOP_INDEX while the file $PCFBENCH_TEST_FLAG exists."""

    name = "interrupts"

    def forecast(self, sample):
        if sample.ref_index == STOP_INDEX and os.path.exists(os.environ["PCFBENCH_TEST_FLAG"]):
            raise KeyboardInterrupt
        return super().forecast(sample)


def plugins():
    p = load_plugins()
    for cls in (Exits, Raises, Interrupts):
        p.methods.add(cls.name, cls, "test")
    return p


def _spec(root, method):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


def _rows(store, root, method):
    df = Cell(store, _spec(root, method)).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)
    return df.drop(columns=[c for c in TIMINGS if c in df])


def _assert_rows_equal(a, b):
    # (the columns' order follows the first row written, which completion order decides under --jobs)
    a, b = a.drop(columns=["traceback"], errors="ignore"), b.drop(columns=["traceback"], errors="ignore")
    pd.testing.assert_frame_equal(a[sorted(a.columns)], b[sorted(b.columns)], check_exact=True)


METHODS = ("copy-last", "raycast-zbuffer", "raises")


@pytest.mark.parametrize("options", [RunOptions(progress=False), RunOptions(progress=False, isolate=True),
                                     RunOptions(progress=False, jobs=2, isolate=True)], ids=["serial", "isolated", "jobs2"])
def test_a_group_writes_the_rows_of_separate_runs(tiny_kitti, tmp_path, options):
    p = plugins()
    for m in METHODS:
        run_cell(_spec(tiny_kitti, m), tmp_path / "apart", RunOptions(progress=False), plugins=p)
    results = run_group([_spec(tiny_kitti, m) for m in METHODS], tmp_path / "group", options, plugins=p)
    assert [r.spec.method for r in results] == list(METHODS)
    assert [(r.status, r.samples, r.processed, r.failed) for r in results] == [("complete", 6, 6, 0), ("complete", 6, 6, 0),
                                                                               ("complete", 6, 6, 1)]
    for m in METHODS:
        _assert_rows_equal(_rows(tmp_path / "group", tiny_kitti, m), _rows(tmp_path / "apart", tiny_kitti, m))
        meta = Cell(tmp_path / "group", _spec(tiny_kitti, m)).read_meta()
        assert meta["status"] == "complete" and meta["counts"]["failed"] == (m == "raises")


def test_a_group_loads_each_sample_once(tiny_kitti, tmp_path, monkeypatch):
    built = []
    original = SampleBuilder.build

    def counting(self, sequence, ref_index):
        built.append((sequence, ref_index))
        return original(self, sequence, ref_index)

    monkeypatch.setattr(SampleBuilder, "build", counting)
    run_group([_spec(tiny_kitti, m) for m in METHODS], tmp_path / "group", RunOptions(progress=False), plugins=plugins())
    assert len(built) == 6 and len(set(built)) == 6
    built.clear()
    for m in METHODS:
        run_cell(_spec(tiny_kitti, m), tmp_path / "apart", RunOptions(progress=False), plugins=plugins())
    assert len(built) == 18


def test_ray_casters_in_a_group_share_what_they_derive_and_score_as_apart(tiny_kitti, tmp_path, monkeypatch):
    """The four ray casters share each sample's aggregate of the past (``Sample.derive``) and
    raycast-voxel / -freespace its voxel grid (freespace carves a copy): built once per sample in
    a group, once per method and sample apart, with the same rows and stored range bins."""
    from pcfbench.methods.raycast import grid

    built = []
    original = grid.VoxelGrid.__init__

    def counting(self, *args, **kwargs):
        built.append(1)
        original(self, *args, **kwargs)

    monkeypatch.setattr(grid.VoxelGrid, "__init__", counting)
    methods = ("raycast-freespace", "raycast-4docc", "raycast-voxel", "raycast-zbuffer")
    run_group([_spec(tiny_kitti, m) for m in methods], tmp_path / "group", RunOptions(progress=False))
    assert len(built) == 6
    for m in methods:
        run_cell(_spec(tiny_kitti, m), tmp_path / "apart", RunOptions(progress=False))
    assert len(built) == 6 + 12
    for m in methods:
        _assert_rows_equal(_rows(tmp_path / "group", tiny_kitti, m), _rows(tmp_path / "apart", tiny_kitti, m))
        ranges = [Cell(store, _spec(tiny_kitti, m)).read_ranges().sort_values(["sample_id", "step"])
                  .reset_index(drop=True) for store in (tmp_path / "group", tmp_path / "apart")]
        assert len(ranges[0]) == 30
        pd.testing.assert_frame_equal(*ranges, check_exact=True)


def test_a_crash_in_a_group_fails_only_its_method_on_its_sample(tiny_kitti, tmp_path):
    p = plugins()
    methods = ("copy-last", "exits", "raycast-zbuffer")
    results = run_group([_spec(tiny_kitti, m) for m in methods], tmp_path / "group",
                        RunOptions(progress=False, isolate=True), plugins=p)
    assert [r.failed for r in results] == [0, 1, 0]
    rows = _rows(tmp_path / "group", tiny_kitti, "exits")
    failed = rows[rows.status == "failed"]
    assert list(failed.sample_id) == ["08/000008"]
    assert failed.error.iloc[0] == "SampleCrash: sample 08/000008: its worker process died with exit code 3"
    for m in ("copy-last", "raycast-zbuffer"):  # the sample's other methods, done by the next worker
        run_cell(_spec(tiny_kitti, m), tmp_path / "apart", RunOptions(progress=False), plugins=p)
        _assert_rows_equal(_rows(tmp_path / "group", tiny_kitti, m), _rows(tmp_path / "apart", tiny_kitti, m))


def test_an_interrupted_group_resumes_each_cell_where_it_stopped(tiny_kitti, tmp_path, monkeypatch):
    flag = tmp_path / "flag"
    flag.write_text("stop")
    monkeypatch.setenv("PCFBENCH_TEST_FLAG", str(flag))
    monkeypatch.setattr("pcfbench.running.runner.CHUNK_SAMPLES", 1)
    p = plugins()
    methods = ("copy-last", "interrupts")
    specs = [_spec(tiny_kitti, m) for m in methods]
    with pytest.raises(KeyboardInterrupt):
        run_group(specs, tmp_path / "group", RunOptions(progress=False), plugins=p)
    # every sample finished before the interruption is kept: copy-last did 8, 9 and 10, the other 8 and 9
    done = {m: sorted(Cell(tmp_path / "group", s).done_ids()) for m, s in zip(methods, specs)}
    assert done == {"copy-last": ["08/000008", "08/000009", "08/000010"], "interrupts": ["08/000008", "08/000009"]}
    assert Cell(tmp_path / "group", specs[0]).read_meta()["status"] == "running"
    flag.unlink()
    results = run_group(specs, tmp_path / "group", RunOptions(progress=False), plugins=p)
    assert [(r.done_before, r.processed) for r in results] == [(3, 3), (2, 4)]
    for m in methods:
        run_cell(_spec(tiny_kitti, m), tmp_path / "apart", RunOptions(progress=False), plugins=p)
        _assert_rows_equal(_rows(tmp_path / "group", tiny_kitti, m), _rows(tmp_path / "apart", tiny_kitti, m))
    again = run_group(specs, tmp_path / "group", RunOptions(progress=False), plugins=p)
    assert [(r.status, r.processed) for r in again] == [("complete", 0), ("complete", 0)]


@pytest.mark.parametrize("options", [RunOptions(progress=False), RunOptions(progress=False, jobs=2, isolate=True)],
                         ids=["serial", "jobs2"])
def test_a_subset_cell_joins_the_pass_and_is_given_only_its_samples(tiny_kitti, tmp_path, monkeypatch, options):
    """CellSpec.subset: a cell scoring 3 of the 6 samples groups with the full cells, gets the
    rows a separate run of it writes (samples 0, 2 and 4: i * 6 // 3) and no others, and the
    pass loads each of the 6 samples once."""
    from dataclasses import replace

    p = plugins()
    full, sub = _spec(tiny_kitti, "copy-last"), replace(_spec(tiny_kitti, "raycast-zbuffer"), subset=3)
    assert groups([full, sub]) == [[full, sub]]
    run_cell(sub, tmp_path / "apart", RunOptions(progress=False), plugins=p)
    results = run_group([full, sub], tmp_path / "group", options, plugins=p)
    assert [(r.status, r.samples, r.processed) for r in results] == [("complete", 6, 6), ("complete", 3, 3)]
    a = Cell(tmp_path / "apart", sub).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)
    g = Cell(tmp_path / "group", sub).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)
    _assert_rows_equal(g.drop(columns=TIMINGS), a.drop(columns=TIMINGS))
    everything = sorted(set(Cell(tmp_path / "group", full).read_rows().sample_id))
    assert sorted(set(g.sample_id)) == [everything[i] for i in (0, 2, 4)]
    assert Cell(tmp_path / "group", sub).read_meta()["samples"] == 3
    built = []
    original = SampleBuilder.build
    monkeypatch.setattr(SampleBuilder, "build", lambda self, s, i: built.append((s, i)) or original(self, s, i))
    run_group([full, sub], tmp_path / "again", RunOptions(progress=False), plugins=p)
    assert len(built) == 6 and len(set(built)) == 6


def test_groups_are_the_cells_that_share_their_samples(tiny_kitti):
    a, b = _spec(tiny_kitti, "copy-last"), _spec(tiny_kitti, "raycast-zbuffer")
    c = CellSpec("copy-last", {}, options_hash(None), "kitti", str(tiny_kitti), "test", "kitti-3s", "full-context", None,
                 METRICS)
    d = CellSpec("copy-last", {}, options_hash(None), "kitti", str(tiny_kitti), "test", "kitti-1s", "full-context", None,
                 ("chamfer",))
    assert groups([a, c, b, d]) == [[a, b], [c], [d]]


def _pid(key):
    time.sleep(0.05)
    return key, os.getpid()


def _both_started(directory, n):
    """Wait (at most a minute) until ``n`` workers have started, so that on a loaded machine one
    worker cannot finish every key before the other has reported ready."""
    (directory / str(os.getpid())).touch()
    deadline = time.monotonic() + 60
    while len(list(directory.iterdir())) < n and time.monotonic() < deadline:
        time.sleep(0.01)


def _fail(key, kind, reason):
    return key, kind


def test_supervised_tasks_of_one_kind_go_to_one_worker_in_turn(tmp_path):
    keys = [(s, m) for s in range(6) for m in range(3)]
    out = list(workers.run_supervised(keys, 2, _both_started, (tmp_path, 2), _pid, _fail, affinity=lambda k: k[0]))
    assert sorted(k for k, _ in out) == keys
    by_sample = {}
    for (s, _), pid in out:
        by_sample.setdefault(s, set()).add(pid)
    # every sample but the last two (where a free worker helps rather than waits) in one worker
    assert all(len(by_sample[s]) == 1 for s in range(4)), by_sample
    assert len({pid for _, pid in out}) == 2


def test_the_cli_runs_a_group_cell_by_cell_when_another_process_holds_one_of_its_cells(tiny_kitti, tmp_path):
    """`pcfbench run` with two methods on the same samples: another process holds the second
    method's cell, so the group cannot lock all its cells; the run falls back to one cell at a
    time and computes the free cell while the other is still held, then the held one once it is
    free (the other process lets it go once the free cell is complete)."""
    import threading

    from click.testing import CliRunner

    from pcfbench.cli import cli

    store = tmp_path / "store"

    def spec(method):  # the cell the command makes (the method's default options resolved as the command does)
        from pcfbench.method import resolve_method
        from pcfbench.plugins import get_plugins

        m = resolve_method(method, get_plugins())
        return CellSpec(m.name, dict(m.raw), m.options_hash, "kitti", str(tiny_kitti), "test", "kitti-1s",
                        "full-context", None, ("chamfer", "l1_mean"))

    free, held = spec("copy-last"), spec("raycast-zbuffer")
    other = Cell(store, held).__enter__()  # its own open file: flock refuses the run's lock as another process's
    seen = []
    finished = threading.Event()  # the command returned (with or without the free cell done)

    def other_process():
        # it finishes once the run has completed the free cell (a group would have waited for it, or failed)
        deadline = time.monotonic() + 120
        try:
            while time.monotonic() < deadline and not finished.is_set():
                if (Cell(store, free).read_meta() or {}).get("status") == "complete":
                    seen.append("free cell complete while the other was held")
                    return
                time.sleep(0.05)
        finally:
            other.__exit__(None, None, None)

    thread = threading.Thread(target=other_process)
    thread.start()
    try:
        res = CliRunner().invoke(cli, ["run", "-d", f"kitti={tiny_kitti}", "-m", "copy-last", "-m", "raycast-zbuffer",
                                       "-s", "kitti-1s", "--split", "test", "--policy", "full-context", "--metric",
                                       "chamfer", "--metric", "l1_mean", "-j", "1", "--store", str(store), "--no-report",
                                       "-q"])
    finally:
        finished.set()
        thread.join()
    assert res.exit_code == 0, res.output
    assert "another pcfbench process is computing one of them; running them one by one" in res.stderr
    assert seen == ["free cell complete while the other was held"]
    for s in (free, held):  # both complete, with the rows of a run of their own
        assert Cell(store, s).read_meta()["status"] == "complete"
        run_cell(s, tmp_path / "alone", RunOptions(progress=False))
        _assert_rows_equal(Cell(store, s).read_rows().drop(columns=TIMINGS),
                           Cell(tmp_path / "alone", s).read_rows().drop(columns=TIMINGS))
