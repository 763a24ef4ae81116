"""Table presets (data, in tables.toml) and the renderers of a leaderboard in their layout.

A preset names the metric columns of a table and their headers; which way each column is
better comes from its metric (``Metric.higher_is_better``, recorded in every cell.json), and
a preset that still says ``better`` must agree with it. :func:`build` turns the analysed
leaderboard (``pcfbench.reporting.report.collect``) into row groups per (dataset, split, setting,
policy[, limit]) ranked best first, and :func:`markdown`, :func:`latex`, :func:`html_table`
and :func:`text` print it. Every value is the flat mean of the leaderboard; the ± (or
[lo, hi]) is its bootstrap interval, and the relative change is against the group's
reference cell (``pcfbench.reporting.stats``).
"""

from __future__ import annotations

import html as _html
import math
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import pandas as pd

from pcfbench.errors import PcfbenchError, unknown_name
from pcfbench.reporting.escape import md_text
from pcfbench.kinds import Better, parse

PRESETS_FILE = "tables.toml"
CI_STYLES = ("pm", "interval", "none")
_PRESET_KEYS = {"title", "description", "columns", "rank_by"}
_COLUMN_KEYS = {"metric", "label", "better"}

# LaTeX page geometry (A4, 2.5 cm margins: 455 x 702 pt) and a \small tabular's glyph width
# (calibrated on pdflatex output, rounded up), in pt.
A4_TEXTWIDTH_PT = 455.0
A4_TEXTHEIGHT_PT = 700.0
_CHAR_PT = 5.0
_COLSEP_PT = 8.0
_FOOTNOTE_SCALE = 8 / 9  # \footnotesize (8 pt) against \small (9 pt)


@dataclass(frozen=True)
class Column:
    metric: str
    label: str
    #: None: the metric's own direction; else a claim :func:`build` checks against it
    better: Better | None = None


@dataclass(frozen=True)
class Preset:
    """A table layout. ``columns`` is None for "every metric in the store"."""

    name: str
    title: str
    columns: tuple[Column, ...] | None
    rank_by: str | None = None
    description: str = ""
    source: str = ""


def _parse_preset(name: str, data: object, source: str) -> Preset:
    where = f"{source}: preset {name!r}"
    if not isinstance(data, dict):
        raise PcfbenchError(f"{where} must be a table of keys ({', '.join(sorted(_PRESET_KEYS))})")
    extra = set(data) - _PRESET_KEYS
    if extra:
        raise PcfbenchError(f"{where}: unknown key(s) {', '.join(sorted(extra))} (known: {', '.join(sorted(_PRESET_KEYS))})")
    title = data.get("title", name)
    description = data.get("description", "")
    if not isinstance(title, str) or not isinstance(description, str):
        raise PcfbenchError(f"{where}: title and description must be strings")
    raw = data.get("columns")
    if raw == "all":
        columns = None
    elif isinstance(raw, list) and raw:
        cols = []
        for i, c in enumerate(raw):
            if not isinstance(c, dict) or not isinstance(c.get("metric"), str) or set(c) - _COLUMN_KEYS:
                raise PcfbenchError(
                    f"{where}: column {i + 1} must be a table {{metric = \"name\", label = \"header\", "
                    f"better = \"lower\"|\"higher\" (optional: the metric's own)}}, got {c!r}"
                )
            better = c.get("better")
            if better is not None:
                better = parse(Better, better, f"{where}: column {c['metric']!r}: better")
            label = c.get("label", c["metric"])
            if not isinstance(label, str) or not label:
                raise PcfbenchError(f"{where}: column {c['metric']!r}: label must be a non-empty string")
            cols.append(Column(c["metric"], label, better))
        names = [c.metric for c in cols]
        if len(set(names)) != len(names):
            raise PcfbenchError(f"{where}: a metric appears twice among the columns ({', '.join(names)})")
        columns = tuple(cols)
    else:
        raise PcfbenchError(f"{where}: columns must be a non-empty list of column tables or \"all\", got {raw!r}")
    rank_by = data.get("rank_by")
    if rank_by is not None and (not isinstance(rank_by, str) or (columns is not None and rank_by not in [c.metric for c in columns])):
        raise PcfbenchError(f"{where}: rank_by {rank_by!r} must be one of its columns' metrics")
    return Preset(name, title, columns, rank_by, description, source)


