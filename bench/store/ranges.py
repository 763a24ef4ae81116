"""Error by ground-truth range, kept in the store at run time for the report's range figure.

For every scored future sweep the runner records, per 10 m bin of the ground-truth range of
the kept rays, the number of rays and the sums of their L1 and AbsRel errors: the very errors
``l1_mean`` and ``absrel_mean`` average (``SweepContext.ray_errors_wrapped``), so a sweep's
ray-weighted mean over its bins is its stored ``l1_mean``/``absrel_mean``. They are stored
beside the cell's rows (``ranges/`` in the cell folder, :mod:`pcfbench.store.cells`), one row per
(sample, future sweep) with the bins as lists, and the report's figure pools them over every
sample of a cell: it reads the store only, no method runs.

Only cells scoring ``l1_mean`` or ``absrel_mean`` record them (then the errors are computed
anyway); ``pcfbench backfill-ranges`` (:func:`pcfbench.running.backfill.backfill`) recomputes them
for a cell made before the store kept them, re-running its method, as an explicit command.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

#: bin width (m) of the ground-truth range
RANGE_BIN_M = 10.0
#: changes whenever what is stored changes; cell.json's ``range_bins`` says which a cell has
VERSION = "1"
#: the metrics whose per-ray errors are binned: a cell scoring one of them records its ranges
METRICS = ("l1_mean", "absrel_mean")
#: the columns of a range row besides ``sample_id`` and ``step`` (lists, one entry per bin)
LIST_COLUMNS = ("bin", "rays", "l1_sum", "absrel_sum")
BACKFILL_COMMAND = "pcfbench backfill-ranges"


def records(metric_names) -> bool:
    """Whether a cell scoring ``metric_names`` records its range bins."""
    return any(m in METRICS for m in metric_names)


def meta() -> dict[str, Any]:
    """What cell.json says of the range bins of a cell that records them."""
    return {"version": VERSION, "bin_m": RANGE_BIN_M, "errors": "SweepContext.ray_errors_wrapped (l1_mean, absrel_mean)"}


def sweep_bins(ctx) -> dict[str, list]:
    """The bins of one scored sweep (a ``SweepContext``): ``bin`` k is [10 k, 10 (k+1)) m of
    the ground-truth range, ``rays`` its kept rays, ``l1_sum`` / ``absrel_sum`` their errors'
    sums. No bins for a sweep without ground truth or with an empty forecast (as l1_mean)."""
    empty: dict[str, list] = {c: [] for c in LIST_COLUMNS}
    if ctx.gt_points.shape[0] == 0 or ctx.pred_points.shape[0] == 0:
        return empty
    errs = ctx.ray_errors_wrapped
    if errs is None or errs[0].size == 0:
        return empty
    l1, absrel = errs
    out: dict[str, list] = {c: [] for c in LIST_COLUMNS}
    for k, rays in ctx.truth.kept_range_groups(RANGE_BIN_M):  # the truth's: shared by every method on the sample
        out["bin"].append(k)
        out["rays"].append(len(rays))
        out["l1_sum"].append(float(np.sum(l1[rays])))
        out["absrel_sum"].append(float(np.sum(absrel[rays])))
    return out


def profile(ranges: pd.DataFrame, bin_m: float = RANGE_BIN_M) -> pd.DataFrame:
    """Per range bin [lo, hi) m, pooled over the sweeps of ``ranges`` (range rows): kept rays,
    their mean L1 (m) and mean AbsRel (fraction)."""
    cols = ["lo_m", "hi_m", "rays", "l1_mean", "absrel_mean"]
    if not len(ranges):
        return pd.DataFrame(columns=cols)
    flat = ranges[list(LIST_COLUMNS)].explode(list(LIST_COLUMNS)).dropna(subset=["bin"])
    if not len(flat):
        return pd.DataFrame(columns=cols)
    flat = flat.astype({"bin": np.int64, "rays": np.int64, "l1_sum": float, "absrel_sum": float})
    g = flat.groupby("bin", sort=True)[["rays", "l1_sum", "absrel_sum"]].sum()
    return pd.DataFrame({
        "lo_m": g.index.to_numpy() * bin_m, "hi_m": (g.index.to_numpy() + 1) * bin_m, "rays": g["rays"].to_numpy(),
        "l1_mean": (g["l1_sum"] / g["rays"]).to_numpy(), "absrel_mean": (g["absrel_sum"] / g["rays"]).to_numpy(),
    })


def missing(meta: dict[str, Any], rows: pd.DataFrame, ranges: pd.DataFrame) -> int:
    """How many of a cell's scored sweeps (ok rows) have no range row in the store (all of
    them when its cell.json records none, or another version of them)."""
    ok = rows[rows["status"] == "ok"] if len(rows) else rows
    if not len(ok):
        return 0
    if (meta.get("range_bins") or {}).get("version") != VERSION:
        return len(ok)
    have = set(zip(ranges["sample_id"], ranges["step"])) if len(ranges) else set()
    return sum((s, int(k)) not in have for s, k in zip(ok["sample_id"], ok["step"]))
