"""What ``pcfbench export`` writes: a run's stored forecasts, each one checked to be the one scored.

The results store keeps a metric row per (cell, sample, future sweep), not forecast points.
A forecast is made again here, by the cell's method built exactly as the run built it
(:func:`pcfbench.running.runner.resolve`: its options, a trained method's checkpoint of the
cell's sha256), on the sample the cell scored, and scored again with the cell's metrics. It is
exported only when every value of every sweep's row equals the stored one (``score_sample``'s
rows do not depend on the thread budget, so equal means bit-equal; NaN equals NaN), and a cell
whose identity (method, dataset and metric versions, protocol, data files) differs from what
made it is refused before any method runs. A method that failed on a sample in the run is not
re-run: the file records its error for that sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pandas as pd

from pcfbench.errors import DataError, PcfbenchError
from pcfbench.geometry import transform_points
from pcfbench.datasets.export_mcap import SampleExport, forecast_topic, unique_topics


def sweep_indices(builder, ref_index: int) -> tuple[list[int], list[int]]:
    """The past and future sweep indices of the sample at ``ref_index`` (as ``SampleBuilder.build``)."""
    s = builder.setting
    return ([ref_index - k * s.stride for k in range(s.past - 1, -1, -1)],
            [ref_index + k * s.stride for k in range(1, s.future + 1)])


def sample_intensity(builder, sample, truth) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]] | None:
    """The reflectance of each past and ground-truth cloud of ``sample``, point for point; None
    when the dataset stores none. The sweep's points go through the builder's filters again (ego
    box; the minimum range for ground truth) and must land exactly on the sample's clouds, so a
    value is never shown on another point."""
    seq = builder.sequence(sample.sequence)
    if seq.intensity_loader is None:
        return None
    n = len(seq)
    past_idx, future_idx = sweep_indices(builder, sample.ref_index)
    where = f"{builder.adapter.name} sequence {seq.name}"

    def one(i: int, T_ref_sensor: np.ndarray, cloud_ref: np.ndarray, future: bool) -> np.ndarray:
        if not 0 <= i < n:
            return np.zeros(0, np.float32)
        pts = np.asarray(seq.load_points(i), np.float32)
        refl = seq.load_intensity(i)
        if refl.shape != (len(pts),):
            raise DataError(f"{where} sweep {i}: {refl.shape} intensity values for {len(pts)} points "
                            "(expected one per point)")
        keep = ~builder.adapter.ego_box.inside(pts)
        pts, refl = pts[keep], refl[keep]
        if future:
            far = np.linalg.norm(pts.astype(np.float64), axis=1) > builder.protocol.min_range_m
            pts, refl = pts[far], refl[far]
        if not np.array_equal(transform_points(T_ref_sensor, pts), cloud_ref):
            raise PcfbenchError(f"{where} sweep {i}: its points, filtered as the sample's, are not the sample's "
                                f"{len(cloud_ref)} points; its intensity cannot be placed")
        return refl

    past = tuple(one(i, T, c, False) for i, T, c in zip(past_idx, sample.past_T_ref_sensor, sample.past_points_ref))
    future = tuple(one(i, T, c, True) for i, T, c in zip(future_idx, sample.future_T_ref_sensor, truth.future_points_ref))
    return past, future


# -- a run's stored forecasts -------------------------------------------------------------------

@dataclass
class StoredCell:
    """A cell of the store chosen for export: its folder, cell.json and spec."""

    dir: Path
    meta: dict[str, Any]
    spec: Any

    @property
    def variant(self) -> str:
        """The method variant as on the command line, plus a trained method's checkpoint."""
        s = self.spec
        label = s.method + (":" + ",".join(f"{k}={v}" for k, v in sorted(s.options.items())) if s.options else "")
        return label + (f" [checkpoint {s.checkpoint_sha256[:12]}]" if s.checkpoint_sha256 else "")


