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


def test_groups_are_the_cells_that_share_their_samples(tiny_kitti):
    a, b = _spec(tiny_kitti, "copy-last"), _spec(tiny_kitti, "raycast-zbuffer")
    c = CellSpec("copy-last", {}, options_hash(None), "kitti", str(tiny_kitti), "test", "kitti-3s", "full-context", None,
                 METRICS)
    d = CellSpec("copy-last", {}, options_hash(None), "kitti", str(tiny_kitti), "test", "kitti-1s", "full-context", None,
                 ("chamfer",))
    assert groups([a, c, b, d]) == [[a, b], [c], [d]]


def _pid(key):
    time.sleep(0.02)
    return key, os.getpid()


def _init():
    pass


def _fail(key, kind, reason):
    return key, kind


def test_supervised_tasks_of_one_kind_go_to_one_worker_in_turn():
    keys = [(s, m) for s in range(6) for m in range(3)]
    out = list(workers.run_supervised(keys, 2, _init, (), _pid, _fail, affinity=lambda k: k[0]))
    assert sorted(k for k, _ in out) == keys
    by_sample = {}
    for (s, _), pid in out:
        by_sample.setdefault(s, set()).add(pid)
    # every sample but the last two (where a free worker helps rather than waits) in one worker
    assert all(len(by_sample[s]) == 1 for s in range(4)), by_sample
    assert len({pid for _, pid in out}) == 2
