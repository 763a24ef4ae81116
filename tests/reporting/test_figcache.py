"""Figures are drawn again only when what they plot changed: a second report draws none, a
changed group redraws its own figures only, a file edited or removed since is redrawn, and the
key follows the plotted data to the last bit."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import write_tiny_kitti
from pcfbench.cli import build_cli
from pcfbench.method import options_hash, parse_options
from pcfbench.plugins import load_plugins
from pcfbench.reporting import figcache, figures, tables
from pcfbench.reporting.report import ReportOptions, collect, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1_median", "absrel_mean", "absrel_median")
STEMS = {f"{kind}-kitti_test_{setting}" for kind in ("horizon", "range") for setting in ("kitti-1s", "kitti-3s")}


def _spec(root, setting, method="copy-last", raw=None):
    opts = parse_options(load_plugins().methods.get(method).Options, raw or {}, method)
    return CellSpec(method, dict(raw or {}), options_hash(opts), "kitti", str(root), "test", setting,
                    "full-context", None, METRICS)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """copy-last and raycast-voxel on kitti-1s and on kitti-3s: two groups, four figures."""
    tmp = tmp_path_factory.mktemp("figcache")
    root = write_tiny_kitti(tmp / "kitti", num_sweeps=64)
    for setting in ("kitti-1s", "kitti-3s"):
        for method in ("copy-last", "raycast-voxel"):
            run_cell(_spec(root, setting, method), tmp / "store", RunOptions(progress=False))
    return root, tmp / "store"


@pytest.fixture
def root(made):
    return made[0]


@pytest.fixture
def store(made, tmp_path):
    """A copy of the module's store, for the test to change."""
    shutil.copytree(made[1], tmp_path / "store")
    return tmp_path / "store"


@pytest.fixture
def drawn(monkeypatch):
    """The stems of the figures drawn (saved), in order."""
    calls: list[str] = []
    save = figures.save

    def counting(fig, out_dir, stem, *args):
        calls.append(stem)
        return save(fig, out_dir, stem, *args)

    monkeypatch.setattr(figures, "save", counting)
    return calls


def _files(out):
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (out / "figures").iterdir()
            if p.suffix in (".png", ".svg")}


def test_a_second_report_draws_no_figure(store, tmp_path, drawn):
    out = tmp_path / "rep"
    first = write_reports(store, out, ReportOptions(figures=True))
    assert set(drawn) == STEMS and len(drawn) == 4 and first.kept_figures == ()
    before = _files(out)
    assert len(before) == 8
    drawn.clear()
    second = write_reports(store, out, ReportOptions(figures=True))
    assert drawn == []
    assert set(second.kept_figures) == STEMS
    assert _files(out) == before  # the very files, untouched
    assert {k for k in second if k.startswith("figures/")} == {k for k in first if k.startswith("figures/")}
    page = second["html"].read_text()
    assert page.count("src='data:image/png;base64,") == 4 and page == first["html"].read_text()
    manifest = json.loads((out / "figures" / figcache.MANIFEST).read_text())
    assert set(manifest["figures"]) == STEMS


def test_a_changed_group_redraws_its_own_figures_only(store, root, tmp_path, drawn):
    out = tmp_path / "rep"
    write_reports(store, out, ReportOptions(figures=True))
    before = _files(out)
    drawn.clear()
    # a new cell in the kitti-3s group: its horizon and range figures change, kitti-1s's do not
    run_cell(_spec(root, "kitti-3s", "raycast-voxel", {"voxel": "0.4"}), store, RunOptions(progress=False))
    paths = write_reports(store, out, ReportOptions(figures=True))
    assert sorted(drawn) == ["horizon-kitti_test_kitti-3s", "range-kitti_test_kitti-3s"]
    assert sorted(paths.kept_figures) == ["horizon-kitti_test_kitti-1s", "range-kitti_test_kitti-1s"]
    after = _files(out)
    for name in before:
        assert (after[name] == before[name]) == ("kitti-1s" in name), name
    # a filtered report that leaves kitti-3s out: the kitti-1s figures stay as they are, kitti-3s's go
    drawn.clear()
    from pcfbench.reporting.select import Selection

    paths = write_reports(store, out, ReportOptions(figures=True, select=Selection(settings=("kitti-1s",))))
    assert drawn == []
    assert sorted(p.name for p in (out / "figures").iterdir() if not p.name.startswith(".")) == \
        sorted(n for n in before if "kitti-1s" in n)