def select_cells(store: Path, selection, cells: tuple[str, ...] = ()) -> list[StoredCell]:
    """The complete cells of ``store`` that ``selection`` (a ``pcfbench.reporting.select.Selection``)
    and the ``cells`` patterns (on the cell's folder under the store) pick; they must share one
    dataset, split, setting and policy (one set of samples), else one error listing them."""
    from pcfbench.store.cells import iter_cells, spec_from_meta

    store = Path(store)
    if not store.is_dir():
        raise PcfbenchError(f"results store {store} does not exist (pcfbench run writes it; pass --store DIR)")
    held = [StoredCell(d, m, spec_from_meta(m)) for d, m in iter_cells(store) if m.get("status") == "complete"]
    if not held:
        raise PcfbenchError(f"results store {store} holds no complete cell: run `pcfbench run` first")
    selection.check([c.spec for c in held])
    chosen = [c for c in held if selection.matches(c.spec)]
    if cells:
        rel = {id(c): str(c.dir.relative_to(store)) for c in chosen}
        unmatched = [p for p in cells if not any(fnmatchcase(r, p) for r in rel.values())]
        if unmatched:
            shown = "\n".join(f"  {r}" for r in sorted(rel.values()))
            raise PcfbenchError(f"--cell {', '.join(repr(p) for p in unmatched)} matches no selected cell; the cells "
                                f"(folders under {store}) are:\n{shown}")
        chosen = [c for c in chosen if any(fnmatchcase(rel[id(c)], p) for p in cells)]
    groups: dict[tuple, list[StoredCell]] = {}
    for c in chosen:
        s = c.spec
        groups.setdefault((s.dataset, s.dataset_root, s.split, s.setting, s.policy), []).append(c)
    if len(groups) > 1:
        shown = "\n".join(f"  {d}:{sp} {st} ({po}) at {root}: {', '.join(c.variant for c in cs)}"
                          for (d, root, sp, st, po), cs in groups.items())
        raise PcfbenchError(f"the selected cells hold {len(groups)} different sets of samples (dataset, root, split, "
                            f"setting, policy); one file shows one set: narrow with --dataset, --setting or --cell:\n{shown}")
    seen: dict[str, StoredCell] = {}
    for c in chosen:
        if c.variant in seen:
            raise PcfbenchError(f"cells {seen[c.variant].dir.relative_to(store)} and {c.dir.relative_to(store)} are the "
                                f"same variant {c.variant}; pick one with --cell")
        seen[c.variant] = c
    return chosen


def _rows_by_sample(df: pd.DataFrame) -> dict[str, pd.DataFrame]:
    return {str(sid): g.sort_values("step") for sid, g in df.groupby("sample_id", sort=False)}


def choose_samples(keys: list[tuple[str, int]], stored: dict[str, dict[str, pd.DataFrame]],
                   count: int | None, ids: tuple[str, ...]) -> list[tuple[str, int]]:
    """The samples to export, in the cells' order: those every cell holds rows of, the first
    ``count`` of them, or exactly ``ids`` (each one error when a cell lacks it)."""
    from pcfbench.protocol import sample_id

    common = [k for k in keys if all(sample_id(*k) in rows for rows in stored.values())]
    if ids:
        by_id = {sample_id(*k): k for k in keys}
        out = []
        for sid in ids:
            lacking = [label for label, rows in stored.items() if sid not in rows]
            if sid not in by_id or lacking:
                span = f"{sample_id(*common[0])} .. {sample_id(*common[-1])}, {len(common)} in all" if common else "none"
                who = ("it is not a sample of the cells" if sid not in by_id
                       else f"cell(s) {', '.join(lacking)} hold no row of it")
                raise PcfbenchError(f"--sample {sid!r}: {who} (the samples every selected cell holds: {span})")
            out.append(by_id[sid])
        return out
    if not common:
        raise PcfbenchError("the selected cells share no sample with rows: export them one at a time with --cell")
    return common if count is None else common[:count]


def _same(a: Any, b: Any) -> bool:
    try:
        fa, fb = float(a), float(b)
    except (TypeError, ValueError):
        return a == b
    return fa == fb or (math.isnan(fa) and math.isnan(fb))


def check_rows(cell: StoredCell, sid: str, stored: pd.DataFrame, fresh: list[dict]) -> None:
    """Return when ``fresh`` (the recomputed rows of sample ``sid``) equals the stored rows value
    for value; else one error naming the cell, sample, sweep and metric."""
    fix = (f"the forecast made now is not the one that was scored: rerun the cell with --force (or export from a "
           f"store this code and data wrote); cell {cell.dir}")
    if list(stored["step"]) != [r["step"] for r in fresh]:
        raise PcfbenchError(f"sample {sid} of {cell.variant}: the store holds sweeps {list(stored['step'])}, the "
                            f"recomputation {[r['step'] for r in fresh]}; {fix}")
    for (_, want), got in zip(stored.iterrows(), fresh):
        for key, value in got.items():
            if key in want.index and not _same(value, want[key]):
                raise PcfbenchError(f"sample {sid} sweep {got['step']} of {cell.variant}: {key} is {value!r} "
                                    f"recomputed but {want[key]!r} stored; {fix}")


