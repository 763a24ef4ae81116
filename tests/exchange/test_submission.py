"""Forecasts made outside pcfbench's process: the query file out, a submission in, scored as a
plugin's forecast is; every hostile submission is one error naming the file and the sample."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from conftest import write_tiny_kitti
from pcfbench.cli import build_cli
from pcfbench.errors import PcfbenchError
from pcfbench.exchange.commands import score_submission
from pcfbench.exchange.queries import read_queries, sample_members, write_queries
from pcfbench.exchange.questions import open_questions
from pcfbench.running.runner import RunOptions, default_metrics, run_cell
from pcfbench.plugins import get_plugins
from pcfbench.store.cells import Cell, CellSpec, iter_cells

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "bring-your-own-method.md"


def _example() -> str:
    (code,) = re.findall(r"^```python\n(.*?)^```", DOC.read_text(encoding="utf-8"), re.S | re.M)
    return code


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A tiny KITTI tree, its kitti-1s questions and their query file."""
    tmp = tmp_path_factory.mktemp("exchange")
    root = write_tiny_kitti(tmp / "kitti")
    q = open_questions("kitti", str(root), "test", "kitti-1s", "full-context")
    write_queries(q, tmp / "queries.npz")
    return tmp, root, q


def _example_submission(queries: Path, out: Path) -> Path:
    """The docs' example run on ``queries`` in a Python of its own, writing ``out``."""
    res = subprocess.run([sys.executable, "-c", _example(), str(queries), str(out)],
                         capture_output=True, text=True, cwd=out.parent)
    assert res.returncode == 0, res.stderr
    return out


def _rows(store: Path, method: str) -> pd.DataFrame:
    for d, meta in iter_cells(store):
        if meta["spec"]["method"] == method:
            rows = Cell.at(store, d.relative_to(store)).read_rows()
            return rows.sort_values(["sample_id", "step"]).reset_index(drop=True)
    raise AssertionError(f"no cell of {method}")


# -- the query file ------------------------------------------------------------------------------

def test_the_query_file_holds_each_sample_as_a_method_sees_it_and_no_truth(world):
    tmp, _root, q = world
    head, npz = read_queries(tmp / "queries.npz")
    assert [s["sample_id"] for s in head["samples"]] == q.ids == ["08/000008", "08/000009", "08/000010", "08/000011",
                                                                  "08/000012", "08/000013"]
    assert head["answers"] == q.answers()
    a = head["answers"]
    assert (a["protocol_version"], a["dataset"], a["split"], a["setting"], a["policy"]) == (
        "1", "kitti", "test", "kitti-1s", "full-context")
    assert len(a["data_fingerprint"]) >= 16 and a["setting_params"] == {"rate_hz": 10.0, "past": 5, "future": 5, "stride": 2}
    s0 = head["samples"][0]
    assert [p["index"] for p in s0["past"]] == [0, 2, 4, 6, 8] and [f["index"] for f in s0["future"]] == [10, 12, 14, 16, 18]
    assert s0["past"][-1]["source"].endswith("000008.bin")
    for key in q.keys:  # every array as the runner hands it to a plugin, bit for bit
        sample, truth = q.builder.build(*key)
        for name, arr in sample_members(sample):
            got = npz[name]
            assert got.dtype == np.asarray(arr).dtype and np.array_equal(got, arr), name
        assert [len(npz[f"{sample.sample_id}/directions_ref/{k}"]) for k in range(5)] == [len(t) for t in truth.future_points_ref]
    names = set(npz.files)
    assert not [n for n in names if "depth" in n or "truth" in n or "future_points" in n]
    assert len(names) == 1 + 6 * (5 + 5 + 6)


# -- the docs' example: made outside, scored as the plugin ----------------------------------------------

