"""The leaderboard: point estimates unchanged, paper-layout presets, intervals and comparisons
in every format, partial cells in their own table, option columns, seconds per horizon."""

import re
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

import pcfbench
import pcfbench.plugins
from conftest import write_tiny_kitti
from tests_helpers import shifted_plugins as _plugins
from pcfbench.errors import PcfbenchError
from pcfbench.method import options_hash, parse_options
from pcfbench.reporting.report import ReportOptions, collect, summary, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec, iter_cells, spec_from_meta
from pcfbench.reporting import tables
from pcfbench.reporting.escape import md_text

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1_median", "absrel_mean", "absrel_median")


def _spec(root, method="copy-last", raw=None, limit=None):
    plugins = _plugins()
    opts = parse_options(plugins.methods.get(method).Options, raw or {}, method)
    return CellSpec(method, dict(raw or {}), options_hash(opts), "kitti", str(root), "test", "kitti-1s",
                    "full-context", limit, METRICS)


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A store: copy-last, shifted by 0 (copy-last again) and by 0.5 m, and two --limit cells."""
    tmp = tmp_path_factory.mktemp("report")
    root = write_tiny_kitti(tmp / "kitti", sequences=("08", "09"))
    store = tmp / "store"
    for method, raw, limit in [("copy-last", None, None), ("shifted", {"dx": "0.5"}, None),
                               ("shifted", {"dx": "0"}, None), ("shifted", {"dx": "0.5"}, 2), ("copy-last", None, 2)]:
        run_cell(_spec(root, method, raw, limit), store, RunOptions(progress=False), plugins=_plugins())
    out = tmp / "rep"
    paths = write_reports(store, out)
    return store, out, paths


def test_point_estimates_are_the_flat_means_of_the_rows(board):
    """The leaderboard's numbers, computed as before the intervals existed: nanmean of ok rows."""
    store, _, paths = board
    csv = pd.read_csv(paths["csv"])
    expected = {}
    for _, meta in iter_cells(store):
        if meta["partial"]:
            continue
        spec = spec_from_meta(meta)
        rows = Cell(store, spec).read_rows()
        ok = rows[rows.status == "ok"]
        expected[spec.options_hash] = {m: float(np.nanmean(ok[m].to_numpy(dtype=float))) for m in METRICS}
    assert len(csv) == len(expected) == 3
    for _, r in csv.iterrows():
        for m in METRICS:
            assert r[m] == expected[r["options_hash"]][m]  # exactly
            assert r[f"{m}_lo"] <= r[m] <= r[f"{m}_hi"]
    lb = collect(store)
    assert len(lb.table) == 3 and len(lb.partial) == 2


def test_csv_has_the_old_lead_columns_option_columns_and_comparisons(board):
    _, _, paths = board
    csv = pd.read_csv(paths["csv"])
    assert list(csv.columns[:9]) == ["dataset", "split", "setting", "policy", "method", "method_version",
                                     "samples", "failed", "sweeps"]
    assert sorted(csv["variant"]) == ["copy-last", "shifted (dx=0)", "shifted (dx=0.5)"]
    assert sorted(csv["option.dx"].dropna()) == [0.0, 0.5]  # pivotable
    ref = csv[csv.is_reference]
    assert ref["method"].tolist() == ["copy-last"] and ref["chamfer_rel"].isna().all()
    same = csv[csv.variant == "shifted (dx=0)"].iloc[0]
    far = csv[csv.variant == "shifted (dx=0.5)"].iloc[0]
    assert same["chamfer_rel"] == 0 and same["chamfer_p"] == 1
    assert far["chamfer_rel"] == pytest.approx(far["chamfer"] / ref["chamfer"].iloc[0] - 1)
    cmp = pd.read_csv(paths["comparisons"])
    row = cmp[(cmp.variant == "shifted (dx=0.5)") & (cmp.metric == "chamfer")].iloc[0]
    assert row["shared_samples"] == 12 and row["reference"] == "copy-last" and bool(row["significant"])
    assert row["diff_lo"] <= row["diff"] <= row["diff_hi"]


def test_by_step_gives_seconds(board):
    _, _, paths = board
    by_step = pd.read_csv(paths["by_step"])
    assert by_step.limit.isna().all() and len(by_step) == 3 * 5  # complete cells only
    partial = pd.read_csv(paths["partial_by_step"])
    assert (partial.limit == 2).all() and len(partial) == 2 * 5
    cell = by_step[by_step.variant == "copy-last"].sort_values("step")
    setting = pcfbench.plugins.get_setting("kitti-1s")
    assert cell["time_s"].tolist() == pytest.approx([setting.step_seconds(k) for k in range(5)])
    assert cell["time_s"].iloc[-1] == pytest.approx(setting.horizon_s)
    assert (cell["chamfer_lo"] <= cell["chamfer"]).all() and (cell["chamfer"] <= cell["chamfer_hi"]).all()


