"""`pcfbench report --dataset/--setting/--method`: only the cells the patterns match reach the
tables, figures and pages, every page says which filters made it, and a pattern that matches
nothing is one error naming what the store holds."""

from __future__ import annotations

import dataclasses
import html

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from conftest import write_tiny_kitti
from tests_helpers import shifted_plugins as _plugins
from pcfbench.cli import build_cli
from pcfbench.errors import PcfbenchError
from pcfbench.method import options_hash, parse_options
from pcfbench.reporting.escape import md_text
from pcfbench.reporting.report import collect
from pcfbench.reporting.select import Selection
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1_median", "absrel_mean", "absrel_median")


def _spec(root, setting, method="copy-last", raw=None):
    opts = parse_options(_plugins().methods.get(method).Options, raw or {}, method)
    return CellSpec(method, dict(raw or {}), options_hash(opts), "kitti", str(root), "test", setting,
                    "full-context", None, METRICS)


#: the store's cells: (setting, method, options)
CELLS = [("kitti-1s", "copy-last", None), ("kitti-1s", "shifted", {"dx": "0.5"}), ("kitti-1s", "shifted", {"dx": "1.5"}),
         ("kitti-3s", "copy-last", None)]


@pytest.fixture(scope="module")
def two_settings(tmp_path_factory):
    """copy-last and two shifted variants on kitti-1s, copy-last on kitti-3s."""
    tmp = tmp_path_factory.mktemp("select")
    root = write_tiny_kitti(tmp / "kitti", num_sweeps=64)
    store = tmp / "store"
    for setting, method, raw in CELLS:
        run_cell(_spec(root, setting, method, raw), store, RunOptions(progress=False), plugins=_plugins())
    return store


def _report(store, out, *args):
    return CliRunner().invoke(build_cli(), ["report", "--store", str(store), "--reports", str(out), *args])


def test_selection_matches_shell_patterns_per_field():
    spec = _spec("/r", "kitti-1s", "copy-last")
    assert Selection().matches(spec) and not Selection().active
    assert Selection(methods=("copy-*",)).matches(spec)
    assert Selection(methods=("raycast-*", "copy-last")).matches(spec)  # any pattern of a field
    assert not Selection(methods=("Copy-last",)).matches(spec)  # case-sensitive, as names are
    assert Selection(datasets=("kit?i",), settings=("kitti-[13]s",)).matches(spec)
    assert not Selection(datasets=("kitti",), settings=("kitti-3s",)).matches(spec)  # every field given must match
    assert Selection(("kitti",), (), ("raycast-*", "copy-last")).describe() == \
        "--dataset kitti --method 'raycast-*' --method copy-last"


def test_filtered_report_holds_only_the_selected_cells_with_the_numbers_of_the_full_one(two_settings, tmp_path):
    store = two_settings
    full = collect(store)
    assert len(full.table) == 4 and full.scope == ""
    res = _report(store, tmp_path / "rep", "--setting", "kitti-1s", "--method", "shift*")
    assert res.exit_code == 0, res.output
    scope = "filtered view: only the cells matching --setting kitti-1s --method 'shift*' (2 of the store's 4 complete cells)"
    assert scope in res.output
    csv = pd.read_csv(tmp_path / "rep" / "leaderboard.csv")
    assert sorted(csv["variant"]) == ["shifted (dx=0.5)", "shifted (dx=1.5)"]
    assert set(csv["setting"]) == {"kitti-1s"}
    # the same cells' numbers as in the report of the whole store (same samples, same draws)
    want = full.table.set_index("variant").loc[csv["variant"]]
    for m in ("chamfer_nf", "l1_mean", "l1_mean_lo", "l1_mean_hi"):
        np.testing.assert_array_equal(csv[m].to_numpy(), want[m].to_numpy())
    # copy-last is filtered out: no comparison, and the page says why
    assert csv["l1_mean_rel"].isna().all()
    md = (tmp_path / "rep" / "leaderboard.md").read_text()
    assert md.splitlines()[2] == f"**{md_text(scope)}**"  # its patterns' * escaped
    assert "no 'copy-last' cell to compare with" in md
    assert "copy-last" not in pd.read_csv(tmp_path / "rep" / "leaderboard_by_step.csv")["method"].tolist()
    shown = f"<p class='scope'><strong>{html.escape(scope)}</strong></p>"
    assert shown in (tmp_path / "rep" / "leaderboard.html").read_text()
    assert (tmp_path / "rep" / "leaderboard.tex").read_text().splitlines()[2] == f"% {scope}"
    for name in ("paper", "roi", "full"):
        assert f"**{md_text(scope)}**" in (tmp_path / "rep" / "tables" / f"{name}.md").read_text()
        assert shown in (tmp_path / "rep" / "tables" / f"{name}.html").read_text()