def test_a_changed_cell_redraws_only_the_figures_that_plot_what_changed(store, root, tmp_path, drawn):
    """One value of one stored row changed (as a recomputed cell with another result would):
    its group's horizon figure plots it and is drawn again; the range figure, drawn from the
    range bins, and the other group's figures are not."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pcfbench.store.cells import Cell

    out = tmp_path / "rep"
    write_reports(store, out, ReportOptions(figures=True))
    before = _files(out)
    chunk = Cell(store, _spec(root, "kitti-3s", "raycast-voxel")).chunk_paths()[0]
    rows = pq.read_table(chunk).to_pandas()
    rows.loc[0, "l1_mean"] += 0.25
    pq.write_table(pa.Table.from_pandas(rows, preserve_index=False), chunk)
    drawn.clear()
    paths = write_reports(store, out, ReportOptions(figures=True))
    assert drawn == ["horizon-kitti_test_kitti-3s"]
    assert sorted(paths.kept_figures) == sorted(STEMS - {"horizon-kitti_test_kitti-3s"})
    after = _files(out)
    assert sorted(n for n in before if after[n] != before[n]) == ["horizon-kitti_test_kitti-3s.png",
                                                                  "horizon-kitti_test_kitti-3s.svg"]


def test_a_figure_edited_or_removed_since_is_drawn_again(store, tmp_path, drawn, monkeypatch):
    out = tmp_path / "rep"
    write_reports(store, out, ReportOptions(figures=True))
    want = (out / "figures" / "range-kitti_test_kitti-1s.svg").read_bytes()
    (out / "figures" / "range-kitti_test_kitti-1s.svg").write_text("<svg>edited</svg>")
    (out / "figures" / "horizon-kitti_test_kitti-3s.png").unlink()
    drawn.clear()
    write_reports(store, out, ReportOptions(figures=True))
    assert sorted(drawn) == ["horizon-kitti_test_kitti-3s", "range-kitti_test_kitti-1s"]
    assert (out / "figures" / "range-kitti_test_kitti-1s.svg").read_bytes() == want  # same data, same bytes
    assert (out / "figures" / "horizon-kitti_test_kitti-3s.png").is_file()
    # other figure code (or another matplotlib): every figure again
    drawn.clear()
    monkeypatch.setattr(figcache, "code_version", lambda: "other")
    write_reports(store, out, ReportOptions(figures=True))
    assert set(drawn) == STEMS
    # a manifest that cannot be read: every figure again, and a good one written
    drawn.clear()
    (out / "figures" / figcache.MANIFEST).write_text("{not json")
    write_reports(store, out, ReportOptions(figures=True))
    assert set(drawn) == STEMS
    drawn.clear()
    write_reports(store, out, ReportOptions(figures=True))
    assert drawn == []


def test_the_key_follows_every_plotted_value_and_label(store):
    lb = collect(store)
    t = tables.build(lb, tables.get_preset("paper", tables.load_presets()))
    steps = lb.by_step[lb.by_step["setting"] == "kitti-1s"]
    key = figcache.figure_key("horizon", **figures.horizon_data(steps, t.columns, "x"))
    assert figcache.figure_key("horizon", **figures.horizon_data(steps.copy(), t.columns, "x")) == key
    assert figcache.figure_key("range", **figures.horizon_data(steps, t.columns, "x")) != key
    assert figcache.figure_key("horizon", **figures.horizon_data(steps, t.columns, "y")) != key
    for col in ("l1_mean", "l1_mean_hi", "time_s"):
        nudged = steps.copy()
        nudged.iloc[0, nudged.columns.get_loc(col)] = np.nextafter(nudged[col].iloc[0], np.inf)  # one ulp
        assert figcache.figure_key("horizon", **figures.horizon_data(nudged, t.columns, "x")) != key, col
    nan = steps.copy()
    nan.iloc[0, nan.columns.get_loc("l1_mean")] = np.nan
    assert figcache.figure_key("horizon", **figures.horizon_data(nan, t.columns, "x")) != key
    relabelled = [type(c)(c.metric, c.label + "!", c.better, c.unit) for c in t.columns]
    assert figcache.figure_key("horizon", **figures.horizon_data(steps, relabelled, "x")) != key
    reordered = steps.iloc[::-1]  # the lines are drawn in row order
    assert figcache.figure_key("horizon", **figures.horizon_data(reordered, t.columns, "x")) != key
    # the range figure's profiles, in the order their lines are drawn
    found = figures.group_ranges(store, lb.table)[("kitti", "test", "kitti-1s", "full-context")]
    assert len(found.profiles) == 2
    rkey = figcache.figure_key("range", **figures.range_data(found, "x"))
    flipped = figures.StoredRanges(dict(reversed(found.profiles.items())), found.sweeps, found.missing, found.why)
    assert figcache.figure_key("range", **figures.range_data(flipped, "x")) != rkey
    fewer = figures.StoredRanges({k: p.iloc[:-1] for k, p in found.profiles.items()}, found.sweeps, found.missing)
    assert figcache.figure_key("range", **figures.range_data(fewer, "x")) != rkey
    # a column the figure does not read does not change it
    other = steps.assign(sweeps=steps["sweeps"] + 1)
    assert figcache.figure_key("horizon", **figures.horizon_data(other, t.columns, "x")) == key


def test_report_prints_a_summary_and_every_path_with_verbose(store, tmp_path, monkeypatch):
    monkeypatch.setenv("PCFBENCH_FIGURES", "1")
    out = tmp_path / "rep"
    args = ["report", "--store", str(store), "--reports", str(out)]
    res = CliRunner().invoke(build_cli(), args)
    assert res.exit_code == 0, res.output
    assert (f"wrote 4 tables (leaderboard and tables/), 4 figure(s) to {out}; leaderboard: {out / 'leaderboard.md'} "
            "and leaderboard.html (-v lists every file)") in res.output
    assert str(out / "leaderboard.csv") not in res.output
    res = CliRunner().invoke(build_cli(), args + ["-v"])
    assert res.exit_code == 0, res.output
    assert "4 figure(s) (4 unchanged, not redrawn)" in res.output
    for name in ("leaderboard.csv", "leaderboard_by_step.csv", "tables/roi.tex", "figures/range-kitti_test_kitti-3s.svg"):
        assert f"{out / name}\n" in res.output