def _md_table(text, heading_start):
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(heading_start))
    block = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        block.append([c.strip() for c in line.strip("|").split("|")])
    return block[0], block[2:]


def test_markdown_is_the_paper_layout_ranked_with_bold_best_and_changes(board):
    store, out, _ = board
    md = (out / "leaderboard.md").read_text()
    head, rows = _md_table(md, "## kitti / test / kitti-1s (1 s)")
    assert head[2:] == ["Chamfer (ROI) ↓ (m²)", "L1 Med ↓ (m)", "AbsRel Med ↓ (%)", "L1 Mean ↓ (m)",
                        "AbsRel Mean ↓ (%)", "Chamfer (full) ↓ (m²)"]
    lb = collect(store)
    ranked = lb.table.sort_values(["chamfer_nf", "variant"])
    assert [r[0] for r in rows] == [v + (" (ref)" if v == "copy-last" else "") for v in ranked["variant"]]
    col = head.index("Chamfer (ROI) ↓ (m²)")
    best = lb.table["chamfer_nf"].min()
    for r, (_, t) in zip(rows, ranked.iterrows()):
        value = f"{t['chamfer_nf']:.3f}"
        assert r[col].startswith(f"**{value}**" if t["chamfer_nf"] == best else value)
        half = (t["chamfer_nf_hi"] - t["chamfer_nf_lo"]) / 2
        assert f"±{half:.3f}" in r[col]
        if t["variant"] == "shifted (dx=0)":
            assert r[col].endswith("(+0 %†)")  # identical to the reference: a tie
        if t["variant"] == "shifted (dx=0.5)":
            assert r[col].endswith(f"({100 * t['chamfer_nf_rel']:+.0f} %)")
    assert "PARTIAL runs (--limit)" in md
    partial = md[md.index("PARTIAL runs"):]
    assert "limit=2" in partial and "2 samples" in partial
    assert "limit=2" not in md[:md.index("PARTIAL runs")]


def test_partial_cells_are_their_own_table_in_every_format(board):
    _, out, paths = board
    partial = pd.read_csv(paths["partial_csv"])
    assert sorted(partial["variant"]) == ["copy-last", "shifted (dx=0.5)"] and (partial.samples == 2).all()
    assert "PARTIAL (--limit)" in paths["tex"].read_text()
    assert "PARTIAL runs (--limit)" in paths["html"].read_text()


def test_latex_booktabs_right_aligned_real_units_and_fit_note(board):
    _, out, paths = board
    tex = paths["tex"].read_text()
    first = tex.splitlines()[0]
    assert first.startswith("% pcfbench leaderboard, preset paper: fits the A4 text width (455 pt) in \\small")
    assert "sidewaystable" not in tex and "resizebox" not in tex and tex.count(r"\begin{table}[tp]") == 1
    assert r"\toprule" in tex and r"\midrule" in tex and r"\bottomrule" in tex
    assert re.search(r"\\begin\{tabular\}\{lr+\}", tex)
    assert r"$\mathrm{m}^{2}$" in tex and r"$\mathrm{m}$" in tex and "m^2" not in tex.replace(r"\mathrm{m}^{2}", "")
    assert r"$\downarrow$" in tex and r"$\pm$" in tex and r"\textbf{" in tex
    assert r"shifted\\[-2pt]{\scriptsize (dx=0.5)}" in tex and r"$^\dagger$" in tex  # options under the name
    assert [ch for ch in tex if ord(ch) > 127] == []  # pdflatex without inputenc setup chokes on the rest


def test_latex_text_escapes_and_symbols():
    assert tables.tex_text("my_method [a&b] 50 % #1 {x} ~ ^") == (
        r"my\_method [a\&b] 50 \% \#1 \{x\} \textasciitilde{} \textasciicircum{}")
    assert tables.tex_text("p >= 0.05 ↓ ↑ † ±") == r"p $\geq$ 0.05 $\downarrow$ $\uparrow$ $^\dagger$ $\pm$"
    assert tables.tex_unit("m^2") == r"$\mathrm{m}^{2}$" and tables.tex_unit("fraction") == r"\%"
    assert tables.unit_text("m^2") == "m²" and tables.unit_text("fraction") == "%"


