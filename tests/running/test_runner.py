import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pcfbench.data import Forecast
from pcfbench.errors import PcfbenchError
from pcfbench.method import Method, options_hash
from pcfbench.plugins import load_plugins
from pcfbench.reporting.report import collect, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec
from pcfbench.testing import check_method
from pcfbench.methods.copy_last import CopyLast
from tests_helpers import write_kitti_tree


class Flaky(Method):
    """Breaks the contract in a different way on different samples."""

    name = "flaky"

    def forecast(self, sample):
        k = sample.ref_index % 5
        last = sample.past_points_ref[-1]
        F = sample.num_future
        if k == 0:
            return Forecast(points_ref=tuple(last[:, :2] for _ in range(F)))  # wrong shape
        if k == 1:
            return Forecast(points_ref=tuple(np.full((3, 3), np.nan) for _ in range(F)))
        if k == 2:
            return Forecast(points_ref=tuple(np.full((3, 3), 1e39) for _ in range(F)))  # outside float32
        if k == 3:
            raise RuntimeError("boom")
        return Forecast(points_ref=tuple(last for _ in range(F)))


def _plugins():
    plugins = load_plugins()
    plugins.methods.add("flaky", Flaky, "test")
    return plugins


def _spec(root, method="copy-last", limit=None, metrics=("chamfer", "chamfer_nf")):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", limit, metrics)


def test_copy_last_contract():
    forecast = check_method(CopyLast())
    assert len(forecast.points_ref) == 5


def test_bad_forecasts_are_recorded_failures_and_the_run_goes_on(tiny_kitti, store):
    result = run_cell(_spec(tiny_kitti, "flaky"), store, RunOptions(progress=False), plugins=_plugins())
    df = Cell(store, _spec(tiny_kitti, "flaky")).read_rows()
    failed = df[df.status == "failed"].set_index("ref_index")
    assert result.failed == len(failed) > 0
    for ref_index, row in failed.iterrows():
        expected = ["shape (N, 3)", "NaN or inf", "outside float32 range", "RuntimeError: boom"][ref_index % 5]
        assert expected in row.error, row.error
        assert f"sample 08/{ref_index:06d}" in row.error or "boom" in row.error
        assert "Traceback" in row.traceback
    ok = df[df.status == "ok"]
    assert set(ok.ref_index % 5) == {4} and len(ok) == 5 * len(set(ok.sample_id))
    meta = json.loads((Cell(store, _spec(tiny_kitti, "flaky")).dir / "cell.json").read_text())
    assert meta["status"] == "complete" and meta["counts"]["failed"] == len(failed)


def test_process_pool_matches_serial(tmp_path):
    root = write_kitti_tree(tmp_path / "k", num_sweeps=40)
    serial = run_cell(_spec(root), tmp_path / "s1", RunOptions(progress=False))
    pooled = run_cell(_spec(root), tmp_path / "s2", RunOptions(jobs=2, progress=False))
    assert serial.samples == pooled.samples
    a = Cell(tmp_path / "s1", _spec(root)).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)
    b = Cell(tmp_path / "s2", _spec(root)).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(a[["sample_id", "step", "chamfer", "chamfer_nf"]], b[["sample_id", "step", "chamfer", "chamfer_nf"]])


def test_limit_is_partial_and_kept_out_of_leaderboard(tiny_kitti, store, tmp_path):
    run_cell(_spec(tiny_kitti, limit=2), store, RunOptions(progress=False))
    assert len(collect(store).table) == 0
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    table = collect(store).table
    assert len(table) == 1 and table.samples.iloc[0] == 6