def _read_presets(text: str, source: str) -> dict[str, Preset]:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PcfbenchError(f"{source} is not valid TOML: {exc}") from None
    if set(doc) - {"presets"} or not isinstance(doc.get("presets"), dict):
        raise PcfbenchError(f"{source}: expected only [presets.NAME] tables, found {', '.join(sorted(doc)) or 'nothing'}")
    return {name: _parse_preset(name, data, source) for name, data in doc["presets"].items()}


def load_presets(extra: Path | str | None = None) -> dict[str, Preset]:
    """The shipped presets, then those of ``extra`` (a TOML file; same name replaces)."""
    shipped = resources.files(__package__).joinpath(PRESETS_FILE)
    presets = _read_presets(shipped.read_text(), f"pcfbench/{PRESETS_FILE}")
    if extra is not None:
        path = Path(extra)
        if not path.is_file():
            raise PcfbenchError(f"table presets file {path} does not exist")
        presets.update(_read_presets(path.read_text(), str(path)))
    return presets


def get_preset(name: str, presets: dict[str, Preset]) -> Preset:
    if name not in presets:
        raise unknown_name("table preset", name, presets)
    return presets[name]


# -- the display model -----------------------------------------------------------------
@dataclass
class ShownColumn:
    metric: str
    label: str
    better: Better
    unit: str


@dataclass
class Group:
    """One row group: a (dataset, split, setting, policy[, limit]) block, rows ranked."""

    title: str
    rows: pd.DataFrame
    reference: str | None
    best: dict[str, float] = field(default_factory=dict)
    #: variant -> the row's label where it is not the variant itself (a trained method's
    #: short name and footnote marker, :func:`footnote_labels`)
    short: dict[str, str] = field(default_factory=dict)


@dataclass
class Table:
    preset: Preset
    columns: list[ShownColumn]
    groups: list[Group]
    partial: list[Group]
    legend: list[str]
    notes: list[str]
    ci: str = "pm"
    alpha: float = 0.05  # a change with p >= alpha is a tie
    heading: str = "pcfbench leaderboard"  # "pcfbench ablation" for a sweep's table
    #: printed where a table has no complete cells ("" prints nothing)
    empty_note: str = "No complete cells in the store yet: run `pcfbench run` first."
    #: which filters made this view of the store (``Leaderboard.scope``), "" for all of it
    scope: str = ""
    #: (marker, text) of each footnote the row labels point to, in marker order
    footnotes: list[tuple[str, str]] = field(default_factory=list)


#: ``copilot4d-token-copy [trained on synthetic-town-realistic:train, ck 84120cdf]``
#: (``labels.trained_label``): the bracket goes to a footnote, the row keeps the name
_TRAINED = re.compile(r"^(?P<name>.*?) \[trained on (?P<data>[^\]]*?), ck (?P<ck>[0-9a-f]+)(?P<own>, ON ITS TRAINING DATA)?\]$")


def footnote_labels(variants: list[str]) -> tuple[dict[str, str], list[tuple[str, str]]]:
    """Short row labels for ``variants``: a trained method's bracket (training data and
    checkpoint, 75 characters wide in a first column) becomes a superscript marker and a
    footnote, one per distinct bracket in the given order; scoring on the training data stays
    in the row, as a warning. Returns (variant -> label, [(marker, footnote)])."""
    short: dict[str, str] = {}
    notes: dict[str, str] = {}  # footnote text -> marker
    for v in variants:
        m = _TRAINED.match(str(v))
        if m is None or v in short:
            continue
        note = f"{m['name']} trained on {m['data']}, checkpoint sha256 {m['ck']}"
        marker = notes.setdefault(note, str(len(notes) + 1).translate(_SUPERSCRIPT))
        short[v] = m["name"] + marker + (" (ON ITS TRAINING DATA)" if m["own"] else "")
    return short, [(marker, note) for note, marker in notes.items()]


