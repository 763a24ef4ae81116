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

import dataclasses
import html as _html
import itertools
import math
import re
import textwrap
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
_PRESET_KEYS = {"title", "description", "columns", "rank_by", "reported"}
_COLUMN_KEYS = {"metric", "label", "better"}

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
    #: show the published results of a group's dataset, split and setting under it
    #: (``pcfbench.reporting.published``): reference rows, never ranked
    reported: bool = False


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
    reported = data.get("reported", False)
    if not isinstance(reported, bool):
        raise PcfbenchError(f"{where}: reported must be true or false, got {reported!r}")
    return Preset(name, title, columns, rank_by, description, source, reported)


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
    #: published results of this group's dataset, split and setting (``Preset.reported``)
    reported: list = field(default_factory=list)


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
    if preset.reported:  # complete groups only: a partial one is not the paper's sample set
        from pcfbench.reporting.published import reported_for

        for g in groups:
            first = g.rows.iloc[0]
            g.reported = reported_for(first["dataset"], first["split"], first["setting"], first["policy"])
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


#: the line above a group's published rows (``Group.reported``)
REPORTED_TITLE = ("Reported in the papers (their code, their samples; not ranked, in no interval or comparison, "
                  "shown because this group's dataset, split and setting are the papers')")


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
        if g.reported:
            out += [f"{REPORTED_TITLE}:", "", "| " + " | ".join(["method", "source"] + head[2 + failed:]) + " |",
                    "|" + "|".join(["---", "---"] + ["---:"] * len(t.columns)) + "|"]
            out += ["| " + " | ".join([md_text(r.method), md_text(r.source)] + [r.values.get(c.metric, "-") for c in t.columns])
                    + " |" for r in g.reported]
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
            reported = [[f"{r.method} (reported: {r.source})", "-"] + [r.values.get(c.metric, "-") for c in t.columns]
                        for r in g.reported]
            widths = [max(len(x[i]) for x in [head] + rows + reported) for i in range(len(head))]
            fmt = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
            out += [title + g.title, fmt(head)] + [fmt(r) for r in rows] + [fmt(r) for r in reported] + [""]
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


@dataclass
class _TexCell:
    """A LaTeX table cell: its main line and the lines under it (text, unescaped)."""

    main: str
    subs: tuple[str, ...] = ()
    bold: bool = False
    align: str = "r"
    #: the lines under the main one are \scriptsize (a value's interval and change, a method's
    #: options); False: the table's size (a header's second line)
    small: bool = True

    def tex(self) -> str:
        main = rf"\textbf{{{tex_text(self.main)}}}" if self.bold else tex_text(self.main)
        if not self.subs:
            return main
        subs = "".join(r"\\[-2pt]{\scriptsize " + _tex_sub(x) + "}" if self.small else r"\\" + tex_text(x)
                       for x in self.subs)
        return (rf"\begin{{tabular}}[{'t' if self.small else 'b'}]{{@{{}}{self.align}@{{}}}}" + main + subs
                + r"\end{tabular}")

    def width(self, size: str) -> float:
        """Its printed width in pt, estimated on the wide side."""
        sub = _CHAR_PT["scriptsize" if self.small else size]
        return max([_chars(self.main) * _CHAR_PT[size]] + [_chars(x) * sub for x in self.subs])

    def height(self, size: str) -> float:
        return _LINE_PT[size] + _LINE_PT["scriptsize" if self.small else size] * len(self.subs)

    def on_one_line(self) -> _TexCell:
        """A value cell with its interval and change on one small line, not two."""
        return dataclasses.replace(self, subs=(" ".join(self.subs),)) if len(self.subs) > 1 else self


def _chars(s: str) -> int:
    """``s``'s width in average glyphs: an arrow (math, 1 em) counts two."""
    return len(s) + sum(s.count(a) for a in "↓↑±")


def _tex_sub(s: str) -> str:
    return tex_text(s).replace(" -", " $-$").replace("(-", "($-$")


def _value_cell(p: Parts) -> _TexCell:
    """A value with its interval and its change on two small lines under it."""
    change = f"({p.change}{'†' if p.tie else ''})" if p.change else ""
    return _TexCell(p.value, tuple(x for x in (p.ci, change) if x), p.best)


