"""``pcfbench backfill-ranges``: the range bins of cells made before the store kept them.

The one place a report's input is recomputed, and an explicit command: each rows chunk of a
complete cell without its range bins (:mod:`pcfbench.store.ranges`) is re-run through the cell's
method and scored again; its bins are written only when the re-run gives back the cell's
stored ``l1_mean``/``absrel_mean``. It sits above the runner (it re-runs methods), and the
runner and the report below it never import it.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Callable

from pcfbench.store import ranges
from pcfbench.metrics.base import SweepContext
from pcfbench.running.runner import resolve
from pcfbench.store.cells import Cell, iter_cells, read_chunk_frame, spec_from_meta
from pcfbench.protocol.validate import validate_forecast

__all__ = ["backfill"]


def backfill(store_root: Path, plugins=None, log: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Recompute the range bins of every complete cell of ``store_root`` missing some (a cell
    made before the store kept them): each rows chunk without them is re-run through the
    method and scored again, and its range rows are written only when the re-run gives back
    the stored ``l1_mean``/``absrel_mean`` of every sweep (a method that does not reproduce
    its rows is named and left as it is). Returns one record per cell looked at."""
    log = log or (lambda s: print(s, file=sys.stderr))
    out = []
    for cell_dir, meta_ in iter_cells(store_root):
        if meta_.get("status") != "complete":
            continue
        reader = Cell.at(store_root, Path(cell_dir).relative_to(store_root))
        reader.spec = spec_from_meta(meta_)
        rows = reader.read_rows()
        if not ranges.missing(meta_, rows, reader.read_ranges()):
            out.append({"cell": str(cell_dir), "status": "has ranges", "chunks": 0})
            continue
        out.append(_backfill_cell(reader, meta_, plugins, log))
    return out


def _backfill_cell(cell, meta_: dict[str, Any], plugins, log) -> dict[str, Any]:
    rec = {"cell": str(cell.dir), "status": "", "chunks": 0}
    spec = cell.spec
    res = resolve(spec, plugins)
    if res.method.version != meta_.get("method_version"):
        rec["status"] = (f"not recomputed: {spec.method} is version {res.method.version} now, the cell was made "
                         f"with {meta_.get('method_version')}")
        log(f"{cell.dir}: {rec['status']}")
        return rec
    with cell:
        stale = (meta_.get("range_bins") or {}).get("version") != ranges.VERSION
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
                                       fc.depths[k] if fc.depths is not None else None,
                                       roi=res.builder.protocol.roi, min_range_m=res.builder.protocol.min_range_m)
                    bins = ranges.sweep_bins(ctx)
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
        meta_ = dict(meta_, range_bins=ranges.meta())
        cell.write_meta(meta_)
    rec["status"] = f"recomputed {rec['chunks']} chunk(s)"
    log(f"{cell.dir}: {rec['status']}")
    return rec