def _title(r: pd.Series, horizon_s: float | None) -> str:
    t = f"{r['dataset']} / {r['split']} / {r['setting']}"
    if isinstance(horizon_s, (int, float)) and math.isfinite(horizon_s):
        t += f" ({horizon_s:g} s)"
    if r["policy"] != "full-context":
        t += f" ({r['policy']})"
    if r.get("limit") is not None and not pd.isna(r.get("limit")):
        t += f", limit={int(r['limit'])}"
    return t


def _failed_by_group(incomplete: pd.DataFrame) -> dict[tuple, int]:
    """Failed samples of the unranked (incomplete) cells per (dataset, split, setting, policy, limit)."""
    if not len(incomplete) or "failed" not in incomplete:
        return {}
    df = incomplete.assign(limit=incomplete["limit"].fillna(-1) if "limit" in incomplete else -1)
    sums = df.groupby(["dataset", "split", "setting", "policy", "limit"], dropna=False)["failed"].sum()
    return {k: int(v) for k, v in sums.items()}


def _groups(df: pd.DataFrame, columns: list[ShownColumn], rank: ShownColumn | None,
            order: list[str] | None = None, failed_elsewhere: dict[tuple, int] | None = None) -> list[Group]:
    out = []
    if not len(df):
        return out
    keys = ["dataset", "split", "setting", "policy", "limit"]
    df = df.copy()
    df["limit"] = df["limit"].fillna(-1) if "limit" in df else -1
    for key, g in df.groupby(keys, sort=True, dropna=False):
        if order is not None:  # a sweep's rows in the experiment's order
            g = g.assign(_row=g["variant"].map({v: i for i, v in enumerate(order)})).sort_values("_row").drop(columns="_row")
        elif rank is not None:
            sign = 1.0 if rank.better == Better.LOWER else -1.0
            score = (sign * g[rank.metric]).fillna(math.inf) if rank.metric in g else pd.Series(0.0, index=g.index)
            g = g.assign(_score=score).sort_values(["_score", "variant"]).drop(columns="_score")
        first = g.iloc[0].copy()
        first["limit"] = None if first["limit"] == -1 else first["limit"]
        title = _title(first, first.get("horizon_s"))
        samples, sweeps = int(g["samples"].max()), int(g["sweeps"].max())
        # failed samples of the group: its rows' and those of its unranked (incomplete) cells
        failed = int(g["failed"].fillna(0).sum()) + (failed_elsewhere or {}).get(key, 0) if "failed" in g else 0
        title += f" - {samples} samples, {sweeps} sweeps, {failed} failed"
        best = {}
        for c in columns:
            vals = g[c.metric].dropna() if c.metric in g else pd.Series(dtype=float)
            if len(vals):
                best[c.metric] = float(vals.min() if c.better == Better.LOWER else vals.max())
        ref = g.loc[g["is_reference"], "variant"]
        out.append(Group(title, g.reset_index(drop=True), ref.iloc[0] if len(ref) else None, best))
    return out


def column_better(preset: Preset, column: Column, higher_is_better: bool | None) -> Better:
    """Which way ``column`` of ``preset`` is better: its metric's direction (``higher_is_better``;
    None where neither the store nor the registry knows it), which a ``better`` the preset
    states must match; lower where nothing says."""
    if higher_is_better is None:
        return column.better or Better.LOWER
    metric = Better.of(higher_is_better)
    if column.better is not None and column.better != metric:
        raise PcfbenchError(
            f"{preset.source or 'table presets'}: preset {preset.name!r}: column {column.metric!r} says better = "
            f"\"{column.better}\", but metric {column.metric!r} is {metric}-is-better (Metric.higher_is_better = "
            f"{higher_is_better}); drop `better` from the column: the metric's own direction is used"
        )
    return metric