def _wrap(text: str, width: int) -> list[str]:
    """``text`` broken after its commas into lines of at most ``width`` characters where it can."""
    lines: list[str] = []
    for part in text.split(", "):
        if lines and len(lines[-1]) + 2 + len(part) <= width:
            lines[-1] += ", " + part
        else:
            if lines:
                lines[-1] += ","
            lines.append(part)
    return lines


def _label_cell(row: pd.Series, group: Group) -> _TexCell:
    """The row's method name (with its footnote marker and "(ref)") on the main line; its
    options and a scored-on-its-training-data warning on small lines under it, so that the
    first column is as wide as the longest method name, not the longest label."""
    variant, method = str(row["variant"]), str(row.get("method", ""))
    base, marker, own = variant, "", False
    if variant in group.short:  # a trained method's: its bracket is a footnote
        short = group.short[variant].removesuffix(_OWN)
        own = group.short[variant].endswith(_OWN)
        base = variant.split(" [trained on ")[0]
        marker = short[len(base):] if short.startswith(base) else ""
    name, opts = (method, base[len(method):].strip()) if method and base.startswith(method + " (") else (base, "")
    main = name + marker + (" (ref)" if variant == group.reference else "")
    return _TexCell(main, tuple((_wrap(opts, _LABEL_SUB_CHARS) if opts else []) + ([_OWN.strip()] if own else [])),
                    align="l")


def _tex_head(c: ShownColumn) -> _TexCell:
    """A column header on two lines (split at the space nearest the middle) with its arrow."""
    arrow = " ↓" if c.better == Better.LOWER else " ↑"
    words = c.label.split(" ")
    if len(words) == 1:
        return _TexCell(c.label + arrow)
    cut = min(range(1, len(words)), key=lambda k: abs(len(" ".join(words[:k])) - len(" ".join(words[k:]))))
    return _TexCell(" ".join(words[:cut]), (" ".join(words[cut:]) + arrow,), small=False)


_OWN = " (ON ITS TRAINING DATA)"
# LaTeX page geometry: A4 with 2.5 cm margins (article, 10 pt): 455 x 703 pt of text.
A4_TEXTWIDTH_PT = 455.0
A4_TEXTHEIGHT_PT = 703.0
#: the most of a page a table's float may fill
_FLOAT_HEIGHT_PT = 0.9 * A4_TEXTHEIGHT_PT
#: an average glyph's width per font size, pt (Computer Modern's digits are 0.5 em), rounded up
#: so that the estimate errs wide (tests/reporting/test_table_fit.py compiles the tables)
_CHAR_PT = {"small": 5.0, "footnotesize": 4.5, "scriptsize": 3.9}
_LINE_PT = {"small": 11.0, "footnotesize": 9.5, "scriptsize": 7.0}
_COLSEP_PT = 8.0  # \tabcolsep 4 pt on each side
_LABEL_SUB_CHARS = 30  # a method's options under its name wrap at this many characters
_TITLE_CHARS = 72  # a row group's title wraps at this many characters


@dataclass
class _TexLayout:
    """How a table is set: its font size, each value's interval and change stacked on two
    lines or on one, the metric columns of each table (part), and the widest part in pt."""

    size: str
    stacked: bool
    parts: list[list[int]]
    width: float


def _layouts(fixed_w: dict[str, float], cols: list[list[_TexCell]], least_w: dict[str, float]):
    """Every layout in the order of preference: one table in \\small with each value's
    interval and change on one small line, then on two, then \\footnotesize; then the metric
    columns split into 2, 3, ... tables (each repeating the method column). ``fixed_w``: the
    width of the method and count columns per size; ``cols``: each metric column's cells;
    ``least_w``: the width of the widest row-group title per size (a table is at least that wide)."""
    n = len(cols)
    for k in range(1, max(n, 1) + 1):
        for stacked, size in ((False, "small"), (True, "small"), (True, "footnotesize")):
            widths = [max((c if stacked else c.on_one_line()).width(size) for c in col) + _COLSEP_PT for col in cols]
            parts = _balanced(list(range(n)), widths, k)
            width = max(fixed_w[size] + sum(widths[i] for i in p) for p in parts)
            yield _TexLayout(size, stacked, parts, max(width, least_w[size]))