def test_selecting_the_reference_too_keeps_the_comparisons(two_settings, tmp_path):
    full = collect(two_settings)
    lb = collect(two_settings, select=Selection(settings=("kitti-1s",), methods=("shifted", "copy-last")))
    assert len(lb.table) == 3 and "3 of the store's 4 complete cells" in lb.scope
    got = lb.table.set_index("variant")["l1_mean_rel"]
    want = full.table[full.table["setting"] == "kitti-1s"].set_index("variant")["l1_mean_rel"]
    pd.testing.assert_series_equal(got.sort_index(), want.sort_index())
    assert got.notna().sum() == 2
    # a reference named explicitly but filtered out: said so, with the fix
    with pytest.raises(PcfbenchError, match=r"reference method 'copy-last' is not among the cells selected by "
                                            r"--method shifted: add --method copy-last"):
        collect(two_settings, reference="copy-last", select=Selection(methods=("shifted",)))


def test_unfiltered_report_says_nothing_of_filters(two_settings, tmp_path):
    res = _report(two_settings, tmp_path / "rep")
    assert res.exit_code == 0, res.output
    assert "filtered view" not in res.output
    for name in ("leaderboard.md", "leaderboard.html", "leaderboard.tex"):
        assert "filtered view" not in (tmp_path / "rep" / name).read_text()
    assert len(pd.read_csv(tmp_path / "rep" / "leaderboard.csv")) == 4


def test_a_pattern_that_matches_nothing_is_one_error_listing_the_store(two_settings, tmp_path):
    res = _report(two_settings, tmp_path / "rep", "--method", "raycast-*", "--dataset", "nuscenes", "--method", "shifted",
                  "--method", "copy-lst")
    assert res.exit_code != 0
    assert "--dataset nuscenes matches no dataset; --method 'raycast-*' matches no method; --method copy-lst matches " \
           "no method (did you mean copy-last?) of the store's 4 complete cell(s), which hold:" in res.output
    assert "  datasets: kitti\n  settings: kitti-1s, kitti-3s\n  methods: copy-last, shifted\n" in res.output
    assert "Traceback" not in res.output
    assert not (tmp_path / "rep").exists()  # no empty report
    # each pattern matches some cell, but no cell matches them all
    res = _report(two_settings, tmp_path / "rep", "--setting", "kitti-3s", "--method", "shifted")
    assert res.exit_code != 0
    assert "no cell matches --setting kitti-3s --method shifted together of the store's 4 complete cell(s)" in res.output
    assert not (tmp_path / "rep").exists()


def test_the_transfer_table_of_a_filtered_view_says_so_too(two_settings, tmp_path):
    from pcfbench.reporting.transfer import write_transfer

    lb = collect(two_settings, select=Selection(settings=("kitti-1s",)))
    table = lb.table.copy()
    table.loc[table["method"] == "shifted", ["train_on", "checkpoint_sha256"]] = ["kitti:train", "0" * 64]  # as if trained
    text = write_transfer(dataclasses.replace(lb, table=table), tmp_path)["transfer_md"].read_text()
    assert text.splitlines()[2] == f"**{lb.scope}**" and lb.scope.startswith("filtered view: ")
    unfiltered = write_transfer(dataclasses.replace(lb, table=table, scope=""), tmp_path)["transfer_md"].read_text()
    assert "filtered view" not in unfiltered
