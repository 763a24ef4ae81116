"""Hostile text in the report's Markdown and CSV files: an option value, a dataset, split or
setting name, a training-data name, a sweep's title and labels reach every .md escaped (no
raw HTML, no extra table cell) and every .csv formula-guarded, and every number is unchanged."""

from __future__ import annotations

import csv
import dataclasses
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import pcfbench
from conftest import write_tiny_kitti
from pcfbench.method import Method, options_hash, parse_options
from pcfbench.plugins import load_plugins
from pcfbench.reporting import escape
from pcfbench.reporting.report import ReportOptions, collect, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec

SCRIPT = "<script>alert(1)</script>"
IMG = "<img src=x onerror=alert(2)>|cell|*em*_u_`code`[link](javascript:alert(3))$x$"
FORMULA = '=HYPERLINK("http://evil.example","click")'
AT = "@SUM(1+1)*cmd|' /C calc'!A0"
PLUS = "+1+2"
MINUS = "-2+3"
NUMBER = "-0.5"  # text that is a number stays a number
HOSTILE = (SCRIPT, IMG, FORMULA, AT, PLUS, MINUS)
METRICS = ("chamfer", "chamfer_nf", "l1_mean")
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


class Tagged(Method):
    """The last past sweep, unchanged; ``tag`` is only a label (any text)."""

    name = "tagged"

    @dataclasses.dataclass(frozen=True)
    class Options:
        tag: str = pcfbench.option("", help="a free-text label")
        dx: float = pcfbench.option(0.0, help="shift along x (m)")

    def forecast(self, sample):
        last = sample.past_points_ref[-1] + np.array([self.options.dx, 0, 0], dtype=np.float32)
        return pcfbench.Forecast(points_ref=tuple(last for _ in range(sample.num_future)))


def _plugins():
    p = load_plugins()
    if "tagged" not in p.methods:
        p.methods.add("tagged", Tagged, "test")
    return p


def _spec(root, method, raw=None, limit=None):
    opts = parse_options(_plugins().methods.get(method).Options, raw or {}, method)
    return CellSpec(method, dict(raw or {}), options_hash(opts), "kitti", str(root), "test", "kitti-1s",
                    "full-context", limit, METRICS)


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    """A store of copy-last and one ``tagged`` cell per hostile option value (one of them also
    run with --limit 2), and its report."""
    tmp = tmp_path_factory.mktemp("escape")
    root = write_tiny_kitti(tmp / "kitti")
    store = tmp / "store"
    run_cell(_spec(root, "copy-last"), store, RunOptions(progress=False), plugins=_plugins())
    for i, tag in enumerate(HOSTILE + (NUMBER,)):
        run_cell(_spec(root, "tagged", {"tag": tag, "dx": str(0.1 * (i + 1))}), store, RunOptions(progress=False),
                 plugins=_plugins())
    run_cell(_spec(root, "tagged", {"tag": SCRIPT}, limit=2), store, RunOptions(progress=False), plugins=_plugins())
    run_cell(_spec(root, "copy-last", limit=2), store, RunOptions(progress=False), plugins=_plugins())
    out = tmp / "rep"
    paths = write_reports(store, out, ReportOptions(figures=False))
    return store, out, paths


def _md_files(out: Path) -> list[Path]:
    return sorted(out.rglob("*.md"))


def _csv_files(out: Path) -> list[Path]:
    return sorted(out.rglob("*.csv"))


_PIPE = re.compile(r"(?<!\\)\|")


def _assert_md_inert(path: Path, values: tuple[str, ...]) -> None:
    text = path.read_text()
    assert "<" not in text, f"{path.name}: raw HTML: {text[text.index('<') - 40:text.index('<') + 60]!r}"
    for v in values:
        assert escape.md_text(v) in text, f"{path.name}: {v!r} missing (escaped)"
    blocks = re.findall(r"(?m)(?:^\|.*\n?)+", text)  # each Markdown table: consecutive | lines
    assert blocks, path.name
    for block in blocks:  # every row has as many cells as the header: no value split a cell
        counts = {len(_PIPE.findall(line)) for line in block.splitlines()}
        assert len(counts) == 1, (path.name, block)


def _cells(path: Path) -> list[str]:
    with open(path, newline="") as f:
        return [c for row in csv.reader(f) for c in row]