def build(lb, preset: Preset, ci: str = "pm", order: list[str] | None = None,
          heading: str = "pcfbench leaderboard") -> Table:
    """The display model of leaderboard ``lb`` (``pcfbench.reporting.report.Leaderboard``) in ``preset``.

    ``order``: variant labels; rows follow it (a sweep's ablation table) instead of being
    ranked. ``heading`` starts the Markdown and HTML titles."""
    if ci not in CI_STYLES:
        raise unknown_name("interval style", ci, CI_STYLES)
    notes = []
    if preset.columns is None:
        wanted = [Column(m, m) for m in lb.metric_columns]
    else:
        wanted = list(preset.columns)
    have = set(lb.metric_columns)
    missing = [c.metric for c in wanted if c.metric not in have]
    if missing and (len(lb.table) or len(lb.partial)):
        notes.append(f"no cell in the store has {', '.join(missing)}: column(s) left out of preset {preset.name!r}")
    directions = getattr(lb, "higher_is_better", {})
    columns = [ShownColumn(c.metric, c.label, column_better(preset, c, directions.get(c.metric)),
                           lb.units.get(c.metric, "")) for c in wanted if c.metric in have]
    rank_name = preset.rank_by or (wanted[0].metric if wanted else None)
    rank = next((c for c in columns if c.metric == rank_name), columns[0] if columns else None)
    legend = [
        "↓: lower is better, ↑: higher is better; the best value of each column of a group is in bold",
        "rows in the experiment's order" if order is not None else f"rows ranked by {rank.label}" if rank else "rows in name order",
        f"values are flat means over (sample, future sweep); {'±: half the width of' if ci == 'pm' else '[lo, hi]:' if ci == 'interval' else 'the CSV has'} "
        f"the {lb.resampling.describe()}",
        f"(+x %): relative change against the reference {lb.reference!r} on the samples both scored; "
        f"†: not significantly different from it (paired bootstrap, p ≥ {1 - lb.resampling.confidence:g})",
        "-: no sweep could be scored",
    ]
    elsewhere = _failed_by_group(getattr(lb, "incomplete", pd.DataFrame()))
    groups = _groups(lb.table, columns, rank, order, elsewhere)
    partial = _groups(lb.partial, columns, rank, order, elsewhere)
    short, footnotes = footnote_labels([v for g in groups + partial for v in g.rows["variant"]])
    for g in groups + partial:
        g.short = {v: short[v] for v in g.rows["variant"] if v in short}
    return Table(preset, columns, groups, partial, legend, notes + list(lb.notes), ci,
                 1.0 - lb.resampling.confidence, heading, scope=getattr(lb, "scope", ""), footnotes=footnotes)


# -- formatting ------------------------------------------------------------------------
def _scale(unit: str) -> tuple[float, int]:
    return (100.0, 2) if unit == "fraction" else (1.0, 3)


_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def unit_text(unit: str) -> str:
    """A metric unit as printed in text tables: fraction -> %, m^2 -> m²."""
    if unit == "fraction":
        return "%"
    base, sep, power = unit.partition("^")
    return base + power.translate(_SUPERSCRIPT) if sep else unit


def _num(v: float, unit: str) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    k, d = _scale(unit)
    return f"{k * v:.{d}f}"


@dataclass
class Parts:
    """The pieces of one table cell, before markup."""

    value: str
    best: bool = False
    ci: str = ""
    change: str = ""
    tie: bool = False
    title: str = ""