def test_the_docs_example_is_numpy_only_and_scores_exactly_as_copy_last(world, tmp_path):
    tmp, root, q = world
    code = _example()
    imported = {a.name for n in ast.walk(ast.parse(code)) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module for n in ast.walk(ast.parse(code)) if isinstance(n, ast.ImportFrom)}
    assert imported == {"json", "sys", "numpy"} and len(code.strip().splitlines()) <= 30
    sub = _example_submission(tmp / "queries.npz", tmp_path / "copy-last.npz")

    store = tmp_path / "store"
    metrics = default_metrics(get_plugins())
    result, checked = score_submission(sub, "outside", q, store, metrics)
    assert checked.answered == 6 and not checked.missing and result.failed == 0
    spec = CellSpec("copy-last", {}, _copy_last_hash(), "kitti", str(root), "test", "kitti-1s", "full-context", None, metrics)
    run_cell(spec, store, RunOptions(progress=False))

    mine, plugin = _rows(store, "submission"), _rows(store, "copy-last")
    columns = [c for c in plugin.columns if not c.startswith("t_")]  # every metric, n_gt, n_pred; not the timings
    assert set(metrics) <= set(columns) and len(plugin) == 30
    pd.testing.assert_frame_equal(mine[columns], plugin[columns], check_exact=True)

    from pcfbench.reporting.report import collect

    board = collect(store).table
    assert set(board["variant"]) == {"copy-last", f"outside (submission {_sha(sub)[:8]})"}
    sub_row = board[board["method"] == "submission"].iloc[0]
    ref_row = board[board["method"] == "copy-last"].iloc[0]
    for m in metrics:
        assert sub_row[m] == ref_row[m] or (np.isnan(sub_row[m]) and np.isnan(ref_row[m])), m


def _copy_last_hash() -> str:
    from pcfbench.method import resolve_method

    return resolve_method("copy-last").options_hash


def _sha(path: Path) -> str:
    from pcfbench.exchange.submission import file_sha256

    return file_sha256(path)


# -- hostile submissions ------------------------------------------------------------------------------

