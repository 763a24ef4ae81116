"""The transfer table: trained methods scored on data other than their training data, in the
layout of Copilot4D's Table 5 ("[AV2 -> KITTI] 1s Prediction": a block per evaluation dataset
and horizon, a row per method and training data, the paper's columns Chamfer within the ROI,
L1 Mean, AbsRel (mean) and Chamfer over the whole sweep).

A block holds every method scored on the same data, setting and samples as a trained cell, so
the untrained baselines (copy-last, ray casting) stand beside it with training data "-". Rows
come from :func:`pcfbench.reporting.report.collect`'s leaderboard: the same flat means as the
leaderboard; cells run with ``--limit`` form their own blocks, marked as partial.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from pcfbench.reporting import tables
from pcfbench.reporting.escape import md_text, write_csv

#: Table 5's columns: (metric, header).
COLUMNS = (("chamfer_nf", "Chamfer"), ("l1_mean", "L1 Mean"), ("absrel_mean", "AbsRel"), ("chamfer", "Chamfer (full)"))
BLOCK = ["dataset", "split", "setting", "policy", "limit"]


def transfer_rows(lb) -> pd.DataFrame:
    """One row per cell of every block that holds a trained cell: the block keys, the method
    (variant without its training suffix), ``train_on`` ("" for untrained methods), the
    checkpoint and Table 5's metrics. Empty when the store holds no trained cell."""
    frames = [f for f in (lb.table, lb.partial) if len(f) and "train_on" in f]
    if not frames:
        return pd.DataFrame()
    df = pd.concat(frames, ignore_index=True)
    df["_limit"] = df["limit"].fillna(-1)
    keep = []
    for _, g in df.groupby(["dataset", "split", "setting", "policy", "_limit"], sort=True):
        if (g["train_on"] != "").any():
            keep.append(g)
    if not keep:
        return pd.DataFrame()
    out = pd.concat(keep, ignore_index=True)
    out["method_label"] = [v.split(" [trained on ")[0] for v in out["variant"]]
    out["trained"] = out["train_on"] != ""
    out = out.sort_values(["dataset", "split", "setting", "policy", "_limit", "trained", "train_on", "method_label"])
    cols = ["dataset", "split", "setting", "policy", "limit", "horizon_s", "method_label", "train_on",
            "checkpoint_sha256", "on_training_data", "samples"] + [m for m, _ in COLUMNS if m in out]
    return out.reindex(columns=cols).reset_index(drop=True)


def markdown(rows: pd.DataFrame, units: dict[str, str], scope: str = "",
             higher_is_better: dict[str, bool] | None = None) -> str:
    """The transfer table as Markdown, every name in it escaped (``escape.md_text``).
    ``scope``: the line that says which filters made a filtered view (``Leaderboard.scope``);
    ``higher_is_better``: each metric's direction (``Leaderboard.higher_is_better``; a metric
    missing from it is lower-is-better), shown by its column's arrow."""
    up = higher_is_better or {}
    lines = ["# Zero-shot transfer (layout of Copilot4D Table 5)", ""]
    lines += [f"**{md_text(scope)}**", ""] if scope else []
    lines += ["Rows: method and its training data (`-`: the method does not train); a block per evaluation "
              "dataset and horizon. Values are flat means over (sample, future sweep), as in the leaderboard; "
              "↓: lower is better, ↑: higher is better.", ""]
    metrics = [(m, h) for m, h in COLUMNS if m in rows]
    for key, g in rows.groupby(["dataset", "split", "setting", "policy", "limit"], sort=False, dropna=False):
        dataset, split, setting, policy, limit = key
        sources = [md_text(x) for x in sorted({t.split(":")[0] for t in g["train_on"] if t})]
        dataset, split, setting, policy = (md_text(x) for x in (dataset, split, setting, policy))
        horizon = g["horizon_s"].iloc[0]
        title = f"[{', '.join(sources)} → {dataset}] {horizon:g}s Prediction" if pd.notna(horizon) else \
            f"[{', '.join(sources)} → {dataset}] {setting}"
        extra = [f"{split} split", setting] + ([policy] if policy != "full-context" else [])
        if pd.notna(limit):
            extra.append(f"PARTIAL: first {int(limit)} samples")
        lines += [f"## {title} ({', '.join(extra)})", ""]
        head = ["Method", "Trained on"] + [f"{h} {'↑' if up.get(m) else '↓'} ({md_text(tables.unit_text(units.get(m, '')))})"
                                           for m, h in metrics] + ["n"]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for _, r in g.iterrows():
            train = r["train_on"] or "-"
            if r["train_on"]:
                train += f" (ck {r['checkpoint_sha256'][:8]})" + (" ON ITS TRAINING DATA" if r["on_training_data"] else "")
            vals = [tables._num(r[m], units.get(m, "")) for m, _ in metrics]
            lines.append("| " + " | ".join([md_text(r["method_label"]), md_text(train), *vals, str(int(r["samples"]))]) + " |")
        lines.append("")
        if g["samples"].nunique() > 1:  # a subset (CellSpec.subset): its means are over fewer samples
            lines += [f"Rows with n below {int(g['samples'].max())} scored a subset of the samples, evenly spaced (the "
                      "default run's for its slowest methods, docs/protocol.md); their means are over their own "
                      "samples.", ""]
    return "\n".join(lines)


def write_transfer(lb, out_dir: Path) -> dict[str, Path]:
    """``transfer.md`` and ``transfer.csv`` under ``out_dir`` when the store holds trained
    cells (stale ones removed otherwise); returns the paths written."""
    out_dir = Path(out_dir)
    rows = transfer_rows(lb)
    paths = {"transfer_md": out_dir / "transfer.md", "transfer_csv": out_dir / "transfer.csv"}
    if not len(rows):
        for p in paths.values():
            p.unlink(missing_ok=True)
        return {}
    paths["transfer_md"].write_text(markdown(rows, lb.units, getattr(lb, "scope", ""), getattr(lb, "higher_is_better", None)))
    write_csv(rows, paths["transfer_csv"])
    return paths
