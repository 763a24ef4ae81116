"""The HTML report: one self-contained page (no network) with the leaderboard tables, their
intervals and comparisons, sortable columns, the figures and each cell's provenance.

Everything is inline: the style, a small script, the figures as ``data:image/png;base64``
URIs. Each row group is its own ``<tbody>``; clicking a column header sorts the rows of every
group by that column (again: the other way), and the page opens sorted when its address ends
in ``#sort=COLUMN`` or ``#sort=COLUMN:desc`` (a link to a sorted view). Every row links to its
cell's provenance in the footer: harness, protocol, method and metric versions, git commit,
dataset fingerprint, checkpoint sha256 (trained methods) and the date its rows were written.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

import pandas as pd

from pcfbench.reporting import tables

PROVENANCE_COLUMNS = (
    ("prov_harness_version", "harness"), ("prov_protocol_version", "protocol"), ("prov_method_version", "method"),
    ("prov_metric_versions", "metrics"), ("prov_git_commit", "git commit"), ("prov_data_fingerprint", "dataset fingerprint"),
    ("prov_checkpoint_sha256", "checkpoint sha256"), ("prov_date", "date"),
)

STYLE = tables.HTML_STYLE + (
    "body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1500px}"
    ".pcf thead th{cursor:pointer;user-select:none;background:#f3f3f3}"
    ".pcf thead th[aria-sort=ascending]::after{content:' \\25B2'}"
    ".pcf thead th[aria-sort=descending]::after{content:' \\25BC'}"
    ".pcf tbody tr:hover td{background:#fafae8}.pcf td a{text-decoration:none;color:#36c;font-size:80%}"
    "figure{margin:0 0 1.5em 0}figure img{max-width:100%;max-height:90vh;border:1px solid #ddd}"
    "figcaption{font-size:90%;color:#444}table.prov{font-size:80%;border-collapse:collapse}"
    "table.prov td,table.prov th{border-bottom:1px solid #eee;padding:2px 6px;text-align:left;vertical-align:top}"
    "table.prov tr:target{background:#fff3b0}code{font-size:90%}"
)

# Sorts the rows of each <tbody> of a table by the data-v of the clicked column (numbers;
# a missing value sorts last either way); #sort=KEY[:desc] applies a sort on load. Once the
# page has loaded, <body data-figures-shown> counts the figures the browser could decode.
SCRIPT = """
(function(){
function sortBy(table, key, desc){
  var heads = table.tHead.rows[0].cells, col = -1;
  for (var i = 0; i < heads.length; i++) {
    var on = heads[i].dataset.key === key;
    if (on) col = i;
    heads[i].removeAttribute('aria-sort');
    if (on) heads[i].setAttribute('aria-sort', desc ? 'descending' : 'ascending');
  }
  if (col < 0) return false;
  Array.prototype.forEach.call(table.tBodies, function(body){
    var rows = Array.prototype.filter.call(body.rows, function(r){ return r.classList.contains('cell'); });
    rows.sort(function(a, b){
      var x = a.cells[col].dataset.v, y = b.cells[col].dataset.v;
      var nx = (x === undefined || x === ''), ny = (y === undefined || y === '');
      if (nx || ny) return nx - ny;
      var fx = parseFloat(x), fy = parseFloat(y), c;
      if (isNaN(fx) || isNaN(fy)) c = x < y ? -1 : x > y ? 1 : 0; else c = fx - fy;
      return desc ? -c : c;
    });
    rows.forEach(function(r){ body.appendChild(r); });
  });
  return true;
}
function fromHash(){
  var m = /sort=([^:&]+)(:desc)?/.exec(decodeURIComponent(location.hash));
  if (!m) return;
  document.querySelectorAll('table.pcf.sortable').forEach(function(t){ sortBy(t, m[1], !!m[2]); });
}
// a click sets the address's #sort=, and the hashchange sorts: one path for both
document.querySelectorAll('table.pcf.sortable').forEach(function(t){
  Array.prototype.forEach.call(t.tHead.rows[0].cells, function(th){
    th.addEventListener('click', function(){
      var desc = th.getAttribute('aria-sort') === 'ascending';
      location.hash = 'sort=' + th.dataset.key + (desc ? ':desc' : '');
    });
  });
});
fromHash();
window.addEventListener('hashchange', fromHash);
window.addEventListener('load', function(){
  var ok = Array.prototype.filter.call(document.images, function(i){ return i.complete && i.naturalWidth > 0; });
  document.body.dataset.figuresShown = String(ok.length);
});
document.body.dataset.ready = '1';
})();
"""


def data_uri(path: Path) -> str:
    """A PNG (or SVG) file as a data URI."""
    mime = "image/svg+xml" if path.suffix == ".svg" else "image/png"
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _value(row: pd.Series, key: str) -> str:
    v = row.get(key)
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return repr(float(v)) if isinstance(v, float) else str(v)


def _table(t: tables.Table, groups: list[tables.Group], caption: str, ids: dict[str, int]) -> str:
    e = html.escape
    head = [("method", "method", "method"), ("n", "samples", ""), ("failed", "failed", "")]
    head += [(tables._header_label(c), c.metric, "") for c in t.columns]
    ths = "".join(f"<th data-key='{e(k)}' class='{cls}' title='click to sort'>{tables.html_head(label)}</th>"
                  for label, k, cls in head)
    bodies = []
    for g in groups:
        rows = [f"<tr class='group'><th colspan='{len(head)}'>{e(g.title)}</th></tr>"]
        for _, r in g.rows.iterrows():
            n = ids.setdefault(str(r["cell_dir"]), len(ids) + 1)
            prov = "; ".join(f"{label} {r.get(k)}" for k, label in PROVENANCE_COLUMNS if r.get(k))
            cells = [f"<td class='method' data-v='{e(tables._label(r, g))}'>{e(tables._label(r, g))} "
                     f"<a href='#cell-{n}' title='{e(prov)}'>[{n}]</a></td>",
                     f"<td data-v='{int(r['samples'])}'>{int(r['samples'])}</td>",
                     f"<td data-v='{int(r['failed'])}'>{int(r['failed'])}</td>"]
            for c in t.columns:
                cell = tables._html_cell(tables.cell_parts(r, c, g.best, t.ci, t.alpha))
                cells.append(cell.replace("<td", f"<td data-v='{e(_value(r, c.metric))}'", 1))
            rows.append(f"<tr class='cell' id='row-{n}'>" + "".join(cells) + "</tr>")
        bodies.append("<tbody>\n" + "\n".join(rows) + "\n</tbody>")
    return (f"<div class='pcf-wrap'><table class='{tables.html_class(t)} sortable'><caption>{e(caption)}</caption>"
            f"<thead><tr>{ths}</tr></thead>\n" + "\n".join(bodies) + "</table></div>")


def _provenance(frames: list[pd.DataFrame], ids: dict[str, int]) -> str:
    e = html.escape
    rows = {}
    for df in frames:
        for _, r in df.iterrows():
            n = ids.get(str(r["cell_dir"]))
            if n is None:
                continue
            where = f"{r['dataset']} / {r['split']} / {r['setting']}" + (
                f", limit={int(r['limit'])}" if r.get("partial") and not pd.isna(r.get("limit")) else "")
            cells = [f"<td>[{n}]</td>", f"<td>{e(str(r['variant']))}</td>", f"<td>{e(where)}</td>"]
            for k, _ in PROVENANCE_COLUMNS:
                v = str(r.get(k) or "")
                cells.append(f"<td><code>{e(v)}</code></td>" if v else "<td>-</td>")
            rows[n] = f"<tr id='cell-{n}'>" + "".join(cells) + "</tr>"
    head = "".join(f"<th>{e(x)}</th>" for x in ["cell", "variant", "dataset / split / setting"]
                   + [label for _, label in PROVENANCE_COLUMNS])
    body = "\n".join(rows[n] for n in sorted(rows))
    return f"<table class='prov'><thead><tr>{head}</tr></thead><tbody>\n{body}\n</tbody></table>"


def page(t: tables.Table, lb, figures: dict[str, Path] | None = None, generated: str = "") -> str:
    """The page of table ``t`` (``tables.build`` of leaderboard ``lb``) with ``figures``
    (``{name: path}``, PNGs embedded, in the given order)."""
    e = html.escape
    ids: dict[str, int] = {}
    parts = [f"<h1>{e(t.heading)}: {e(t.preset.title)}</h1>"]
    parts += [f"<p class='scope'><strong>{e(t.scope)}</strong></p>"] if t.scope else []
    parts += ["<ul class='legend'>"]
    parts += [f"<li>{e(x)}</li>" for x in t.legend + ["click a column header to sort the rows of every group by it"]]
    parts.append("</ul>")
    parts += [f"<p class='note'>note: {e(n)}</p>" for n in t.notes]
    if t.groups:
        parts.append(_table(t, t.groups, t.preset.title, ids))
    elif t.empty_note:
        parts.append(f"<p>{e(t.empty_note)}</p>")
    if t.partial:
        parts.append("<div class='partial'><h2>PARTIAL runs (--limit): the first N samples only, "
                     "not comparable with the table above</h2>")
        parts.append(_table(t, t.partial, "partial runs", ids) + "</div>")
    parts += [f"<p class='footnote'>{e(x)}</p>" for x in tables.footnote_lines(t)]
    if len(getattr(lb, "incomplete", [])):
        parts.append("<h2>Incomplete cells (not ranked)</h2><ul>")
        for _, r in lb.incomplete.iterrows():
            parts.append(f"<li>{e(r['dataset'])} / {e(r['split'])} / {e(r['setting'])} {e(r['variant'])}: "
                         f"{e(str(r['coverage']))} samples scored, {int(r['failed'])} failed "
                         "(<code>pcfbench failures</code> lists them)</li>")
        parts.append("</ul>")
    pngs = [(name, p) for name, p in (figures or {}).items() if Path(p).suffix == ".png"]
    if pngs:
        parts.append("<h2>Figures</h2>")
        for name, p in pngs:
            stem = Path(name).stem
            parts.append(f"<figure id='fig-{e(stem)}'><img alt='{e(stem)}' src='{data_uri(Path(p))}'>"
                         f"<figcaption>{e(stem)} (figures/{e(stem)}.svg)</figcaption></figure>")
    parts.append("<h2 id='provenance'>Provenance of each cell</h2>")
    parts.append(_provenance([lb.table, lb.partial], ids))
    if generated:
        parts.append(f"<p class='generated'>{e(generated)}</p>")
    return ("<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<title>{e(t.heading)}: {e(t.preset.title)}</title><style>{STYLE}</style></head><body>\n"
            + "\n".join(parts) + f"\n<script>{SCRIPT}</script>\n</body></html>\n")