def cell_parts(row: pd.Series, col: ShownColumn, best: dict[str, float], ci: str, alpha: float) -> Parts:
    m, unit = col.metric, col.unit
    v = row.get(m, math.nan)
    if v is None or not math.isfinite(v):
        return Parts("-")
    p = Parts(_num(v, unit), best=best.get(m) == v)
    lo, hi = row.get(f"{m}_lo", math.nan), row.get(f"{m}_hi", math.nan)
    if math.isfinite(lo) and math.isfinite(hi):
        k, d = _scale(unit)
        if ci == "pm":
            p.ci = f"±{k * (hi - lo) / 2:.{d}f}"
        elif ci == "interval":
            p.ci = f"[{_num(lo, unit)}, {_num(hi, unit)}]"
        p.title = f"95% CI [{_num(lo, unit)}, {_num(hi, unit)}]"
    rel, pv = row.get(f"{m}_rel", math.nan), row.get(f"{m}_p", math.nan)
    if rel is not None and math.isfinite(rel):
        p.change = f"{100 * rel:+.0f} %"
        p.tie = not (pv is not None and math.isfinite(pv) and pv < alpha)
        p.title += f"; {p.change} vs reference, p = {pv:.3g}"
    return p


def _header_label(c: ShownColumn) -> str:
    arrow = "↓" if c.better == Better.LOWER else "↑"
    u = unit_text(c.unit)
    return f"{c.label} {arrow}" + (f" ({u})" if u else "")


def _show_failed(t: Table) -> bool:
    return any(len(g.rows) and g.rows["failed"].fillna(0).astype(int).gt(0).any() for g in t.groups + t.partial)


def _label(row: pd.Series, group: Group) -> str:
    v = row["variant"]
    return group.short.get(v, v) + (" (ref)" if v == group.reference else "")


def footnote_lines(t: Table) -> list[str]:
    """``¹ copilot4d-token-copy trained on synthetic-town-realistic:train, checkpoint sha256
    84120cdf``: one line per footnote."""
    return [f"{marker} {note}" for marker, note in t.footnotes]


# -- Markdown --------------------------------------------------------------------------
def _md_cell(p: Parts) -> str:
    s = f"**{p.value}**" if p.best else p.value
    if p.ci:
        s += f" {p.ci}"
    if p.change:
        s += f" ({p.change}{'†' if p.tie else ''})"
    return s


def _md_groups(t: Table, groups: list[Group], level: str) -> list[str]:
    failed = _show_failed(t)
    head = ["method", "n"] + (["failed"] if failed else []) + [md_text(_header_label(c)) for c in t.columns]
    out = []
    for g in groups:
        out += [f"{level} {md_text(g.title)}", "", "| " + " | ".join(head) + " |",
                "|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|"]
        for _, r in g.rows.iterrows():
            cells = [md_text(_label(r, g)), str(int(r["samples"]))] + ([str(int(r["failed"]))] if failed else [])
            cells += [_md_cell(cell_parts(r, c, g.best, t.ci, t.alpha)) for c in t.columns]
            out.append("| " + " | ".join(cells) + " |")
        out.append("")
    return out


def markdown(t: Table, heading: str = "#") -> str:
    """The table as Markdown; every name, label, title and note in it is escaped (``escape.md_text``)."""
    lines = [f"{heading} {md_text(t.heading)}: {md_text(t.preset.title)}", ""]
    lines += [f"**{md_text(t.scope)}**", ""] if t.scope else []
    lines += [f"- {md_text(x)}" for x in t.legend] + [""]
    lines += [f"> note: {md_text(n)}" for n in t.notes] + ([""] if t.notes else [])
    if not t.groups and t.empty_note:
        lines += [t.empty_note, ""]
    lines += _md_groups(t, t.groups, heading + "#")
    if t.partial:
        lines += [f"{heading}# PARTIAL runs (--limit): the first N samples only, not comparable with the tables above", ""]
        lines += _md_groups(t, t.partial, heading + "##")
    lines += [f"{md_text(x)}  " for x in footnote_lines(t)]
    return "\n".join(lines).rstrip() + "\n"


