"""Error by ground-truth range, kept in the store at run time for the report's range figure.

For every scored future sweep the runner records, per 10 m bin of the ground-truth range of
the kept rays, the number of rays and the sums of their L1 and AbsRel errors: the very errors
``l1_mean`` and ``absrel_mean`` average (``SweepContext.ray_errors_wrapped``), so a sweep's
ray-weighted mean over its bins is its stored ``l1_mean``/``absrel_mean``. They are stored
beside the cell's rows (``ranges/`` in the cell folder, :mod:`pcfbench.store`), one row per
(sample, future sweep) with the bins as lists, and the report's figure pools them over every
sample of a cell: it reads the store only, no method runs.

Only cells scoring ``l1_mean`` or ``absrel_mean`` record them (then the errors are computed
anyway); ``pcfbench backfill-ranges`` (:func:`backfill`) recomputes them for a cell made
before the store kept them, re-running its method, as an explicit command.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Callable

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
    b = np.floor(ctx.gt_ranges[ctx.ray_kept] / RANGE_BIN_M).astype(np.int64)
    out: dict[str, list] = {c: [] for c in LIST_COLUMNS}
    for k in np.unique(b):
        m = b == k
        out["bin"].append(int(k))
        out["rays"].append(int(m.sum()))
        out["l1_sum"].append(float(np.sum(l1[m])))
        out["absrel_sum"].append(float(np.sum(absrel[m])))
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


def backfill(store_root: Path, plugins=None, log: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Recompute the range bins of every complete cell of ``store_root`` missing some (a cell
    made before the store kept them): each rows chunk without them is re-run through the
    method and scored again, and its range rows are written only when the re-run gives back
    the stored ``l1_mean``/``absrel_mean`` of every sweep (a method that does not reproduce
    its rows is named and left as it is). Returns one record per cell looked at."""
    from pcfbench.store import Cell, iter_cells, spec_from_meta

    log = log or (lambda s: print(s, file=sys.stderr))
    out = []
    for cell_dir, meta_ in iter_cells(store_root):
        if meta_.get("status") != "complete":
            continue
        reader = Cell.at(store_root, Path(cell_dir).relative_to(store_root))
        reader.spec = spec_from_meta(meta_)
        rows = reader.read_rows()
        if not missing(meta_, rows, reader.read_ranges()):
            out.append({"cell": str(cell_dir), "status": "has ranges", "chunks": 0})
            continue
        out.append(_backfill_cell(reader, meta_, plugins, log))
    return out


def _backfill_cell(cell, meta_: dict[str, Any], plugins, log) -> dict[str, Any]:
    from pcfbench.runner import resolve
    from pcfbench.store import read_chunk_frame
    from pcfbench.validate import validate_forecast
    from pcfbench.metrics.base import SweepContext

    rec = {"cell": str(cell.dir), "status": "", "chunks": 0}
    spec = cell.spec
    res = resolve(spec, plugins)
    if res.method.version != meta_.get("method_version"):
        rec["status"] = (f"not recomputed: {spec.method} is version {res.method.version} now, the cell was made "
                         f"with {meta_.get('method_version')}")
        log(f"{cell.dir}: {rec['status']}")
        return rec
    with cell:
        stale = (meta_.get("range_bins") or {}).get("version") != VERSION
        for path in cell.chunk_paths():
            chunk = read_chunk_frame(path)
            ok = chunk[chunk["status"] == "ok"]
            have = cell.read_ranges_for(path)
            if not stale and have is not None and set(zip(ok["sample_id"], ok["step"])) <= set(zip(have["sample_id"], have["step"])):
                continue
            ranges_rows, differs = [], []
            for sid, g in ok.groupby("sample_id", sort=False):
                seq, _, idx = str(sid).rpartition("/")
                sample, truth = res.builder.build(seq, int(idx))
                fc = validate_forecast(sample, res.method.forecast(sample.for_method()))
                by_step = {int(k): r for k, r in zip(g["step"], g.to_dict("records"))}
                for k, q in enumerate(sample.queries):
                    if k not in by_step:
                        continue
                    ctx = SweepContext(truth.future_points_ref[k], q,
                                       fc.points_ref[k] if fc.points_ref is not None else None,
                                       fc.depths[k] if fc.depths is not None else None)
                    bins = sweep_bins(ctx)
                    n = sum(bins["rays"])
                    for name, col in (("l1_mean", "l1_sum"), ("absrel_mean", "absrel_sum")):
                        want = by_step[k].get(name)
                        if want is None or not math.isfinite(float(want)) or not n:
                            continue
                        if not math.isclose(float(want), sum(bins[col]) / n, rel_tol=1e-6, abs_tol=1e-9):
                            differs.append(f"{sid} sweep {k} {name}")
                    ranges_rows.append({"sample_id": sid, "step": k, **bins})
            if differs:
                rec["status"] = (f"not recomputed: re-running {spec.method} does not give back its stored rows "
                                 f"({', '.join(differs[:3])}{', ...' if len(differs) > 3 else ''})")
                log(f"{cell.dir}: {rec['status']}")
                return rec
            cell.write_ranges_for(path, ranges_rows)
            rec["chunks"] += 1
        meta_ = dict(meta_, range_bins=meta())
        cell.write_meta(meta_)
    rec["status"] = f"recomputed {rec['chunks']} chunk(s)"
    log(f"{cell.dir}: {rec['status']}")
    return rec
