"""Leaderboards regenerated from the store: paper-layout tables with intervals and comparisons.

A report reads the store only: no method runs (the figures' data is stored at run time,
``pcfbench.reporting.figures``), except the gallery, drawn only when asked for (``ReportOptions.gallery``).

:func:`collect` reads every complete cell: the flat mean over (sample, future sweep) of each
metric (the point estimate; skipped sweeps are counted, never averaged), its bootstrap
interval over samples, and, per (dataset, split, setting, policy[, limit]) group, a paired
comparison of every cell with the group's reference method on the samples both scored
(``pcfbench.reporting.stats``). Partial cells (``--limit``) are kept apart in their own tables. A cell
whose samples did not all score (a failed sample, or rows missing for some of the sample ids
its cell.json was created with: :func:`coverage`) is never ranked: it is listed apart with its
coverage ("80/84") in the notes, the summary and ``leaderboard_incomplete.csv``. A
column never mixes metric versions. :func:`write_reports` renders the tables of
``pcfbench.reporting.tables``' presets as Markdown, CSV, LaTeX and HTML.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

from pcfbench.reporting import stats, tables
from pcfbench.reporting.escape import write_csv
from pcfbench.reporting.select import Selection
from pcfbench.errors import PcfbenchError, unknown_name
from pcfbench.reporting.labels import cell_label, method_label, trained_label  # noqa: F401 - re-exported
from pcfbench.store.cells import Cell, iter_cells, spec_from_meta

#: Columns in the order of the published tables; other metrics follow alphabetically.
PREFERRED_ORDER = (
    "chamfer_nf", "chamfer", "l1_mean", "absrel_mean", "l1_median", "absrel_median",
    "chamfer_nf@4docc", "l1@4docc", "absrel@4docc", "l1_ray", "absrel_ray",
)
BLOCK_KEYS = ["dataset", "split", "setting", "policy"]
GROUP_KEYS = BLOCK_KEYS + ["limit"]
DEFAULT_REFERENCE = "copy-last"
DEFAULT_PRESET = "paper"
#: The CSV's leading columns, in this order (scripts read them by position).
CSV_LEAD = ["dataset", "split", "setting", "policy", "method", "method_version", "samples", "failed", "sweeps"]


@dataclass
class ReportOptions:
    """How the report is computed and printed (``pcfbench report``'s options)."""

    preset: str = DEFAULT_PRESET
    tables_file: str | None = None
    reference: str | None = None  # None: DEFAULT_REFERENCE, and groups without it are only noted
    ci: str = "pm"
    resampling: stats.Resampling = field(default_factory=stats.Resampling)
    #: write reports/figures/ (and embed them in leaderboard.html); default: yes, unless the
    #: environment has PCFBENCH_FIGURES=0 (the test suite's quick runs)
    figures: bool = field(default_factory=lambda: os.environ.get("PCFBENCH_FIGURES", "1") != "0")
    #: also draw the gallery of forecasts (``pcfbench report --gallery``): the one figure not
    #: drawn from the store, as it re-runs every method on ``figure_samples`` samples per group
    gallery: bool = False
    #: samples re-run per group for the gallery (0: no gallery)
    figure_samples: int = 2
    #: only the cells it selects (``pcfbench report --dataset/--setting/--method``); the pages say so
    select: Selection = field(default_factory=Selection)


@dataclass
class Leaderboard:
    """``table`` / ``partial``: one row per complete (resp. ``--limit``) cell, holding per
    metric ``m`` the flat mean ``m``, its interval ``m_lo``/``m_hi``, the skipped sweeps
    ``m__skipped`` and against the reference ``m_rel`` (relative change) and ``m_p``.
    ``by_step``: one row per (cell, future step) with the step's time in seconds (``partial``
    marks the ``--limit`` cells' rows).
    ``comparisons``: one row per (cell, metric) paired comparison."""

    table: pd.DataFrame
    by_step: pd.DataFrame
    metric_columns: list[str]
    units: dict[str, str]
    partial: pd.DataFrame = field(default_factory=pd.DataFrame)
    comparisons: pd.DataFrame = field(default_factory=pd.DataFrame)
    resampling: stats.Resampling = field(default_factory=stats.Resampling)
    reference: str = DEFAULT_REFERENCE
    notes: list[str] = field(default_factory=list)
    #: cells whose samples did not all score (failed, or rows missing): never ranked; one row
    #: each with ``coverage`` ("80/84"), ``expected`` and ``missing`` (sample ids without rows)
    incomplete: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: metric -> ``Metric.higher_is_better`` (from the cells' cell.json, else the registry);
    #: a metric neither knows is absent, and its columns are shown lower-is-better
    higher_is_better: dict[str, bool] = field(default_factory=dict)
    #: "" for every cell of the store, else the line that says which filters made this view
    #: (:class:`pcfbench.reporting.select.Selection`), printed on every page made from it
    scope: str = ""


@dataclass(frozen=True)
class Coverage:
    """How many of a cell's samples scored, from its rows checked against its cell.json.

    ``expected``: the samples the cell was created for (``samples`` in cell.json); ``ok`` /
    ``failed``: sample ids whose rows say so; ``missing``: expected samples without rows (a
    chunk deleted), also when the ids present do not hash to the cell's ``sample_ids_hash``.
    A cell is complete only when every expected sample scored."""

    expected: int
    ok: int
    failed: int
    missing: int

    @property
    def complete(self) -> bool:
        return self.ok == self.expected and not self.failed and not self.missing

    @property
    def text(self) -> str:
        return f"{self.ok}/{self.expected}"


def coverage(meta: dict, rows: pd.DataFrame) -> Coverage:
    """The :class:`Coverage` of a cell from its ``cell.json`` and its rows (``Cell.read_rows``)."""
    from pcfbench.protocol import ids_hash

    status = rows.groupby("sample_id")["status"].first() if len(rows) else pd.Series(dtype=object)
    ok = int((status == "ok").sum())
    failed = int((status == "failed").sum())
    expected = int(meta.get("samples") or meta.get("counts", {}).get("samples") or len(status))
    missing = max(expected - len(status), 0)
    want = meta.get("sample_ids_hash")
    if not missing and want and ids_hash([str(i) for i in status.index]) != want:
        missing = max(expected - ok - failed, 1)  # ids other than the cell's own: some are missing
    return Coverage(expected, ok, failed, missing)


#: the provenance of a cell, from its cell.json (:func:`provenance`), in the order the HTML shows it
PROVENANCE_KEYS = ("harness_version", "protocol_version", "method_version", "metric_versions", "git_commit",
                   "data_fingerprint", "checkpoint_sha256", "date")


def provenance(meta: dict) -> dict[str, str]:
    """What a cell's numbers were computed with: harness, protocol, method and metric versions,
    git commit, dataset fingerprint, checkpoint sha256 (trained methods) and the date its
    rows were last written (UTC), as strings ("" where cell.json lacks one)."""
    import datetime

    when = meta.get("updated") or meta.get("created")
    date = (datetime.datetime.fromtimestamp(float(when), datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
            if isinstance(when, (int, float)) else "")
    versions = meta.get("metric_versions") or {}
    return {
        "prov_harness_version": str(meta.get("harness_version") or ""),
        "prov_protocol_version": str(meta.get("protocol_version") or ""),
        "prov_method_version": str(meta.get("method_version") or ""),
        "prov_metric_versions": ", ".join(f"{k} v{v}" for k, v in sorted(versions.items())),
        "prov_git_commit": str(meta.get("git_commit") or ""),
        "prov_data_fingerprint": str(meta.get("data_fingerprint") or ""),
        "prov_checkpoint_sha256": str(meta.get("checkpoint_sha256") or (meta.get("spec") or {}).get("checkpoint_sha256") or ""),
        "prov_date": date,
    }


def _step_seconds(setting: str, steps: np.ndarray, notes: list[str]) -> np.ndarray:
    from pcfbench.plugins import get_setting

    try:
        s = get_setting(setting)
    except PcfbenchError as exc:
        notes.append(f"per-horizon times of setting {setting!r} unknown ({exc}); time_s left empty")
        return np.full(len(steps), np.nan)
    return np.array([s.step_seconds(int(k)) for k in steps])


def _horizon(setting: str) -> float:
    from pcfbench.plugins import get_setting

    try:
        return get_setting(setting).horizon_s
    except PcfbenchError:
        return math.nan


def _check_versions(versions: dict[str, dict[str, list[str]]]) -> None:
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


def collect(store_root: Path, resampling: stats.Resampling | None = None,
            reference: str | None = None, cells: Iterable[Path] | None = None,
            reference_options_hash: str | None = None, select: Selection | None = None,
            plugins=None) -> Leaderboard:
    """Read and analyse every complete cell under ``store_root``.

    ``reference``: the method every cell is compared with; None means ``copy-last`` where a
    group has it. A reference named explicitly must be a method of the store; by its name alone
    it is the method's cell of the shortest label in each group, as ``NAME:key=value,...`` (a
    method spec, as ``pcfbench run -m`` takes it, resolved against ``plugins``, default the
    installed ones) its cell of exactly those options, which the store must hold.
    ``reference_options_hash``: with ``reference``, only its cell of these options is the
    reference (a sweep's reference row). ``cells``: only these cell folders (a sweep's grid).
    ``select``: only the cells it matches (a pattern that matches no cell is one error listing
    what the store holds); ``Leaderboard.scope`` then says so.
    """
    from threadpoolctl import threadpool_limits

    label = reference
    if reference is not None and ":" in reference:
        if reference_options_hash is not None:
            raise ValueError(f"reference {reference!r}: give its options in the spec or as reference_options_hash, not both")
        from pcfbench.method import resolve_method

        spec = resolve_method(reference, plugins)
        reference, reference_options_hash = spec.name, spec.options_hash
    # The products are small (resamples x units x metrics): BLAS threads only add overhead.
    with threadpool_limits(1):
        board = _collect(Path(store_root), resampling or stats.Resampling(), reference,
                         None if cells is None else {Path(c).resolve() for c in cells}, reference_options_hash,
                         select or Selection())
    if label == reference:
        return board
    scored = pd.concat([board.table, board.partial])
    own = scored[scored["method"] == reference] if len(scored) else scored
    if len(scored) and not (own["options_hash"] == reference_options_hash).any():
        raise PcfbenchError(f"reference {label!r}: the store has no complete cell of {reference} with these options "
                            f"(options hash {reference_options_hash}); its cells: "
                            f"{', '.join(sorted(set(own['variant'])))}")
    return dataclasses.replace(board, reference=label)


def _collect(store_root: Path, resampling: stats.Resampling, reference: str | None,
             cells: set[Path] | None = None, reference_options_hash: str | None = None,
             select: Selection = Selection()) -> Leaderboard:
    rows, step_rows, sums, notes = [], [], [], []
    held = []  # every cell this report could read: what a selection is checked against
    versions = {False: {}, True: {}}
    units: dict[str, str] = {}
    directions: dict[str, bool] = {}
    for cell_dir, meta in iter_cells(store_root):
        if meta.get("status") != "complete" or (cells is not None and cell_dir.resolve() not in cells):
            continue
        spec = spec_from_meta(meta)
        held.append(spec)
        if not select.matches(spec):
            continue
        partial = bool(meta.get("partial"))
        # in sample order: every mean below adds in one order, whatever the chunk order
        df = stats.in_sample_order(Cell(store_root, spec).read_rows())
        ok = df[df["status"] == "ok"] if len(df) else df
        cov = coverage(meta, df)  # from the rows: a deleted chunk cannot claim its samples
        metric_versions = meta.get("metric_versions", {})
        units.update(meta.get("metric_units", {}))
        directions.update(meta.get("metric_higher_is_better", {}))
        base = {
            "dataset": spec.dataset, "split": spec.split, "setting": spec.setting, "policy": spec.policy,
            "method": spec.method, "method_version": meta.get("method_version"),
            "samples": cov.ok, "failed": cov.failed, "expected": cov.expected, "missing": cov.missing,
            "coverage": cov.text, "incomplete": not cov.complete,
            "sweeps": len(ok), "variant": method_label(spec.method, spec.options) + trained_label(spec, meta),
            "options_hash": spec.options_hash, "train_on": spec.train_on or "",
            "checkpoint_sha256": spec.checkpoint_sha256 or "",
            "on_training_data": bool(meta.get("evaluated_on_training_data", False)),
            "limit": spec.limit if partial else None, "subset": spec.subset, "horizon_s": _horizon(spec.setting),
            "cell_dir": str(cell_dir.resolve()), **provenance(meta),
        }
        for k, v in sorted(spec.options.items()):
            base[f"option.{k}"] = v
        block = tuple(str(base[k]) for k in BLOCK_KEYS)
        names = sorted(metric_versions)
        for name, version in metric_versions.items():
            versions[partial].setdefault(name, {}).setdefault(version, []).append(f"{cell_dir} ({'/'.join(block)})")
        ss = stats.sample_sums(ok, names)
        iv = stats.interval(ss, resampling)
        row = dict(base, partial=partial, ci_units=iv.units)
        for j, name in enumerate(names):
            values = ok[name].to_numpy(dtype=float) if name in ok else np.array([])
            row[name] = float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")
            row[f"{name}_lo"], row[f"{name}_hi"] = float(iv.lo[j]), float(iv.hi[j])
            row[f"{name}__skipped"] = int((~np.isfinite(values)).sum())
        rows.append(row)
        sums.append(ss)
        if len(ok) and cov.complete:  # an incomplete cell's per-horizon means are not published
            groups = list(ok.groupby("step"))
            seconds = _step_seconds(spec.setting, np.array([s for s, _ in groups]), notes)
            for (step, g), t in zip(groups, seconds):
                srow = {k: base[k] for k in ("dataset", "split", "setting", "policy", "method", "variant", "options_hash", "limit")}
                srow["partial"] = partial
                srow.update(step=int(step), time_s=float(t), sweeps=len(g))
                siv = stats.interval(stats.sample_sums(g, names), resampling)
                for j, name in enumerate(names):
                    v = g[name].to_numpy(dtype=float) if name in g else np.array([])
                    srow[name] = float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
                    srow[f"{name}_lo"], srow[f"{name}_hi"] = float(siv.lo[j]), float(siv.hi[j])
                step_rows.append(srow)
    select.check(held)
    scope = (f"filtered view: only the cells matching {select.describe()} ({len(rows)} of the store's {len(held)} "
             "complete cells)" if select.active else "")
    _check_versions(versions[False])
    _check_versions(versions[True])
    all_names = set(versions[False]) | set(versions[True])
    metric_cols = sorted(all_names, key=lambda n: (PREFERRED_ORDER.index(n) if n in PREFERRED_ORDER else 99, n))
    table = pd.DataFrame(rows)
    if len(table) and reference is not None and reference not in set(table["method"]):
        if select.active and reference in {s.method for s in held}:
            raise PcfbenchError(f"the reference method {reference!r} is not among the cells selected by "
                                f"{select.describe()}: add --method {reference}")
        raise unknown_name("reference method", reference, set(table["method"]), "the store has no cell of it")
    reference = reference or DEFAULT_REFERENCE
    incomplete = pd.DataFrame()
    if len(table):
        incomplete = table[table["incomplete"]].sort_values(GROUP_KEYS + ["variant"], na_position="first")
        table = table[~table["incomplete"]].copy()
        for _, r in incomplete.iterrows():
            limit = _partial_note(r)
            notes.append(f"{r['dataset']} / {r['split']} / {r['setting']}{limit} {r['variant']}: INCOMPLETE, "
                         f"{r['coverage']} samples scored ({r['failed']} failed, {r['missing']} without rows): "
                         "not ranked (leaderboard_incomplete.csv)")
    notes.extend(_subset_notes(table))
    for _, r in table.iterrows():
        if r["ci_units"] < stats.MIN_UNITS:
            limit = _partial_note(r)
            notes.append(f"{r['dataset']} / {r['split']} / {r['setting']}{limit} {r['variant']}: {r['ci_units']} "
                         f"resampling unit(s) ({resampling.unit}), too few for an interval")
    comparisons = (_compare_groups(table, sums, reference, resampling, notes, reference_options_hash)
                   if len(table) else pd.DataFrame())
    if len(table):
        table["partial"] = table["partial"].astype(bool)
        table = table.sort_values(GROUP_KEYS + ["variant"], na_position="first").reset_index(drop=True)
        complete, partial_t = table[~table["partial"]], table[table["partial"]]
    else:
        complete, partial_t = table, table
    directions = metric_directions(metric_cols, directions, notes)
    return Leaderboard(complete.reset_index(drop=True), pd.DataFrame(step_rows), metric_cols, units,
                       partial_t.reset_index(drop=True), comparisons, resampling, reference, sorted(set(notes)),
                       incomplete=incomplete.reset_index(drop=True), higher_is_better=directions, scope=scope)


def _subset_notes(table: pd.DataFrame) -> list[str]:
    """One note per table whose rows score different samples: which methods scored a subset
    (``CellSpec.subset``) and how many of the most any row of the table scored."""
    if not len(table) or "subset" not in table or not table["subset"].notna().any():
        return []
    out = []
    for key, g in table.groupby(["dataset", "split", "setting", "policy"], sort=True):
        most = int(g["samples"].max())
        sub = g[g["subset"].notna() & ~g["partial"].astype(bool) & (g["samples"] < most)]
        if not len(sub):  # a subset as large as the policy's samples is all of them
            continue
        # a method scored with two option sets (the default run's two token-copies) is named by both
        labels = sub["variant"].map(lambda v: str(v).split(" [trained on ")[0])
        names = ", ".join(f"{m} ({int(n)})" for m, n in sorted(zip(labels, sub["samples"])))
        out.append(f"{' / '.join(map(str, key[:3]))}: {names} scored a subset of the {most} samples, "
                   "evenly spaced (the default run's for its slowest methods, docs/protocol.md); each is compared "
                   "with the reference on the samples they share; `pcfbench run --subset 0` scores every sample")
    return out


def _partial_note(r) -> str:
    """`` (limit=N)`` for a --limit cell's row, `` (partial)`` for another partial one (a
    submission missing samples, ``pcfbench score --partial``), else ""."""
    if not r["partial"]:
        return ""
    return f" (limit={int(r['limit'])})" if pd.notna(r["limit"]) else " (partial)"


def metric_directions(names: list[str], recorded: dict[str, bool], notes: list[str] | None = None) -> dict[str, bool]:
    """``Metric.higher_is_better`` of each metric of ``names``: as the cells recorded it
    (``metric_higher_is_better`` in cell.json), else from the metric registry (cells written
    before the direction was recorded). A metric neither knows (its plugin is not installed)
    is left out, with a line in ``notes``."""
    out = {n: bool(recorded[n]) for n in names if n in recorded}
    missing = [n for n in names if n not in out]
    if missing:
        from pcfbench.plugins import get_plugins

        registry = get_plugins().metrics
        for name in missing:
            try:
                out[name] = bool(registry.get(name).higher_is_better)
            except PcfbenchError:  # not registered, or its plugin fails to load
                if notes is not None:
                    notes.append(f"metric {name!r}: which way is better is neither recorded in its cells nor known "
                                 "to an installed plugin; its columns are shown lower-is-better")
    return out


def _compare_groups(table: pd.DataFrame, sums: list, reference: str, resampling: stats.Resampling,
                    notes: list[str], reference_options_hash: str | None = None) -> pd.DataFrame:
    """Fill ``m_rel``/``m_p`` of ``table`` in place; the long comparison table."""
    table["is_reference"] = False
    out = []
    keyed = table.assign(_limit=table["limit"].fillna(-1))
    for key, g in keyed.groupby(BLOCK_KEYS + ["_limit"], sort=True):
        refs = g[g["method"] == reference].sort_values("variant", key=lambda s: s.str.len())
        if reference_options_hash is not None:
            refs = refs[refs["options_hash"] == reference_options_hash]
        if not len(refs):
            notes.append(f"{' / '.join(map(str, key[:4]))}: no {reference!r} cell to compare with")
            continue
        ri = refs.index[0]
        table.loc[ri, "is_reference"] = True
        rss = sums[ri]
        for i in g.index:
            if i == ri:
                continue
            css = sums[i]
            if css.metrics != rss.metrics:
                common = tuple(m for m in css.metrics if m in rss.metrics)
                css, rss_i = _restrict(css, common), _restrict(rss, common)
            else:
                rss_i = rss
            c = stats.compare(css, rss_i, resampling)
            for j, name in enumerate(css.metrics):
                table.loc[i, f"{name}_rel"] = float(c.relative[j])
                table.loc[i, f"{name}_p"] = float(c.p[j])
                out.append({
                    **{k: table.loc[i, k] for k in BLOCK_KEYS + ["limit", "method", "variant", "options_hash"]},
                    "reference": table.loc[ri, "variant"], "metric": name, "shared_samples": c.shared,
                    "ci_units": c.units, "mean": float(c.mean[j]), "reference_mean": float(c.reference_mean[j]),
                    "diff": float(c.diff[j]), "diff_lo": float(c.diff_lo[j]), "diff_hi": float(c.diff_hi[j]),
                    "relative_change": float(c.relative[j]), "p_value": float(c.p[j]),
                    "significant": bool(np.isfinite(c.p[j]) and c.p[j] < 1 - resampling.confidence),
                })
    return pd.DataFrame(out)


def _restrict(ss: stats.SampleSums, metrics: tuple[str, ...]) -> stats.SampleSums:
    cols = [ss.metrics.index(m) for m in metrics]
    return stats.SampleSums(ss.sample_ids, ss.sequences, ss.ref_index, metrics, ss.sums[:, cols], ss.counts[:, cols])


def _csv_frame(lb: Leaderboard, df: pd.DataFrame) -> pd.DataFrame:
    option_cols = sorted(c for c in df.columns if c.startswith("option."))
    metric_cols = []
    for m in lb.metric_columns:
        metric_cols += [m, f"{m}_lo", f"{m}_hi", f"{m}_rel", f"{m}_p"]
    keep = (CSV_LEAD + ["variant", "options_hash", "train_on", "checkpoint_sha256", "on_training_data"] + option_cols
            + ["horizon_s", "ci_units", "is_reference"] + metric_cols)
    if not len(df):
        return pd.DataFrame(columns=keep)
    return df.reindex(columns=keep)


class ReportPaths(dict):
    """What :func:`write_reports` wrote: key -> final path, as a dict; ``kept_figures``: the
    stems of the figures left in place because their data had not changed (not drawn again);
    ``range_gaps``: the notes on cells whose range bins the store lacks (figures only)."""

    kept_figures: tuple[str, ...] = ()
    range_gaps: tuple[str, ...] = ()


def written_summary(paths: ReportPaths, out_dir: Path) -> str:
    """One line for the terminal: how many tables and figures a report wrote, and where."""
    tables_written = sum(1 for k in paths if k == "md" or (k.startswith("tables/") and k.endswith(".md")))
    stems = {Path(k).stem for k in paths if k.startswith("figures/")}
    kept = len(set(getattr(paths, "kept_figures", ())) & stems)
    figs = f"{len(stems)} figure(s)" + (f" ({kept} unchanged, not redrawn)" if kept else "") if stems else "no figures"
    return (f"wrote {tables_written} tables (leaderboard and tables/), {figs} to {out_dir}; "
            f"leaderboard: {paths['md']} and {paths['html'].name} (-v lists every file)")


def write_reports(store_root: Path, out_dir: Path, options: ReportOptions | None = None,
                  leaderboard: Leaderboard | None = None, plugins=None) -> ReportPaths:
    """Write the leaderboard (Markdown, CSV, LaTeX in the chosen preset; ``leaderboard.html`` the
    self-contained page with the figures), the per-horizon and comparison CSVs, every preset's
    tables under ``tables/`` and the figures under ``figures/``; returns the final paths.

    Published atomically: everything is written into a staging folder inside ``out_dir`` first,
    then each file is renamed into place, so a report killed at any moment leaves every file
    either old or new, never half written. ``leaderboard``: the :func:`collect` result of the
    same store and options, if already made.

    A figure whose key (a hash of exactly what it plots and of the figure code:
    ``pcfbench.reporting.figcache``) is the one recorded in ``figures/.figures.json`` for the
    file in place is not drawn again: that file stays.
    """
    import shutil

    options = options or ReportOptions()
    presets = tables.load_presets(options.tables_file)
    main = tables.get_preset(options.preset, presets)
    out_dir = Path(out_dir)
    check_reports_dir(out_dir)
    lb = leaderboard or collect(store_root, options.resampling, options.reference, select=options.select)
    out_dir.mkdir(parents=True, exist_ok=True)
    _remove_stale_staging(out_dir)
    stage = out_dir / f".report-{os.getpid()}.tmp"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    rel: dict[str, Path] = {}  # key -> path relative to out_dir
    found_ranges, gaps = None, []
    if options.figures:  # a cell whose range bins the store lacks: the tables say so too
        from pcfbench.reporting.figures import group_ranges, range_gaps

        found_ranges = group_ranges(store_root, lb.table)  # read once: for these notes and the figures
        gaps = range_gaps(lb, store_root, found_ranges)
        if gaps:
            lb = dataclasses.replace(lb, notes=sorted(set(lb.notes) | set(gaps)))
    try:
        def render(preset, stem: Path, key: str | None, page: bool = False) -> tables.Table:
            t = tables.build(lb, preset, options.ci)
            tex, _fit = tables.latex(t)  # the fit is the .tex file's first line
            for ext, content in (("md", tables.markdown(t)), ("tex", tex), ("html", None if page else tables.html_page(t))):
                if content is None:
                    continue
                (stage / stem).with_suffix(f".{ext}").write_text(content)
                rel[f"{key}.{ext}" if key else ext] = stem.with_suffix(f".{ext}")
            return t

        main_table = render(main, Path("leaderboard"), None, page=True)
        figures: dict[str, Path] = {}
        cache = None
        in_place: set[str] = set()  # keys of the figures kept where they are: nothing to publish
        if options.figures:
            from pcfbench.reporting.figcache import FigureCache
            from pcfbench.reporting.figures import FIGURES_DIR, write_figures

            cache = FigureCache(out_dir / FIGURES_DIR)
            figures = write_figures(lb, main_table, store_root, stage / FIGURES_DIR, samples=options.figure_samples,
                                    plugins=plugins, gallery=options.gallery, cache=cache, ranges=found_ranges)
            for name, p in figures.items():
                if p.is_relative_to(stage):
                    rel[f"figures/{name}"] = p.relative_to(stage)
                else:
                    rel[f"figures/{name}"] = p.relative_to(out_dir)
                    in_place.add(f"figures/{name}")
        from pcfbench.reporting.htmlreport import page

        (stage / "leaderboard.html").write_text(page(main_table, lb, figures, generated=(
            f"generated by pcfbench {__import__('pcfbench').__version__} from the store {store_root}; "
            "each cell's date is in its provenance")))
        rel["html"] = Path("leaderboard.html")
        rel["csv"] = Path("leaderboard.csv")
        write_csv(_csv_frame(lb, lb.table), stage / rel["csv"])
        rel["partial_csv"] = Path("leaderboard_partial.csv")
        write_csv(_csv_frame(lb, lb.partial), stage / rel["partial_csv"])
        for key, name, keep in (("by_step", "leaderboard_by_step.csv", False), ("partial_by_step", "leaderboard_partial_by_step.csv", True)):
            rel[key] = Path(name)
            steps = lb.by_step[lb.by_step["partial"] == keep] if len(lb.by_step) else lb.by_step
            write_csv(steps.drop(columns="partial", errors="ignore"), stage / name)
        rel["incomplete_csv"] = Path("leaderboard_incomplete.csv")
        incomplete = _csv_frame(lb, lb.incomplete)
        incomplete.insert(CSV_LEAD.index("samples"), "coverage", lb.incomplete["coverage"] if len(lb.incomplete) else [])
        incomplete.insert(CSV_LEAD.index("failed") + 2, "missing", lb.incomplete["missing"] if len(lb.incomplete) else [])
        write_csv(incomplete, stage / rel["incomplete_csv"])
        rel["comparisons"] = Path("leaderboard_comparisons.csv")
        write_csv(lb.comparisons, stage / rel["comparisons"])
        from pcfbench.reporting.transfer import write_transfer  # trained cells: the zero-shot table (Copilot4D Table 5)

        for key, p in write_transfer(lb, stage).items():
            rel[key] = Path(p).relative_to(stage)
        (stage / "tables").mkdir(exist_ok=True)
        for name, preset in presets.items():
            render(preset, Path("tables") / name, f"tables/{name}")
        publish(stage, out_dir, [rel[k] for k in rel if k not in in_place])
        if cache is not None:  # after the figures it describes are in place
            cache.write()
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    if "transfer_md" not in rel:  # no trained cells (any more): no transfer table
        for name in ("transfer.md", "transfer.csv"):
            (out_dir / name).unlink(missing_ok=True)
    if options.figures:
        _remove_old_figures(out_dir, {p.name for k, p in rel.items() if k.startswith("figures/")})
    written = ReportPaths({k: out_dir / p for k, p in rel.items()})
    written.kept_figures = tuple(cache.kept) if cache is not None else ()
    written.range_gaps = tuple(gaps)
    return written


def check_reports_dir(out_dir: Path) -> None:
    """One clear error when the reports folder is an existing file (or lies below one)."""
    for p in [Path(out_dir), *Path(out_dir).parents]:
        if p.exists() and not p.is_dir():
            raise PcfbenchError(f"the reports folder {out_dir} cannot be created: {p} is a file, not a folder "
                                "(give --reports / $PCFBENCH_REPORTS a folder)")
        if p.exists():
            return


def publish(stage: Path, out_dir: Path, files: list[Path]) -> None:
    """Rename each of ``files`` (relative paths) from ``stage`` into ``out_dir`` (same file
    system: each rename is atomic); leaderboard.* last, so a reader who sees the new
    leaderboard sees the new tables and figures too."""
    for f in sorted(files, key=lambda f: (f.parts[0] == f.name and f.name.startswith("leaderboard."), str(f))):
        dest = out_dir / f
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(stage / f, dest)


def _remove_stale_staging(out_dir: Path) -> None:
    """Staging folders of reports that were killed (their process is gone)."""
    import shutil

    for d in out_dir.glob(".report-*.tmp"):
        try:
            pid = int(d.name.split("-")[1].split(".")[0])
            os.kill(pid, 0)
            if pid == os.getpid():
                raise ProcessLookupError
        except (ValueError, ProcessLookupError):
            shutil.rmtree(d, ignore_errors=True)
        except PermissionError:
            pass


def _remove_old_figures(out_dir: Path, keep: set[str]) -> None:
    """Leaderboard figures of groups that are gone (a sweep's ablation figures stay)."""
    d = out_dir / "figures"
    if not d.is_dir():
        return
    for p in d.iterdir():
        if p.name.startswith(("horizon-", "range-", "gallery-")) and p.name not in keep:
            p.unlink(missing_ok=True)


def summary(store_root: Path, options: ReportOptions | None = None, leaderboard: Leaderboard | None = None) -> str:
    """The terminal summary: the preset's columns with intervals, a block per group."""
    options = options or ReportOptions()
    preset = tables.get_preset(options.preset, tables.load_presets(options.tables_file))
    lb = leaderboard or collect(store_root, options.resampling, options.reference, select=options.select)
    out = tables.text(tables.build(lb, preset, options.ci))
    if len(lb.incomplete):
        lines = [f"INCOMPLETE cells, not ranked ({len(lb.incomplete)}): samples scored / expected"]
        for _, r in lb.incomplete.iterrows():
            lines.append(f"  {r['dataset']} / {r['split']} / {r['setting']}  {r['variant']}: {r['coverage']} "
                         f"({r['failed']} failed, {r['missing']} without rows)")
        out = (out + "\n\n" if out else "") + "\n".join(lines)
    return out


def failures(store_root: Path) -> pd.DataFrame:
    """Every failed sample of the store: one row per (cell, sample) with ``cell`` (its label,
    options included), ``cell_dir``, ``sample_id``, ``error`` (the exception's first line) and
    ``traceback``, cells in store order, samples in sample order."""
    out = []
    for cell_dir, meta in iter_cells(store_root):
        spec = spec_from_meta(meta)
        rows = Cell(store_root, spec).read_rows()
        if not len(rows) or "status" not in rows:
            continue
        bad = stats.in_sample_order(rows[rows["status"] == "failed"])
        for _, r in bad.iterrows():
            out.append({"cell": cell_label(spec), "cell_dir": str(cell_dir), "sample_id": r["sample_id"],
                        "error": str(r.get("error") or "").splitlines()[0] if r.get("error") else "",
                        "traceback": str(r.get("traceback") or "")})
    return pd.DataFrame(out, columns=["cell", "cell_dir", "sample_id", "error", "traceback"])