def _balanced(items: list[int], widths: list[float], k: int) -> list[list[int]]:
    """``items`` cut into ``k`` contiguous parts whose widest part is as narrow as it can be."""
    if not items:
        return [items]
    k = min(k, len(items))
    best: tuple[float, list[list[int]]] | None = None
    for cuts in itertools.combinations(range(1, len(items)), k - 1):
        bounds = [0, *cuts, len(items)]
        parts = [items[a:b] for a, b in zip(bounds, bounds[1:])]
        w = max(sum(widths[i] for i in p) for p in parts)
        if best is None or w < best[0]:
            best = (w, parts)
    return best[1] if best else [items]


def latex(t: Table) -> tuple[str, str]:
    """The booktabs table (a fragment for \\input; needs \\usepackage{booktabs}) and a line
    saying how it was fitted to a portrait A4 page. Nothing is scaled or turned.

    The width is estimated from the longest entry of each column. The first that fits the text
    width of: \\small with each value's interval and change on one small line under it, on two
    lines, \\footnotesize; else the metric columns are split into tables of fewer columns (each
    repeating the method column). A table taller than a page is split between row groups (a
    group taller than a page, between its rows, marked "continued").
    """
    failed = _show_failed(t)
    groups = [(g, False) for g in t.groups] + [(g, True) for g in t.partial]
    heads = [_tex_head(c) for c in t.columns]
    units = [f"[{tex_unit(c.unit)}]" if c.unit else "" for c in t.columns]
    rows = []  # (group index, label cell, count cells, value cells)
    for gi, (g, _) in enumerate(groups):
        for _, r in g.rows.iterrows():
            counts = [_TexCell(str(int(r["samples"])))] + ([_TexCell(str(int(r["failed"])))] if failed else [])
            rows.append((gi, _label_cell(r, g), counts,
                         [_value_cell(cell_parts(r, c, g.best, t.ci, t.alpha)) for c in t.columns]))
    fixed_cols = [[_TexCell("Method", align="l")] + [r[1] for r in rows], [_TexCell("n")] + [r[2][0] for r in rows]]
    fixed_cols += [[_TexCell("failed")] + [r[2][1] for r in rows]] if failed else []
    fixed_w = {s: sum(max(c.width(s) for c in col) + _COLSEP_PT for col in fixed_cols) for s in ("small", "footnotesize")}
    unit_cells = [_TexCell(f"[{unit_text(c.unit)}]") for c in t.columns]
    value_cols = [[heads[i], unit_cells[i]] + [r[3][i] for r in rows] for i in range(len(t.columns))]
    titles = [_group_title(g, partial) for g, partial in groups]
    least_w = {s: max([len(x) * _CHAR_PT[s] + _COLSEP_PT for lines in titles for x in lines], default=0.0)
               for s in ("small", "footnotesize")}
    layout = one_line = None
    for layout in _layouts(fixed_w, value_cols, least_w):
        one_line = one_line or layout.width
        if layout.width <= A4_TEXTWIDTH_PT:
            break
    assert layout is not None and one_line is not None
    blocks = _row_blocks(t, titles, rows, layout.size)
    parts = layout.parts
    fit = f"fits the A4 text width ({A4_TEXTWIDTH_PT:.0f} pt) in \\{layout.size}: about {layout.width:.0f} pt wide"
    if layout.stacked:
        fit += f", each value's interval and change on two small lines under it ({one_line:.0f} pt on one line)"
    if len(parts) > 1:
        fit = (f"split into {len(parts)} tables of columns to fit the A4 text width ({A4_TEXTWIDTH_PT:.0f} pt): "
               f"the widest about {layout.width:.0f} pt in \\{layout.size} ({one_line:.0f} pt as one table)")
    if layout.width > A4_TEXTWIDTH_PT:
        fit = (f"WIDER than the A4 text width ({A4_TEXTWIDTH_PT:.0f} pt) even with one metric column per table: "
               f"about {layout.width:.0f} pt in \\{layout.size}, for its long method names")
    if len(blocks) > 1:
        fit += f"; split into {len(blocks)} tables of rows to fit the A4 text height ({A4_TEXTHEIGHT_PT:.0f} pt)"
    out = [f"% {_tex_comment(t.heading)}, preset {_tex_comment(t.preset.name)}: {fit}", r"% needs \usepackage{booktabs}"]
    out += [f"% {_tex_comment(t.scope)}"] if t.scope else []
    floats = [(part, block) for part in parts for block in blocks]
    for n, (part, block) in enumerate(floats, 1):
        out += _tex_float(t, titles, rows, block, part, heads, units, layout, failed, n, len(floats))
    return "\n".join(out) + "\n", fit