# -- plain text (the terminal) ---------------------------------------------------------
def text(t: Table) -> str:
    """A compact fixed-width summary: the preset's columns with their intervals."""
    out = []
    for title, groups in (("", t.groups), ("PARTIAL (--limit) ", t.partial)):
        for g in groups:
            head = ["method", "n"] + [_header_label(c) for c in t.columns]
            rows = []
            for _, r in g.rows.iterrows():
                cells = [_label(r, g), str(int(r["samples"]))]
                for c in t.columns:
                    p = cell_parts(r, c, g.best, t.ci, t.alpha)
                    s = ("*" if p.best else "") + p.value + (f" {p.ci}" if p.ci else "")
                    cells.append(s + (f" {p.change}{'†' if p.tie else ''}" if p.change else ""))
                rows.append(cells)
            widths = [max(len(x[i]) for x in [head] + rows) for i in range(len(head))]
            fmt = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
            out += [title + g.title, fmt(head)] + [fmt(r) for r in rows] + [""]
    if out:
        out.append("*: best in its column; ±: half the 95 % interval; +x %: against the reference; †: not significant")
        out += footnote_lines(t)
    return "\n".join(out)


# -- LaTeX -----------------------------------------------------------------------------
_TEX_ESCAPES = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def tex_escape(s: str) -> str:
    return "".join(_TEX_ESCAPES.get(ch, ch) for ch in str(s))


_TEX_SYMBOLS = {"±": r"$\pm$", "≥": r"$\geq$", "↓": r"$\downarrow$", "↑": r"$\uparrow$", "†": r"$^\dagger$", ">=": r"$\geq$",
                "<=": r"$\leq$", "<": r"$<$", ">": r"$>$",
                **{sup: f"$^{d}$" for d, sup in zip("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹")}}


def tex_text(s: str) -> str:
    """Escape ``s`` for LaTeX text mode, with the symbols the legends use as math."""
    out = tex_escape(s)
    for sym, tex in _TEX_SYMBOLS.items():
        out = out.replace(sym, tex)
    return out


def tex_unit(unit: str) -> str:
    """A metric unit in LaTeX math: m -> \\mathrm{m}, m^2 -> \\mathrm{m}^2, fraction -> \\%."""
    if unit == "fraction":
        return r"\%"
    if not unit:
        return ""
    base, _, power = unit.partition("^")
    return rf"$\mathrm{{{tex_escape(base)}}}" + (f"^{{{power}}}" if power else "") + "$"


def _tex_cell(p: Parts) -> tuple[str, float]:
    """The LaTeX of a cell and its approximate printed width in characters of the body font.

    The interval and the change go on a second, smaller line under the value, which keeps
    a six-column table within a portrait A4 page.
    """
    value = rf"\textbf{{{p.value}}}" if p.best else p.value
    extra = []
    if p.ci:
        extra.append(tex_escape(p.ci).replace("±", r"$\pm$"))
    if p.change:
        extra.append("(" + tex_escape(p.change).replace("-", "$-$") + (r"$^\dagger$" if p.tie else "") + ")")
    if not extra:
        return value, len(p.value)
    small = " ".join(extra)
    width = max(len(p.value), 0.85 * (len(p.ci) + len(p.change) + 3 + int(p.tie)))
    return r"\begin{tabular}[t]{@{}r@{}}" + value + r"\\[-2pt]{\scriptsize " + small + r"}\end{tabular}", width


def _tex_head(c: ShownColumn) -> tuple[str, int]:
    """A column header on two lines (split at the space nearest the middle) with its arrow."""
    arrow = r" $\downarrow$" if c.better == Better.LOWER else r" $\uparrow$"
    words = c.label.split(" ")
    if len(words) == 1:
        return tex_text(c.label) + arrow, len(c.label) + 2
    cut = min(range(1, len(words)), key=lambda k: abs(len(" ".join(words[:k])) - len(" ".join(words[k:]))))
    top, bottom = " ".join(words[:cut]), " ".join(words[cut:])
    return (r"\begin{tabular}[b]{@{}r@{}}" + tex_text(top) + r"\\" + tex_text(bottom) + arrow + r"\end{tabular}",
            max(len(top), len(bottom) + 2))