def _assert_csv_guarded(path: Path, values: tuple[str, ...]) -> None:
    cells = _cells(path)
    bad = [c for c in cells if c.startswith(FORMULA_START) and not re.fullmatch(r"[+-]?[\d.]+([eE][+-]?\d+)?", c)]
    assert not bad, f"{path.name}: cells a spreadsheet runs as formulas: {bad[:3]}"
    for v in values:
        want = "'" + v if v.startswith(FORMULA_START) else v
        assert any(want in c for c in cells), f"{path.name}: {want!r} missing"


def test_md_text_renders_as_the_characters_and_never_as_markup():
    assert escape.md_text(SCRIPT) == "&lt;script&gt;alert(1)&lt;/script&gt;"
    assert escape.md_text("a|b *c* _d_ `e` [f](g) ~h~ $i$ \\ #") == \
        r"a\|b \*c\* \_d\_ \`e\` \[f\](g) \~h\~ \$i\$ \\ \#"
    assert escape.md_text("two\nlines\r\nthree") == "two lines three"
    assert escape.md_text("A&B") == "A&amp;B" and escape.md_text("raycast-voxel (voxel=0.2)") == "raycast-voxel (voxel=0.2)"


def test_csv_cell_guards_formulas_and_keeps_numbers():
    for v in (FORMULA, AT, PLUS, MINUS, "-inf", "\t=1", "\r=1", "-", "+", "=", "@"):
        assert escape.csv_cell(v) == "'" + v
    for v in (NUMBER, "-3", "+2.5", "-1e-3", ".5", "-.5e+2", "copy-last", "a=b", "", "0.5"):
        assert escape.csv_cell(v) == v
    for v in (-0.5, -3, float("-inf"), None, True):
        assert escape.csv_cell(v) is v or escape.csv_cell(v) == v
    df = pd.DataFrame({"x": [-0.5, 1.25], "n": [-2, 3], "s": [FORMULA, NUMBER], "=col": ["a", "b"]})
    text = escape.csv_text(df)
    assert text.splitlines() == ["x,n,s,'=col", "-0.5,-2,\"'=HYPERLINK(\"\"http://evil.example\"\",\"\"click\"\")\",a",
                                 "1.25,3,-0.5,b"]
    back = pd.read_csv(__import__("io").StringIO(text))
    assert back["x"].tolist() == [-0.5, 1.25] and back["n"].tolist() == [-2, 3]


def test_a_hostile_option_value_reaches_every_markdown_file_escaped(hostile):
    _, out, _ = hostile
    files = _md_files(out)
    assert {p.relative_to(out).as_posix() for p in files} >= {"leaderboard.md", "tables/paper.md", "tables/full.md"}
    for p in files:
        _assert_md_inert(p, tuple(f"tag={v}" for v in HOSTILE))


def test_a_hostile_option_value_reaches_every_csv_file_guarded_and_numbers_stay_numbers(hostile):
    store, out, paths = hostile
    names = {p.relative_to(out).as_posix() for p in _csv_files(out)}
    assert names >= {"leaderboard.csv", "leaderboard_partial.csv", "leaderboard_by_step.csv",
                     "leaderboard_partial_by_step.csv", "leaderboard_comparisons.csv", "leaderboard_incomplete.csv"}
    for name in ("leaderboard.csv", "leaderboard_partial.csv", "leaderboard_by_step.csv",
                 "leaderboard_partial_by_step.csv", "leaderboard_comparisons.csv"):
        values = (SCRIPT,) if "partial" in name else HOSTILE
        _assert_csv_guarded(out / name, tuple(f"tag={v}" for v in values))
    # the option column holds the value itself: guarded where it would be a formula
    with open(paths["csv"], newline="") as f:
        tags = [r["option.tag"] for r in csv.DictReader(f) if r["option.tag"]]
    assert sorted(tags) == sorted(["'" + v if v[0] in "=+-@" else v for v in HOSTILE] + [NUMBER])
    board = pd.read_csv(paths["csv"])
    # every number as collect() computed it, bit for bit
    lb = collect(store)
    mine = lb.table.set_index("cell_dir").sort_index()
    theirs = board.set_index(board["options_hash"] + board["method"]).sort_index()
    mine = mine.set_index(mine["options_hash"] + mine["method"]).sort_index()
    for m in [c for m in METRICS for c in (m, f"{m}_lo", f"{m}_hi", f"{m}_rel", f"{m}_p")]:
        assert np.array_equal(theirs[m].to_numpy(float), mine[m].to_numpy(float), equal_nan=True), m
    assert theirs["samples"].dtype.kind == "i" and theirs["horizon_s"].dtype.kind == "f"


