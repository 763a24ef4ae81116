"""Sweeps: an experiment file (TOML) names a grid of cells; ``run_sweep`` runs it resumably
and writes its ablation tables.

The experiment file is data (read with ``tomllib``, nothing in it is executed); its format is
documented in docs/experiments.md. :func:`load_experiment` checks every key, method, option
(against the method's typed ``Options`` through ``pcfbench.method.resolve_method``), seed,
setting, split, policy, metric, dataset and table before anything runs: a bad file is one
``PcfbenchError`` naming the file and the key, and nothing is written.

The grid is method variant x dataset x split x setting. Each cell runs through
``pcfbench.running.runner.run_cell`` into the results store like any ``pcfbench run`` cell (same
paths, same identity), so a finished cell is reused, an interrupted one resumed, and
``pcfbench report`` sees them too. The ablation table (one row per variant in the
experiment's order, the preset's columns, the relative change against the experiment's
reference row, as in Copilot4D's Tables 3 and 4) is computed by ``pcfbench.reporting.report.collect``
over the sweep's cells only and rendered by ``pcfbench.reporting.tables`` as Markdown, CSV, LaTeX and
HTML under ``<reports>/sweeps/``. Each file is written whole (a temporary file renamed into
place) after every cell is complete.
"""

from __future__ import annotations

import dataclasses
import itertools
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import pandas as pd

from pcfbench import config
from pcfbench.errors import PcfbenchError, UnknownNameError, unknown_name
from pcfbench.method import MethodSpec, resolve_method
from pcfbench.plugins import Plugins, get_plugins
from pcfbench.reporting.labels import cell_label, method_label
from pcfbench.store.cells import CellSpec, atomic_write_bytes

__all__ = ["Experiment", "SweepResult", "TableSpec", "Variant", "ablation_tables", "count_cells", "iter_plan",
           "load_experiment", "plan", "run_sweep"]

#: top-level keys of an experiment file, and those of its [[methods]] and [[tables]] entries
EXPERIMENT_KEYS = ("name", "description", "methods", "datasets", "settings", "splits", "policy", "metrics",
                   "seeds", "train_on", "train_split", "limit", "jobs", "max_cells", "tables")
METHOD_KEYS = ("name", "options", "grid", "variants", "seeds")
TABLE_KEYS = ("preset", "reference", "stem", "title", "ci")
#: the reference row of a table when the file names none, if the grid has it
DEFAULT_REFERENCE = "copy-last"
#: the most cells a grid may have unless the file (``max_cells``) or ``--max-cells`` raises it:
#: a typo in a grid (one list too many) is refused at once, before anything is expanded or run
MAX_CELLS = 1000
SWEEPS_DIR = "sweeps"
_STEM = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class Variant:
    """One row of the grid's methods: a resolved method spec and its row label."""

    method: MethodSpec
    label: str
    where: str  # the key that made it, e.g. "methods[1].grid"

    @property
    def key(self) -> tuple[str, str]:
        return (self.method.name, self.method.options_hash)


@dataclass(frozen=True)
class TableSpec:
    """One ablation table: the preset's columns, the reference row, the output stem."""

    preset: str
    reference: Variant
    stem: str
    title: str
    ci: str = "pm"


@dataclass(frozen=True)
class Experiment:
    """A validated experiment file. ``datasets`` holds (name, root or None: configured or
    the adapter's default); empty ``settings``/``splits`` mean each dataset's defaults."""

    path: Path
    name: str
    description: str
    variants: tuple[Variant, ...]
    datasets: tuple[tuple[str, str | None], ...]
    settings: tuple[str, ...]
    splits: tuple[str, ...]
    #: None: each dataset's ``default_policy``
    policy: str | None
    metrics: tuple[str, ...]
    train_on: tuple[str, ...]
    train_split: str
    limit: int | None
    jobs: int
    tables: tuple[TableSpec, ...]
    #: the cap on the grid's cells this file was checked against
    max_cells: int = MAX_CELLS