def latex(t: Table) -> tuple[str, str]:
    """The booktabs table (a fragment for \\input) and how it was fitted to an A4 page.

    Needs \\usepackage{booktabs,graphicx,rotating}. The width is estimated from the longest
    entry of each column; a table wider than the text width turns landscape
    (sidewaystable), and one wider than the landscape text width is also scaled down.
    """
    failed = _show_failed(t)
    groups = [(g, False) for g in t.groups] + [(g, True) for g in t.partial]
    ncols = 2 + int(failed) + len(t.columns)
    heads = [_tex_head(c) for c in t.columns]
    head1 = ["Method", "$n$"] + (["failed"] if failed else []) + [h for h, _ in heads]
    head2 = ["", ""] + ([""] if failed else []) + [f"[{tex_unit(c.unit)}]" if c.unit else "" for c in t.columns]
    widths: list[float] = [max(w, 6) for _, w in heads]
    widths = [max(len("Method"), 1), 3] + ([6] if failed else []) + widths
    body = []
    for g, partial in groups:
        body.append(r"\midrule")
        title = ("PARTIAL (--limit), not comparable: " if partial else "") + g.title
        body.append(rf"\multicolumn{{{ncols}}}{{l}}{{\textit{{{tex_text(title)}}}}} \\")
        for _, r in g.rows.iterrows():
            label = _label(r, g)
            cells = [tex_text(label), str(int(r["samples"]))] + ([str(int(r["failed"]))] if failed else [])
            widths[0] = max(widths[0], len(label))
            for i, c in enumerate(t.columns):
                s, w = _tex_cell(cell_parts(r, c, g.best, t.ci, t.alpha))
                cells.append(s)
                j = 2 + int(failed) + i
                widths[j] = max(widths[j], w)
            body.append(" & ".join(cells) + r" \\")
    chars = sum(widths)
    est = _CHAR_PT * chars + _COLSEP_PT * len(widths)  # set in \small
    est_fn = _CHAR_PT * _FOOTNOTE_SCALE * chars + _COLSEP_PT * len(widths)  # in \footnotesize
    env, size, resize = "table", r"\small", False
    fit = "fits the A4 text width"
    if est > A4_TEXTWIDTH_PT and est_fn <= A4_TEXTWIDTH_PT:
        size = r"\footnotesize"
        fit = (f"set in \\footnotesize to fit the A4 text width ({A4_TEXTWIDTH_PT:.0f} pt): "
               f"about {est:.0f} pt wide in \\small, {est_fn:.0f} pt in \\footnotesize")
    elif est > A4_TEXTWIDTH_PT:
        env = "sidewaystable"
        fit = (f"switched to a landscape table (sidewaystable): about {est:.0f} pt wide, "
               f"the A4 text width is {A4_TEXTWIDTH_PT:.0f} pt")
        if est > A4_TEXTHEIGHT_PT:
            resize = True
            fit = (f"switched to a landscape table scaled to the page: about {est:.0f} pt wide, "
                   f"more than the A4 landscape text width of {A4_TEXTHEIGHT_PT:.0f} pt")
    caption = tex_text(t.preset.title) + ". " + tex_text("; ".join(t.legend[:4]))
    lines = [
        f"% {t.heading}, preset {t.preset.name}: {fit}",
        r"% needs \usepackage{booktabs,graphicx,rotating}",
        *([f"% {t.scope}"] if t.scope else []),
        rf"\begin{{{env}}}" + ("[p]" if env == "sidewaystable" else "[t]"),
        r"\centering" + size + r"\setlength{\tabcolsep}{4pt}",
        rf"\caption{{{caption}}}",
        rf"\label{{tab:pcfbench-{tex_escape(t.preset.name)}}}",
    ]
    if resize:
        lines.append(r"\resizebox{\linewidth}{!}{%")
    lines += [rf"\begin{{tabular}}{{l{'r' * (ncols - 1)}}}", r"\toprule",
              " & ".join(head1) + r" \\", " & ".join(head2) + r" \\"]
    lines += body or [r"\midrule", rf"\multicolumn{{{ncols}}}{{l}}{{no complete cells in the store}} \\"]
    lines += [r"\bottomrule", r"\end{tabular}"]
    if resize:
        lines.append("}")
    if t.footnotes:  # under the table, inside its float, in the table's own size
        lines.append(r"\par\smallskip" + r"\\".join(tex_text(x) for x in footnote_lines(t)))
    lines.append(rf"\end{{{env}}}")
    return "\n".join(lines) + "\n", fit


