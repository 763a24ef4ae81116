"""The terminal: grid progress and variant options on each cell's line, Ctrl-C keeps the
finished work and says how to resume (exit 130), ``pcfbench failures`` lists failed samples,
and every rendered table shows the failed count."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from click.testing import CliRunner

from conftest import write_tiny_kitti
from pcfbench.cli import build_cli
from pcfbench.data import Forecast
from pcfbench.method import Method, options_hash, parse_options
from pcfbench.plugins import load_plugins
from pcfbench.reporting.report import collect, failures, write_reports, ReportOptions
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec
from pcfbench.reporting import tables

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1_median", "absrel_mean", "absrel_median")
PCFBENCH = str(Path(sys.executable).parent / "pcfbench")


class FailsOnOdd(Method):
    """copy-last, but raises on samples whose reference index is odd."""

    name = "fails-on-odd"

    @dataclasses.dataclass(frozen=True)
    class Options:
        pass

    def forecast(self, sample):
        if sample.ref_index % 2:
            raise RuntimeError(f"odd reference index {sample.ref_index}\nsecond line")
        return Forecast(points_ref=tuple(sample.past_points_ref[-1] for _ in range(sample.num_future)))


def _plugins():
    plugins = load_plugins()
    if "fails-on-odd" not in plugins.methods:
        plugins.methods.add("fails-on-odd", FailsOnOdd, "test")
    return plugins


def _spec(root, method):
    opts = parse_options(_plugins().methods.get(method).Options, {}, method)
    return CellSpec(method, {}, options_hash(opts), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


@pytest.fixture(scope="module")
def failing_store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fail")
    root = write_tiny_kitti(tmp / "kitti")
    store = tmp / "store"
    for method in ("copy-last", "fails-on-odd"):
        run_cell(_spec(root, method), store, RunOptions(progress=False), plugins=_plugins())
    return store


def test_failures_lists_each_failed_sample_with_its_error(failing_store):
    df = failures(failing_store)
    assert list(df["sample_id"]) == ["08/000009", "08/000011", "08/000013"]  # samples 8..13, the odd ones
    assert set(df["error"]) == {f"RuntimeError: odd reference index {i}" for i in (9, 11, 13)}
    assert df["traceback"].str.contains("in forecast").all()
    res = CliRunner().invoke(build_cli(), ["failures", str(failing_store)])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].startswith("fails-on-odd | kitti:test | kitti-1s: 3 failed sample(s) (")
    assert lines[1:4] == [f"  08/{i:06d}: RuntimeError: odd reference index {i}" for i in (9, 11, 13)]
    assert lines[-1] == "3 failed sample(s) in 1 cell(s); --traceback prints the tracebacks"
    tb = CliRunner().invoke(build_cli(), ["failures", str(failing_store), "--traceback"]).output
    assert "Traceback (most recent call last)" in tb and "second line" in tb
    empty = CliRunner().invoke(build_cli(), ["failures", str(failing_store.parent / "nothing")])
    assert empty.exit_code == 2 and "does not exist" in empty.output


def test_every_rendered_table_shows_the_failed_count(failing_store, tmp_path):
    lb = collect(failing_store)
    assert list(lb.incomplete["failed"]) == [3]  # the failing cell is not ranked
    paths = write_reports(failing_store, tmp_path / "rep", ReportOptions(figures=False))
    title = "kitti / test / kitti-1s (1 s) - 6 samples, 30 sweeps, 3 failed"
    t = tables.build(lb, tables.get_preset("paper", tables.load_presets()))
    assert title in tables.text(t)
    for key in ("md", "html", "tex", "tables/roi.md", "tables/full.html"):
        assert title in paths[key].read_text(), key
    assert "<th data-key='failed' class='' title='click to sort'>failed</th>" in paths["html"].read_text()


def test_run_lines_show_the_grid_position_and_the_variant_options(tmp_path):
    root = write_tiny_kitti(tmp_path / "kitti")
    res = CliRunner().invoke(build_cli(), ["run", "-d", f"kitti={root}", "-s", "kitti-1s", "-m", "copy-last",
                                           "-m", "raycast-voxel:voxel=0.8", "--limit", "1", "--no-report",
                                           "--store", str(tmp_path / "store"), "-q"])
    assert res.exit_code == 0, res.output
    lines = [x for x in res.output.splitlines() if x.startswith("cell ")]
    assert lines[0].startswith("cell 1/2: copy-last | kitti:test | kitti-1s limit=1: 1 samples (1 now, 0 failed)")
    assert lines[1].startswith("cell 2/2: raycast-voxel (voxel=0.8) | kitti:test | kitti-1s limit=1: 1 samples")


@pytest.mark.slow
def test_ctrl_c_keeps_the_finished_work_and_says_how_to_resume(tmp_path):
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08", "09"))
    store = tmp_path / "store"
    cmd = [PCFBENCH, "run", "-d", f"kitti={root}", "-s", "kitti-1s", "-m", "copy-last", "-m", "raycast-voxel:voxel=0.2",
           "--store", str(store), "--no-report", "--jobs", "1"]
    env = {**os.environ, "PCFBENCH_CHUNK_SAMPLES": "1", "PCFBENCH_NO_PROGRESS": "1"}
    # SIGINT at its default disposition, as under a terminal: a test suite started in the
    # background (`pytest &`) inherits it ignored, and Python then never raises KeyboardInterrupt
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # The two methods share their samples, so they run as one group, one pass over each sample
    # (pcfbench.running.group): interrupt as soon as raycast-voxel's first sample lands, in the
    # middle of both cells (a fixed sleep raced the whole run on a fast machine).
    deadline = time.monotonic() + 120
    while not list(store.glob("kitti/kitti-1s/test/raycast-voxel.*/rows/*.parquet")):
        assert time.monotonic() < deadline and proc.poll() is None, "raycast-voxel never wrote a chunk"
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C sends: the whole foreground process group
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert "pcfbench: interrupted: the finished work is kept in the store" in err
    assert "(0 of 2 cell(s) complete, and every sample finished in the interrupted cell" in err
    assert "run the same command again to resume:\n  pcfbench run -d kitti=" in err
    assert "Traceback" not in err
    kept = len(pd.concat([pd.read_parquet(p) for p in Cell(store, _spec_of(store, "raycast-voxel")).chunk_paths()]))
    assert 0 < kept < 12 * 5
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert again.returncode == 0, again.stderr
    assert "cell 2/2: raycast-voxel" in again.stdout and "complete, nothing to do" not in again.stdout, again.stdout
    for method in ("copy-last", "raycast-voxel"):
        rows = pd.concat([pd.read_parquet(p) for p in Cell(store, _spec_of(store, method)).chunk_paths()])
        assert len(rows) == 12 * 5 and not rows.duplicated(["sample_id", "step"]).any()
        assert (rows["status"] == "ok").all()  # an interrupted sample is not recorded as failed


def _spec_of(store, method):
    from pcfbench.store.cells import iter_cells, spec_from_meta

    return next(spec_from_meta(m) for _, m in iter_cells(store) if m["spec"]["method"] == method)


def test_a_file_as_the_reports_folder_is_one_error(failing_store, tmp_path, monkeypatch):
    f = tmp_path / "reports.txt"
    f.write_text("not a folder")
    monkeypatch.setenv("PCFBENCH_REPORTS", str(f))
    res = CliRunner().invoke(build_cli(), ["report", "--store", str(failing_store)])
    assert res.exit_code == 2 and f.read_text() == "not a folder"
    assert res.output.strip() == (f"pcfbench: error: the reports folder {f} ($PCFBENCH_REPORTS) is a file, not a folder: "
                                  "give a folder")


@pytest.mark.slow
def test_run_writes_the_figures_and_the_page_by_default(tmp_path, monkeypatch):
    monkeypatch.delenv("PCFBENCH_FIGURES")  # the suite turns them off (conftest); a user's run has them
    root = write_tiny_kitti(tmp_path / "kitti")
    rep = tmp_path / "rep"
    res = CliRunner().invoke(build_cli(), ["run", "-d", f"kitti={root}", "-s", "kitti-1s", "-m", "copy-last",
                                           "--reports", str(rep), "-q"])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (rep / "figures").iterdir())
    # the figures, and the manifest of what each one plots (figcache: a rerun redraws none of them)
    assert names == sorted([".figures.json", *(f"{k}-kitti_test_kitti-1s.{e}" for k in ("horizon", "range")
                                               for e in ("png", "svg"))])
    page = (rep / "leaderboard.html").read_text()
    assert page.count("src='data:image/png;base64,") == 2 and "<tr id='cell-1'>" in page


def test_ctrl_c_in_a_sweep_says_the_same(tmp_path, monkeypatch):
    import pcfbench.experiments.sweep

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pcfbench.experiments.sweep, "run_sweep", interrupted)
    exp = Path(__file__).resolve().parents[2] / "docs" / "experiments" / "raycast-voxel-size.toml"
    res = CliRunner().invoke(build_cli(), ["sweep", str(exp), "--store", str(tmp_path / "s"), "-q"])
    assert res.exit_code == 130, res.output
    assert "pcfbench: interrupted: the finished work is kept in the store" in res.output
    assert "run the same command again to resume:" in res.output


def test_report_leaves_the_figures_out_with_pcfbench_figures_0_or_no_figures(failing_store, tmp_path, monkeypatch):
    """PCFBENCH_FIGURES=0 applies to `pcfbench report` as to run and sweep (the command used
    to force figures on unless --no-figures), and --no-figures wins over the environment."""
    monkeypatch.setenv("PCFBENCH_FIGURES", "0")
    res = CliRunner().invoke(build_cli(), ["report", "--store", str(failing_store), "--reports", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "a" / "leaderboard.md").is_file() and not (tmp_path / "a" / "figures").exists()
    monkeypatch.setenv("PCFBENCH_FIGURES", "1")
    res = CliRunner().invoke(build_cli(), ["report", "--store", str(failing_store), "--reports", str(tmp_path / "b"),
                                           "--no-figures"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "b" / "leaderboard.md").is_file() and not (tmp_path / "b" / "figures").exists()


@pytest.mark.parametrize("explicit", [True, False], ids=["--store", "default-store"])
def test_report_on_a_store_that_does_not_exist_is_one_error_and_writes_nothing(tmp_path, explicit):
    reports = tmp_path / "reports"
    reports.mkdir()
    (reports / "leaderboard.md").write_text("the last real leaderboard\n")
    missing = tmp_path / "stroe" if explicit else reports / "store"
    args = ["report", "--reports", str(reports)] + (["--store", str(missing)] if explicit else [])
    res = CliRunner().invoke(build_cli(), args)
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    errors = [line for line in res.stderr.splitlines() if line.startswith("pcfbench: error:")]
    assert len(errors) == 1 and f"results store {missing} does not exist" in errors[0], res.stderr
    assert not missing.exists()
    assert [p.name for p in reports.iterdir()] == ["leaderboard.md"]
    assert (reports / "leaderboard.md").read_text() == "the last real leaderboard\n"