class _Reader:
    """Prefixes every error with the file and the key at fault (keeping its type)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def error(self, key: str, message: str, cls: type[PcfbenchError] = PcfbenchError) -> PcfbenchError:
        return cls(f"experiment {self.path}: {key}: {message}")

    def wrap(self, key: str, exc: PcfbenchError) -> PcfbenchError:
        cls = UnknownNameError if isinstance(exc, UnknownNameError) else PcfbenchError
        return self.error(key, str(exc), cls)

    def keys(self, table: dict, allowed: tuple[str, ...], where: str) -> None:
        for k in table:
            if k not in allowed:
                raise self.wrap(f"{where}{k}" if where else k, unknown_name("key", k, allowed))

    def strings(self, value: Any, key: str, allow_scalar: bool = True) -> tuple[str, ...]:
        if allow_scalar and isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
            raise self.error(key, f"expected a non-empty list of strings, got {value!r}")
        dupes = sorted({v for v in value if value.count(v) > 1})
        if dupes:
            raise self.error(key, f"{', '.join(map(repr, dupes))} given twice")
        return tuple(value)


def _option_text(value: Any, key: str, reader: _Reader) -> str:
    """A TOML option value as the string a method spec would carry, so that the method's
    typed parser converts it exactly as on the command line (an integer 1 for a float option
    is the float 1.0, and hashes the same as ``NAME:key=1``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return value
    raise reader.error(key, f"an option value must be a string, number or boolean, got {value!r}")


def _count_variants(entry: Any, seeds: Any) -> int:
    """How many variants a [[methods]] entry makes (grid: the product of its lists' lengths;
    times its seeds), counted without making them; malformed entries count 1 (and are refused
    with their own error when they are read)."""
    if not isinstance(entry, dict):
        return 1
    seeds = entry.get("seeds", seeds)
    n = len(seeds) if isinstance(seeds, list) and seeds else 1
    if isinstance(entry.get("grid"), dict):
        for values in entry["grid"].values():
            n *= max(1, len(values)) if isinstance(values, list) else 1
    elif isinstance(entry.get("variants"), list):
        n *= max(1, len(entry["variants"]))
    return n


def _check_size(reader: _Reader, cells: int, cap: int, what: str) -> None:
    if cells > cap:
        raise reader.error("max_cells", f"the grid has {cells:,} cells ({what}), over the cap of {cap:,}: check the "
                                        f"grid's lists, or raise the cap (max_cells = {cells} in the file, or "
                                        f"--max-cells {cells})")


def _variants_of(entry: Any, index: int, seeds: Any, plugins: Plugins, reader: _Reader) -> list[Variant]:
    where = f"methods[{index}]"
    if not isinstance(entry, dict):
        raise reader.error(where, f"expected a table {{name = ..., grid = {{...}}}}, got {entry!r}")
    reader.keys(entry, METHOD_KEYS, f"{where}.")
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise reader.error(f"{where}.name", f"expected a method name, got {name!r}")
    try:
        cls = plugins.methods.get(name)
    except PcfbenchError as exc:
        raise reader.wrap(f"{where}.name", exc) from None
    if "grid" in entry and "variants" in entry:
        raise reader.error(where, "give grid (a product of option lists) or variants (explicit option sets), not both")
    base = entry.get("options", {})
    if not isinstance(base, dict):
        raise reader.error(f"{where}.options", f"expected a table of option = value, got {base!r}")
    option_sets: list[tuple[str, dict[str, Any]]] = []
    if "grid" in entry:
        grid = entry["grid"]
        if not isinstance(grid, dict) or not grid:
            raise reader.error(f"{where}.grid", f"expected a table of option = [values], got {grid!r}")
        axes = []
        for k, values in grid.items():
            values = values if isinstance(values, list) else [values]
            if not values:
                raise reader.error(f"{where}.grid.{k}", "an empty list of values")
            axes.append([(k, v) for v in values])
        for combo in itertools.product(*axes):
            option_sets.append((f"{where}.grid", dict(combo)))
    elif "variants" in entry:
        variants = entry["variants"]
        if not isinstance(variants, list) or not variants or not all(isinstance(v, dict) for v in variants):
            raise reader.error(f"{where}.variants", f"expected a non-empty list of option tables, got {variants!r}")
        option_sets = [(f"{where}.variants[{i}]", dict(v)) for i, v in enumerate(variants)]
    else:
        option_sets = [(where, {})]
    seeds = entry.get("seeds", seeds)
    seed_key = f"{where}.seeds" if "seeds" in entry else "seeds"
    if seeds is not None:
        if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
            raise reader.error(seed_key, f"expected a non-empty list of integers, got {seeds!r}")
        fields = [f.name for f in dataclasses.fields(cls.Options)]
        if "seed" not in fields:
            raise reader.error(seed_key, f"method {name} has no 'seed' option to pass the seeds to (its options: "
                               f"{', '.join(fields) or 'none'})")
    out = []
    for key, opts in option_sets:
        merged = dict(base)
        for k in opts:
            if k in merged:
                raise reader.error(f"{key}.{k}", f"option {k!r} is also fixed in {where}.options")
        merged.update(opts)
        if seeds is not None and "seed" in merged:
            raise reader.error(f"{key}.seed", f"give the seed in {seed_key} or as an option, not both")
        for seed in seeds if seeds is not None else [None]:
            raw = {k: _option_text(v, f"{key}.{k}", reader) for k, v in merged.items()}
            if seed is not None:
                raw["seed"] = str(seed)
            try:
                spec = resolve_method((name, raw), plugins)
            except PcfbenchError as exc:
                raise reader.wrap(key, exc) from None
            out.append(Variant(spec, method_label(name, raw), key))
    return out


def _datasets(value: Any, reader: _Reader, plugins: Plugins) -> tuple[tuple[str, str | None], ...]:
    items = reader.strings(value, "datasets")
    out = []
    for item in items:
        name, sep, root = item.partition("=")
        try:
            plugins.datasets.get(name)
        except PcfbenchError as exc:
            raise reader.wrap("datasets", exc) from None
        if sep and not root:
            raise reader.error("datasets", f"{item!r}: empty root (use NAME=ROOT)")
        if sep:
            path, _, query = root.partition("?")
            p = Path(path).expanduser()
            if not p.is_absolute():
                p = reader.path.parent / p  # relative to the experiment file
            if not p.exists():
                raise reader.error("datasets", f"{item!r}: root {p} does not exist")
            root = str(p.resolve()) + (f"?{query}" if query else "")
        if name in [n for n, _ in out]:
            raise reader.error("datasets", f"dataset {name!r} given twice")
        out.append((name, root if sep else None))
    return tuple(out)


def load_experiment(path: str | Path, plugins: Plugins | None = None, max_cells: int | None = None) -> Experiment:
    """Read and validate experiment file ``path``; every problem is one error naming the
    file and the key (``PcfbenchError``, ``UnknownNameError`` with a did-you-mean).

    A grid of more than ``max_cells`` cells (default: the file's ``max_cells``, else
    ``MAX_CELLS``) is refused, naming the count: first from the method variants alone, counted
    before any is made, then from every dataset, split, setting and checkpoint."""
    from pcfbench.reporting import tables as tables_mod
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SAMPLE_POLICIES, check_compatible

    path = Path(path)
    plugins = plugins or get_plugins()
    reader = _Reader(path)
    if not path.is_file():
        raise PcfbenchError(f"experiment file {path} does not exist")
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PcfbenchError(f"experiment {path} is not valid TOML: {exc}") from None
    reader.keys(doc, EXPERIMENT_KEYS, "")
    name = doc.get("name", path.stem)
    description = doc.get("description", "")
    if not isinstance(name, str) or not name or not isinstance(description, str):
        raise reader.error("name" if not isinstance(name, str) or not name else "description", "expected a string")

    methods = doc.get("methods")
    if not isinstance(methods, list) or not methods:
        raise reader.error("methods", "expected at least one [[methods]] table (name = \"METHOD\", grid = {...})")
    if max_cells is None:
        max_cells = doc.get("max_cells", MAX_CELLS)
        if not isinstance(max_cells, int) or isinstance(max_cells, bool) or max_cells < 1:
            raise reader.error("max_cells", f"expected a positive integer (the most cells the grid may have), "
                                            f"got {max_cells!r}")
    n_variants = sum(_count_variants(entry, doc.get("seeds")) for entry in methods)
    _check_size(reader, n_variants, max_cells, f"{n_variants:,} method variants, before datasets and settings")
    variants: list[Variant] = []
    for i, entry in enumerate(methods):
        variants += _variants_of(entry, i, doc.get("seeds"), plugins, reader)
    seen: dict[tuple[str, str], Variant] = {}
    for v in variants:
        if v.key in seen:
            raise reader.error(v.where, f"{v.label} and {seen[v.key].label} ({seen[v.key].where}) are the same "
                               f"options (hash {v.method.options_hash}): one cell, listed twice")
        seen[v.key] = v

    if "datasets" not in doc:
        embedded = [n for n in plugins.datasets.names() if getattr(plugins.datasets.get(n), "embedded", False)]
        if not embedded:
            raise reader.error("datasets", "not given and no embedded dataset is registered")
        datasets = tuple((n, None) for n in embedded)
    else:
        datasets = _datasets(doc["datasets"], reader, plugins)

    settings = reader.strings(doc["settings"], "settings") if "settings" in doc else ()
    for s in settings:
        try:
            setting = get_setting(s, plugins)
        except PcfbenchError as exc:
            raise reader.wrap("settings", exc) from None
        for ds, _ in datasets:
            try:
                check_compatible(setting, plugins.datasets.get(ds))
            except PcfbenchError as exc:
                raise reader.wrap("settings", exc) from None
    for ds, _ in datasets:
        if not settings and not plugins.datasets.get(ds).default_settings:
            raise reader.error("settings", f"dataset {ds!r} declares no default settings: list them")
    splits = reader.strings(doc["splits"], "splits") if "splits" in doc else ()

    policy = doc.get("policy")  # None: each dataset's own default policy
    if policy is not None and policy not in SAMPLE_POLICIES:
        raise reader.wrap("policy", unknown_name("sample policy", str(policy), SAMPLE_POLICIES))
    if "metrics" in doc:
        metrics = reader.strings(doc["metrics"], "metrics")
        for m in metrics:
            try:
                plugins.metrics.get(m)
            except PcfbenchError as exc:
                raise reader.wrap("metrics", exc) from None
    else:
        from pcfbench.running.runner import default_metrics

        metrics = default_metrics(plugins)

    train_on = _train_on(doc, variants, reader, plugins)
    train_split = doc.get("train_split", "train")
    if not isinstance(train_split, str) or not train_split:
        raise reader.error("train_split", f"expected a split name, got {train_split!r}")

    limit = doc.get("limit")
    if limit is not None and (not isinstance(limit, int) or isinstance(limit, bool) or limit < 1):
        raise reader.error("limit", f"expected a positive integer (the first N samples), got {limit!r}")
    jobs = doc.get("jobs", 0)
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 0:
        raise reader.error("jobs", f"expected an integer >= 0 (0: one worker per CPU for large cells), got {jobs!r}")

    presets = tables_mod.load_presets()
    raw_tables = doc.get("tables", [{}])
    if not isinstance(raw_tables, list) or not raw_tables:
        raise reader.error("tables", "expected one or more [[tables]] (preset, reference, stem)")
    specs = []
    for i, t in enumerate(raw_tables):
        where = f"tables[{i}]"
        if not isinstance(t, dict):
            raise reader.error(where, f"expected a table (preset, reference, stem), got {t!r}")
        reader.keys(t, TABLE_KEYS, f"{where}.")
        preset = t.get("preset", "paper")
        if not isinstance(preset, str):
            raise reader.error(f"{where}.preset", f"expected a preset name, got {preset!r}")
        try:
            tables_mod.get_preset(preset, presets)
        except PcfbenchError as exc:
            raise reader.wrap(f"{where}.preset", exc) from None
        reference = _reference(t.get("reference"), variants, f"{where}.reference", reader, plugins)
        stem = t.get("stem", path.stem if len(raw_tables) == 1 else f"{path.stem}-{preset}")
        if not isinstance(stem, str) or not _STEM.match(stem):
            raise reader.error(f"{where}.stem", f"expected a file name (letters, digits, '.', '_', '-'), got {stem!r}")
        title = t.get("title", name)
        ci = t.get("ci", "pm")
        if not isinstance(title, str):
            raise reader.error(f"{where}.title", f"expected a string, got {title!r}")
        if ci not in tables_mod.CI_STYLES:
            raise reader.wrap(f"{where}.ci", unknown_name("interval style", str(ci), tables_mod.CI_STYLES))
        if stem in [s.stem for s in specs]:
            raise reader.error(f"{where}.stem", f"{stem!r} is already the stem of another table")
        specs.append(TableSpec(preset, reference, stem, title, ci))
    exp = Experiment(path, name, description, tuple(variants), datasets, settings, splits, policy, tuple(metrics),
                     train_on, train_split, limit, jobs, tuple(specs), max_cells)
    n = count_cells(exp, plugins)
    _check_size(reader, n, max_cells, f"{len(variants):,} method variants x datasets, splits, settings and checkpoints")
    return exp


def count_cells(exp: Experiment, plugins: Plugins | None = None) -> int:
    """How many cells :func:`plan` yields for ``exp``, counted without making them."""
    plugins = plugins or get_plugins()
    per_data = sum(len(exp.splits or (1,)) * len(exp.settings or plugins.datasets.get(name).default_settings)
                   for name, _ in exp.datasets)
    per_variant = sum(len(exp.train_on or (None,)) if _is_trained(v.method.cls) else 1 for v in exp.variants)
    return per_data * per_variant


def _reference(value: Any, variants: list[Variant], key: str, reader: _Reader, plugins: Plugins) -> Variant:
    """The variant ``value`` (a method spec ``NAME[:key=value,...]``) names: the row every
    change is relative to. Default: copy-last where the grid has it, else the first row."""
    if value is None:
        return next((v for v in variants if v.method.name == DEFAULT_REFERENCE), variants[0])
    if not isinstance(value, str):
        raise reader.error(key, f"expected a method spec NAME[:key=value,...], got {value!r}")
    try:
        spec = resolve_method(value, plugins)
    except PcfbenchError as exc:
        raise reader.wrap(key, exc) from None
    for v in variants:
        if v.key == (spec.name, spec.options_hash):
            return v
    raise reader.wrap(key, unknown_name("reference row", value, [v.label for v in variants],
                                        "the reference must be one of the experiment's variants"))


def _train_on(doc: dict, variants: list[Variant], reader: _Reader, plugins: Plugins) -> tuple[str, ...]:
    """``train_on``: the training data (``NAME`` or ``NAME=ROOT``) of the grid's trained
    methods, an axis of their cells; methods that do not train run once. Without the trained-
    method support of ``pcfbench.training`` in the runner, it is refused rather than ignored."""
    if "train_on" not in doc:
        return ()
    items = reader.strings(doc["train_on"], "train_on")
    for item in items:
        try:
            plugins.datasets.get(item.partition("=")[0])
        except PcfbenchError as exc:
            raise reader.wrap("train_on", exc) from None
    if not _training_supported():
        raise reader.error("train_on", "not yet supported: this pcfbench cannot evaluate a trained method's checkpoint "
                           "(issue 13, items 1-4); the rest of the file is valid")
    if not any(_is_trained(v.method.cls) for v in variants):
        raise reader.error("train_on", f"applies to trained methods, and none of {', '.join(v.label for v in variants)} "
                           "trains (drop train_on, or add a trained method)")
    return items


def _training_supported() -> bool:
    try:
        import pcfbench.training  # noqa: F401
    except ImportError:
        return False
    return "checkpoint_sha256" in {f.name for f in dataclasses.fields(CellSpec)}


def _is_trained(cls: type) -> bool:
    if not _training_supported():
        return False
    from pcfbench.training import is_trained

    return is_trained(cls)


def _checkpoints(exp: Experiment, v: Variant, plugins: Plugins, progress: bool) -> list[dict[str, Any]]:
    """The CellSpec fields of each checkpoint a variant is evaluated with: one per ``train_on``
    for a trained method (default: its own default training data), none for the others. A
    missing or altered checkpoint is one error naming the key (and how to train it)."""
    if not _is_trained(v.method.cls):
        return [{}]
    from pcfbench.training import checkpoint_for

    out = []
    for t in exp.train_on or (None,):
        try:
            ck = checkpoint_for(v.method, train_on=t, split=exp.train_split, plugins=plugins, progress=progress,
                                split_option='train_split = "{}"')
        except PcfbenchError as exc:
            raise _Reader(exp.path).wrap("train_on" if t else v.where, exc) from None
        out.append({"checkpoint": str(ck.dir.resolve()), "checkpoint_sha256": ck.sha256, "train_on": ck.train_on_label})
    return out


# -- running -------------------------------------------------------------------------------
@dataclass
class SweepResult:
    """The cells of the grid (in run order), what each run did, and the files written."""

    cells: list[CellSpec]
    results: list[Any]
    paths: dict[str, Path]
    summaries: list[str]


def row_label(spec: CellSpec) -> str:
    """The ablation row of a cell: ``raycast-voxel (voxel=0.4)``, a trained method's with its
    training data and checkpoint (``[trained on synthetic-town:train, ck 0123abcd]``)."""
    label = method_label(spec.method, spec.options)
    train_on = getattr(spec, "train_on", None)
    if train_on:
        label += f" [trained on {train_on}, ck {str(spec.checkpoint_sha256)[:8]}]"
    return label


def _row_key(method: str, options_hash: str, checkpoint_sha256: Any) -> tuple[str, str, str]:
    return (method, options_hash, checkpoint_sha256 if isinstance(checkpoint_sha256, str) else "")


def plan(exp: Experiment, *, limit: int | None = None, plugins: Plugins | None = None,
         progress: bool = True) -> list[CellSpec]:
    """The grid's cells: dataset x split x setting x variant, in the file's order. Resolves
    the roots (an embedded dataset prepares its data now), checks every split and that every
    (dataset, split, setting) has samples, before any cell runs."""
    return list(iter_plan(exp, limit=limit, plugins=plugins, progress=progress))


def iter_plan(exp: Experiment, *, limit: int | None = None, plugins: Plugins | None = None,
              progress: bool = True) -> Iterator[CellSpec]:
    """:func:`plan`'s cells one at a time (``pcfbench sweep --dry-run`` prints each as it comes):
    a dataset's roots, splits and samples are checked when its first cell is due."""
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder

    plugins = plugins or get_plugins()
    reader = _Reader(exp.path)
    limit = limit if limit is not None else exp.limit
    checkpoints: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for name, root in exp.datasets:
        cls = plugins.datasets.get(name)
        try:
            root = config.resolve_root(name, cls, {name: root} if root else {}, progress)
            adapter = config.open_adapter(name, cls, root)
        except PcfbenchError as exc:
            raise reader.wrap("datasets", exc) from None
        splits = exp.splits or (cls.default_split,)
        for split in splits:
            if split not in adapter.splits():
                raise reader.wrap("splits", unknown_name(f"split of dataset {name}", split, adapter.splits()))
        policy = exp.policy or cls.default_policy
        for split, setting in itertools.product(splits, exp.settings or cls.default_settings):
            try:
                builder = SampleBuilder(adapter, get_setting(setting, plugins), policy)
                keys = builder.sample_keys(split)
            except PcfbenchError as exc:
                raise reader.wrap("datasets", exc) from None
            if not keys:
                from pcfbench.protocol.nosamples import EXPERIMENT_FILE, explain

                why = explain(builder, split, settings=[get_setting(s, plugins) for s in cls.default_settings],
                              options=EXPERIMENT_FILE)
                raise reader.error({"split": "splits", "setting": "settings"}.get(why.kind, "datasets"), why.message)
            for v in exp.variants:
                m = v.method
                for ck in checkpoints.setdefault(v.key, _checkpoints(exp, v, plugins, progress)):
                    yield CellSpec(m.name, dict(m.raw), m.options_hash, name, root, split, setting, policy, limit,
                                   exp.metrics, **ck)


def run_sweep(exp: Experiment, store: Path, reports: Path, *, limit: int | None = None, jobs: int | None = None,
              threads: int | None = None, force: bool = False, progress: bool = True,
              plugins: Plugins | None = None, echo: Callable[[str], None] = print, executor: Any = None,
              timeout: float | None = None, isolate: bool | None = None,
              limits: dict[str, Any] | None = None) -> SweepResult:
    """Run (or resume) every cell of ``exp`` through ``run_cell``, then write its ablation
    tables to ``reports/sweeps/``. Complete cells are reused without calling the method;
    ``force`` recomputes them. ``limit``/``jobs`` override the file's. ``executor``: run_cell's
    (``pcfbench.running.ray_executor.RayExecutor``; the file's ``jobs`` then does not apply).
    ``timeout``/``isolate``: run_cell's per-sample time limit and worker processes; ``limits``:
    RunOptions' other limits (``scoring_timeout``, ``max_memory_gb``, ``forecast_ratio``)."""
    from tqdm import tqdm

    from pcfbench.running.group import group_key, run_group
    from pcfbench.running.runner import RunOptions, _progress_disabled

    plugins = plugins or get_plugins()
    cells = plan(exp, limit=limit, plugins=plugins, progress=progress)
    jobs = exp.jobs if jobs is None else jobs
    results: dict[int, Any] = {}
    bar = tqdm(total=len(cells), desc=f"sweep {exp.name}", unit="cell", position=0, leave=True,
               disable=_progress_disabled() if progress else True, dynamic_ncols=True)
    say = (lambda m: tqdm.write(m)) if not bar.disable else echo
    # cells that differ only in the method and its options share one pass over their samples
    by_samples: dict[tuple, list[int]] = {}
    for i, spec in enumerate(cells, 1):
        by_samples.setdefault(group_key(spec), []).append(i)
    try:
        for members in by_samples.values():
            for i in members:
                say(f"cell {i}/{len(cells)}: {cell_label(cells[i - 1])}")
            line = f"cell {members[0]}/{len(cells)}" if len(members) == 1 else \
                f"cells {', '.join(map(str, members))}/{len(cells)}"
            options = RunOptions(jobs=jobs, force=force, progress=progress, threads=threads, executor=executor,
                                 progress_label=line, timeout=timeout, isolate=isolate, **(limits or {}))
            specs = [cells[i - 1] for i in members]
            for i, r in zip(members, run_group(specs, store, options, plugins=plugins)):
                results[i] = r
                done = "complete, nothing to do" if r.processed == 0 and r.done_before == r.samples else \
                    f"{r.processed} sample(s) now, {r.failed} failed, {r.seconds:.1f} s"
                say(f"cell {i}/{len(cells)}: {done} ({r.samples} samples) -> {r.path}")
                bar.update(1)
    finally:
        bar.close()
    results = [results[i] for i in range(1, len(cells) + 1)]
    paths, summaries = ablation_tables(exp, store, reports, cells, [r.path for r in results])
    return SweepResult(cells, results, paths, summaries)


# -- the ablation table --------------------------------------------------------------------
def ablation_tables(exp: Experiment, store: Path, reports: Path, cells: list[CellSpec],
                    cell_dirs: list[Path]) -> tuple[dict[str, Path], list[str]]:
    """Render every table of ``exp`` from the sweep's ``cells`` (in the store at ``cell_dirs``) and write
    ``reports/sweeps/<stem>.{md,csv,tex,html}`` and its ablation figures (metric vs option
    value, ``reports/figures/ablation-<stem>_*``); returns the paths (``"<stem>.<ext>"``,
    ``"figures/<name>"``) and each table as terminal text.
    Everything is rendered in memory first, then each file is written atomically. A grid with a
    limited or incomplete cell writes under ``reports/partial/`` instead, in the same layout: a
    partial table never replaces a complete one."""
    from pcfbench.reporting import report, tables
    from pcfbench.reporting.escape import csv_text

    presets = tables.load_presets()
    labels = {_row_key(c.method, c.options_hash, getattr(c, "checkpoint_sha256", None)): row_label(c) for c in cells}
    order = list(dict.fromkeys(labels.values()))
    contents: dict[str, str] = {}
    summaries = []
    figure_paths: dict[str, Path] = {}
    root: Path | None = None  # the reports folder, or its partial/ when a cell is limited or incomplete
    for t in exp.tables:
        lb = report.collect(store, reference=t.reference.method.name, cells=cell_dirs,
                            reference_options_hash=t.reference.method.options_hash)
        if root is None:  # every table has the same cells: complete for one, complete for all
            root = Path(reports) if _every_cell_complete(lb, cell_dirs) else config.partial_reports_dir(reports)
        for df in (lb.table, lb.partial):
            if len(df):  # rows labelled by the experiment (a reused cell keeps the label of its first run)
                cks = df["checkpoint_sha256"] if "checkpoint_sha256" in df else [""] * len(df)
                df["variant"] = [labels[_row_key(m, h, c)] for m, h, c in zip(df["method"], df["options_hash"], cks)]
        lb.reference = t.reference.label
        preset = dataclasses.replace(tables.get_preset(t.preset, presets), name=t.stem,
                                     title=f"{t.title} (columns of preset {t.preset})")
        table = tables.build(lb, preset, t.ci, order=order, heading="pcfbench ablation")
        table.empty_note = "" if table.partial else "No complete cell of the sweep."
        tex, _fit = tables.latex(table)
        contents[f"{t.stem}.md"] = tables.markdown(table)
        contents[f"{t.stem}.tex"] = tex
        contents[f"{t.stem}.html"] = tables.html_page(table)
        contents[f"{t.stem}.csv"] = csv_text(_csv(lb, order))
        summaries.append(f"{table.heading}: {preset.title}\n{tables.text(table)}")
        from pcfbench.reporting.figures import FIGURES_DIR, ablation_figures  # metric vs option value

        figure_paths.update(ablation_figures(lb, table.columns, root / FIGURES_DIR, t.stem))
    if root != Path(reports):
        summaries.append(f"PARTIAL sweep (a --limit, or a cell not scored on every sample): its tables and figures "
                         f"are under {root}, never over the complete ones under {Path(reports)}")
    out = root / SWEEPS_DIR
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, text in contents.items():
        atomic_write_bytes(out / name, text.encode())
        paths[name] = out / name
    paths.update({f"figures/{k}": p for k, p in figure_paths.items()})
    return paths, summaries


def _every_cell_complete(lb, cell_dirs: list[Path]) -> bool:
    """Every cell of the grid is ranked: complete, not limited, scored on every sample."""
    ranked = set(lb.table["cell_dir"]) if len(lb.table) else set()
    return ranked == {str(Path(d).resolve()) for d in cell_dirs}


def _csv(lb, order: list[str]) -> pd.DataFrame:
    """The report's CSV columns for the sweep's rows (complete and partial), with ``limit``,
    in the experiment's row order within each (dataset, split, setting, limit) block."""
    from pcfbench.reporting.report import _csv_frame

    frames = [df for df in (lb.table, lb.partial) if len(df)]
    if not frames:
        return _csv_frame(lb, lb.table).assign(limit=None)
    df = pd.concat(frames, ignore_index=True)
    rank = {label: i for i, label in enumerate(order)}
    df = df.assign(_row=df["variant"].map(rank), _limit=df["limit"].fillna(-1))
    df = df.sort_values(["dataset", "split", "setting", "policy", "_limit", "_row"]).reset_index(drop=True)
    out = _csv_frame(lb, df)
    out.insert(4, "limit", df["limit"].astype("Int64"))
    return out