def test_latex_width_estimate_picks_the_page_layout():
    lb = _tiny_board({"chamfer": 1.0})
    narrow = tables.latex(tables.build(lb, tables.Preset("n", "narrow", (tables.Column("chamfer", "CD"),)), "none"))
    assert narrow[1].startswith("fits the A4 text width (455 pt) in \\small") and r"\centering\small" in narrow[0]
    seven = _tiny_board({f"metric_{i}": 1.0 + i for i in range(7)})
    small = tables.latex(tables.build(seven, tables.Preset("s", "seven", None), "pm"))
    assert small[1].startswith("fits the A4 text width") and small[0].count(r"\begin{table}") == 1
    wide = _tiny_board({f"metric_{i}": 1.0 + i for i in range(14)})
    big = tables.latex(tables.build(wide, tables.Preset("w", "wide", None), "interval"))
    assert big[1].startswith("split into ") and big[0].count(r"\begin{table}") > 1
    for tex, _ in (narrow, small, big):
        assert "resizebox" not in tex and "sidewaystable" not in tex


def _tiny_board(values):
    """A one-cell leaderboard built by hand."""
    from pcfbench.reporting.report import Leaderboard

    row = {"dataset": "d", "split": "s", "setting": "kitti-1s", "policy": "full-context", "method": "m",
           "variant": "m", "samples": 3, "failed": 0, "sweeps": 15, "limit": None, "horizon_s": 1.0,
           "is_reference": True, "partial": False}
    for k, v in values.items():
        row.update({k: v, f"{k}_lo": v - 0.1, f"{k}_hi": v + 0.1})
    return Leaderboard(pd.DataFrame([row]), pd.DataFrame(), list(values), {k: "m" for k in values},
                       pd.DataFrame())


