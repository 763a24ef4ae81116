"""The report's figures (error vs forecast time, vs range, BEV gallery, sweep ablations), the
self-contained HTML page, and the atomic publish of the reports folder; a report reads the
store only (no method runs), the range bins stored at run time."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

import pcfbench
from conftest import write_tiny_kitti
from tests_helpers import Shifted, shifted_plugins as _plugins, chromium, headless
from pcfbench.reporting import figures, tables
from pcfbench.data import Forecast
from pcfbench.errors import PcfbenchError
from pcfbench.method import Method, options_hash, parse_options
from pcfbench.reporting.report import ReportOptions, collect, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "l1_median", "absrel_mean", "absrel_median")


def _spec(root, method="copy-last", raw=None):
    opts = parse_options(_plugins().methods.get(method).Options, raw or {}, method)
    return CellSpec(method, dict(raw or {}), options_hash(opts), "kitti", str(root), "test", "kitti-1s",
                    "full-context", None, METRICS)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A store of copy-last and shifted by 0.5 m and 1.5 m, and its reports."""
    tmp = tmp_path_factory.mktemp("figs")
    root = write_tiny_kitti(tmp / "kitti")
    store = tmp / "store"
    for method, raw in [("copy-last", None), ("shifted", {"dx": "0.5"}), ("shifted", {"dx": "1.5"})]:
        run_cell(_spec(root, method, raw), store, RunOptions(progress=False), plugins=_plugins())
    out = tmp / "rep"
    paths = write_reports(store, out, ReportOptions(figures=True), plugins=_plugins())
    return store, out, paths


def test_figures_are_on_by_default_and_off_with_pcfbench_figures_0(monkeypatch):
    monkeypatch.delenv("PCFBENCH_FIGURES")
    assert ReportOptions().figures is True
    monkeypatch.setenv("PCFBENCH_FIGURES", "0")  # what tests/conftest.py sets for the quick CLI runs
    assert ReportOptions().figures is False


def test_every_kind_of_figure_is_written_as_png_and_svg_with_labelled_axes(made):
    import matplotlib.image

    _, out, paths = made
    assert not any("gallery" in k for k in paths)  # the gallery re-runs methods: only on request
    for kind in ("horizon", "range"):
        stem = f"{kind}-kitti_test_kitti-1s"
        png, svg = out / "figures" / f"{stem}.png", out / "figures" / f"{stem}.svg"
        assert paths[f"figures/{stem}.png"] == png and paths[f"figures/{stem}.svg"] == svg
        assert matplotlib.image.imread(png).shape[0] > 200
        text = svg.read_text()
        assert text.startswith("<?xml") and "</svg>" in text
    # every axis says its unit (SVG text is kept as text: svg.fonttype 'path' stores glyphs, so check the figure objects)
    lb = collect(made[0])
    t = tables.build(lb, tables.get_preset("paper", tables.load_presets()))
    fig = figures.horizon_figure(lb.by_step, t.columns, "x")
    for ax in fig.axes:
        if ax.get_visible():
            assert ax.get_xlabel() == "forecast time after t=0 (s)"
            assert ax.get_ylabel().endswith(("(m)", "(%)", "(m$^{2}$)")), ax.get_ylabel()


def test_horizon_lines_and_bands_are_the_per_step_means_and_intervals(made):
    store = made[0]
    lb = collect(store)
    t = tables.build(lb, tables.get_preset("paper", tables.load_presets()))
    fig = figures.horizon_figure(lb.by_step, t.columns, "x")
    ax = fig.axes[[c.metric for c in t.columns].index("l1_mean")]
    steps = lb.by_step[lb.by_step["variant"] == "shifted (dx=1.5)"].sort_values("time_s")
    line = next(ln for ln in ax.lines if ln.get_label() == "shifted (dx=1.5)")
    np.testing.assert_array_equal(line.get_xdata(), [0.2, 0.4, 0.6, 0.8, 1.0])
    np.testing.assert_array_equal(line.get_ydata(), steps["l1_mean"].to_numpy())
    # the band: the collection drawn with the line spans [lo, hi] of each step
    band = ax.collections[[ln.get_label() for ln in ax.lines].index("shifted (dx=1.5)")]
    ys = band.get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(steps["l1_mean_lo"].min()) and ys.max() == pytest.approx(steps["l1_mean_hi"].max())


def test_range_bins_pool_exactly_the_errors_the_stored_l1_and_absrel_average(made):
    """A bin's count-weighted mean over one re-run sweep gives back that sweep's stored l1_mean
    and absrel_mean; bins are [10 k, 10 (k+1)) m of the ground-truth range."""
    store = made[0]
    lb = collect(store)
    cells = lb.table[lb.table["variant"] == "shifted (dx=0.5)"]
    rows = Cell.at(store, cells.iloc[0]["cell_dir"]).read_rows()
    sid = rows["sample_id"].iloc[0]
    run = figures.rerun(store, cells, [sid], _plugins())
    assert run.mismatch == []
    for sweep in run.errors["shifted (dx=0.5)"][sid]:
        prof = figures.range_profile([sweep])
        stored = rows[(rows.sample_id == sid) & (rows.step == sweep.step)].iloc[0]
        n = prof["rays"].to_numpy()
        assert (prof["hi_m"] - prof["lo_m"] == 10).all() and n.sum() == sweep.ray_l1_m.size
        assert np.sum(prof["l1_mean"] * n) / n.sum() == pytest.approx(stored["l1_mean"], rel=1e-12)
        assert np.sum(prof["absrel_mean"] * n) / n.sum() == pytest.approx(stored["absrel_mean"], rel=1e-12)
        lo = prof["lo_m"].to_numpy()
        for k in range(len(prof)):
            inside = (sweep.ray_range_m >= lo[k]) & (sweep.ray_range_m < lo[k] + 10)
            assert inside.sum() == n[k]


