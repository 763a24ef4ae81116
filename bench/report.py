"""Leaderboards regenerated from the store, in the shape of the published tables.

A block per (dataset, split, setting, policy), a row per method (+ options), a column per
metric, the sample count beside each row. Partial cells (``--limit``) are left out, and a
column never mixes metric versions.
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pcfbench.errors import PcfbenchError
from pcfbench.store import Cell, iter_cells, spec_from_meta

#: Columns in the order of the published tables; other metrics follow alphabetically.
PREFERRED_ORDER = (
    "chamfer_nf", "chamfer", "l1_mean", "absrel_mean", "l1_median", "absrel_median",
    "chamfer_nf@4docc", "l1@4docc", "absrel@4docc", "l1_ray", "absrel_ray",
)
BLOCK_KEYS = ["dataset", "split", "setting", "policy"]


@dataclass
class Leaderboard:
    table: pd.DataFrame  # one row per cell; metric columns hold flat means over sweeps
    by_step: pd.DataFrame  # one row per (cell, future step)
    metric_columns: list[str]
    units: dict[str, str]


def _method_label(spec) -> str:
    if not spec.options:
        return spec.method
    opts = ",".join(f"{k}={v}" for k, v in sorted(spec.options.items()))
    return f"{spec.method}[{opts}]"


def collect(store_root: Path) -> Leaderboard:
    """Read every complete, non-partial cell under ``store_root``."""
    rows, step_rows = [], []
    versions: dict[str, dict[str, list[str]]] = {}
    units: dict[str, str] = {}
    for cell_dir, meta in iter_cells(store_root):
        if meta.get("status") != "complete" or meta.get("partial"):
            continue
        spec = spec_from_meta(meta)
        df = Cell(store_root, spec).read_rows()
        ok = df[df["status"] == "ok"] if len(df) else df
        metric_versions = meta.get("metric_versions", {})
        units.update(meta.get("metric_units", {}))
        base = {
            "dataset": spec.dataset, "split": spec.split, "setting": spec.setting, "policy": spec.policy,
            "method": _method_label(spec), "method_version": meta.get("method_version"),
            "samples": meta.get("counts", {}).get("ok", 0), "failed": meta.get("counts", {}).get("failed", 0),
            "sweeps": len(ok),
        }
        block = tuple(base[k] for k in BLOCK_KEYS)
        row = dict(base)
        for name, version in metric_versions.items():
            versions.setdefault(name, {}).setdefault(version, []).append(f"{cell_dir} ({'/'.join(block)})")
            values = ok[name].to_numpy(dtype=float) if name in ok else np.array([])
            row[name] = float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")
            row[f"{name}__skipped"] = int((~np.isfinite(values)).sum())
        rows.append(row)
        if len(ok):
            for step, g in ok.groupby("step"):
                srow = dict(base, step=int(step), sweeps=len(g))
                for name in metric_versions:
                    v = g[name].to_numpy(dtype=float) if name in g else np.array([])
                    srow[name] = float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
                step_rows.append(srow)
    mixed = {n: v for n, v in versions.items() if len(v) > 1}
    if mixed:
        lines = []
        for name, by_version in mixed.items():
            for version, cells in sorted(by_version.items()):
                lines.append(f"  {name} v{version}: {len(cells)} cell(s), e.g. {cells[0]}")
        raise PcfbenchError(
            "refusing to mix metric versions in one column:\n" + "\n".join(lines)
            + "\nrerun the older cells with --force (or remove them) so every cell uses the same version"
        )
    table = pd.DataFrame(rows)
    metric_cols = sorted(versions, key=lambda n: (PREFERRED_ORDER.index(n) if n in PREFERRED_ORDER else 99, n))
    if len(table):
        table = table.sort_values(BLOCK_KEYS + ["method"]).reset_index(drop=True)
    return Leaderboard(table, pd.DataFrame(step_rows), metric_cols, units)


def _fmt(value: float, unit: str) -> str:
    if value is None or not np.isfinite(value):
        return "-"
    if unit == "fraction":
        return f"{100 * value:.2f}%"
    return f"{value:.3f}"


def _header(name: str, unit: str) -> str:
    return f"{name} (%)" if unit == "fraction" else (f"{name} ({unit})" if unit else name)


def display_blocks(lb: Leaderboard) -> list[tuple[str, pd.DataFrame]]:
    """(title, formatted table) per block, columns: method, samples, metrics."""
    blocks = []
    if not len(lb.table):
        return blocks
    for key, g in lb.table.groupby(BLOCK_KEYS, sort=True):
        dataset, split, setting, policy = key
        cols = [m for m in lb.metric_columns if m in g and g[m].notna().any()]
        out = pd.DataFrame({"method": g["method"], "samples": g["samples"].astype(int)})
        for m in cols:
            out[_header(m, lb.units.get(m, ""))] = [_fmt(v, lb.units.get(m, "")) for v in g[m]]
        title = f"{dataset} / {split} / {setting}" + ("" if policy == "full-context" else f" ({policy})")
        sweeps = int(g["sweeps"].max())
        title += f" - {int(g['samples'].max())} samples, {sweeps} sweeps"
        blocks.append((title, out.reset_index(drop=True)))
    return blocks


def _markdown(df: pd.DataFrame) -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" if c == "method" else "---:" for c in cols) + "|"]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(str(r[c]) for c in cols) + " |")
    return "\n".join(lines)


def write_reports(store_root: Path, out_dir: Path) -> dict[str, Path]:
    """Write leaderboard.{md,csv,tex,html} and leaderboard_by_step.csv; returns the paths."""
    lb = collect(store_root)
    out_dir.mkdir(parents=True, exist_ok=True)
    blocks = display_blocks(lb)
    paths = {ext: out_dir / f"leaderboard.{ext}" for ext in ("md", "csv", "tex", "html")}
    md = ["# pcfbench leaderboard", ""]
    if not blocks:
        md.append("No complete cells in the store yet: run `pcfbench run` first.")
    md.append("Metric means are flat over (sample, future sweep); `-` means no sweep could be scored.\n")
    for title, df in blocks:
        md += [f"## {title}", "", _markdown(df), ""]
    paths["md"].write_text("\n".join(md) + "\n")
    keep = BLOCK_KEYS + ["method", "method_version", "samples", "failed", "sweeps"] + lb.metric_columns
    csv_table = lb.table[[c for c in keep if c in lb.table]] if len(lb.table) else pd.DataFrame(columns=keep)
    csv_table.to_csv(paths["csv"], index=False)
    tex = []
    for title, df in blocks:
        tex.append(f"% {title}")
        tex.append(df.to_latex(index=False, caption=title.replace("_", r"\_"), escape=True))
    paths["tex"].write_text("\n".join(tex) + "\n")
    body = "".join(f"<h2>{html.escape(t)}</h2>\n{df.to_html(index=False, border=0)}\n" for t, df in blocks)
    paths["html"].write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>pcfbench leaderboard</title>"
        "<style>body{font-family:sans-serif}td,th{padding:2px 8px;text-align:right}</style></head><body>"
        f"<h1>pcfbench leaderboard</h1>\n{body}</body></html>\n"
    )
    paths["by_step"] = out_dir / "leaderboard_by_step.csv"
    lb.by_step.to_csv(paths["by_step"], index=False)
    return paths