def test_hostile_names_of_datasets_splits_settings_and_training_data_are_escaped_everywhere(hostile, tmp_path):
    """Names a plugin or a user gives (dataset, split, setting, training data, a note naming
    an incomplete cell) through every Markdown and CSV writer of the report, transfer table included."""
    store, _, _ = hostile
    lb = collect(store)
    names = {"dataset": "<b>town</b>|x", "split": "=test", "setting": "@kitti-1s", "policy": "-every<i>third"}

    def rename(df):
        return df.assign(**{k: v for k, v in names.items() if k in df}) if len(df) else df

    trained = lb.table.index[lb.table["method"] == "tagged"][0]
    table = rename(lb.table)
    table.loc[trained, "train_on"] = "+evil<script>:train"
    table.loc[trained, "checkpoint_sha256"] = "ab" * 32
    table.loc[trained, "variant"] = "tagged [trained on +evil<script>:train, ck abababab]"
    incomplete = rename(lb.table.iloc[[0]]).assign(coverage="1/2", missing=1, incomplete=True)
    lb = dataclasses.replace(lb, table=table, partial=rename(lb.partial), by_step=rename(lb.by_step),
                             comparisons=rename(lb.comparisons), incomplete=incomplete,
                             notes=lb.notes + [f"{names['dataset']} / {names['split']}: {SCRIPT}: INCOMPLETE"])
    out = tmp_path / "rep"
    write_reports(store, out, ReportOptions(figures=False), leaderboard=lb)
    assert (out / "transfer.md").is_file() and (out / "transfer.csv").is_file()
    for p in _md_files(out):
        _assert_md_inert(p, tuple(names.values())[:1] + (names["split"],) + (("evil",) if p.name == "transfer.md" else ()))
        assert "&lt;b&gt;town&lt;/b&gt;\\|x" in p.read_text()
    assert "+evil&lt;script&gt;:train" in (out / "transfer.md").read_text()
    assert "&lt;script&gt;alert(1)&lt;/script&gt;: INCOMPLETE" in (out / "leaderboard.md").read_text()
    for p in _csv_files(out):
        _assert_csv_guarded(p, tuple(names.values()))
    assert "'+evil<script>:train" in _cells(out / "transfer.csv")


def test_a_sweep_s_title_and_hostile_labels_are_escaped_in_its_markdown_and_csv(tmp_path, tiny_kitti):
    from pcfbench.experiments.sweep import load_experiment, run_sweep

    exp = tmp_path / "exp.toml"
    exp.write_text(f"""
name = "hostile"
datasets = ["kitti={tiny_kitti}"]
settings = ["kitti-1s"]
metrics = ["chamfer"]

[[methods]]
name = "tagged"
variants = [{{ tag = '{SCRIPT}' }}, {{ tag = '{FORMULA}' }}, {{ tag = '{NUMBER}' }}]

[[methods]]
name = "copy-last"

[[tables]]
preset = "full"
title = "{IMG.replace('"', "'")}"
""")
    plugins = _plugins()
    res = run_sweep(load_experiment(exp, plugins), tmp_path / "s", tmp_path / "r", limit=2, progress=False,
                    plugins=plugins, echo=lambda s: None)
    md = next(p for k, p in res.paths.items() if k.endswith(".md"))
    _assert_md_inert(md, (f"tag={SCRIPT}", f"tag={FORMULA}", IMG.replace('"', "'")))
    sweep_csv = next(p for k, p in res.paths.items() if k.endswith(".csv"))
    _assert_csv_guarded(sweep_csv, (f"tag={SCRIPT}", FORMULA))
    tags = pd.read_csv(sweep_csv)["option.tag"].tolist()
    assert tags[:3] == [SCRIPT, "'" + FORMULA, NUMBER]  # the number-like text unprefixed