def _group_title(g: Group, partial: bool) -> list[str]:
    """A row group's title on lines of at most 72 characters (the title of a group in a
    narrow table would otherwise set the width of its last column)."""
    title = ("PARTIAL (--limit), not comparable: " if partial else "") + g.title
    return textwrap.wrap(title, _TITLE_CHARS, break_long_words=False) or [""]


def _row_blocks(t: Table, titles: list[list[str]], rows, size: str) -> list[list[tuple[int, list[int]]]]:
    """The rows of each table float, as (group index, row indices) pairs: every row in one
    float unless that is taller than a page (estimated), then split before the row that
    would overflow it (a group's title is repeated, "continued", in the next)."""
    caption = len(t.preset.title + ". " + "; ".join(t.legend[:4])) * _CHAR_PT["small"] / A4_TEXTWIDTH_PT
    overhead = (caption + 5) * _LINE_PT["small"] + (len(t.footnotes) + 1) * _LINE_PT[size]
    blocks: list[list[tuple[int, list[int]]]] = [[]]
    used = overhead
    for i, (gi, label, _, values) in enumerate(rows):
        h = max(c.height(size) for c in [label, *values]) + 1  # a row's strut
        new_group = not blocks[-1] or blocks[-1][-1][0] != gi
        title_h = _LINE_PT[size] * len(titles[gi]) + 4
        if blocks[-1] and used + h + (title_h if new_group else 0) > _FLOAT_HEIGHT_PT:
            blocks.append([])
            used, new_group = overhead, True
        if new_group:
            blocks[-1].append((gi, []))
            used += title_h
        blocks[-1][-1][1].append(i)
        used += h
    return blocks


def _tex_comment(s: str) -> str:
    """``s`` on one line: a line break in a name would end the % comment and run as TeX."""
    return " ".join(str(s).splitlines())


def _tex_float(t: Table, titles: list[list[str]], rows, block, part: list[int], heads: list[_TexCell], units: list[str],
               layout: _TexLayout, failed: bool, n: int, total: int) -> list[str]:
    """Table float ``n`` of ``total``: the rows of ``block`` ((group index, row indices) pairs),
    the metric columns ``part``; the first has the legend in its caption, the others say
    which part they are."""
    ncols = 2 + int(failed) + len(part)
    caption = tex_text(t.preset.title)
    if n == 1:
        caption += ". " + tex_text("; ".join(t.legend[:4]))
    else:
        caption += tex_text(f" (continued, {n} of {total}: {', '.join(t.columns[i].label for i in part)})")
    head1 = ["Method", "$n$"] + (["failed"] if failed else []) + [heads[i].tex() for i in part]
    head2 = [""] * (2 + int(failed)) + [units[i] for i in part]
    lines = [r"\begin{table}[tp]", rf"\centering\{layout.size}\setlength{{\tabcolsep}}{{4pt}}",
             rf"\caption{{{caption}}}", rf"\label{{tab:pcfbench-{tex_escape(t.preset.name)}{'' if n == 1 else f'-{n}'}}}",
             rf"\begin{{tabular}}{{l{'r' * (ncols - 1)}}}", r"\toprule",
             " & ".join(head1) + r" \\", " & ".join(head2) + r" \\"]
    markers: set[str] = set()
    for gi, members in block:
        title = list(titles[gi])
        if members[0] != next(i for i, r in enumerate(rows) if r[0] == gi):
            title[-1] += " (continued)"
        lines.append(r"\midrule")
        lines += [rf"\multicolumn{{{ncols}}}{{l}}{{\textit{{{tex_text(x)}}}}} \\" for x in title]
        for i in members:
            _, label, counts, values = rows[i]
            cells = [label, *counts] + [values[j] if layout.stacked else values[j].on_one_line() for j in part]
            markers |= set(label.main) & set(_SUPERSCRIPT_DIGITS)
            lines.append(" & ".join(c.tex() for c in cells) + r" \\")
    if not block:
        lines += [r"\midrule", rf"\multicolumn{{{ncols}}}{{l}}{{no complete cells in the store}} \\"]
    lines += [r"\bottomrule", r"\end{tabular}"]
    notes = [f"{m} {x}" for m, x in t.footnotes if set(m) & markers]
    if notes:  # under the table, inside its float, in the table's own size
        lines.append(r"\par\smallskip" + r"\\".join(tex_text(x) for x in notes))
    lines.append(r"\end{table}")
    return lines