# -- HTML ------------------------------------------------------------------------------
HTML_STYLE = (
    "table.pcf{border-collapse:collapse;font-variant-numeric:tabular-nums;margin-bottom:1.5em}"
    ".pcf th,.pcf td{padding:2px 10px;text-align:right;white-space:nowrap}"
    ".pcf th.method,.pcf td.method{text-align:left}"
    ".pcf tr.group th{text-align:left;font-style:italic;border-top:1px solid #999;padding-top:6px}"
    ".pcf .ci,.pcf .chg{font-size:80%;color:#555}.pcf caption{text-align:left;font-weight:bold}"
    ".partial{border-left:4px solid #c60;padding-left:8px}"
)


def _html_cell(p: Parts) -> str:
    v = _html.escape(p.value)
    s = f"<strong>{v}</strong>" if p.best else v
    if p.ci:
        s += f" <span class='ci'>{_html.escape(p.ci)}</span>"
    if p.change:
        s += f" <span class='chg'>({_html.escape(p.change)}{'†' if p.tie else ''})</span>"
    title = f" title='{_html.escape(p.title)}'" if p.title else ""
    return f"<td{title}>{s}</td>"


def html_table(t: Table, groups: list[Group], caption: str) -> str:
    failed = _show_failed(t)
    head = ["<th class='method'>method</th>", "<th>n</th>"] + (["<th>failed</th>"] if failed else [])
    head += [f"<th>{_html.escape(_header_label(c))}</th>" for c in t.columns]
    rows = []
    for g in groups:
        rows.append(f"<tr class='group'><th colspan='{len(head)}'>{_html.escape(g.title)}</th></tr>")
        for _, r in g.rows.iterrows():
            cells = [f"<td class='method'>{_html.escape(_label(r, g))}</td>", f"<td>{int(r['samples'])}</td>"]
            cells += [f"<td>{int(r['failed'])}</td>"] if failed else []
            cells += [_html_cell(cell_parts(r, c, g.best, t.ci, t.alpha)) for c in t.columns]
            rows.append("<tr>" + "".join(cells) + "</tr>")
    return (f"<table class='pcf'><caption>{_html.escape(caption)}</caption><thead><tr>{''.join(head)}</tr></thead>"
            f"<tbody>\n" + "\n".join(rows) + "\n</tbody></table>")


def html_page(t: Table) -> str:
    parts = [f"<h1>{_html.escape(t.heading)}: {_html.escape(t.preset.title)}</h1>"]
    parts += [f"<p class='scope'><strong>{_html.escape(t.scope)}</strong></p>"] if t.scope else []
    parts += ["<ul>"]
    parts += [f"<li>{_html.escape(x)}</li>" for x in t.legend] + ["</ul>"]
    parts += [f"<p class='note'>note: {_html.escape(n)}</p>" for n in t.notes]
    if t.groups:
        parts.append(html_table(t, t.groups, t.preset.title))
    elif t.empty_note:
        note = _html.escape(t.empty_note).split("`")  # `code` spans as <code>
        parts.append("<p>" + "".join(f"<code>{x}</code>" if i % 2 else x for i, x in enumerate(note)) + "</p>")
    if t.partial:
        parts.append("<div class='partial'><h2>PARTIAL runs (--limit): the first N samples only, "
                     "not comparable with the table above</h2>")
        parts.append(html_table(t, t.partial, "partial runs") + "</div>")
    parts += [f"<p class='footnote'>{_html.escape(x)}</p>" for x in footnote_lines(t)]
    return ("<!doctype html><html><head><meta charset='utf-8'>"
            f"<title>{_html.escape(t.heading)}: {_html.escape(t.preset.title)}</title>"
            f"<style>body{{font-family:sans-serif}}{HTML_STYLE}</style></head><body>\n"
            + "\n".join(parts) + "\n</body></html>\n")