def test_per_point_error_is_the_distance_to_the_nearest_ground_truth_point():
    rng = np.random.default_rng(3)
    gt = rng.uniform(-20, 20, (300, 3)).astype(np.float32)
    pred = rng.uniform(-20, 20, (200, 3)).astype(np.float32)
    from pcfbench.data import RayQuery

    dirs = gt / np.linalg.norm(gt, axis=1, keepdims=True)
    e = figures.sweep_errors(0, gt, RayQuery(np.zeros(3), dirs.astype(np.float32)), pred, None)
    brute = np.sqrt(((pred[:, None, :].astype(np.float64) - gt[None].astype(np.float64)) ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(e.pred_error_m, brute, rtol=1e-6, atol=1e-6)


def test_bev_grid_cells_hold_the_mean_error_of_their_points():
    pts = np.array([[0.1, 0.1, 0], [0.9, 0.2, 5], [-1.5, 1.5, 0], [9.0, 0, 0], [1.2, -1.9, 0]], np.float32)
    err = np.array([1.0, 3.0, 7.0, 100.0, 4.0])
    g = figures.bev_grid(pts, err, 2.0, 2)  # 2 m cells over [-2, 2]^2; row 0 is +y
    np.testing.assert_array_equal(g, [[7.0, 2.0], [np.nan, 4.0]])  # (9, 0) is outside
    np.testing.assert_array_equal(figures.bev_grid(pts, None, 2.0, 2), [[1, 2], [0, 1]])


def test_chosen_samples_are_the_median_and_the_worst():
    rows = pd.DataFrame({"sample_id": list("abcde") * 2, "step": [0] * 5 + [1] * 5, "status": "ok",
                         "chamfer_nf": [5, 1, 3, 9, 2, 5, 1, 3, 9, 2]})
    assert figures.choose_samples(rows, "chamfer_nf", 2) == ["c", "d"]  # ranked b e c a d
    assert figures.choose_samples(rows, "chamfer_nf", 3) == ["b", "c", "d"]
    assert figures.choose_samples(rows, "chamfer_nf", 1) == ["c"]


LONG = "copilot4d-token-copy [trained on synthetic-town-realistic:train, ck 84120cdf]"
FOOTNOTE = "¹ copilot4d-token-copy trained on synthetic-town-realistic:train, checkpoint sha256 84120cdf"


def _legend_texts(fig) -> list[str]:
    """The legend entries of ``fig`` and of its subfigures (the body above the footnotes)."""
    return [t.get_text() for f in (fig, *fig.subfigs) for lg in f.legends for t in lg.get_texts()]


def _footnotes(fig) -> list[str]:
    return [t.get_text() for f in fig.subfigs for t in f.texts]


def _texts_do_not_collide(fig) -> None:
    """Every title, axis label and the suptitle, drawn: inside the figure, and no two overlap."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    texts = [fig._suptitle] + [t for f in fig.subfigs for t in f.texts]
    for ax in fig.axes:
        texts += [ax.title, ax.xaxis.label, ax.yaxis.label]
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in texts
             if t is not None and t.get_visible() and t.get_text()]
    page = fig.bbox
    for text, box in boxes:
        assert box.x0 >= page.x0 - 0.5 and box.x1 <= page.x1 + 0.5 and box.y0 >= page.y0 - 0.5 \
            and box.y1 <= page.y1 + 0.5, f"{text!r} is cut off at the figure's edge"
    for i, (ta, a) in enumerate(boxes):
        for tb, b in boxes[i + 1:]:
            assert not a.overlaps(b), f"{ta!r} overlaps {tb!r}"


def _gallery_run(made, samples=2):
    store = made[0]
    lb = collect(store)
    rows = Cell.at(store, lb.table.iloc[0]["cell_dir"]).read_rows()
    ids = list(dict.fromkeys(rows["sample_id"]))[:samples]
    return figures.rerun(store, lb.table, ids, _plugins())


def test_gallery_has_a_row_per_method_a_column_per_sample_and_one_colour_bar(made):
    """Rows: past, ground truth, then one per variant; columns: the samples; each forecast
    panel coloured by its per-point error on one scale with a single colour bar."""
    run = _gallery_run(made)
    variants = list(run.errors)
    assert len(variants) == 3 and len(run.sample_ids) == 2
    fig = figures.gallery_figure(run, "t", "t = +1 s")
    panels = [ax for ax in fig.axes if ax.images and ax.get_label() != "<colorbar>"]
    assert len(panels) == (2 + 3) * 2
    grid = np.array(panels, dtype=object).reshape(5, 2)  # subplots are added row by row
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(bars) == 1 and bars[0].get_xlabel() == "forecast point to nearest ground-truth point (m)"
    rows = [ax.get_ylabel() for ax in grid[:, 0]]
    assert rows == ["past sweeps\n(darkest: t = 0)", "ground truth\nt = +1 s", *variants]
    assert [ax.get_title() for ax in grid[0]] == [f"sample {sid}" for sid in run.sample_ids]
    assert all(ax.get_title() == "" for ax in grid[1:].ravel())  # one title per column, none between rows
    for r, v in enumerate(variants, start=2):
        for c, sid in enumerate(run.sample_ids):
            e = run.errors[v][sid][-1]
            shown = np.ma.filled(grid[r, c].images[0].get_array().astype(float), np.nan)
            np.testing.assert_array_equal(shown, figures.bev_grid(e.pred_points, e.pred_error_m, 50.0, 250))
            assert grid[r, c].images[0].get_clim() == grid[2, 0].images[0].get_clim()  # one scale
    assert all(ax.get_xlabel() == "x (m)" for ax in grid[-1])
    assert not _footnotes(fig)


def test_gallery_titles_never_collide_and_a_long_label_becomes_a_footnote(made):
    """A trained method's 75-character label: its row says its name and a marker, the training
    data and checkpoint are a footnote; no title or label overlaps another or leaves the page;
    the figure is taller than wide (a page's column of rows, not a strip)."""
    run = _gallery_run(made)
    last = list(run.errors)[-1]
    run.errors = {(LONG if v == last else v): e for v, e in run.errors.items()}
    fig = figures.gallery_figure(run, "kitti / test / kitti-1s", "t = +1 s")
    rows = [ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()]
    assert rows[-1] == "copilot4d-token-\ncopy¹" and all(len(line) <= 20 for r in rows for line in r.split("\n"))
    assert _footnotes(fig) == [FOOTNOTE]
    _texts_do_not_collide(fig)
    w, h = fig.get_size_inches()
    assert h > w


def test_ablation_figure_plots_the_metric_against_the_option_value(made, tmp_path):
    store = made[0]
    lb = collect(store)
    t = tables.build(lb, tables.get_preset("roi", tables.load_presets()))
    paths = figures.ablation_figures(lb, t.columns, tmp_path, "exp", _plugins())
    assert set(paths) == {"ablation-exp_shifted_dx.png", "ablation-exp_shifted_dx.svg"}
    g = lb.table[lb.table["method"] == "shifted"].sort_values("option.dx")
    fig = figures._ablation_figure(g, "option.dx", [], t.columns, "shifted", {"dx": "m"})
    ax = fig.axes[0]
    assert ax.get_xlabel() == "shifted option dx (m)"
    line = ax.lines[0]
    np.testing.assert_array_equal(line.get_xdata(), [0.5, 1.5])
    np.testing.assert_array_equal(line.get_ydata(), g[t.columns[0].metric].to_numpy())
    units = figures._method_units("raycast-voxel")  # "voxel edge of the occupancy grid, metres"
    assert units["voxel"] == "m" and "cone_factor" not in units  # "(0: thin rays)" is no unit


def test_ablation_legend_names_the_options_that_tell_its_lines_apart_and_a_footnote_the_shared_ones():
    """A sweep of `k` over two values of `w` with two options every line shares: the legend says
    `w=0` and `w=2` (whole numbers without `.0`, `0.5` as written), not the shared options, which
    one footnote names; before, every fixed option was in every label and the labels ran off the
    figure."""
    rows = [{"dataset": "d", "split": "test", "setting": "kitti-1s", "method": "m", "variant": f"m (k={k}, w={w})",
             "option.k": float(k), "option.w": float(w), "option.steps": 1000.0, "option.config": "tiny-window",
             "option.lr": 0.5, "l1_mean": 1.0 + k + w, "l1_mean_lo": 0.5 + k + w, "l1_mean_hi": 1.5 + k + w}
            for w in (0, 2) for k in (1, 3)]
    g = pd.DataFrame(rows)
    others = ["option.w", "option.steps", "option.config", "option.lr"]
    fig = figures._ablation_figure(g, "option.k", others, [L1], "m", {})
    assert _legend_texts(fig) == ["kitti-1s, w=0", "kitti-1s, w=2"]
    assert _footnotes(fig) == ["every line: steps=1000, config=tiny-window, lr=0.5"]
    np.testing.assert_array_equal(fig.axes[0].lines[0].get_ydata(), [2, 4])  # w=0: k=1, 3
    _texts_do_not_collide(fig)


def test_ablation_legend_names_the_split_when_the_lines_come_from_two():
    """A sweep of val and test: each line and each split's reference line says its split (before,
    the two splits' lines were both "kitti-3s, w=0" and the two references both "ref (reference)");
    a figure of one split keeps the setting alone."""
    rows = [{"dataset": "d", "split": split, "setting": "kitti-3s", "method": "m", "variant": f"m (k={k}, w={w})",
             "option.k": float(k), "option.w": float(w), "l1_mean": 1.0 + k + w, "l1_mean_lo": 0.5 + k + w,
             "l1_mean_hi": 1.5 + k + w} for split in ("val", "test") for w in (0, 2) for k in (1, 3)]
    refs = pd.DataFrame([{"dataset": "d", "split": split, "setting": "kitti-3s", "method": "ref", "variant": "ref",
                          "l1_mean": x} for split, x in (("val", 5.0), ("test", 6.0))])
    fig = figures._ablation_figure(pd.DataFrame(rows), "option.k", ["option.w"], [L1], "m", {}, refs)
    assert sorted(_legend_texts(fig)) == ["ref (reference, test)", "ref (reference, val)", "test / kitti-3s, w=0",
                                          "test / kitti-3s, w=2", "val / kitti-3s, w=0", "val / kitti-3s, w=2"]
    ys = {ln.get_label(): ln.get_ydata()[0] for ln in fig.axes[0].lines if "reference" in ln.get_label()}
    assert ys == {"ref (reference, val)": 5.0, "ref (reference, test)": 6.0}
    one = figures._ablation_figure(pd.DataFrame(rows[:4]), "option.k", ["option.w"], [L1], "m", {}, refs[:1])
    assert sorted(_legend_texts(one)) == ["kitti-3s, w=0", "kitti-3s, w=2", "ref (reference)"]
    _texts_do_not_collide(fig)



def test_ablation_reference_lines_never_share_a_look():
    """Two splits x two settings: four references. Each line differs from every other in colour or
    dash (three colours cycled, so the fourth reference is dash-dotted), its band is its colour, and
    the title says the dashes."""
    from matplotlib.colors import to_rgb
    from matplotlib.text import Text

    rows = [{"dataset": "d", "split": split, "setting": setting, "method": "m", "variant": f"m (k={k})",
             "option.k": float(k), "l1_mean": 1.0 + k} for split in ("val", "test")
            for setting in ("kitti-1s", "kitti-3s") for k in (1, 3)]
    refs = pd.DataFrame([{"dataset": "d", "split": split, "setting": setting, "method": "ref", "variant": "ref",
                          "l1_mean": 5.0 + i, "l1_mean_lo": 4.5 + i, "l1_mean_hi": 5.5 + i}
                         for i, (split, setting) in enumerate((s, t) for s in ("val", "test")
                                                              for t in ("kitti-1s", "kitti-3s"))])
    fig = figures._ablation_figure(pd.DataFrame(rows), "option.k", [], [L1], "m", {}, refs)
    lines = [ln for ln in fig.axes[0].lines if "reference" in ln.get_label()]
    looks = {(ln.get_color(), ln.get_linestyle()) for ln in lines}
    assert len(lines) == 4 and len(looks) == 4
    assert {ln.get_linestyle() for ln in lines} == {"--", "-."}
    bands = [p.get_facecolor()[:3] for p in fig.axes[0].patches]
    assert len(bands) == 4 and all(np.allclose(b, to_rgb(ln.get_color())) for b, ln in zip(bands, lines))
    assert any("dashed(thendash-dot,dotted)" in "".join(t.get_text().split()) for t in fig.findobj(Text))
    _texts_do_not_collide(fig)


def test_html_page_is_self_contained_with_figures_sortable_rows_and_provenance(made):
    _, out, paths = made
    page = paths["html"].read_text()
    assert "http://" not in page and "https://" not in page and "<link" not in page and "src='http" not in page
    assert page.count("<img") == 2 and page.count("src='data:image/png;base64,") == 2
    assert page.count("<tr class='cell'") == 3 and "table class='pcf sortable'" in page
    for key in ("harness", "protocol", "git commit", "dataset fingerprint", "checkpoint sha256", "date"):
        assert f"<th>{key}</th>" in page
    assert page.count("<tr id='cell-") == 3
    assert pcfbench.__version__ in page


def test_report_publishes_atomically_and_refuses_a_file_as_folder(made, tmp_path, monkeypatch):
    store = made[0]
    out = tmp_path / "rep"
    write_reports(store, out, ReportOptions(figures=False))
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    # killed half way through the rendering: nothing in place changed, the staging folder is dropped
    import pcfbench.reporting.htmlreport as hr

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(hr, "page", boom)
    with pytest.raises(KeyboardInterrupt):
        write_reports(store, out, ReportOptions(figures=False, ci="interval"))
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert not list(out.glob(".report-*"))
    monkeypatch.undo()
    # a staging folder left by a killed process (a pid that is gone) is removed by the next report
    stale = out / ".report-999999999.tmp"
    stale.mkdir()
    (stale / "leaderboard.md").write_text("half")
    write_reports(store, out, ReportOptions(figures=False))
    assert not stale.exists()
    # a file where the folder should be: one error naming it
    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(PcfbenchError, match=r"afile is a file, not a folder"):
        write_reports(store, f, ReportOptions(figures=False))
    with pytest.raises(PcfbenchError, match=r"afile is a file, not a folder"):
        write_reports(store, f / "sub", ReportOptions(figures=False))
    assert f.read_text() == "x"


@pytest.mark.slow
def test_html_page_renders_in_headless_chromium(made, tmp_path):
    """Debian's chromium renders the page: every row and value, the figures decoded, sorting
    by a column (the #sort= address a header click sets) reorders each group; a screenshot is kept."""
    from html.parser import HTMLParser

    exe = chromium()
    store, _, paths = made
    lb = collect(store)
    url = paths["html"].resolve().as_uri()

    class Dom(HTMLParser):
        def __init__(self):
            super().__init__()
            self.rows, self.body, self.heads, self._row = [], {}, [], None

        def handle_starttag(self, tag, attrs):
            a = dict(attrs)
            if tag == "body":
                self.body = a
            elif tag == "th" and "data-key" in a:
                self.heads.append(a["data-key"])
            elif tag == "tr" and "cell" in (a.get("class") or "").split():
                self._row = []
                self.rows.append(self._row)
            elif tag == "td" and self._row is not None:
                self._row.append(a.get("data-v"))

        def handle_endtag(self, tag):
            if tag == "tr":
                self._row = None

    def dom(address):
        d = Dom()
        d.feed(headless(exe, "--dump-dom", address))
        return d

    plain = dom(url)
    assert plain.body.get("data-ready") == "1" and plain.body.get("data-figures-shown") == "2"
    assert len(plain.rows) == len(lb.table) == 3
    col = plain.heads.index("l1_mean")
    shown = {r[0]: float(r[col]) for r in plain.rows}
    for _, r in lb.table.iterrows():
        assert shown[r["variant"] + (" (ref)" if r["is_reference"] else "")] == r["l1_mean"]
    ranked = [r[0] for r in plain.rows]  # ranked by Chamfer (ROI), best first
    assert ranked == sorted(ranked, key=lambda v: next(float(r[plain.heads.index("chamfer_nf")]) for r in plain.rows if r[0] == v))
    for key, desc in (("l1_mean", True), ("method", False)):
        d = dom(f"{url}#sort={key}" + (":desc" if desc else ""))
        values = [r[d.heads.index(key)] for r in d.rows]
        want = sorted(values, key=(float if key != "method" else str), reverse=desc)
        assert values == want and len(values) == 3
        if key == "l1_mean":
            assert [r[0] for r in d.rows] != ranked  # it did reorder
    shot = tmp_path / "leaderboard.png"
    headless(exe, f"--screenshot={shot}", "--window-size=1400,1800", url)
    import matplotlib.image

    assert matplotlib.image.imread(shot).shape[:2] == (1800, 1400)


def test_ablation_fills_in_the_defaults_of_a_cell_run_without_options():
    """A sweep reuses the cell of a plain run (no options) for its default variant: that row's
    option value is the method's default, so the figure still has its point."""
    g = pd.DataFrame({"method": ["shifted", "shifted"], "option.dx": [np.nan, "0.5"]})
    filled = figures._with_defaults(g, "shifted", ["option.dx"], _plugins())
    assert list(filled["option.dx"]) == [0.0, 0.5]
    np.testing.assert_array_equal(figures._numeric(filled["option.dx"]), [0.0, 0.5])


def test_ablation_draws_no_figure_for_an_option_with_one_value(made, tmp_path):
    """A cell that named the default ("0.0", as recorded) and one run without options hold
    the same value: no 'ablation' of a single point (it happened for copilot4d's cfg_weight)."""
    store = made[0]
    lb = collect(store)
    shifted = lb.table[lb.table["method"] == "shifted"]
    lb.table = shifted.assign(**{"option.dx": ["0.0", np.nan][: len(shifted)]})
    t = tables.build(lb, tables.get_preset("roi", tables.load_presets()))
    assert figures.ablation_figures(lb, t.columns, tmp_path, "exp", _plugins()) == {}
    g = pd.DataFrame({"method": ["shifted"] * 3, "option.dx": ["0.0", np.nan, "abc"]})
    assert list(figures._with_defaults(g, "shifted", ["option.dx"], _plugins())["option.dx"]) == [0.0, 0.0, "abc"]


# -- a report reads the store only ------------------------------------------------------------
def _no_method_runs(monkeypatch):
    """Make every way a report could run a method raise: the methods' forecasts, the runner's
    entry points and the re-run of samples."""
    import pcfbench.running.runner
    from pcfbench.methods.copy_last import CopyLast

    def boom(*a, **k):
        raise AssertionError("a report ran a method")

    for cls in (Shifted, CopyLast, Method):
        monkeypatch.setattr(cls, "forecast", boom)
    for name in ("resolve", "process_sample", "run_cell"):
        monkeypatch.setattr(pcfbench.running.runner, name, boom)
    monkeypatch.setattr(figures, "rerun", boom)


def test_report_and_its_figures_run_no_method(made, tmp_path, monkeypatch):
    """`pcfbench report` and write_reports draw every figure (the range one included) from
    the store, with every method's forecast and the runner made to raise."""
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    store = made[0]
    _no_method_runs(monkeypatch)
    paths = write_reports(store, tmp_path / "api", ReportOptions(figures=True), plugins=_plugins())
    assert {"figures/range-kitti_test_kitti-1s.png", "figures/horizon-kitti_test_kitti-1s.png"} <= set(paths)
    monkeypatch.setenv("PCFBENCH_FIGURES", "1")
    res = CliRunner().invoke(build_cli(), ["report", "--store", str(store), "--reports", str(tmp_path / "cli")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "cli" / "figures" / "range-kitti_test_kitti-1s.svg").is_file()
    assert "backfill" not in res.output  # every cell has its range bins


def test_range_bins_stored_at_run_time_are_those_a_rerun_recomputes(made):
    """The bins the runner stored for each sweep are the per-ray errors of a re-run of the
    sample binned by ground-truth range (the old figure's recomputation); one bin by hand."""
    from pcfbench.store import ranges

    store = made[0]
    lb = collect(store)
    cells = lb.table[lb.table["variant"] == "shifted (dx=1.5)"]
    cell = Cell.at(store, cells.iloc[0]["cell_dir"])
    rows, stored = cell.read_rows(), cell.read_ranges()
    assert len(stored) == len(rows[rows.status == "ok"]) and not stored.duplicated(["sample_id", "step"]).any()
    sid = rows["sample_id"].iloc[len(rows) // 2]
    run = figures.rerun(store, cells, [sid], _plugins())
    assert run.mismatch == [] and run.skipped == {}
    for sweep in run.errors["shifted (dx=1.5)"][sid]:
        mine = stored[(stored.sample_id == sid) & (stored.step == sweep.step)]
        assert len(mine) == 1
        got, want = ranges.profile(mine), figures.range_profile([sweep])
        np.testing.assert_array_equal(got["lo_m"].to_numpy(float), want["lo_m"].to_numpy(float))
        np.testing.assert_array_equal(got["rays"].to_numpy(int), want["rays"].to_numpy(int))
        np.testing.assert_allclose(got["l1_mean"].to_numpy(float), want["l1_mean"].to_numpy(float), rtol=1e-12)
        np.testing.assert_allclose(got["absrel_mean"].to_numpy(float), want["absrel_mean"].to_numpy(float), rtol=1e-12)
        # by hand: the kept rays whose ground truth lies 10-20 m away
        r = mine.iloc[0]
        inside = (sweep.ray_range_m >= 10.0) & (sweep.ray_range_m < 20.0)
        k = list(r["bin"]).index(1)
        assert r["rays"][k] == inside.sum() > 0
        assert r["l1_sum"][k] == pytest.approx(float(np.sum(sweep.ray_l1_m[inside])), rel=1e-12)
        assert r["absrel_sum"][k] == pytest.approx(float(np.sum(sweep.ray_absrel[inside])), rel=1e-12)
        # and the ray-weighted mean over the bins is the sweep's stored l1_mean
        stored_row = rows[(rows.sample_id == sid) & (rows.step == sweep.step)].iloc[0]
        assert sum(r["l1_sum"]) / sum(r["rays"]) == pytest.approx(stored_row["l1_mean"], rel=1e-12)


def test_range_figure_pools_every_stored_sweep(made):
    import matplotlib.colors

    from pcfbench.store import ranges

    store = made[0]
    lb = collect(store)
    found = figures.stored_ranges(store, lb.table)
    assert set(found.profiles) == set(lb.table["variant"]) and not found.missing
    fig = figures.range_figure(found, "t")
    ax_l1 = fig.axes[0]
    for _, r in lb.table.iterrows():
        cell = Cell.at(store, r["cell_dir"])
        prof = ranges.profile(cell.read_ranges())
        line = next(ln for ln in ax_l1.lines if ln.get_label() == r["variant"])
        np.testing.assert_array_equal(line.get_ydata(), prof["l1_mean"].to_numpy(float))
        np.testing.assert_array_equal(line.get_xdata(), ((prof["lo_m"] + prof["hi_m"]) / 2).to_numpy(float))
        assert found.sweeps[r["variant"]] == r["sweeps"]
    assert "a point: the mean over every ray in its bin, all 30 scored sweeps of a method pooled\n" \
        "band: 95 % percentile bootstrap over samples, 2000 resamples, seed 17" in fig.get_suptitle()
    # every curve has its band: one filled area per line, in its colour
    for ax in fig.axes:
        assert len(ax.collections) == len(ax.lines) == 3
        for line, band in zip(ax.lines, ax.collections):
            assert tuple(band.get_facecolor()[0][:3]) == pytest.approx(matplotlib.colors.to_rgb(line.get_color()))


def test_a_cell_made_before_the_store_kept_range_bins_is_named_and_backfilled(made, tmp_path, monkeypatch):
    """A cell without range bins is left out of the range figure with a note naming it and the
    command; the report runs no method for it; `pcfbench backfill-ranges` recomputes the very
    bins the run stored."""
    import json
    import shutil

    from pcfbench.running import backfill

    from pcfbench.store import ranges

    store = tmp_path / "store"
    shutil.copytree(made[0], store)
    lb = collect(store)
    old = lb.table[lb.table["variant"] == "shifted (dx=0.5)"].iloc[0]
    cell = Cell.at(store, old["cell_dir"])
    kept = cell.read_ranges()
    shutil.rmtree(cell.dir / "ranges")  # as a cell made before this version
    meta = json.loads((cell.dir / "cell.json").read_text())
    del meta["range_bins"]
    (cell.dir / "cell.json").write_text(json.dumps(meta))

    with monkeypatch.context() as m:
        _no_method_runs(m)
        paths = write_reports(store, tmp_path / "rep", ReportOptions(figures=True), plugins=_plugins())
        found = figures.stored_ranges(store, collect(store).table)
    assert "figures/range-kitti_test_kitti-1s.png" in paths
    assert found.missing == {"shifted (dx=0.5)": old["cell_dir"]} and "shifted (dx=0.5)" not in found.profiles
    title = figures.range_figure(found, "t").get_suptitle()
    assert "\nleft out, no range bins in the store: shifted (dx=0.5) (`pcfbench backfill-ranges`" in title
    md = paths["md"].read_text()
    from pcfbench.reporting.escape import md_text  # the note is text, escaped as Markdown like every other

    assert md_text(f"no range bins in the store for cell {old['cell_dir']}") in md and "pcfbench backfill-ranges" in md

    done = backfill.backfill(store, _plugins(), log=lambda s: None)
    assert [d["status"] for d in done if d["cell"] == str(cell.dir)] == ["recomputed 1 chunk(s)"]
    assert sum(d["status"] == "has ranges" for d in done) == 2
    again = cell.read_ranges()
    pd.testing.assert_frame_equal(again, kept)
    assert json.loads((cell.dir / "cell.json").read_text())["range_bins"] == ranges.meta()
    assert not figures.stored_ranges(store, collect(store).table).missing
    assert backfill.backfill(store, _plugins(), log=lambda s: None)[0]["status"] == "has ranges"  # nothing left to do


def test_backfill_ranges_command_and_a_method_that_does_not_reproduce_its_rows(made, tmp_path, monkeypatch):
    """`pcfbench backfill-ranges` recomputes a cell's missing bins; a cell whose re-run gives
    other numbers than its rows is named, left without bins, and the command exits 1."""
    import json
    import shutil

    from click.testing import CliRunner

    from pcfbench.running import backfill
    from pcfbench.cli import build_cli

    store = tmp_path / "store"
    shutil.copytree(made[0], store)
    lb = collect(store)

    def strip(variant):
        cell = Cell.at(store, lb.table[lb.table["variant"] == variant].iloc[0]["cell_dir"])
        kept = cell.read_ranges()
        shutil.rmtree(cell.dir / "ranges")
        meta = json.loads((cell.dir / "cell.json").read_text())
        del meta["range_bins"]
        (cell.dir / "cell.json").write_text(json.dumps(meta))
        return cell, kept

    cell, kept = strip("copy-last")
    res = CliRunner().invoke(build_cli(), ["backfill-ranges", "--store", str(store)])
    assert res.exit_code == 0, res.output
    assert f"{cell.dir}: recomputed 1 chunk(s)" in res.output and "1 cell(s) recomputed, 0 left as they are" in res.output
    pd.testing.assert_frame_equal(cell.read_ranges(), kept)

    cell, _ = strip("shifted (dx=1.5)")
    monkeypatch.setattr(Shifted, "forecast", lambda self, sample: Forecast(points_ref=tuple(
        sample.past_points_ref[-1] + np.float32(2.0) for _ in range(sample.num_future))))
    done = [d for d in backfill.backfill(store, _plugins(), log=lambda s: None) if d["cell"] == str(cell.dir)]
    assert done[0]["status"].startswith("not recomputed: re-running shifted does not give back its stored rows")
    assert not (cell.dir / "ranges").exists() and "range_bins" not in json.loads((cell.dir / "cell.json").read_text())
    note = figures.range_gaps(collect(store), store)
    assert note == [f"shifted (dx=1.5): no range bins in the store for cell {cell.dir} (made before the store kept "
                    f"them), so the error-by-range figure leaves it out; `pcfbench backfill-ranges --store {store}` "
                    "recomputes them (it re-runs the method)"]


def test_gallery_is_drawn_only_when_asked_for(made, tmp_path):
    store = made[0]
    paths = write_reports(store, tmp_path / "rep", ReportOptions(figures=True, gallery=True), plugins=_plugins())
    assert {"figures/gallery-kitti_test_kitti-1s.png", "figures/gallery-kitti_test_kitti-1s.svg"} <= set(paths)
    assert paths["html"].read_text().count("src='data:image/png;base64,") == 3
    again = write_reports(store, tmp_path / "rep", ReportOptions(figures=True), plugins=_plugins())
    assert not any("gallery" in k for k in again) and not list((tmp_path / "rep" / "figures").glob("gallery-*"))


def test_ablation_ticks_at_the_grid_values_and_draws_the_reference_method(made, tmp_path, monkeypatch):
    """A grid of two values gets two ticks, at those values (not matplotlib's 0.6, 0.8, ...
    between them), and the table's reference (copy-last) is a dashed horizontal line at its
    value, in the legend."""
    store = made[0]
    lb = collect(store)
    t = tables.build(lb, tables.get_preset("roi", tables.load_presets()))
    drawn = {}
    monkeypatch.setattr(figures, "save", lambda fig, out_dir, stem, *a: drawn.setdefault(stem, fig) and {})
    figures.ablation_figures(lb, t.columns, tmp_path, "exp", _plugins())
    fig = drawn["ablation-exp_shifted_dx"]
    ref = lb.table[lb.table["is_reference"]].iloc[0]
    assert ref["method"] == "copy-last"
    for ax, col in zip(fig.axes, t.columns):
        np.testing.assert_array_equal(ax.get_xticks(), [0.5, 1.5])
        assert [x.get_text() for x in ax.get_xticklabels()] == ["0.5", "1.5"]
        k, _ = figures._unit_scale(col.unit)
        (line,) = [ln for ln in ax.lines if ln.get_label() == "copy-last (reference)"]
        assert line.get_linestyle() == "--"
        np.testing.assert_allclose(line.get_ydata(), [k * ref[col.metric]] * 2)
    assert "copy-last (reference)" in _legend_texts(fig)


def _hand_steps(values_by_step: dict[int, list[float]]) -> pd.DataFrame:
    """Per-step rows of one variant, its means and intervals from ``stats`` (what ``collect``
    does): three samples of one sequence, l1_mean per (sample, step)."""
    from pcfbench.reporting import stats

    rows = pd.DataFrame([{"sample_id": f"s/{i}", "sequence": "s", "ref_index": i, "step": step, "status": "ok",
                          "l1_mean": v} for step, vs in values_by_step.items() for i, v in enumerate(vs)])
    out = []
    for step, g in rows.groupby("step"):
        iv = stats.interval(stats.sample_sums(g, ["l1_mean"]), stats.Resampling())
        out.append({"variant": "v", "time_s": 0.2 * (step + 1), "l1_mean": g["l1_mean"].mean(),
                    "l1_mean_lo": iv.lo[0], "l1_mean_hi": iv.hi[0]})
    return pd.DataFrame(out)


L1 = SimpleNamespace(metric="l1_mean", label="L1 Mean", unit="m", better="lower")


def test_horizon_band_is_the_bootstrap_interval_and_brackets_the_mean_by_hand():
    """Three samples, L1 1, 2, 6 m at the first step and 0, 3, 3 m at the second. The mean is 3
    and 2 m; a resample of three is all one sample with probability 1/27 = 3.7 % > 2.5 %, so the
    95 % percentile interval runs from the smallest to the largest value: [1, 6] and [0, 3] m."""
    steps = _hand_steps({0: [1.0, 2.0, 6.0], 1: [0.0, 3.0, 3.0]})
    np.testing.assert_allclose(steps[["l1_mean", "l1_mean_lo", "l1_mean_hi"]].to_numpy(), [[3, 1, 6], [2, 0, 3]])
    ax = figures.horizon_figure(steps, [L1], "x").axes[0]
    np.testing.assert_allclose(ax.lines[0].get_ydata(), [3, 2])
    (band,) = ax.collections
    xy = band.get_paths()[0].vertices
    for t, mean, lo, hi in [(0.2, 3, 1, 6), (0.4, 2, 0, 3)]:
        ys = xy[np.isclose(xy[:, 0], t), 1]
        assert ys.min() == pytest.approx(lo) and ys.max() == pytest.approx(hi)
        assert ys.min() <= mean <= ys.max()


def test_a_one_step_curve_gets_error_bars_and_a_curve_without_interval_says_so():
    """A band over one point is 0 wide: the interval is drawn as an error bar instead. One
    sample has no interval (fewer than 2 resampling units): its legend entry says so."""
    ax = figures.horizon_figure(_hand_steps({0: [1.0, 2.0, 6.0]}), [L1], "x").axes[0]
    (bars,) = ax.containers
    segments = bars.lines[2][0].get_segments()
    np.testing.assert_allclose(segments[0], [[0.2, 1.0], [0.2, 6.0]])
    one = _hand_steps({0: [1.0], 1: [2.0]})
    assert one["l1_mean_lo"].isna().all()
    fig = figures.horizon_figure(one, [L1], "x")
    assert _legend_texts(fig) == ["v (no interval: < 2 resampling units)"]


def test_the_horizon_figure_states_and_is_keyed_on_how_its_interval_was_computed():
    from pcfbench.reporting import figcache, stats

    steps = _hand_steps({0: [1.0, 2.0, 6.0], 1: [0.0, 3.0, 3.0]})
    by_sequence = stats.Resampling("sequence").describe()
    assert by_sequence in figures.horizon_figure(steps, [L1], "x", by_sequence)._suptitle.get_text()
    keys = {figcache.figure_key("horizon", **figures.horizon_data(steps, [L1], "x", how))
            for how in (stats.Resampling().describe(), by_sequence)}
    assert len(keys) == 2


def _hand_ranges(bins_by_sample: dict[str, list[tuple[int, int, float]]]) -> figures.StoredRanges:
    """The stored ranges of one variant 'v' from (bin, rays, L1 sum) per sample, one future
    sweep per sample of sequence 's' (AbsRel sum = L1 sum / 10), read as ``stored_ranges``
    reads a cell's."""
    from pcfbench.store import ranges

    stored = pd.DataFrame([{"sample_id": sid, "step": 0, "bin": [b for b, _, _ in bins],
                            "rays": [n for _, n, _ in bins], "l1_sum": [x for _, _, x in bins],
                            "absrel_sum": [x / 10 for _, _, x in bins]} for sid, bins in bins_by_sample.items()])
    rows = pd.DataFrame({"sample_id": list(bins_by_sample), "sequence": "s", "ref_index": range(len(bins_by_sample)),
                         "step": 0, "status": "ok"})
    return figures.StoredRanges({"v": ranges.profile(stored)}, {"v": len(rows)}, {}, {},
                                {"v": figures._per_sample_bins(stored, rows)})


def test_range_band_is_the_bootstrap_interval_of_each_bin_by_hand():
    """Three samples. Bin [0, 10) m: 1 ray of L1 1 m, 1 ray of 2 m, 2 rays summing to 12 m: the
    ray-weighted mean is 15 / 4 m; a resample of three is all one sample with probability
    1/27 = 3.7 % > 2.5 %, so the 95 % interval runs from the smallest sample mean to the
    largest: [1, 6] m. Bin [10, 20) m: one ray each, 0, 3, 3 m: mean 2, interval [0, 3] m."""
    found = _hand_ranges({"s/0": [(0, 1, 1.0), (1, 1, 0.0)], "s/1": [(0, 1, 2.0), (1, 1, 3.0)],
                          "s/2": [(0, 2, 12.0), (1, 1, 3.0)]})
    iv = figures.range_intervals(found)["v"]
    np.testing.assert_allclose(iv[["lo_m", "l1_lo", "l1_hi"]].to_numpy(), [[0, 1, 6], [10, 0, 3]])
    np.testing.assert_allclose(iv[["absrel_lo", "absrel_hi"]].to_numpy(), [[0.1, 0.6], [0, 0.3]])
    assert (iv["units"] == 3).all()
    fig = figures.range_figure(found, "x")
    ax_l1, ax_ar = fig.axes
    np.testing.assert_allclose(ax_l1.lines[0].get_ydata(), [15 / 4, 2])
    (band,) = ax_l1.collections
    xy = band.get_paths()[0].vertices
    for mid, mean, lo, hi in [(5, 15 / 4, 1, 6), (15, 2, 0, 3)]:
        ys = xy[np.isclose(xy[:, 0], mid), 1]
        assert ys.min() == pytest.approx(lo) and ys.max() == pytest.approx(hi) and lo <= mean <= hi
    ys = ax_ar.collections[0].get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(0) and ys.max() == pytest.approx(60)  # AbsRel in %


def test_a_one_bin_range_curve_gets_error_bars_and_one_sample_says_it_has_no_interval():
    found = _hand_ranges({"s/0": [(2, 1, 1.0)], "s/1": [(2, 1, 2.0)], "s/2": [(2, 2, 12.0)]})
    ax = figures.range_figure(found, "x").axes[0]
    (bars,) = ax.containers
    np.testing.assert_allclose(bars.lines[2][0].get_segments()[0], [[25, 1], [25, 6]])
    one = _hand_ranges({"s/0": [(0, 3, 3.0), (1, 1, 2.0)]})
    assert figures.range_intervals(one)["v"][["l1_lo", "l1_hi"]].isna().all().all()
    fig = figures.range_figure(one, "x")
    assert _legend_texts(fig) == ["v (no interval: < 2 resampling units)"] and not fig.axes[0].collections


def test_range_intervals_follow_the_resampling_and_it_is_in_the_title_and_the_key():
    """Whole sequences as the unit: two sequences, the interval differs from the samples' one;
    the title names it and the figure's key changes with it."""
    from pcfbench.reporting import figcache, stats

    found = _hand_ranges({f"s/{i}": [(0, 1, float(i))] for i in range(6)})
    found.samples["v"]["sequence"] = ["a", "a", "a", "b", "b", "b"]
    by_seq = stats.Resampling("sequence")
    a, b = figures.range_intervals(found)["v"], figures.range_intervals(found, by_seq)["v"]
    assert a["units"].iloc[0] == 6 and b["units"].iloc[0] == 2
    np.testing.assert_allclose(b[["l1_lo", "l1_hi"]].to_numpy(), [[1, 4]])  # the two sequences' means
    assert by_seq.describe() in figures.range_figure(found, "x", by_seq).get_suptitle()
    keys = {figcache.figure_key("range", **figures.range_data(found, "x", r)) for r in (None, by_seq)}
    assert len(keys) == 2


def test_legends_hold_short_names_and_the_training_data_is_a_footnote(made, tmp_path, monkeypatch):
    """A trained method's label (75 characters) sets no legend's width: every figure's legend
    names it `copilot4d-token-copy¹` and the footnote under the figure says what it was trained
    on and which checkpoint."""
    store = made[0]
    lb = collect(store)
    for df in (lb.table, lb.by_step):  # the reference, copy-last, named as a trained method would be
        df["variant"] = df["variant"].replace({"copy-last": LONG})
    assert lb.table.loc[lb.table["is_reference"], "variant"].tolist() == [LONG]
    t = tables.build(lb, tables.get_preset("paper", tables.load_presets()))
    found = figures.stored_ranges(store, lb.table)
    horizon = figures.horizon_figure(lb.by_step, t.columns, "x")
    ranged = figures.range_figure(found, "x")
    drawn = {}
    monkeypatch.setattr(figures, "save", lambda fig, out_dir, stem, *a: drawn.setdefault(stem, fig) and {})
    figures.ablation_figures(lb, t.columns, tmp_path, "exp", _plugins())
    ablation = drawn["ablation-exp_shifted_dx"]
    for fig, want in ((horizon, "copilot4d-token-copy¹"), (ranged, "copilot4d-token-copy¹"),
                      (ablation, "copilot4d-token-copy¹ (reference)")):
        texts = _legend_texts(fig)
        assert want in texts and max(map(len, texts)) <= 40, texts
        assert _footnotes(fig) == [FOOTNOTE]
        _texts_do_not_collide(fig)
    data = figures.horizon_data(lb.by_step, t.columns, "x")
    assert data["legend"] == figures.short_labels(lb.by_step["variant"].unique())


def test_ablation_title_names_the_resampling_of_its_error_bars(made, tmp_path, monkeypatch):
    from pcfbench.reporting import stats

    store = made[0]
    lb = collect(store, stats.Resampling("block", 3))
    t = tables.build(lb, tables.get_preset("roi", tables.load_presets()))
    drawn = {}
    monkeypatch.setattr(figures, "save", lambda fig, out_dir, stem, *a: drawn.setdefault(stem, fig) and {})
    figures.ablation_figures(lb, t.columns, tmp_path, "exp", _plugins())
    title = drawn["ablation-exp_shifted_dx"].get_suptitle()
    assert "error bars: 95 % percentile bootstrap over blocks of 3 consecutive samples" in title