_SUPERSCRIPT_DIGITS = "⁰¹²³⁴⁵⁶⁷⁸⁹"


# -- HTML ------------------------------------------------------------------------------
# A table fits a 1400 px window: each value's interval and change on a small line under it,
# headers wrap (at spaces, after _ and @); values and method names never do. A table wider
# than its page scrolls inside its own box (a scroll bar, nothing cut off) with the method
# column held in view.
HTML_STYLE = (
    ".pcf-wrap{overflow-x:auto;max-width:100%;margin-bottom:1.5em}"
    "table.pcf{border-collapse:collapse;font-variant-numeric:tabular-nums}"
    ".pcf th,.pcf td{padding:2px 8px;text-align:right;white-space:nowrap;vertical-align:top}"
    ".pcf thead th{white-space:normal;vertical-align:bottom;min-width:4em}"
    ".pcf th.method,.pcf td.method{text-align:left}"
    ".pcf td.method{position:sticky;left:0;background:#fff}"
    ".pcf tr.group th{text-align:left;font-style:italic;border-top:1px solid #999;padding-top:6px;white-space:normal}"
    ".pcf .sub{display:block;font-size:80%;color:#555}.pcf caption{text-align:left;font-weight:bold}"
    ".pcf.stacked .chg{display:block}"
    ".partial{border-left:4px solid #c60;padding-left:8px}"
)


#: a table with more metric columns than this stacks each value's change under its interval
HTML_STACK_COLUMNS = 7


def html_class(t: Table) -> str:
    """The table's classes: ``pcf``, and ``stacked`` when it has many metric columns."""
    return "pcf stacked" if len(t.columns) > HTML_STACK_COLUMNS else "pcf"


def html_head(label: str) -> str:
    """A column header as HTML: escaped, with break opportunities after _ and @ too."""
    return _html.escape(label).replace("_", "_<wbr>").replace("@", "@<wbr>")


def _html_cell(p: Parts) -> str:
    v = _html.escape(p.value)
    s = f"<strong>{v}</strong>" if p.best else v
    sub = [f"<span class='ci'>{_html.escape(p.ci)}</span>"] if p.ci else []
    sub += [f"<span class='chg'>({_html.escape(p.change)}{'†' if p.tie else ''})</span>"] if p.change else []
    if sub:  # on a line of its own under the value
        s += f"<span class='sub'>{' '.join(sub)}</span>"
    title = f" title='{_html.escape(p.title)}'" if p.title else ""
    return f"<td{title}>{s}</td>"


def html_table(t: Table, groups: list[Group], caption: str) -> str:
    failed = _show_failed(t)
    head = ["<th class='method'>method</th>", "<th>n</th>"] + (["<th>failed</th>"] if failed else [])
    head += [f"<th>{html_head(_header_label(c))}</th>" for c in t.columns]
    rows = []
    for g in groups:
        rows.append(f"<tr class='group'><th colspan='{len(head)}'>{_html.escape(g.title)}</th></tr>")
        for _, r in g.rows.iterrows():
            cells = [f"<td class='method'>{_html.escape(_label(r, g))}</td>", f"<td>{int(r['samples'])}</td>"]
            cells += [f"<td>{int(r['failed'])}</td>"] if failed else []
            cells += [_html_cell(cell_parts(r, c, g.best, t.ci, t.alpha)) for c in t.columns]
            rows.append("<tr>" + "".join(cells) + "</tr>")
        if g.reported:
            rows.append(f"<tr class='reported'><td colspan='{len(head)}'>{_html.escape(REPORTED_TITLE)}</td></tr>")
            pad = "<td></td>" * (1 + failed)
            for r in g.reported:
                rows.append(f"<tr class='reported'><td class='method'>{_html.escape(f'{r.method} ({r.source})')}</td>{pad}"
                            + "".join(f"<td>{_html.escape(r.values.get(c.metric, '-'))}</td>" for c in t.columns) + "</tr>")
    return (f"<div class='pcf-wrap'><table class='{html_class(t)}'><caption>{_html.escape(caption)}</caption>"
            f"<thead><tr>{''.join(head)}</tr></thead><tbody>\n" + "\n".join(rows) + "\n</tbody></table></div>")


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