@pytest.mark.skipif(not (shutil.which("pdflatex") or shutil.which("lualatex")), reason="no TeX engine installed")
def test_latex_compiles_on_an_a4_page_without_overfull_boxes(board, tmp_path):
    _, out, _ = board
    engine = shutil.which("pdflatex") or shutil.which("lualatex")
    for tex in sorted((out / "tables").glob("*.tex")):
        doc = tmp_path / f"doc-{tex.stem}.tex"
        doc.write_text("\\documentclass[a4paper]{article}\n\\usepackage[margin=2.5cm]{geometry}\n"
                       "\\usepackage{booktabs}\n\\begin{document}\n"
                       f"\\input{{{tex}}}\n\\end{{document}}\n")
        res = subprocess.run([engine, "-interaction=nonstopmode", "-halt-on-error", doc.name], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stdout[-3000:]
        assert "Overfull \\hbox" not in doc.with_suffix(".log").read_text(), tex.name


def test_html_keeps_method_names_on_one_line(board):
    _, _, paths = board
    page = paths["html"].read_text()
    assert "white-space:nowrap" in page
    assert "<td class='method' data-v='shifted (dx=0.5)'>shifted (dx=0.5) <a href='#cell-" in page
    assert "<strong>" in page and "95% CI [" in page and "'>Chamfer (ROI) ↓ (m²)</th>" in page
    assert "<span class='sub'><span class='ci'>±" in page  # the interval on a line under the value
    simple = (paths["html"].parent / "tables" / "paper.html").read_text()  # the per-preset pages stay plain tables
    assert "<td class='method'>shifted (dx=0.5)</td>" in simple and "<th>Chamfer (ROI) ↓ (m²)</th>" in simple


def test_every_preset_is_written_and_reports_are_deterministic(board, tmp_path):
    store, out, paths = board
    for name in ("paper", "roi", "full"):
        for ext in ("md", "tex", "html"):
            assert (out / "tables" / f"{name}.{ext}").is_file()
    full = (out / "tables" / "full.md").read_text()
    for m in METRICS:  # a metric's name is Markdown-escaped: chamfer\_nf
        assert f"| {md_text(m)} ↓" in full or f"{md_text(m)} ↓ (" in full
    assert "Chamfer (full)" not in (out / "tables" / "roi.md").read_text()
    again = write_reports(store, tmp_path / "again")
    for key in ("md", "csv", "tex", "html", "by_step", "comparisons"):
        assert again[key].read_text() == paths[key].read_text(), key


def test_user_presets_extend_and_bad_presets_are_named(board, tmp_path):
    store, _, _ = board
    mine = tmp_path / "mine.toml"
    mine.write_text('[presets.cd]\ntitle = "Chamfer only"\n'
                    'columns = [{ metric = "chamfer", label = "CD" }, { metric = "nope", label = "X" }]\n')
    paths = write_reports(store, tmp_path / "r", ReportOptions(preset="cd", tables_file=str(mine)))
    md = paths["md"].read_text()
    assert "| CD ↓ (m²) |" in md and "no cell in the store has nope" in md
    assert (tmp_path / "r" / "tables" / "paper.md").is_file()
    cases = {
        '[presets.x]\ncolumns = "all"\ncolour = 1\n': r"mine.toml: preset 'x': unknown key\(s\) colour",
        '[presets.x]\ncolumns = [{ metric = "chamfer", better = "up" }]\n': "better must be",
        '[presets.x]\nrank_by = "l1_mean"\ncolumns = [{ metric = "chamfer" }]\n': "rank_by 'l1_mean'",
        '[presets.x]\ncolumns = []\n': "columns must be a non-empty list",
        'presets = 3\n': r"expected only \[presets.NAME\]",
        '[presets.x\n': "not valid TOML",
    }
    for text, message in cases.items():
        mine.write_text(text)
        with pytest.raises(PcfbenchError, match=message):
            tables.load_presets(mine)
    with pytest.raises(PcfbenchError, match="does not exist"):
        tables.load_presets(tmp_path / "missing.toml")
    with pytest.raises(PcfbenchError, match="unknown table preset 'papr'; did you mean 'paper'"):
        write_reports(store, tmp_path / "r", ReportOptions(preset="papr"))


def test_interval_style_and_resampling_options(board, tmp_path):
    store, _, _ = board
    from pcfbench.reporting.stats import Resampling

    paths = write_reports(store, tmp_path / "r", ReportOptions(ci="interval", resampling=Resampling.parse("sequence")))
    csv = pd.read_csv(paths["csv"])
    assert (csv["ci_units"] == 2).all()  # two sequences
    md = paths["md"].read_text()
    assert re.search(r"\[\d+\.\d{3}, \d+\.\d{3}\]", md) and "whole sequences" in md
    none = write_reports(store, tmp_path / "n", ReportOptions(ci="none"))["md"].read_text()
    assert "±" not in none.split("## ", 1)[1]


def test_summary_and_cli_report(board, tmp_path):
    store, _, _ = board
    text = summary(store)
    assert "kitti / test / kitti-1s (1 s)" in text and "copy-last (ref)" in text and "±" in text
    assert "PARTIAL (--limit) kitti / test / kitti-1s" in text
    from pcfbench.cli import build_cli

    res = CliRunner().invoke(build_cli(), ["report", "--store", str(store), "--reports", str(tmp_path / "r"),
                                           "--preset", "roi", "--resample", "block:2", "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert "Chamfer ↓ (m²)" in res.output and "pcfbench leaderboard, preset roi:" in res.output
    assert "blocks of 2 consecutive samples" in (tmp_path / "r" / "leaderboard.md").read_text()
    bad = CliRunner().invoke(build_cli(), ["report", "--store", str(store), "--reports", str(tmp_path / "r"),
                                           "--resample", "block:0"])
    assert bad.exit_code == 2 and "block:N with N >= 1" in bad.output


def test_reference_choice(board, tmp_path):
    store, _, _ = board
    with pytest.raises(PcfbenchError, match="unknown reference method 'copy-lst'; did you mean 'copy-last'"):
        collect(store, reference="copy-lst")
    lb = collect(store, reference="shifted")
    ref = lb.table[lb.table.is_reference]
    assert ref["variant"].tolist() == ["shifted (dx=0)"]  # the shortest label of the method: its first variant
    assert lb.table.loc[lb.table.variant == "copy-last", "chamfer_rel"].iloc[0] == 0
    md = write_reports(store, tmp_path / "r", ReportOptions(reference="shifted"))["md"].read_text()
    assert "shifted (dx=0) (ref)" in md and "reference 'shifted'" in md


def test_reference_with_options_is_that_cell(board, tmp_path):
    """``NAME:k=v``: the method's cell of exactly those options, not its shortest label; options
    the store has no cell of are one error listing the cells it has."""
    store, _, _ = board
    lb = collect(store, reference="shifted:dx=0.5", plugins=_plugins())
    ref = lb.table[lb.table.is_reference]
    assert ref["variant"].tolist() == ["shifted (dx=0.5)"] and lb.reference == "shifted:dx=0.5"
    rows = lb.table.set_index("variant")
    assert np.isnan(rows.loc["shifted (dx=0.5)", "chamfer_rel"])  # the reference is not compared with itself
    by_name = collect(store, reference="shifted").table.set_index("variant")
    # the two shifted cells against each other, both ways round: mean / reference mean - 1
    there, back = rows.loc["shifted (dx=0)", "chamfer_rel"], by_name.loc["shifted (dx=0.5)", "chamfer_rel"]
    assert there != 0 and (1 + there) * (1 + back) == pytest.approx(1, rel=1e-12)
    assert rows.loc["copy-last", "chamfer_rel"] == there  # dx=0 forecasts what copy-last does
    comparisons = lb.comparisons
    assert set(comparisons["reference"]) == {"shifted (dx=0.5)"}
    with pytest.raises(PcfbenchError, match=r"reference 'shifted:dx=2': the store has no complete cell of shifted "
                                             r"with these options \(options hash [0-9a-f]+\); its cells: "
                                             r"shifted \(dx=0\), shifted \(dx=0.5\)"):
        collect(store, reference="shifted:dx=2", plugins=_plugins())
    md = write_reports(store, tmp_path / "r", ReportOptions(reference="shifted:dx=0.5"),
                       leaderboard=lb)["md"].read_text()
    assert "shifted (dx=0.5) (ref)" in md and "reference 'shifted:dx=0.5'" in md


def test_too_few_units_are_noted(board):
    store, _, _ = board
    from pcfbench.reporting.stats import Resampling

    lb = collect(store, Resampling.parse("block:100"))  # one block per sequence: 2 units
    assert (lb.table["ci_units"] == 2).all()
    # the --limit 2 cells hold 2 samples of one sequence: one unit, no interval, and a note says so
    assert (lb.partial["ci_units"] == 1).all() and lb.partial["chamfer_lo"].isna().all()
    assert lb.notes == [f"kitti / test / kitti-1s (limit=2) {v}: 1 resampling unit(s) (block), too few for an interval"
                        for v in ("copy-last", "shifted (dx=0.5)")]
    one = tables.build(_tiny_board({"chamfer": 1.0}), tables.Preset("p", "p", None))
    assert one.notes == []


def test_empty_store_reports_nothing_yet(tmp_path):
    paths = write_reports(tmp_path / "none", tmp_path / "r")
    assert "No complete cells in the store yet" in paths["md"].read_text()
    assert list(pd.read_csv(paths["csv"]).columns[:9])[0] == "dataset"


def test_run_prints_the_summary_table(tiny_kitti, tmp_path):
    from pcfbench.cli import build_cli

    res = CliRunner().invoke(build_cli(), ["run", "--dataset", f"kitti={tiny_kitti}", "--setting", "kitti-1s",
                                           "--method", "copy-last", "--reports", str(tmp_path / "rep"), "-q"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    at = lines.index("kitti / test / kitti-1s (1 s) - 6 samples, 30 sweeps, 0 failed")
    assert lines[at + 1].split()[:3] == ["method", "n", "Chamfer"]
    assert lines[at + 2].startswith("copy-last (ref)") and "±" in lines[at + 2]
    assert lines[-1] == f"leaderboard: {tmp_path / 'rep' / 'leaderboard.md'}"


def test_report_and_sweep_do_not_import_each_other():
    """The cell labels both need live below them (pcfbench.reporting.labels): the report never imports
    the sweeps, and neither module imports the other at load time."""
    import ast
    from pathlib import Path

    import pcfbench.reporting.labels
    import pcfbench.reporting.report
    import pcfbench.experiments.sweep

    def imported(module) -> set[str]:
        names = set()
        for node in ast.walk(ast.parse(Path(module.__file__).read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                names.add(node.module)
            elif isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
        return names

    assert not {n for n in imported(pcfbench.reporting.report) if n.startswith("pcfbench.experiments.sweep")}
    assert not {n for n in imported(pcfbench.reporting.labels) if n in ("pcfbench.reporting.report", "pcfbench.experiments.sweep")}
    top = {n.module for n in ast.parse(Path(pcfbench.experiments.sweep.__file__).read_text()).body if isinstance(n, ast.ImportFrom)}
    assert "pcfbench.reporting.report" not in top
    assert pcfbench.reporting.report.method_label is pcfbench.experiments.sweep.method_label is pcfbench.reporting.labels.method_label
    assert pcfbench.experiments.sweep.cell_label is pcfbench.reporting.labels.cell_label