def test_a_subset_is_complete_ranked_beside_the_full_cells_and_compared_on_the_shared_samples(tiny_kitti, store):
    """CellSpec.subset: at most N of the policy's samples, evenly spaced (i * count // N); its
    own folder and label; not partial, so ranked in the same table as the full cells with its
    sample count, a note saying which rows scored a subset, and compared with the reference on
    the samples the two share."""
    from dataclasses import replace

    full = _spec(tiny_kitti)
    sub = replace(_spec(tiny_kitti, "raycast-zbuffer"), subset=4)
    assert sub.relpath().name.endswith(".subset4") and "subset=4" in sub.label and not sub.partial
    run_cell(full, store, RunOptions(progress=False))
    res = run_cell(sub, store, RunOptions(progress=False))
    all_ids = sorted(set(Cell(store, full).read_rows().sample_id))
    assert len(all_ids) == 6 and res.samples == 4
    assert sorted(set(Cell(store, sub).read_rows().sample_id)) == [all_ids[i] for i in (0, 1, 3, 4)]  # i * 6 // 4
    meta = json.loads((Cell(store, sub).dir / "cell.json").read_text())
    assert meta["status"] == "complete" and meta["spec"]["subset"] == 4 and not meta["partial"]
    lb = collect(store)
    table = lb.table.set_index("method")
    assert table.loc["raycast-zbuffer", "samples"] == 4 and table.loc["copy-last", "samples"] == 6
    assert any("raycast-zbuffer (4) scored a subset of the 6 samples" in n for n in lb.notes), lb.notes
    cmp = lb.comparisons[lb.comparisons.method == "raycast-zbuffer"]
    assert len(cmp) and set(cmp.shared_samples) == {4}
    # a subset of another size is another cell; one as large as the policy's samples is all of
    # them, and no note calls it a subset
    whole = replace(_spec(tiny_kitti, "raycast-4docc"), subset=10)
    assert Cell(store, whole).dir != Cell(store, replace(whole, subset=4)).dir
    assert run_cell(whole, store, RunOptions(progress=False)).samples == 6
    notes = [n for n in collect(store).notes if "scored a subset" in n]
    assert len(notes) == 1 and "raycast-4docc" not in notes[0]
    # one method with two option sets (the default run's two token-copies): the note names each
    from pcfbench.method import resolve_method

    other = resolve_method("raycast-zbuffer:fill_ring=4")
    ring = replace(sub, options=dict(other.raw), options_hash=other.options_hash)
    assert run_cell(ring, store, RunOptions(progress=False)).samples == 4
    notes = [n for n in collect(store).notes if "scored a subset" in n]
    assert len(notes) == 1 and "raycast-zbuffer (4), raycast-zbuffer (fill_ring=4) (4) scored" in notes[0], notes


def test_the_default_run_subset_applies_to_the_default_method_set_only():
    from types import SimpleNamespace

    from pcfbench.cli import _subset

    slow = SimpleNamespace(cls=type("Slow", (), {"default_run_subset": 10}))
    fast = SimpleNamespace(cls=CopyLast)
    assert _subset(slow, None, default_set=True) == 10 and _subset(fast, None, default_set=True) is None
    assert _subset(slow, None, default_set=False) is None  # named with --method: every sample
    assert _subset(slow, 0, default_set=True) is None and _subset(fast, 0, default_set=True) is None  # --subset 0
    assert _subset(fast, 5, default_set=False) == 5 and _subset(slow, 5, default_set=True) == 5  # --subset 5


def test_rerun_with_changed_samples_requires_force(tmp_path):
    root = write_kitti_tree(tmp_path / "k", num_sweeps=24)
    run_cell(_spec(root), tmp_path / "s", RunOptions(progress=False))
    write_kitti_tree(tmp_path / "k", num_sweeps=30)
    with pytest.raises(PcfbenchError, match="sample_ids_hash.*--force"):
        run_cell(_spec(root), tmp_path / "s", RunOptions(progress=False))
    assert run_cell(_spec(root), tmp_path / "s", RunOptions(progress=False, force=True)).processed == 12


def test_report_refuses_mixed_metric_versions(tiny_kitti, store):
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    other = _spec(tiny_kitti, method="flaky")
    run_cell(other, store, RunOptions(progress=False), plugins=_plugins())
    meta_path = Cell(store, other).dir / "cell.json"
    meta = json.loads(meta_path.read_text())
    meta["metric_versions"]["chamfer"] = "0"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(PcfbenchError, match="(?s)refusing to mix metric versions.*chamfer v0"):
        write_reports(store, store.parent / "rep")