def _members(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _header(members: dict) -> dict:
    return json.loads(str(members["header.json"]))


def _save(path: Path, members: dict, header: dict | None = None) -> Path:
    if header is not None:
        members = {**members, "header.json": np.array(json.dumps(header))}
    np.savez(path, **members)
    return path


def _refused(world, tmp_path, members, match, header=None, partial=False):
    _tmp, _root, q = world
    sub = _save(tmp_path / "hostile.npz", members, header)
    with pytest.raises(PcfbenchError, match=match) as err:
        score_submission(sub, "hostile", q, tmp_path / "store", ("chamfer",), partial)
    assert str(sub) in str(err.value)
    assert not (tmp_path / "store").exists()  # nothing written
    return str(err.value)


@pytest.fixture
def good(world, tmp_path):
    return _members(_example_submission(world[0] / "queries.npz", tmp_path / "good.npz"))


def _depths(world, good):
    """The good submission answered with depths (10 m per ray) instead of points."""
    _tmp, _root, q = world
    head, npz = read_queries(world[0] / "queries.npz")
    out = {"header.json": good["header.json"]}
    for s in head["samples"]:
        for k in range(5):
            out[f"{s['sample_id']}/depths/{k}"] = np.full(len(npz[f"{s['sample_id']}/directions_ref/{k}"]), 10.0, np.float32)
    return out


def test_a_missing_sample_is_refused_naming_it(world, tmp_path, good):
    members = {k: v for k, v in good.items() if not k.startswith("08/000010/")}
    msg = _refused(world, tmp_path, members, r"misses 1 of the 6 samples: 08/000010; pass --partial")
    assert "never ranked" in msg


def test_an_extra_sample_is_refused_naming_it(world, tmp_path, good):
    members = {**good, **{f"08/000099/points_ref/{k}": good[f"08/000008/points_ref/{k}"] for k in range(5)}}
    _refused(world, tmp_path, members, r"has 1 sample\(s\) that kitti:test kitti-1s \(full-context\) does not have: 08/000099")


def test_a_wrong_ray_count_is_refused_naming_sample_and_sweep(world, tmp_path, good):
    members = _depths(world, good)
    d = members["08/000012/depths/2"]
    members["08/000012/depths/2"] = d[:-1]
    _refused(world, tmp_path, members, rf"sample 08/000012, future sweep 2: depths have shape \({len(d) - 1},\), "
                                       rf"expected \({len(d)},\) \(one per query ray\)")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_and_inf_are_refused_naming_sample_and_sweep(world, tmp_path, good, bad):
    members = _depths(world, good)
    members["08/000009/depths/4"] = members["08/000009/depths/4"].copy()
    members["08/000009/depths/4"][7] = bad
    _refused(world, tmp_path, members, r"sample 08/000009, future sweep 4: 1 depth\(s\) are NaN or inf")
    points = dict(good)
    points["08/000011/points_ref/0"] = points["08/000011/points_ref/0"].copy()
    points["08/000011/points_ref/0"][3, 1] = bad
    _refused(world, tmp_path, points, r"sample 08/000011, future sweep 0: 1 point\(s\) with NaN or inf coordinates")


def test_a_missing_future_sweep_is_refused(world, tmp_path, good):
    members = {k: v for k, v in good.items() if k != "08/000013/points_ref/4"}
    _refused(world, tmp_path, members, r"sample 08/000013: points_ref for future sweeps \[0, 1, 2, 3\], expected 0..4 "
                                       r"\(missing \[4\]\)")


@pytest.mark.parametrize("field, value", [
    ("setting", "kitti-3s"), ("data_fingerprint", "0" * 16), ("protocol_version", "0"), ("policy", "every-frame"),
    ("dataset_version", "0"),
])
def test_answers_to_other_questions_are_refused_naming_the_difference(world, tmp_path, good, field, value):
    header = _header(good)
    want = header["answers"][field]
    header["answers"][field] = value
    msg = _refused(world, tmp_path, good, "answers other questions", header=header)
    assert f"{field}: the file's {value!r}, this benchmark's {want!r}" in msg


def test_a_query_file_of_another_setting_is_refused(world, tmp_path):
    tmp, root, _q = world
    other = open_questions("kitti", str(root), "test", "kitti-3s", "every-frame")  # 24 sweeps: too few for full context
    write_queries(other, tmp_path / "queries.npz")
    members = _members(_example_submission(tmp_path / "queries.npz", tmp_path / "other.npz"))
    msg = _refused(world, tmp_path, members, "answers other questions")
    assert "setting: the file's 'kitti-3s', this benchmark's 'kitti-1s'" in msg
    assert "setting_params" in msg and "sample_ids_hash" in msg


@pytest.mark.parametrize("what, header, match", [
    ("no header", None, r"has no header.json member"),
    ("another format", {"format": "pcfbench-queries", "exchange_version": 1}, r"says format 'pcfbench-queries', expected "
                                                                               r"'pcfbench-submission'"),
    ("another version", {"format": "pcfbench-submission", "exchange_version": 99}, r"exchange version 99, this pcfbench "
                                                                                   r"reads version 1"),
])
def test_another_format_or_version_is_refused(world, tmp_path, good, what, header, match):
    members = {k: v for k, v in good.items() if k != "header.json"}
    _refused(world, tmp_path, members, match, header=header)


def test_a_stray_member_and_a_pickle_are_refused(world, tmp_path, good):
    _refused(world, tmp_path, {**good, "notes.txt": np.array("hello")}, r"member 'notes.txt' is not SAMPLE_ID/depths/K")
    members = dict(good)
    members["08/000008/points_ref/0"] = np.array([object()], dtype=object)
    _refused(world, tmp_path, members, r"member '08/000008/points_ref/0' is not a plain NumPy array")


def test_a_changed_file_makes_a_new_cell_and_the_old_one_refuses_to_resume(world, tmp_path, good):
    _tmp, _root, q = world
    store = tmp_path / "store"
    sub = _save(tmp_path / "mine.npz", good)
    first, _ = score_submission(sub, "mine", q, store, ("chamfer",))
    again, _ = score_submission(sub, "mine", q, store, ("chamfer",))  # the same file: the same cell, reused
    assert again.path == first.path and again.processed == 0
    shifted = {k: (v + np.float32(0.5) if k.endswith("/points_ref/0") else v) for k, v in good.items()}
    _save(sub, shifted)
    second, _ = score_submission(sub, "mine", q, store, ("chamfer",))
    assert second.path != first.path and second.processed == 6
    cells = {meta["submission"]["sha256"]: d for d, meta in iter_cells(store)}
    assert len(cells) == 2
    old = [d for d, meta in iter_cells(store) if d == first.path][0]
    old_spec = json.loads((old / "cell.json").read_text())["spec"]
    (old / "cell.json").write_text(json.dumps({**json.loads((old / "cell.json").read_text()), "status": "running"}))
    from pcfbench.store.cells import spec_from_meta

    with pytest.raises(PcfbenchError, match=r"mine.npz changed since its cell was set up"):
        run_cell(spec_from_meta({"spec": old_spec}), store, RunOptions(progress=False))


def test_a_partial_submission_is_scored_only_when_asked_and_marked_partial(world, tmp_path, good):
    _tmp, _root, q = world
    members = {k: v for k, v in good.items() if not k.startswith(("08/000010/", "08/000011/"))}
    sub = _save(tmp_path / "partial.npz", members)
    store = tmp_path / "store"
    with pytest.raises(PcfbenchError, match="misses 2 of the 6 samples"):
        score_submission(sub, "part", q, store, ("chamfer",))
    result, checked = score_submission(sub, "part", q, store, ("chamfer",), partial=True)
    assert checked.answered == 4 and checked.missing == ("08/000010", "08/000011") and result.failed == 2
    meta = json.loads((result.path / "cell.json").read_text())
    assert meta["partial"] is True and meta["submission"]["missing"] == 2 and meta["submission"]["answered"] == 4
    rows = Cell.at(store, result.path.relative_to(store)).read_rows()
    failed = rows[rows["status"] == "failed"]
    assert sorted(failed["sample_id"]) == ["08/000010", "08/000011"]
    assert failed["error"].str.contains("is not in the partial submission").all()

    from pcfbench.reporting.report import collect

    board = collect(store)
    assert not len(board.table)  # never ranked
    assert any("(partial) part (submission" in n and "INCOMPLETE, 4/6" in n for n in board.notes)


# -- the command line ------------------------------------------------------------------------------------

def test_the_commands_score_and_refuse_with_one_line(world, tmp_path):
    tmp, root, _q = world
    cli = build_cli()
    queries = tmp_path / "q.npz"
    res = CliRunner().invoke(cli, ["queries", "-d", f"kitti={root}", "-s", "kitti-1s", "-o", str(queries), "-q"])
    assert res.exit_code == 0, res.output
    assert res.output == f"6 samples of kitti:test kitti-1s (full-context) -> {queries}\n"
    assert np.array_equal(np.load(queries)["08/000010/directions_ref/3"], np.load(tmp / "queries.npz")["08/000010/directions_ref/3"])
    sub = _example_submission(queries, tmp_path / "copy-last.npz")
    base = ["score", str(sub), "--name", "outside", "-d", f"kitti={root}", "-s", "kitti-1s", "--metric", "chamfer",
            "--store", str(tmp_path / "store"), "-q"]
    res = CliRunner().invoke(cli, base)
    assert res.exit_code == 0, res.output
    assert res.output.startswith("submission outside: 6 samples scored -> ")
    res = CliRunner().invoke(cli, [*base, "--policy", "every-frame"])
    assert res.exit_code == 2 and res.output.count("\n") == 1
    assert res.output.startswith(f"pcfbench: error: submission {sub} answers other questions")
    assert "policy: the file's 'full-context', this benchmark's 'every-frame'" in res.output


def test_a_plain_run_leaves_the_submission_method_out(world):
    from pcfbench.cli import _selected_methods

    real = get_plugins().methods

    class Methods:  # the two methods only: the trained ones would look for their training data
        def names(self):
            return ["copy-last", "submission"]

        def get(self, name):
            return real.get(name)

    class Plugins:
        methods = Methods()

    assert [m.name for m in _selected_methods(Plugins(), ())] == ["copy-last"]
    assert "submission" in real.names()
