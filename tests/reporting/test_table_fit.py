"""Tables that fit their page: the LaTeX table on a portrait A4 page at the text width (no
\\resizebox, no landscape float; split into tables of fewer columns or rows when it must be),
compiled with pdflatex where one is installed; the HTML table within a 1400 px window in
headless chromium."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from tests_helpers import chromium, headless

from pcfbench.reporting import htmlreport, tables
from pcfbench.reporting.report import Leaderboard

TRAINED = "copilot4d-token-copy [trained on synthetic-town-realistic:train, ck 84120cdf]"
PAPER = ["raycast-freespace", "raycast-voxel", "raycast-zbuffer", "copy-last", TRAINED, "raycast-4docc"]
SWEEP = ["copy-last", "raycast-voxel (cone_factor=1.0, max_range=70.0, surface=mean, voxel=0.2)",
         "raycast-voxel (cone_factor=0.0, max_range=70.0, surface=median, voxel=0.4)",
         "raycast-zbuffer (fill_ring=4, splat=2)"]
ALL = ["chamfer_nf", "chamfer", "l1_mean", "absrel_mean", "l1_median", "absrel_median", "chamfer_nf@4docc",
       "l1@4docc", "absrel@4docc", "l1_ray", "absrel_ray"]
UNITS = {m: "fraction" if "absrel" in m else "m^2" if "chamfer" in m else "m" for m in ALL}


def _board(variants: list[str], metrics: list[str], settings=("kitti-1s", "kitti-3s"), seeds: int = 0) -> Leaderboard:
    """A leaderboard of the published one's shape: its numbers' widths, a 75-character trained
    label, intervals and changes on every row; ``seeds`` more rows per variant make it long."""
    rng = np.random.default_rng(0)
    rows = []
    for s, setting in enumerate(settings):
        labels = variants + [f"{v.split(' ')[0]} (seed={k}, voxel=0.2)" for k in range(seeds) for v in variants[1:2]]
        for i, v in enumerate(labels):
            r = {"dataset": "synthetic-town-realistic", "split": "test", "setting": setting, "policy": "every-third",
                 "limit": None, "horizon_s": float(1 + 2 * s), "variant": v, "method": v.split(" ")[0],
                 "samples": 28, "sweeps": 140, "failed": 0, "is_reference": v == "copy-last", "train_on": "",
                 "cell_dir": f"/store/{setting}/{i}"}
            for m in metrics:
                x = float(rng.uniform(0.05, 30.0)) if "absrel" not in m else float(rng.uniform(0.01, 0.3))
                r.update({m: x, f"{m}_lo": x * 0.9, f"{m}_hi": x * 1.1,
                          f"{m}_rel": np.nan if v == "copy-last" else float(rng.uniform(-0.6, 1.8)),
                          f"{m}_p": float(rng.choice([0.001, 0.4]))})
            rows.append(r)
    return Leaderboard(pd.DataFrame(rows), pd.DataFrame(), list(metrics), {m: UNITS.get(m, "m") for m in metrics},
                       higher_is_better={m: False for m in metrics})


def _cases() -> dict[str, tables.Table]:
    presets = tables.load_presets()
    return {
        "paper": tables.build(_board(PAPER, ALL), presets["paper"]),
        "roi-interval": tables.build(_board(PAPER, ALL), presets["roi"], ci="interval"),
        "full": tables.build(_board(PAPER, ALL), presets["full"]),
        "sweep": tables.build(_board(SWEEP, ALL[:6]), presets["paper"], order=SWEEP),
        "long": tables.build(_board(SWEEP, ALL[:6], seeds=30), presets["paper"]),
    }


def _fit_width(fit: str) -> float:
    return float(re.search(r"about (\d+) pt", fit).group(1))


def test_every_latex_table_is_portrait_unscaled_and_within_the_text_width():
    for name, t in _cases().items():
        tex, fit = tables.latex(t)
        assert "resizebox" not in tex and "sideways" not in tex and "landscape" not in fit, name
        assert tex.count(r"\begin{table}[tp]") == tex.count(r"\end{table}") >= 1, name
        assert _fit_width(fit) <= tables.A4_TEXTWIDTH_PT, (name, fit)
        assert tex.isascii() and r"% needs \usepackage{booktabs}" in tex, name


def test_the_published_table_is_one_table_and_its_labels_are_short():
    tex, fit = tables.latex(_cases()["paper"])
    assert tex.count(r"\begin{table}") == 1 and fit.startswith("fits the A4 text width (455 pt) in \\small"), fit
    assert TRAINED not in tex and "trained on synthetic-town-realistic:train" in tex  # in the footnote
    firsts = [line.split(" & ")[0] for line in tex.splitlines() if line.count(" & ") >= 7]
    mains = [re.sub(r"\\begin\{tabular\}\[t\]\{@\{\}l@\{\}\}|\\\\\[-2pt\].*", "", f) for f in firsts]
    assert "copilot4d-token-copy$^1$" in mains and max(len(m) for m in mains) <= 28, mains


def test_a_sweep_s_options_go_under_the_method_name_wrapped():
    tex, _ = tables.latex(_cases()["sweep"])
    row = next(line for line in tex.splitlines() if "surface=mean" in line)
    assert row.startswith(r"\begin{tabular}[t]{@{}l@{}}raycast-voxel\\[-2pt]{\scriptsize (cone\_factor=1.0,}"
                          r"\\[-2pt]{\scriptsize max\_range=70.0, surface=mean,}\\[-2pt]{\scriptsize voxel=0.2)}"
                          r"\end{tabular} & 28 & "), row  # at most 30 characters a line


def test_too_many_columns_split_into_tables_each_with_every_row_and_the_method_column():
    t = _cases()["full"]
    tex, fit = tables.latex(t)
    k = tex.count(r"\begin{table}")
    assert k > 1 and fit.startswith(f"split into {k} tables of columns"), fit
    heads = [line for line in tex.splitlines() if line.startswith("Method & $n$ & ")]
    assert len(heads) == k and sum(h.count("&") - 1 for h in heads) == len(t.columns)  # each column once
    for part in tex.split(r"\begin{table}")[1:]:
        assert sum(line.count(" & ") > 0 and not line.startswith(("Method", " &")) for line in part.splitlines()) == 12
    assert "(continued, 2 of" in tex and r"\label{tab:pcfbench-full-2}" in tex


def test_a_table_taller_than_a_page_is_split_between_rows():
    t = _cases()["long"]  # 2 groups of 34 rows
    tex, fit = tables.latex(t)
    k = tex.count(r"\begin{table}")
    assert "tables of rows to fit the A4 text height" in fit and k > 1, fit
    body = [line for line in tex.splitlines() if " & 28 & " in line]
    column_parts = len(set(re.findall(r"(?m)^Method & .*$", tex)))
    assert len(body) == 68 * column_parts and k > column_parts  # every row once in each part of the columns
    assert "(continued)" in tex


def test_a_line_break_in_a_name_does_not_end_the_tex_comment():
    t = _cases()["paper"]
    t.preset = tables.Preset("evil\n\\input{/etc/passwd}", "x", t.preset.columns)
    tex, _ = tables.latex(t)
    assert not any(line.startswith("\\input") for line in tex.splitlines())


# -- compiled with pdflatex ----------------------------------------------------------------
TEX_ENGINE = shutil.which("pdflatex")


@pytest.mark.skipif(TEX_ENGINE is None, reason="pdflatex is not installed (texlive-latex-base, "
                    "texlive-latex-recommended, texlive-fonts-recommended); CI does not install TeX")
def test_latex_tables_compile_on_a4_portrait_without_overfull_boxes_and_no_wider_than_estimated(tmp_path):
    for name, t in _cases().items():
        tex, fit = tables.latex(t)
        # each tabular measured: \sbox0{tabular}, its width to the log, then set
        measured = re.sub(r"(?m)^(\\begin\{tabular\}\{l.*)$", r"\\sbox0{\1", tex)
        measured = re.sub(r"(?m)^\\end\{tabular\}$", r"\\end{tabular}}\\typeout{TABLEWIDTH=\\the\\wd0}\\usebox0", measured)
        (tmp_path / f"{name}.tex").write_text(measured)
        doc = tmp_path / f"doc-{name}.tex"
        doc.write_text("\\documentclass[a4paper]{article}\n\\usepackage[margin=2.5cm]{geometry}\n"
                       f"\\usepackage{{booktabs}}\n\\begin{{document}}\n\\input{{{name}.tex}}\n\\end{{document}}\n")
        res = subprocess.run([TEX_ENGINE, "-interaction=nonstopmode", "-halt-on-error", doc.name], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stdout[-3000:]
        log = doc.with_suffix(".log").read_text()
        assert "Overfull" not in log and "Float too large" not in log, (name, log[log.find("Overfull") - 200:][:800])
        widths = [float(w) for w in re.findall(r"TABLEWIDTH=([\d.]+)pt", log)]
        assert len(widths) == tex.count(r"\begin{table}") and max(widths) <= _fit_width(fit) <= 455, (name, widths, fit)


# -- the HTML page in headless chromium --------------------------------------------------
MEASURE = """<script>window.addEventListener('load', function(){
  var out = [];
  document.querySelectorAll('table.pcf').forEach(function(t){
    var w = t.parentElement;  // its scrolling box (or, with none, the page's body)
    out.push([Math.ceil(t.getBoundingClientRect().width), w.clientWidth, w.scrollWidth, getComputedStyle(w).overflowX].join(','));
  });
  document.body.dataset.fit = out.join(';');
  document.body.dataset.page = document.documentElement.scrollWidth + ',' + window.innerWidth;
});</script></body>"""


def _measure(exe: str, page: str, path: Path, width: int = 1400) -> tuple[list[tuple[int, int, int, str]], tuple[int, int]]:
    path.write_text(page.replace("</body>", MEASURE))
    dom = headless(exe, f"--window-size={width},1000", "--dump-dom", path.resolve().as_uri())
    fit = re.search(r'data-fit="([^"]*)"', dom).group(1)
    page_w = tuple(int(x) for x in re.search(r'data-page="([^"]*)"', dom).group(1).split(","))
    wraps = [(int(a), int(b), int(c), d) for a, b, c, d in (x.split(",") for x in fit.split(";"))]
    return wraps, page_w


def test_the_html_tables_fit_a_1400_px_window(tmp_path):
    """The leaderboard page (the paper preset, the 75-character trained label) and every
    per-preset page, `full`'s 11 metrics included, show the whole table at 1400 px; a wider
    table would scroll inside its own box (overflow-x: auto), never be cut off silently."""
    exe = chromium()
    cases = _cases()
    shot_dir = os.environ.get("PCFBENCH_TABLE_SHOTS")
    pages = {"leaderboard": htmlreport.page(cases["paper"], _board(PAPER, ALL)),
             "paper": tables.html_page(cases["paper"]), "roi-interval": tables.html_page(cases["roi-interval"]),
             "sweep": tables.html_page(cases["sweep"]), "full": tables.html_page(cases["full"])}
    for name, page in pages.items():
        wraps, (doc_w, view_w) = _measure(exe, page, tmp_path / f"{name}.html")
        assert view_w == 1400 and doc_w <= view_w, (name, doc_w, view_w)  # the page itself never scrolls sideways
        assert wraps, name
        for table_w, box_w, scroll_w, overflow in wraps:
            assert table_w <= box_w and scroll_w <= box_w, (name, table_w, box_w)
            assert overflow == "auto", name
        if shot_dir:
            headless(exe, f"--screenshot={Path(shot_dir) / f'html-{name}-1400.png'}", "--window-size=1400,1100",
                      (tmp_path / f"{name}.html").resolve().as_uri())
