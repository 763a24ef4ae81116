"""Issue 15: failures count. A cell whose samples did not all score is not ranked beside
complete ones (its coverage is shown), ``pcfbench run`` exits non-zero when samples failed,
and a cell with a chunk deleted is found incomplete on read."""


import pandas as pd
from click.testing import CliRunner

import pcfbench.plugins
from pcfbench.running import runner
from pcfbench.cli import cli
from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.protocol import ids_hash
from pcfbench.reporting.report import collect, coverage, summary, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec

METRICS = ("chamfer", "chamfer_nf")


class HalfFails(CopyLast):
    """copy-last on even reference indices; raises on odd ones (so it would score like copy-last)."""

    name = "half-fails"

    def forecast(self, sample):
        if sample.ref_index % 2:
            raise RuntimeError("no forecast today")
        return super().forecast(sample)


def _plugins():
    plugins = load_plugins()
    plugins.methods.add("half-fails", HalfFails, "test")
    return plugins


def _spec(root, method="copy-last"):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


def test_coverage_hand_made():
    rows = pd.DataFrame({"sample_id": ["a", "a", "b", "c"], "status": ["ok", "ok", "failed", "ok"]})
    meta = {"samples": 4, "sample_ids_hash": ids_hash(["a", "b", "c", "d"])}
    cov = coverage(meta, rows)
    assert (cov.expected, cov.ok, cov.failed, cov.missing, cov.text, cov.complete) == (4, 2, 1, 1, "2/4", False)
    full = pd.DataFrame({"sample_id": list("abcd"), "status": ["ok"] * 4})
    assert coverage(meta, full).complete and coverage(meta, full).text == "4/4"
    # as many ids as expected, but not the cell's own: some are missing
    other = pd.DataFrame({"sample_id": list("abce"), "status": ["ok"] * 4})
    assert not coverage(meta, other).complete and coverage(meta, other).missing >= 1
    # a pre-identity cell (no hash): the count alone
    assert coverage({"samples": 4}, full).complete and not coverage({"samples": 5}, full).complete


def test_a_cell_with_failed_samples_is_not_ranked(tiny_kitti, store, tmp_path):
    plugins = _plugins()
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False), plugins=plugins)
    result = run_cell(_spec(tiny_kitti, "half-fails"), store, RunOptions(progress=False), plugins=plugins)
    n = result.samples
    assert 0 < result.failed < n
    lb = collect(store)
    assert list(lb.table.method) == ["copy-last"]  # half-fails is not ranked beside it
    assert list(lb.incomplete.method) == ["half-fails"]
    row = lb.incomplete.iloc[0]
    assert row.coverage == f"{n - result.failed}/{n}" and row.failed == result.failed and row.missing == 0
    assert any("half-fails: INCOMPLETE" in note and f"{n - result.failed}/{n} samples scored" in note for note in lb.notes)
    paths = write_reports(store, tmp_path / "reports")
    board = pd.read_csv(paths["csv"])
    assert list(board.method) == ["copy-last"]
    incomplete = pd.read_csv(paths["incomplete_csv"])
    assert list(incomplete.method) == ["half-fails"] and incomplete.coverage.tolist() == [f"{n - result.failed}/{n}"]
    assert "INCOMPLETE" in paths["md"].read_text()
    assert f"half-fails: {n - result.failed}/{n} ({result.failed} failed" in summary(store, leaderboard=lb)
    by_step = pd.read_csv(paths["by_step"])
    assert set(by_step.method) == {"copy-last"}


def test_a_deleted_chunk_is_found_on_read(tiny_kitti, store, monkeypatch):
    monkeypatch.setattr(runner, "CHUNK_SAMPLES", 2)
    run_cell(_spec(tiny_kitti), store, RunOptions(progress=False))
    cell = Cell(store, _spec(tiny_kitti))
    chunks = cell.chunk_paths()
    assert len(chunks) >= 3
    meta = cell.read_meta()
    assert meta["status"] == "complete" and collect(store).table.method.tolist() == ["copy-last"]
    gone = set(pd.read_parquet(chunks[1]).sample_id)
    chunks[1].unlink()
    assert cell.read_meta()["counts"]["ok"] == meta["samples"]  # cell.json still claims every sample
    lb = collect(store)
    assert len(lb.table) == 0 and list(lb.incomplete.method) == ["copy-last"]
    row = lb.incomplete.iloc[0]
    assert row.missing == len(gone) and row.coverage == f"{meta['samples'] - len(gone)}/{meta['samples']}"


def _cli_run(store, root, *extra):
    return CliRunner().invoke(cli, ["run", "-d", f"kitti={root}", "-m", "half-fails", "-m", "copy-last",
                                                    "-s", "kitti-1s", "--metric", "chamfer", "--store", str(store),
                                                    "--reports", str(store.parent / "reports"), "-q", *extra])


def test_run_exits_non_zero_when_samples_failed_unless_keep_going(tiny_kitti, tmp_path, monkeypatch):
    monkeypatch.setattr(pcfbench.plugins, "_PLUGINS", _plugins())
    store = tmp_path / "store"
    res = _cli_run(store, tiny_kitti)
    assert res.exit_code == 1, res.output
    assert "sample(s) failed in 1 cell(s), which are incomplete and not ranked" in res.stderr
    assert "INCOMPLETE cells, not ranked (1)" in res.stdout
    # a rerun reuses the cells: the failures still count
    again = _cli_run(store, tiny_kitti)
    assert again.exit_code == 1 and "complete, nothing to do" in again.stdout
    kept = _cli_run(store, tiny_kitti, "--keep-going")
    assert kept.exit_code == 0 and "sample(s) failed" in kept.stderr
    ok = CliRunner().invoke(cli, ["run", "-d", f"kitti={tiny_kitti}", "-m", "copy-last", "-s", "kitti-1s", "--metric",
                                  "chamfer", "--store", str(tmp_path / "s2"), "--no-report", "-q"])
    assert ok.exit_code == 0, ok.output