def test_report_shape(tiny_kitti, store, tmp_path):
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    paths = write_reports(store, tmp_path / "rep")
    csv = pd.read_csv(paths["csv"])
    assert list(csv.columns[:9]) == ["dataset", "split", "setting", "policy", "method", "method_version", "samples", "failed", "sweeps"]
    assert csv.samples.iloc[0] == 6 and csv.sweeps.iloc[0] == 30
    rows = Cell(store, _spec(tiny_kitti)).read_rows()
    assert csv.chamfer.iloc[0] == pytest.approx(rows.chamfer.mean())
    by_step = pd.read_csv(paths["by_step"])
    assert sorted(by_step.step) == [0, 1, 2, 3, 4]
    assert "\\begin{tabular}" in paths["tex"].read_text()
    assert "<table" in paths["html"].read_text()


@pytest.mark.slow
def test_sigkill_at_any_moment_loses_and_duplicates_nothing(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("08", "09"), num_sweeps=90)
    env = {**os.environ, "PCFBENCH_CHUNK_SAMPLES": "3", "PCFBENCH_NO_PROGRESS": "1"}
    args = [str(Path(sys.executable).parent / "pcfbench"), "run", "--dataset", f"kitti={root}", "--setting", "kitti-1s",
            "--method", "copy-last", "--store", str(tmp_path / "store"), "--reports", str(tmp_path / "rep"), "--no-report"]
    rng = np.random.default_rng(0)
    kills = 0
    for attempt in range(6):
        proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(rng.uniform(1.5, 3.5))
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            kills += 1
        proc.wait()
    assert kills >= 2
    final = subprocess.run(args, env=env, capture_output=True, text=True)
    assert final.returncode == 0, final.stderr
    spec = CellSpec("copy-last", {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None,
                    tuple(json.loads(next((tmp_path / "store").rglob("cell.json")).read_text())["spec"]["metrics"]))
    cell = Cell(tmp_path / "store", spec)
    raw = pd.concat([pd.read_parquet(p) for p in cell.chunk_paths()])
    assert not raw.duplicated(["sample_id", "step"]).any()
    clean = subprocess.run([*args[:-5], "--store", str(tmp_path / "clean"), "--reports", str(tmp_path / "rep2"), "--no-report"],
                           env=env, capture_output=True, text=True)
    assert clean.returncode == 0, clean.stderr
    ref = pd.concat([pd.read_parquet(p) for p in Cell(tmp_path / "clean", spec).chunk_paths()])
    key = ["sample_id", "step"]
    a = raw.sort_values(key).reset_index(drop=True)
    b = ref.sort_values(key).reset_index(drop=True)
    assert len(a) == len(b) == 2 * (90 - 18) * 5
    pd.testing.assert_frame_equal(a[key + ["chamfer", "chamfer_nf"]], b[key + ["chamfer", "chamfer_nf"]])
    assert json.loads((cell.dir / "cell.json").read_text())["status"] == "complete"
    # the range bins beside the rows: none lost, none twice, the clean run's
    raw_ranges = pd.concat([cell.read_ranges_for(p) for p in cell.chunk_paths()])
    assert not raw_ranges.duplicated(key).any() and len(raw_ranges) == len(a)
    pd.testing.assert_frame_equal(raw_ranges.sort_values(key).reset_index(drop=True),
                                  Cell(tmp_path / "clean", spec).read_ranges().sort_values(key).reset_index(drop=True))


def test_range_bins_are_written_with_their_rows_and_a_resumed_run_neither_loses_nor_repeats_them(tmp_path, monkeypatch):
    """Each chunk of rows has its range bins in ranges/ under its name, written just before
    it: a run killed between the two leaves a range file without rows, which is never read
    and which the resumed run replaces. The rows are those of a run that keeps no bins."""
    import pcfbench.running.runner as runner
    import pcfbench.store.cells as store_mod

    root = write_kitti_tree(tmp_path / "k", num_sweeps=30)
    spec = _spec(root, metrics=("chamfer", "l1_mean"))
    monkeypatch.setattr(runner, "CHUNK_SAMPLES", 4)
    real = store_mod.rows_to_parquet
    calls = []

    def killed_on_second(rows):
        calls.append(1)
        if len(calls) >= 2:  # the process dies after chunk 1's range file, before its rows
            raise KeyboardInterrupt
        return real(rows)

    monkeypatch.setattr(store_mod, "rows_to_parquet", killed_on_second)
    with pytest.raises(KeyboardInterrupt):
        run_cell(spec, tmp_path / "s", RunOptions(progress=False))
    cell = Cell(tmp_path / "s", spec)
    assert [p.name for p in cell.chunk_paths()] == ["chunk-000000.parquet"]
    assert sorted(p.name for p in (cell.dir / "ranges").iterdir()) == ["chunk-000000.parquet", "chunk-000001.parquet"]
    assert set(cell.read_ranges()["sample_id"]) == cell.done_ids()  # the orphan is not read
    monkeypatch.setattr(store_mod, "rows_to_parquet", real)
    run_cell(spec, tmp_path / "s", RunOptions(progress=False))
    clean = Cell(tmp_path / "clean", spec)
    run_cell(spec, tmp_path / "clean", RunOptions(progress=False))
    key = ["sample_id", "step"]
    got, want = cell.read_ranges(), clean.read_ranges()
    assert sorted(p.name for p in (cell.dir / "ranges").iterdir()) == [p.name for p in cell.chunk_paths()]
    raw = pd.concat([cell.read_ranges_for(p) for p in cell.chunk_paths()])
    assert not raw.duplicated(key).any() and len(raw) == len(cell.read_rows()) == 12 * 5
    pd.testing.assert_frame_equal(got.sort_values(key).reset_index(drop=True), want.sort_values(key).reset_index(drop=True))
    assert json.loads((cell.dir / "cell.json").read_text())["range_bins"]["bin_m"] == 10.0
    # a cell scoring neither l1_mean nor absrel_mean keeps no bins and its rows are unchanged
    monkeypatch.setattr(runner.ranges, "records", lambda names: False)
    other = tmp_path / "none"
    run_cell(spec, other, RunOptions(progress=False))
    assert not (Cell(other, spec).dir / "ranges").exists() and "range_bins" not in Cell(other, spec).read_meta()
    a, b = Cell(other, spec).read_rows(), clean.read_rows()
    assert list(a.columns) == list(b.columns)
    pd.testing.assert_frame_equal(a.drop(columns=[c for c in a if c.startswith("t_")]),
                                  b.drop(columns=[c for c in b if c.startswith("t_")]))
    assert not run_cell(_spec(root), tmp_path / "chamfer-only", RunOptions(progress=False)).failed
    assert not (Cell(tmp_path / "chamfer-only", _spec(root)).dir / "ranges").exists()


def test_run_options_pick_the_workers_and_the_isolation():
    import os

    from pcfbench.running.runner import AUTO_POOL_MIN_SAMPLES

    auto = RunOptions(jobs=0)
    assert auto.workers(AUTO_POOL_MIN_SAMPLES - 1) == 1  # too few samples to pay for a pool
    assert auto.workers(AUTO_POOL_MIN_SAMPLES) == (os.cpu_count() or 1)
    # isolated, a worker starts either way: one per CPU from the first sample (the callers cap it at the samples)
    assert RunOptions(jobs=0, isolate=True).workers(2) == RunOptions(jobs=0, timeout=5).workers(1) == (os.cpu_count() or 1)
    assert RunOptions(jobs=3).workers(1) == 3  # a pool asked for is a pool (run_cell caps it at the samples)
    assert not RunOptions().isolated and RunOptions(timeout=5).isolated  # a time limit needs a worker to kill
    assert not RunOptions(timeout=5, isolate=False).isolated and RunOptions(isolate=True).isolated
    assert RunOptions().execution().threads >= 1 and RunOptions(threads=2).execution().threads == 2
