"""Figures of a leaderboard (matplotlib, Agg), each written as PNG and SVG under ``reports/figures/``.

Every figure but the gallery is drawn from the store alone: no method runs in a report.

- ``horizon-<group>``: each preset column against the forecast time in seconds, one line per
  method variant, the band its 95 % bootstrap interval (the per-step rows of
  ``pcfbench.reporting.report.collect``, resampling samples).
- ``range-<group>``: L1 and AbsRel against the ground-truth range, per 10 m bin, every scored
  sweep of each cell pooled. The runner stores each sweep's bins (rays, error sums) beside its
  rows (``pcfbench.store.ranges``): the errors are those of ``SweepContext.ray_errors_wrapped``, the
  very errors ``l1_mean``/``absrel_mean`` average, so a sweep's ray-weighted mean over its bins
  is its stored value. The band of each bin is its bootstrap interval over the resampling
  units (:func:`range_intervals`). A cell made before the store kept them is left out of the
  figure and named, with the command that recomputes them (``pcfbench backfill-ranges``).
- ``gallery-<group>``: only when asked for (``pcfbench report --gallery``), as it **re-runs**
  the methods on a few samples (``figure_samples`` per group, chosen below): bird's-eye views,
  a column per sample, a row each for the past sweeps, the ground truth at the horizon and
  each variant's forecast of it, its points coloured by their distance to the nearest
  ground-truth point (m) on one scale with one colour bar.

Legends name variants by their short labels (:func:`short_labels`): a trained method's
training data and checkpoint go to a footnote under the figure.
- ``ablation-<stem>``: a sweep's metric against an option's value (``pcfbench.experiments.sweep``).

Chosen samples (the gallery): per group, the reference cell's (else the first cell's) samples
ranked by their mean of the group's ranking metric; the median one and the worst one (for
``figure_samples=2``), evenly spaced ranks for more.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pcfbench.errors import PcfbenchError
from pcfbench.store.ranges import RANGE_BIN_M

FIGURES_DIR = "figures"
FORMATS = ("png", "svg")
#: the gallery's PNG resolution: a 1.3 inch panel of a 250-cell raster keeps every cell
GALLERY_DPI = 200
#: an ablation figure's reference lines: three colours, then the next dash (dashed, dash-dot, dotted)
REFERENCE_DASHES = ("--", "-.", ":")
_RC = {"svg.hashsalt": "pcfbench", "font.size": 9, "axes.grid": True, "grid.alpha": 0.3}


def _unit_scale(unit: str) -> tuple[float, str]:
    if unit == "fraction":
        return 100.0, "%"
    base, sep, power = unit.partition("^")
    return 1.0, (f"{base}$^{{{power}}}$" if sep else unit)


def _slug(*parts: Any) -> str:
    text = "_".join(str(p) for p in parts if p not in (None, ""))
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-")


def _new_figure(w: float, h: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), layout="constrained")


_NOTE_LINE_IN = 0.15  # height of one 7 pt footnote line (inches)


def _wrap(text: str, width_in: float, pt: float) -> str:
    """``text`` with each line wrapped to fit ``width_in`` inches at ``pt`` points (a DejaVu
    Sans character is about 0.55 em wide on average); continuation lines indented."""
    import textwrap

    chars = max(30, int(width_in * 72 / (0.55 * pt)))
    return "\n".join(part for line in text.split("\n")
                     for part in (textwrap.wrap(line, chars, subsequent_indent="  ") or [""]))


def _framed(w: float, h: float, notes: list[str]):
    """A ``w`` x ``h`` inch figure and the (sub)figure to draw in; with ``notes``, a strip below
    it holds them, one per line, left-aligned (the caption's footnotes: what a short legend
    label's marker stands for). Returns (figure, body)."""
    if not notes:
        fig = _new_figure(w, h)
        return fig, fig
    notes = _wrap("\n".join(notes), w, 7).split("\n")
    foot_h = _NOTE_LINE_IN * len(notes) + 0.1
    fig = _new_figure(w, h + foot_h)
    body, foot = fig.subfigures(2, 1, height_ratios=[h, foot_h])
    foot.text(0.01, 1.0, "\n".join(notes), ha="left", va="top", fontsize=7)
    return fig, body


def short_labels(variants) -> tuple[dict[str, str], list[str]]:
    """Legend labels for ``variants`` and the footnotes they point to: a trained method's
    training data and checkpoint go to a footnote (the tables' ``footnote_labels``), the legend
    keeps its name and marker. Returns (variant -> label, footnote lines)."""
    from pcfbench.reporting.tables import footnote_labels

    short, notes = footnote_labels(list(dict.fromkeys(str(v) for v in variants)))
    return {str(v): short.get(str(v), str(v)) for v in variants}, [f"{m} {text}" for m, text in notes]


def save(fig, out_dir: Path, stem: str, dpi: int = 110) -> dict[str, Path]:
    """Write ``fig`` as ``stem.png`` (``dpi`` pixels per inch) and ``stem.svg``, each through a
    temporary file renamed into place (no date in the metadata: same data, same bytes)."""
    import matplotlib

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    with matplotlib.rc_context(_RC):
        for ext in FORMATS:
            p = out_dir / f"{stem}.{ext}"
            tmp = out_dir / f".{stem}.{ext}.{os.getpid()}.tmp"
            meta = {"Date": None} if ext == "svg" else {"Software": None}
            fig.savefig(tmp, format=ext, dpi=dpi, metadata=meta)
            os.replace(tmp, p)  # whole or not at all
            paths[f"{stem}.{ext}"] = p
    return paths


def _group_title(r: pd.Series) -> str:
    t = f"{r['dataset']} / {r['split']} / {r['setting']}"
    return t if r["policy"] == "full-context" else f"{t} ({r['policy']})"


def _group_stem(kind: str, r: pd.Series) -> str:
    policy = "" if r["policy"] == "full-context" else r["policy"]
    return f"{kind}-" + _slug(r["dataset"], r["split"], r["setting"], policy)


# -- error vs forecast time ------------------------------------------------------------------
def horizon_figure(steps: pd.DataFrame, columns: list, title: str, interval: str | None = None):
    """One panel per column (``tables.ShownColumn``): mean per future sweep against its time
    (s) for each variant, with the interval (``m_lo``/``m_hi`` of the per-step rows) as a band,
    as error bars where a variant has one point; ``interval`` says how it was computed
    (``Resampling.describe()``, the default resampling's when None). A variant with no
    interval at any step (fewer than 2 resampling units) says so in the legend. Legends hold
    :func:`short_labels`, with their footnotes under the figure."""
    if interval is None:
        from pcfbench.reporting.stats import Resampling

        interval = Resampling().describe()
    with _rc():
        n = len(columns)
        ncols = min(3, n)
        nrows = math.ceil(n / ncols)
        names, notes = short_labels(steps["variant"].unique()) if len(steps) else ({}, [])
        fig, body = _framed(4.2 * ncols, 3.2 * nrows + 0.4, notes)
        axes = body.subplots(nrows, ncols, squeeze=False).ravel()
        unbanded = {v for v, g in steps.groupby("variant", sort=False)
                    if not any(np.isfinite(g[f"{c.metric}_{e}"].to_numpy(float)).any()
                               for c in columns for e in ("lo", "hi") if f"{c.metric}_{e}" in g)}
        for ax, col in zip(axes, columns):
            k, unit = _unit_scale(col.unit)
            for variant, g in steps.groupby("variant", sort=False):
                g = g.sort_values("time_s")
                t = g["time_s"].to_numpy(float)
                y = k * g[col.metric].to_numpy(float) if col.metric in g else np.full(len(g), np.nan)
                name = names.get(str(variant), str(variant))
                label = f"{name} (no interval: < 2 resampling units)" if variant in unbanded else name
                (line,) = ax.plot(t, y, marker="o", ms=3, label=label)
                lo, hi = g.get(f"{col.metric}_lo"), g.get(f"{col.metric}_hi")
                if lo is None or hi is None:
                    continue
                lo, hi = k * lo.to_numpy(float), k * hi.to_numpy(float)
                if len(t) > 1:
                    ax.fill_between(t, lo, hi, color=line.get_color(), alpha=0.18, linewidth=0)
                elif np.isfinite(lo).all() and np.isfinite(hi).all():  # one point: a band would be 0 wide
                    ax.errorbar(t, y, yerr=np.vstack([y - lo, hi - y]), color=line.get_color(), capsize=3,
                                linestyle="none")
            arrow = "lower is better" if col.better == "lower" else "higher is better"
            ax.set_title(f"{col.label} ({arrow})")
            ax.set_xlabel("forecast time after t=0 (s)")
            ax.set_ylabel(f"{col.label} ({unit})" if unit else col.label)
        for ax in axes[n:]:
            ax.set_visible(False)
        handles, labels = axes[0].get_legend_handles_labels()
        body.legend(handles, labels, loc="outside lower center", ncols=min(4, max(1, len(labels))), fontsize=8)
        fig.suptitle(f"{title}: error per future sweep\nband: {interval}")
    return fig


def _rc():
    import matplotlib

    return matplotlib.rc_context(_RC)


# -- re-run samples (the gallery, on request): per-ray and per-point errors ----------------------
@dataclass
class SweepErrors:
    """One re-run future sweep of one variant: what the figures need, reference frame."""

    step: int
    ray_range_m: np.ndarray  # (R,) ground-truth range of each kept ray
    ray_l1_m: np.ndarray  # (R,) its L1 error (m)
    ray_absrel: np.ndarray  # (R,) its AbsRel error (fraction)
    pred_points: np.ndarray  # (K, 3) float32
    pred_error_m: np.ndarray  # (K,) distance of each forecast point to the nearest ground-truth point
    gt_points: np.ndarray  # (M, 3) float32


@dataclass
class Rerun:
    """The chosen samples of a group re-run for every variant: ``errors[variant][sample_id]``
    is the list of its future sweeps' :class:`SweepErrors`; ``samples`` the (Sample,
    GroundTruth) pairs; ``mismatch`` the variants whose re-run differs from their stored rows."""

    sample_ids: list[str]
    samples: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    errors: dict[str, dict[str, list[SweepErrors]]] = field(default_factory=dict)
    mismatch: list[str] = field(default_factory=list)
    #: variants that could not be re-run, with why (their plugin is gone, their method raised)
    skipped: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0


def sweep_errors(step: int, gt: np.ndarray, query, pred_points, pred_depths) -> SweepErrors:
    """The per-ray and per-point errors of one future sweep, through ``SweepContext`` (the
    metrics' own definitions)."""
    from pcfbench.metrics.base import SweepContext

    ctx = SweepContext(gt_points=gt, query=query, pred_points=pred_points, pred_depths=pred_depths)
    empty = np.zeros(0)
    if gt.shape[0] == 0 or ctx.pred_points.shape[0] == 0:
        return SweepErrors(step, empty, empty, empty, ctx.pred_points, np.full(ctx.pred_points.shape[0], np.nan), gt)
    l1, absrel = ctx.ray_errors_wrapped
    pred_err = np.sqrt(ctx.nn_pred_to_gt[0])
    return SweepErrors(step, ctx.gt_ranges[ctx.ray_kept], l1, absrel, ctx.pred_points, pred_err, gt)


def choose_samples(rows: pd.DataFrame, metric: str | None, n: int, higher_is_better: bool = False) -> list[str]:
    """``n`` sample ids of a cell's ok rows: ranked by their mean of ``metric``, best first
    (``higher_is_better``: the metric's direction); the median and the worst for n = 2, else
    evenly spaced ranks from the best to the worst."""
    ok = rows[rows["status"] == "ok"]
    if not len(ok) or n < 1:
        return []
    if metric is not None and metric in ok:
        score = ok.groupby("sample_id")[metric].mean() * (-1.0 if higher_is_better else 1.0)
        score = score.fillna(np.inf)
    else:
        score = ok.groupby("sample_id")["step"].count() * 0.0
    order = score.sort_values(kind="stable").index.tolist()
    if n == 1 or len(order) == 1:
        return [order[len(order) // 2]]
    if n == 2:
        picks = [len(order) // 2, len(order) - 1]
    else:
        picks = np.linspace(0, len(order) - 1, n).round().astype(int).tolist()
    return list(dict.fromkeys(order[i] for i in picks))


def rerun(store_root: Path, cells: pd.DataFrame, sample_ids: list[str], plugins=None) -> Rerun:
    """Forecast ``sample_ids`` again with every cell of ``cells`` (rows of the leaderboard with
    their ``cell_dir``) and compute their errors."""
    import time

    from pcfbench.errors import DataError
    from pcfbench.running.runner import resolve
    from pcfbench.store.cells import Cell, spec_from_meta
    from pcfbench.protocol.validate import validate_forecast

    t0 = time.perf_counter()
    out = Rerun(list(sample_ids))
    builder = None
    for _, row in cells.iterrows():
        cell_dir = Path(row["cell_dir"])
        spec = spec_from_meta(Cell.at(store_root, cell_dir).read_meta() or {})
        try:
            res = resolve(spec, plugins)
        except PcfbenchError as exc:  # a plugin gone, a checkpoint moved: the tables stand, the figure says so
            out.skipped[row["variant"]] = str(exc).splitlines()[0]
            continue
        if builder is None:
            builder = res.builder
            for sid in sample_ids:
                seq, _, idx = sid.rpartition("/")
                out.samples[sid] = builder.build(seq, int(idx))
        stored = Cell(store_root, spec).read_rows()
        per_sample: dict[str, list[SweepErrors]] = {}
        differs = False
        for sid, (sample, truth) in out.samples.items():
            try:
                fc = validate_forecast(sample, res.method.forecast(sample.for_method()))
            except DataError:
                raise
            except Exception as exc:  # noqa: BLE001 - as the runner: a method failing is recorded, not fatal
                out.skipped[row["variant"]] = f"{type(exc).__name__}: {exc}".splitlines()[0]
                break
            sweeps = []
            for k, q in enumerate(sample.queries):
                e = sweep_errors(k, truth.future_points_ref[k], q,
                                 fc.points_ref[k] if fc.points_ref is not None else None,
                                 fc.depths[k] if fc.depths is not None else None)
                sweeps.append(e)
                want = stored[(stored["sample_id"] == sid) & (stored["step"] == k)]
                if "l1_mean" in want and len(want) and e.ray_l1_m.size:
                    differs |= not math.isclose(float(want["l1_mean"].iloc[0]), float(np.mean(e.ray_l1_m)),
                                                rel_tol=1e-6, abs_tol=1e-9)
            per_sample[sid] = sweeps
        if row["variant"] in out.skipped:
            continue
        out.errors[row["variant"]] = per_sample
        if differs:
            out.mismatch.append(row["variant"])
    out.seconds = time.perf_counter() - t0
    return out


# -- error vs range --------------------------------------------------------------------------
def range_profile(sweeps: list[SweepErrors], bin_m: float = RANGE_BIN_M) -> pd.DataFrame:
    """Per range bin [lo, hi) m: kept rays, their mean L1 (m) and mean AbsRel (fraction),
    pooled over re-run ``sweeps`` (what the store's range bins hold, recomputed per ray)."""
    rng = np.concatenate([s.ray_range_m for s in sweeps]) if sweeps else np.zeros(0)
    l1 = np.concatenate([s.ray_l1_m for s in sweeps]) if sweeps else np.zeros(0)
    ar = np.concatenate([s.ray_absrel for s in sweeps]) if sweeps else np.zeros(0)
    if not rng.size:
        return pd.DataFrame(columns=["lo_m", "hi_m", "rays", "l1_mean", "absrel_mean"])
    b = np.floor(rng / bin_m).astype(int)
    rows = []
    for k in np.unique(b):
        m = b == k
        rows.append({"lo_m": k * bin_m, "hi_m": (k + 1) * bin_m, "rays": int(m.sum()),
                     "l1_mean": float(l1[m].mean()), "absrel_mean": float(ar[m].mean())})
    return pd.DataFrame(rows)


@dataclass
class StoredRanges:
    """The range profiles of a group's cells, read from the store: ``profiles[variant]``
    (:func:`pcfbench.store.ranges.profile`), ``sweeps[variant]`` the scored sweeps pooled, and
    ``missing[variant]`` the cell folder of each cell whose range bins the store lacks, and
    ``why[variant]`` why it lacks them; ``samples[variant]`` the bins summed per sample (one
    row per sample and bin: ``sample_id``, ``sequence``, ``ref_index``, ``bin``, ``rays``,
    ``l1_sum``, ``absrel_sum``), what :func:`range_intervals` resamples."""

    profiles: dict[str, pd.DataFrame] = field(default_factory=dict)
    sweeps: dict[str, int] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    why: dict[str, str] = field(default_factory=dict)
    samples: dict[str, pd.DataFrame] = field(default_factory=dict)


def _per_sample_bins(stored: pd.DataFrame, rows: pd.DataFrame) -> pd.DataFrame:
    """The range rows ``stored`` (one per scored sweep, bins as lists) summed per (sample, bin),
    with each sample's sequence and reference index from the cell's ``rows``."""
    from pcfbench.store import ranges

    cols = ["sample_id", "sequence", "ref_index", "bin", "rays", "l1_sum", "absrel_sum"]
    lists = list(ranges.LIST_COLUMNS)
    flat = stored[["sample_id", *lists]].explode(lists).dropna(subset=["bin"]) if len(stored) else stored
    if not len(flat):
        return pd.DataFrame(columns=cols)
    flat = flat.astype({"bin": np.int64, "rays": np.int64, "l1_sum": float, "absrel_sum": float})
    per = flat.groupby(["sample_id", "bin"], sort=True)[["rays", "l1_sum", "absrel_sum"]].sum().reset_index()
    where = rows.drop_duplicates("sample_id").set_index("sample_id")[["sequence", "ref_index"]]
    return per.join(where, on="sample_id")[cols]


def stored_ranges(store_root: Path, cells: pd.DataFrame) -> StoredRanges:
    """The range profile of every cell of ``cells`` (rows of the leaderboard with their
    ``cell_dir``) from its range bins in the store; a cell without them for every scored sweep
    goes to ``missing``. Reads the store only."""
    from pcfbench.store import ranges
    from pcfbench.store.cells import Cell

    out = StoredRanges()
    for _, row in cells.iterrows():
        cell = Cell.at(store_root, row["cell_dir"])
        rows, stored, meta = cell.read_rows(), cell.read_ranges(), cell.read_meta() or {}
        gaps = ranges.missing(meta, rows, stored)
        if gaps:
            out.missing[row["variant"]] = str(row["cell_dir"])
            ok = int((rows["status"] == "ok").sum())
            out.why[row["variant"]] = (
                "it scores neither l1_mean nor absrel_mean" if not ranges.records(meta.get("metric_versions") or {})
                else "made before the store kept them" if gaps == ok else f"{gaps} of its {ok} scored sweeps have none")
            continue
        ok = rows[rows["status"] == "ok"]
        keys = set(zip(ok["sample_id"], ok["step"].astype(int)))
        mine = stored[[(s, int(k)) in keys for s, k in zip(stored["sample_id"], stored["step"])]] if len(stored) else stored
        out.profiles[row["variant"]] = ranges.profile(mine)
        out.sweeps[row["variant"]] = len(ok)
        out.samples[row["variant"]] = _per_sample_bins(mine, ok)
    return out


def range_intervals(found: StoredRanges, resampling=None) -> dict[str, pd.DataFrame]:
    """Per variant and range bin, the bootstrap interval of its L1 and AbsRel means
    (``lo_m``, ``l1_lo``, ``l1_hi``, ``absrel_lo``, ``absrel_hi``, ``units``): the statistic is
    the bin's ray-weighted mean, each resample draws whole resampling units (samples by
    default: ``resampling``, a ``stats.Resampling``) with their rays, as the tables' intervals
    do. NaN where a bin has no interval (fewer than 2 units, or in fewer than half the
    resamples)."""
    from pcfbench.reporting import stats

    resampling = resampling or stats.Resampling()
    out: dict[str, pd.DataFrame] = {}
    for variant, per in found.samples.items():
        if not len(per):
            continue
        # (samples, bins) matrices: a sample's rays and error sums in each bin, 0 where it has none
        first, sample = np.unique(per["sample_id"].to_numpy(str), return_index=True, return_inverse=True)[1:]
        bins, col = np.unique(per["bin"].to_numpy(np.int64), return_inverse=True)
        n, k = len(first), len(bins)
        rays, l1, absrel = np.zeros((n, k)), np.zeros((n, k)), np.zeros((n, k))
        for m, c in ((rays, "rays"), (l1, "l1_sum"), (absrel, "absrel_sum")):
            np.add.at(m, (sample, col), per[c].to_numpy(float))
        ids, seqs, refs = (per[c].to_numpy()[first] for c in ("sample_id", "sequence", "ref_index"))
        metrics = [f"{m}@{b}" for m in ("l1", "absrel") for b in bins]
        ss = stats.SampleSums.of(ids, seqs, refs, metrics, np.hstack([l1, absrel]), np.hstack([rays, rays]))
        iv = stats.interval(ss, resampling)
        out[variant] = pd.DataFrame({"lo_m": bins * RANGE_BIN_M, "l1_lo": iv.lo[:k], "l1_hi": iv.hi[:k],
                                     "absrel_lo": iv.lo[k:], "absrel_hi": iv.hi[k:], "units": iv.units})
    return out


GROUP_KEYS = ["dataset", "split", "setting", "policy"]


def group_ranges(store_root: Path, table: pd.DataFrame) -> dict[tuple, StoredRanges]:
    """:func:`stored_ranges` of each (dataset, split, setting, policy) group of ``table``, the
    group's key to it: what a report reads once for both the notes and the range figures."""
    if not len(table):
        return {}
    return {key: stored_ranges(store_root, g) for key, g in table.groupby(GROUP_KEYS, sort=True)}


def range_gaps(lb, store_root: Path, found: dict[tuple, StoredRanges] | None = None) -> list[str]:
    """One note per complete cell of ``lb`` whose range bins the store lacks: its range figure
    leaves it out, and the note says how to recompute them. ``found``: the
    :func:`group_ranges` of ``lb.table``, if already read."""
    from pcfbench.store import ranges

    if not len(lb.table):
        return []
    found = group_ranges(store_root, lb.table) if found is None else found
    return [f"{variant}: no range bins in the store for cell {cell_dir} ({g.why[variant]}), "
            f"so the error-by-range figure leaves it out; `{ranges.BACKFILL_COMMAND} --store {store_root}` "
            "recomputes them (it re-runs the method)" for g in found.values() for variant, cell_dir in g.missing.items()]


def _sweep_count(sweeps: dict[str, int]) -> str:
    counts = sorted(set(sweeps.values()))
    return f"{counts[0]}" if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"


def range_figure(found: StoredRanges, title: str, resampling=None):
    """L1 and AbsRel per range bin of each variant with range bins in the store, each bin's
    bootstrap interval (:func:`range_intervals`) as a band (as error bars for a one-bin curve).
    The title says what a point pools and how the band was computed; a cell left out (no range
    bins in the store) is named, with the command that recomputes them."""
    from pcfbench.reporting import stats
    from pcfbench.store import ranges

    resampling = resampling or stats.Resampling()
    intervals = range_intervals(found, resampling)
    shown = [v for v, prof in found.profiles.items() if len(prof)]
    names, notes = short_labels(list(shown) + list(found.missing))
    with _rc():
        fig, body = _framed(9.5, 3.8, notes)
        ax_l1, ax_ar = body.subplots(1, 2)
        for variant in shown:
            prof = found.profiles[variant]
            iv = intervals.get(variant)
            banded = iv is not None and np.isfinite(iv[["l1_lo", "absrel_lo"]].to_numpy(float)).any()
            label = names[variant] + ("" if banded else " (no interval: < 2 resampling units)")
            mid = ((prof["lo_m"] + prof["hi_m"]) / 2).to_numpy(float)
            for ax, what, k in ((ax_l1, "l1", 1.0), (ax_ar, "absrel", 100.0)):
                y = k * prof[f"{what}_mean"].to_numpy(float)
                (line,) = ax.plot(mid, y, marker="o", ms=3, label=label)
                if not banded:
                    continue
                at = iv.set_index("lo_m").reindex(prof["lo_m"].to_numpy(float))
                lo, hi = k * at[f"{what}_lo"].to_numpy(float), k * at[f"{what}_hi"].to_numpy(float)
                if len(mid) > 1:
                    ax.fill_between(mid, lo, hi, color=line.get_color(), alpha=0.18, linewidth=0)
                else:  # one bin: a band would be 0 wide
                    ax.errorbar(mid, y, yerr=np.vstack([y - lo, hi - y]), color=line.get_color(), capsize=3,
                                linestyle="none")
        for ax, what in ((ax_l1, "L1 mean (m)"), (ax_ar, "AbsRel mean (%)")):
            ax.set_xlabel(f"ground-truth range, {RANGE_BIN_M:g} m bins (m)")
            ax.set_ylabel(what)
        ax_l1.set_title("L1 error by range (lower is better)")
        ax_ar.set_title("AbsRel error by range (lower is better)")
        handles, labels = ax_l1.get_legend_handles_labels()
        if labels:
            body.legend(handles, labels, loc="outside lower center", ncols=min(4, max(1, len(labels))), fontsize=8)
        if found.sweeps:
            note = (f"a point: the mean over every ray in its bin, all {_sweep_count(found.sweeps)} scored "
                    f"sweeps of a method pooled\nband: {resampling.describe()}")
        else:
            note = "no cell with range bins in the store"
        if found.missing:  # a line of its own: the title stays within the figure
            note += (f"\nleft out, no range bins in the store: {', '.join(names[v] for v in found.missing)} "
                     f"(`{ranges.BACKFILL_COMMAND}` recomputes them)")
        fig.suptitle(f"{title}: error by ground-truth range\n{note}")
    return fig


# -- BEV gallery -----------------------------------------------------------------------------
def bev_grid(points: np.ndarray, values: np.ndarray | None, extent_m: float, pixels: int) -> np.ndarray:
    """A bird's-eye raster of ``points`` over [-extent, extent]^2 m, ``pixels`` square cells,
    row 0 at the top (+y): per cell the mean of ``values`` of its points (NaN where empty), or
    with ``values`` None the number of points in it."""
    xy = np.asarray(points, np.float64)[:, :2]
    cell = 2 * extent_m / pixels
    ij = np.floor((xy + extent_m) / cell).astype(np.int64)
    inside = (ij >= 0).all(1) & (ij < pixels).all(1)
    flat = (pixels - 1 - ij[inside, 1]) * pixels + ij[inside, 0]
    count = np.bincount(flat, minlength=pixels * pixels).astype(np.float64)
    if values is None:
        return count.reshape(pixels, pixels)
    total = np.bincount(flat, weights=np.asarray(values, np.float64)[inside], minlength=pixels * pixels)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (total / count).reshape(pixels, pixels)


def _row_label(text: str, width: int = 16) -> str:
    """A gallery row's name on at most a few short lines (wrapped at spaces and hyphens)."""
    import textwrap

    return "\n".join(textwrap.wrap(text, width, break_on_hyphens=True, break_long_words=False)) or text


def gallery_figure(run: Rerun, title: str, horizon_label: str, extent_m: float = 50.0, pixels: int = 250):
    """One column per chosen sample; rows: the past sweeps, the ground truth at the last future
    sweep, then one row per variant: its forecast of that sweep, coloured by distance to the
    nearest ground-truth point (m) on one scale, with one colour bar. Row names sit left of the
    first column (legend labels, :func:`short_labels`, their footnotes under the figure), sample
    ids above the first row: no title shares a line with another.

    Drawn as rasters (:func:`bev_grid`, 0.4 m cells by default: the mean error of the points in
    a cell), which keeps the figure quick to render and small whatever the point count. A
    panel is 1.3 to 2.2 inches square, smaller the more rows, so that up to seven rows keep
    the figure within a page's height."""
    import matplotlib

    variants = list(run.errors)
    names, notes = short_labels(variants)
    ncols = max(1, len(run.sample_ids))
    nrows = 2 + len(variants)
    side = min(2.2, max(1.3, 9.0 / nrows))
    errs = [e.pred_error_m[np.isfinite(e.pred_error_m)] for v in variants for sweeps in run.errors[v].values()
            for e in sweeps[-1:]]
    pooled = np.concatenate(errs) if errs else np.zeros(0)
    vmax = max(float(np.percentile(pooled, 95)) if pooled.size else 1.0, 0.05)
    box = (-extent_m, extent_m, -extent_m, extent_m)
    viridis = matplotlib.colormaps["viridis"].with_extremes(bad="white")
    greys = matplotlib.colormaps["Greys"].with_extremes(under="white")
    ticks = [-extent_m * 0.8, 0.0, extent_m * 0.8]
    with _rc():
        width = max(5.0, side * ncols + 1.6)
        fig, body = _framed(width, side * nrows + 1.8, notes)
        axes = body.subplots(nrows, ncols, squeeze=False, sharex=True, sharey=True)
        mappable = None
        for c, sid in enumerate(run.sample_ids):
            sample, truth = run.samples[sid]
            col = axes[:, c]
            past = sample.past_points_ref
            # older sweeps lighter: each cell shows its most recent sweep's shade
            age = np.zeros((pixels, pixels))
            for j, pts in enumerate(past):
                hit = bev_grid(pts, None, extent_m, pixels) > 0
                age[hit] = (j + 1) / len(past)
            col[0].imshow(age, extent=box, cmap=greys, vmin=1e-9, vmax=1.0, interpolation="nearest")
            col[0].set_title(f"sample {sid}", fontsize=8)
            occ = bev_grid(truth.future_points_ref[-1], None, extent_m, pixels) > 0
            col[1].imshow(occ.astype(float), extent=box, cmap=greys, vmin=1e-9, vmax=1.0, interpolation="nearest")
            for j, v in enumerate(variants):
                e = run.errors[v][sid][-1]
                grid = bev_grid(e.pred_points, e.pred_error_m, extent_m, pixels)
                mappable = col[2 + j].imshow(grid, extent=box, cmap=viridis, vmin=0.0, vmax=vmax,
                                             interpolation="nearest")
        rows = ["past sweeps\n(darkest: t = 0)", f"ground truth\n{horizon_label}"] + [_row_label(names[v]) for v in variants]
        for r, ax_row in enumerate(axes):
            ax_row[0].set_ylabel(rows[r], rotation=0, ha="right", va="center", fontsize=8, labelpad=4)
            for ax in ax_row:
                ax.plot([0], [0], marker="^", color="r", ms=4)
                ax.set_xlim(-extent_m, extent_m)
                ax.set_ylim(-extent_m, extent_m)
                ax.set_aspect("equal")
                ax.set_xticks(ticks)
                ax.set_yticks(ticks)
                ax.tick_params(labelsize=7)
                ax.grid(False)
        for ax in axes[-1]:
            ax.set_xlabel("x (m)", fontsize=8)
        if mappable is not None:
            body.colorbar(mappable, ax=axes.ravel().tolist(), location="bottom", extend="max", shrink=0.9,
                          aspect=25, pad=0.01, label="forecast point to nearest ground-truth point (m)")
        fig.suptitle(_wrap(f"{title}: bird's-eye view, forecasts of {horizon_label}\n"
                           f"x, y in the reference frame (m), {2 * extent_m / pixels:g} m cells; "
                           "red triangle: the sensor at t = 0", width, 9), fontsize=9)
    return fig


# -- sweeps: metric vs option value ------------------------------------------------------------
def ablation_figures(lb, columns: list, out_dir: Path, stem: str, plugins=None) -> dict[str, Path]:
    """For each option that varies among one method's variants of a sweep: each column's
    value (with its interval as error bars) against the option's value, a line per
    (dataset, split, setting) group and per combination of the method's other options, ticks
    at the grid's values; the table's reference row (``is_reference``, when it is another
    method's) as a dashed horizontal line with its interval as a faint band. The title says how
    the intervals were computed (``lb.resampling``)."""
    df = lb.table if len(lb.table) else lb.partial
    resampling = getattr(lb, "resampling", None)
    interval = resampling.describe() if resampling is not None else None
    paths: dict[str, Path] = {}
    if not len(df):
        return paths
    option_cols = [c for c in df.columns if c.startswith("option.")]
    refs = df[df["is_reference"].fillna(False).astype(bool)] if "is_reference" in df else df.iloc[0:0]
    for method, g in df.groupby("method", sort=True):
        g = _with_defaults(g, method, option_cols, plugins)
        for opt in option_cols:
            values = g[opt].dropna()
            if values.nunique() < 2:
                continue
            others = [c for c in option_cols if c != opt and g[c].notna().any()]
            fig = _ablation_figure(g[g[opt].notna()], opt, others, columns, method, _method_units(method, plugins),
                                   refs[refs["method"] != method], interval)
            paths.update(save(fig, out_dir, "ablation-" + _slug(stem, method, opt.removeprefix("option."))))
    return paths


def _with_defaults(g: pd.DataFrame, method: str, option_cols: list[str], plugins=None) -> pd.DataFrame:
    """``g`` with the options a cell left at their defaults filled in (a cell run without
    options is the same cell as one naming the defaults, and keeps the empty spec)."""
    from pcfbench.options import describe_options
    from pcfbench.plugins import get_plugins

    try:
        cls = (plugins or get_plugins()).methods.get(method)
        defaults = {f.name: f.default for f in describe_options(cls.Options, f"method {method}")}
    except (PcfbenchError, AttributeError):
        defaults = {}
    g = g.copy()
    for col in option_cols:
        name = col.removeprefix("option.")
        if name in defaults and g[col].notna().any():
            g[col] = g[col].astype(object).where(g[col].notna(), defaults[name])
        # one value, one point: a cell that named cfg_weight=2.0 records "2.0", and the cell
        # of a run that left it at its default gets the float 2.0 filled in above
        g[col] = g[col].map(_canonical, na_action="ignore")
    return g


def _canonical(value):
    """An option value as compared and plotted: a number (given as one or as its text) as a
    float, anything else as its text."""
    if isinstance(value, bool):
        return str(value)
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)


def _option_text(value) -> str:
    """An option value as a legend writes it: a whole number without its ``.0`` (an int option
    is a float after :func:`_canonical`), other numbers as ``%g``, anything else as its text."""
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() else f"{value:g}"
    return str(value)


def _numeric(values: pd.Series) -> np.ndarray | None:
    try:
        return np.array([float(v) for v in values])
    except (TypeError, ValueError):
        return None


def _ablation_figure(g: pd.DataFrame, opt: str, others: list[str], columns: list, method: str,
                     units: dict[str, str], refs: pd.DataFrame | None = None, interval: str | None = None):
    """The figure of one option; ``refs``: reference rows drawn as horizontal lines, those of
    the (dataset, split, setting) groups ``g`` plots, named in the legend by their short label
    (:func:`short_labels`, the footnote under the figure); ``interval``: how the error bars were
    computed (``Resampling.describe()``, the default resampling's when None)."""
    if interval is None:
        from pcfbench.reporting.stats import Resampling

        interval = Resampling().describe()
    name = opt.removeprefix("option.")
    groups = ["dataset", "split", "setting"]
    if refs is not None and len(refs):
        plotted = set(g[groups].itertuples(index=False, name=None))
        refs = refs[[tuple(r) in plotted for r in refs[groups].itertuples(index=False, name=None)]]
    else:
        refs = g.iloc[0:0]
    numeric = _numeric(g[opt])
    ref_names, notes = short_labels(refs["variant"]) if len(refs) else ({}, [])
    # the legend names only the options that tell its lines apart; those every line shares are
    # one footnote (a sweep of one option with six fixed ones drew labels wider than the figure)
    apart = [o for o in others if g[o].nunique(dropna=False) > 1]
    shared = [o for o in others if o not in apart and g[o].notna().any()]
    # a line is named by its setting, and by its dataset and split where the figure's lines come
    # from more than one (a sweep of val and test drew two lines named alike, and two references)
    named = [i for i, c in enumerate(groups) if c == "setting" or g[c].nunique(dropna=False) > 1]
    ref_named = [c for c in groups if refs[c].nunique(dropna=False) > 1]
    if shared:
        notes = [*notes, "every line: " + ", ".join(
            f"{o.removeprefix('option.')}={_option_text(g[o].dropna().iloc[0])}" for o in shared)]
    with _rc():
        n = len(columns)
        ncols = min(3, n)
        nrows = math.ceil(n / ncols)
        fig, body = _framed(4.2 * ncols, 3.2 * nrows + 0.6, notes)
        axes = body.subplots(nrows, ncols, squeeze=False).ravel()
        categories = sorted(g[opt].astype(str).unique())
        keys = ["dataset", "split", "setting"] + others
        for ax, col in zip(axes, columns):
            k, unit = _unit_scale(col.unit)
            for key, line in g.groupby(keys, sort=True, dropna=False):
                x = _numeric(line[opt])
                if x is None or numeric is None:
                    x = np.array([categories.index(str(v)) for v in line[opt]], float)
                order = np.argsort(x, kind="stable")
                y = k * line[col.metric].to_numpy(float)[order] if col.metric in line else np.full(len(x), np.nan)
                lo = k * line.get(f"{col.metric}_lo", pd.Series(np.nan, index=line.index)).to_numpy(float)[order]
                hi = k * line.get(f"{col.metric}_hi", pd.Series(np.nan, index=line.index)).to_numpy(float)[order]
                yerr = np.vstack([np.where(np.isfinite(lo), y - lo, 0), np.where(np.isfinite(hi), hi - y, 0)])
                label = " / ".join(str(key[i]) for i in named) + "".join(
                    f", {o.removeprefix('option.')}={_option_text(v)}" for o, v in zip(others, key[3:])
                    if o in apart and not pd.isna(v))
                if not (np.isfinite(lo) & np.isfinite(hi)).any():  # every cell of the line has < 2 units
                    label += " (no interval: < 2 resampling units)"
                ax.errorbar(x[order], y, yerr=yerr, marker="o", ms=3, capsize=3, label=label)
            if numeric is None:
                ax.set_xticks(range(len(categories)), categories)
            else:  # the grid's values, not matplotlib's round steps between them
                grid = np.unique(numeric)
                ax.set_xticks(grid, [f"{v:g}" for v in grid])
            for i, (_, r) in enumerate(refs.iterrows()):
                if col.metric not in r or not np.isfinite(float(r[col.metric])):
                    continue
                # greys and olives, away from the swept lines' first colours; past three references
                # (a sweep of two splits and two settings has four) the dash changes, so none share a look
                colour, dash = f"C{7 + i % 3}", REFERENCE_DASHES[i // 3 % len(REFERENCE_DASHES)]
                where = "".join(f", {r[c]}" for c in ref_named)
                ax.axhline(k * float(r[col.metric]), color=colour, linestyle=dash, linewidth=1.2,
                           label=f"{ref_names[str(r['variant'])]} (reference{where})")
                lo, hi = float(r.get(f"{col.metric}_lo", np.nan)), float(r.get(f"{col.metric}_hi", np.nan))
                if np.isfinite(lo) and np.isfinite(hi):
                    ax.axhspan(k * lo, k * hi, color=colour, alpha=0.12, linewidth=0)
            arrow = "lower is better" if col.better == "lower" else "higher is better"
            ax.set_title(f"{col.label} ({arrow})")
            ax.set_xlabel(f"{method} option {name}" + (f" ({units[name]})" if units.get(name) else ""))
            ax.set_ylabel(f"{col.label} ({unit})" if unit else col.label)
        for ax in axes[n:]:
            ax.set_visible(False)
        handles, labels = axes[0].get_legend_handles_labels()
        body.legend(handles, labels, loc="outside lower center", ncols=min(3, max(1, len(labels))), fontsize=8)
        ref_note = ("; dashed" + (" (then dash-dot, dotted)" if len(refs) > 3 else "")
                    + ": the reference method, its band its interval") if len(refs) else ""
        # wrapped to the figure: one panel is 4.2 inches, narrower than the sentence
        fig.suptitle(_wrap(f"ablation: {method} {name}\nerror bars: {interval}{ref_note}", 4.2 * ncols, 12))
    return fig


_UNIT_WORDS = {"metres": "m", "meters": "m", "seconds": "s", "degrees": "deg"}
_UNITS = {"m", "s", "deg", "rad", "Hz", "%", "m/s", "m^2", "cm", "mm", "ms", *_UNIT_WORDS}


def _method_units(method: str, plugins=None) -> dict[str, str]:
    """``{option: unit}`` of a method's options, from the trailing ``(unit)`` of each option's
    help text (``"voxel edge (m)"``); empty when the method does not load."""
    from pcfbench.options import describe_options
    from pcfbench.plugins import get_plugins

    out: dict[str, str] = {}
    try:
        cls = (plugins or get_plugins()).methods.get(method)
        fields = describe_options(cls.Options, f"method {method}")
    except (PcfbenchError, AttributeError):
        return out
    for f in fields:
        help_text = (f.help or "").strip()
        m = re.search(r"\(([^()]{1,12})\)$", help_text) or re.search(r", (metres|meters|seconds|degrees)$", help_text)
        if m and m.group(1) in _UNITS:
            out[f.name] = _UNIT_WORDS.get(m.group(1), m.group(1))
    return out


# -- everything for a leaderboard --------------------------------------------------------------
def horizon_data(steps: pd.DataFrame, columns: list, title: str, interval: str | None = None) -> dict:
    """Everything :func:`horizon_figure` plots, for its key (``figcache``): the per-step rows'
    columns it reads (the means and their intervals), in its order, each column's label, unit
    and direction, and how the intervals were computed."""
    used = ["variant", "time_s"] + [c for col in columns for c in (col.metric, f"{col.metric}_lo", f"{col.metric}_hi")
                                    if c in steps]
    return {"title": title, "interval": interval, "steps": steps[used],
            "columns": [(c.metric, c.label, str(c.better), c.unit) for c in columns],
            "legend": short_labels(steps["variant"].unique()) if len(steps) else None}


def range_data(found: StoredRanges, title: str, resampling=None) -> dict:
    """Everything :func:`range_figure` plots, for its key (``figcache``): the profiles, their
    intervals and how they were computed, the legend's labels and footnotes."""
    from pcfbench.reporting import stats
    from pcfbench.store import ranges

    resampling = resampling or stats.Resampling()
    return {"title": title, "profiles": found.profiles, "sweeps": found.sweeps, "missing": found.missing,
            "bin_m": RANGE_BIN_M, "backfill": ranges.BACKFILL_COMMAND, "interval": resampling.describe(),
            "intervals": range_intervals(found, resampling),
            "legend": short_labels([v for v, p in found.profiles.items() if len(p)] + list(found.missing))}


def write_figures(lb, table, store_root: Path, out_dir: Path, *, samples: int = 2, plugins=None,
                  gallery: bool = False, cache=None, ranges: dict[tuple, StoredRanges] | None = None) -> dict[str, Path]:
    """Every figure of leaderboard ``lb`` (complete cells) in the layout of ``table``
    (``tables.Table``: its columns) under ``out_dir``, from the store alone; with ``gallery``
    also the gallery, which re-runs ``samples`` samples per group with every method (0: no
    gallery). ``cache`` (``figcache.FigureCache``): a horizon or range figure whose key it
    holds is not drawn again, and its path is the one in the cache's folder; the gallery is
    always drawn (its data are forecasts made anew). ``ranges``: the :func:`group_ranges` of
    ``lb.table``, if already read. Returns the paths."""
    from pcfbench.plugins import get_setting

    def draw(kind: str, stem: str, data: dict, make) -> None:
        from pcfbench.reporting.figcache import figure_key

        key = figure_key(kind, **data) if cache is not None else ""
        kept = cache.fresh(stem, key) if cache is not None else None
        if kept is not None:
            paths.update(kept)
            return
        drawn = save(make(), out_dir, stem)
        paths.update(drawn)
        if cache is not None:
            cache.record(stem, key, drawn)

    out_dir = Path(out_dir)
    paths: dict[str, Path] = {}
    if not len(lb.table):
        return paths
    columns = table.columns
    steps = lb.by_step[~lb.by_step["partial"].astype(bool)] if len(lb.by_step) else lb.by_step
    rank = table.preset.rank_by or (columns[0].metric if columns else None)
    for key, g in lb.table.groupby(GROUP_KEYS, sort=True):
        first = g.iloc[0]
        title = _group_title(first)
        gs = steps
        for k in ("dataset", "split", "setting", "policy"):
            gs = gs[gs[k] == first[k]] if len(gs) else gs
        gs = gs[gs["variant"].isin(set(g["variant"]))] if len(gs) else gs
        if len(gs) and columns:
            how = lb.resampling.describe()
            draw("horizon", _group_stem("horizon", first), horizon_data(gs, columns, title, how),
                 lambda: horizon_figure(gs, columns, title, how))
        found = ranges[key] if ranges is not None and key in ranges else stored_ranges(store_root, g)
        draw("range", _group_stem("range", first), range_data(found, title, lb.resampling),
             lambda: range_figure(found, title, lb.resampling))
        if not gallery or samples <= 0:
            continue
        ref = g[g["is_reference"]] if "is_reference" in g else g.iloc[0:0]
        base = ref.iloc[0] if len(ref) else g.iloc[0]
        from pcfbench.store.cells import Cell

        rows = Cell.at(store_root, base["cell_dir"]).read_rows()
        ids = choose_samples(rows, rank, samples, any(c.metric == rank and c.better == "higher" for c in columns))
        if not ids:
            continue
        run = rerun(store_root, g, ids, plugins)
        if not run.errors:  # no variant could be re-run
            continue
        try:
            s = get_setting(first["setting"])
            horizon = f"t = +{s.step_seconds(s.future - 1):g} s"
        except PcfbenchError:
            horizon = "last future sweep"
        paths.update(save(gallery_figure(run, title, horizon), out_dir, _group_stem("gallery", first), GALLERY_DPI))
    return paths