def stored_forecasts(store: Path, selection, cells: tuple[str, ...] = (), count: int | None = None,
                     ids: tuple[str, ...] = (), plugins=None,
                     progress: Callable[[int, int], None] | None = None
                     ) -> tuple[Iterator[SampleExport], dict[str, dict], dict[str, str]]:
    """The selected cells' forecasts of the chosen samples, each checked against its stored
    rows: (one :class:`SampleExport` per sample, made as it is asked for; topic -> what it
    shows; the export record). Cells and samples are checked before the first is made."""
    from pcfbench.protocol import ids_hash, sample_id
    from pcfbench.running.runner import cell_identity, resolve, sample_keys
    from pcfbench.store.cells import Cell, check_identity

    store = Path(store)
    chosen = select_cells(store, selection, cells)
    resolved, stored = [], {}
    for c in chosen:
        res = resolve(c.spec, plugins)
        keys = sample_keys(res, c.spec, plugins)
        fingerprint = res.builder.adapter.fingerprint(c.spec.split)
        identity = cell_identity(res, c.spec, ids_hash([sample_id(*k) for k in keys]), fingerprint.digest, True)
        try:
            check_identity(c.dir, c.meta, identity, fingerprint)
        except PcfbenchError as exc:
            raise PcfbenchError(f"cannot export the forecasts of {c.variant}: {exc}") from None
        reader = Cell.at(store, c.dir.relative_to(store))
        stored[c.variant] = _rows_by_sample(reader.read_rows())
        resolved.append(res)
    topics = unique_topics({c.variant: forecast_topic(c.spec.method, c.spec.options, c.spec.checkpoint_sha256)
                            for c in chosen})
    builder = resolved[0].builder
    chosen_keys = choose_samples(builder.sample_keys(chosen[0].spec.split), stored, count, ids)

    def items() -> Iterator[SampleExport]:
        for n, key in enumerate(chosen_keys):
            yield _remade(key, builder, chosen, resolved, stored, topics)
            if progress is not None:
                progress(n + 1, len(chosen_keys))

    head = chosen[0]
    record = {"source": f"results store {store}", "dataset": head.spec.dataset, "split": head.spec.split,
              "setting": head.spec.setting, "policy": head.spec.policy,
              "metric_versions": ", ".join(f"{m.name} v{m.version}" for m in resolved[0].metrics)}
    described = {topics[c.variant]: {"method": c.spec.method, "options": c.spec.options, "spec": c.variant,
                                     "cell": str(c.dir.relative_to(store)), "checkpoint_sha256": c.spec.checkpoint_sha256,
                                     "train_on": c.spec.train_on, "method_version": c.meta.get("method_version")}
                 for c in chosen}
    return items(), described, record


def _remade(key: tuple[str, int], builder, chosen: list[StoredCell], resolved: list, stored: dict, topics: dict[str, str]
            ) -> SampleExport:
    """One sample with each cell's forecast made again and checked against its stored rows."""
    from pcfbench.metrics.base import score_sample
    from pcfbench.protocol.validate import validate_forecast

    sample, truth = builder.build(*key)
    sid = sample.sample_id
    forecasts, scores, failed = {}, {}, {}
    for c, res in zip(chosen, resolved):
        rows = stored[c.variant][sid]
        topic = topics[c.variant]
        if (rows["status"] == "failed").any():
            failed[topic] = str(rows["error"].iloc[0]) if "error" in rows else "failed"
            continue
        try:
            fc = validate_forecast(sample, res.method.forecast(sample.for_method()))
        except DataError:
            raise
        except Exception as exc:  # noqa: BLE001 - it was scored in the run: a failure now is a mismatch
            raise PcfbenchError(f"sample {sid} of {c.variant}: the method fails now ({type(exc).__name__}: {exc}) "
                                f"but was scored in the run; cell {c.dir}") from None
        fresh = score_sample(sample, truth, fc, res.metrics, protocol=res.builder.protocol)
        check_rows(c, sid, rows[rows["status"] == "ok"], fresh)
        forecasts[topic], scores[topic] = fc, fresh
    intensity = sample_intensity(builder, sample, truth)
    return SampleExport(sample, truth, forecasts, scores, failed, *(intensity or (None, None)))
