"""Runs cells: samples through a method, forecasts through the metrics, rows into the store."""

from __future__ import annotations

import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from tqdm import tqdm

import pcfbench
from pcfbench import config
from pcfbench.store import ranges
from pcfbench.running import workers
from pcfbench.errors import DataError, PcfbenchError
from pcfbench.execution import ExecutionContext, applied
from pcfbench.execution import apply as apply_execution
from pcfbench.provenance import code_identity, code_unit, environment, git_commit
from pcfbench.method import Method, resolve_method
from pcfbench.metrics import backend as metrics_backend
from pcfbench.metrics.base import Metric, SweepTruth, score_sample, sweep_truths
from pcfbench.plugins import Plugins, get_plugins
from pcfbench.plugins import get_setting
from pcfbench.protocol import SampleBuilder, check_compatible, ids_hash, sample_id
from pcfbench.protocol.settings import evenly_spaced
from pcfbench.dataset import FINGERPRINT_KIND, options_identity
from pcfbench.store.cells import RANGE_KEY, Cell, CellSpec, check_identity, spec_to_meta
from pcfbench.protocol.validate import FORECAST_RATIO, check_forecast_size, validate_forecast

#: Flush a chunk after this many samples or seconds, whichever comes first.
CHUNK_SAMPLES = int(os.environ.get("PCFBENCH_CHUNK_SAMPLES", 64))
CHUNK_SECONDS = float(os.environ.get("PCFBENCH_CHUNK_SECONDS", 20.0))
#: With ``jobs=0`` (auto), unisolated cells with fewer samples to do than this run serially (in
#: this process); isolated ones start a worker per CPU whatever their count (``RunOptions.workers``).
AUTO_POOL_MIN_SAMPLES = 24


def _progress_disabled() -> bool | None:
    if os.environ.get("CI") or os.environ.get("PCFBENCH_NO_PROGRESS"):
        return True
    return None  # tqdm: disabled when not a terminal


@dataclass
class Resolved:
    """Everything a worker needs to process samples of one cell."""

    builder: SampleBuilder
    method: Method
    metrics: list[Metric]
    #: the thread budget of the method and the metrics (None: the process's); set by ``bind``
    execution: ExecutionContext | None = None
    #: the forecast size cap, a multiple of the ground truth's points (``check_forecast_size``; None: none)
    forecast_ratio: float | None = FORECAST_RATIO
    #: where the metrics' searches run (``pcfbench.metrics.backend``: auto, numpy or torch)
    metrics_backend: str = "auto"

    def bind(self, execution: ExecutionContext) -> None:
        """Give the method and the metrics ``execution``'s thread budget."""
        self.execution = execution
        self.method.execution = execution


def resolve(spec: CellSpec, plugins: Plugins | None = None) -> Resolved:
    plugins = plugins or get_plugins()
    adapter_cls = plugins.datasets.get(spec.dataset)
    method = resolve_method((spec.method, spec.options), plugins)
    setting = get_setting(spec.setting, plugins)
    root, root_options = config.split_root_options(spec.dataset_root)
    adapter = adapter_cls(root, **root_options)
    check_compatible(setting, adapter)
    metrics = [plugins.metrics.get(m) for m in spec.metrics]
    return Resolved(SampleBuilder(adapter, setting, spec.policy), _create_method(spec, method), metrics)


def _create_method(spec: CellSpec, method: Any) -> Method:
    """The method of ``spec``; a trained one with its checkpoint loaded (verified, and the
    very file the cell is keyed by)."""
    from pcfbench.training import Checkpoint, is_trained

    instance = method.create()
    if not is_trained(method.cls):
        return instance
    if not spec.checkpoint:
        raise PcfbenchError(f"cell {spec.label}: {spec.method} is a trained method and the cell names no checkpoint")
    ck = Checkpoint.open(spec.checkpoint)
    ck.check_method(method)
    if ck.sha256 != spec.checkpoint_sha256:
        raise PcfbenchError(f"checkpoint {ck.weights_path} changed since cell {spec.label} was set up "
                            f"(sha256 {ck.sha256[:12]}, the cell is keyed by {str(spec.checkpoint_sha256)[:12]}); run again")
    instance.load(ck)
    instance.checkpoint = ck
    return instance


class SharedSample:
    """The last sample built in this process, with its sweeps' ground-truth structures
    (:class:`~pcfbench.metrics.base.SweepTruth`: k-d tree, angles, ROI masks, clamps), kept for
    the next method scored on it: the shared pass of :func:`run_group` loads a sample and
    builds its ground truth's structures once for every method. Methods get read-only copies
    (``Sample.for_method``) and never see the ground truth, so what one method does cannot reach
    another's rows."""

    def __init__(self) -> None:
        self.key: tuple[str, int] | None = None
        self.value: tuple[Any, Any, list[SweepTruth], float] | None = None

    def get(self, builder: SampleBuilder, key: tuple[str, int]) -> tuple[Any, Any, list[SweepTruth], float]:
        """(sample, truth, sweep truths, seconds its loading took) of ``key``, built on first use."""
        if self.key != key or self.value is None:
            self.key = self.value = None  # a failing build leaves nothing stale behind
            t0 = time.perf_counter()
            sample, truth = builder.build(*key)
            self.value = (sample, truth, sweep_truths(sample, truth, builder.protocol), time.perf_counter() - t0)
            self.key = key
        return self.value


def process_sample(res: Resolved, key: tuple[str, int], shared: SharedSample | None = None) -> list[dict[str, Any]]:
    """Rows for one sample: one per future sweep, or one failure row with the traceback.

    Data errors (a bad file) propagate: they stop the run rather than being blamed on the method.
    When the cell scores ``l1_mean`` or ``absrel_mean``, each ok row also carries its sweep's
    range bins under ``pcfbench.store.cells.RANGE_KEY`` (``pcfbench.store.ranges``), which the store
    writes beside the rows, never into them.

    ``shared``: the sample as the previous method scored on it left it (:class:`SharedSample`);
    the rows are the same, ``t_load`` is the one loading's time.
    """
    t0 = time.perf_counter()
    if shared is not None:
        sample, truth, truths, t_load = shared.get(res.builder, key)
        t0 = time.perf_counter() - t_load
    else:
        sample, truth = res.builder.build(*key)
        truths = None
    t1 = time.perf_counter()
    base = {"sample_id": sample.sample_id, "sequence": sample.sequence, "ref_index": sample.ref_index}
    bins: dict[int, dict[str, list]] = {}

    def keep_bins(row: dict, ctx: Any) -> None:
        bins[int(row["step"])] = ranges.sweep_bins(ctx)

    record = ranges.records(m.name for m in res.metrics)
    try:
        # the method gets a read-only copy; the forecast is checked and scored against `sample`
        forecast = validate_forecast(sample, res.method.forecast(sample.for_method()))
        check_forecast_size(sample, truth, forecast, res.method.name, res.forecast_ratio)
        t2 = time.perf_counter()
        workers.phase(workers.SCORING)  # in a worker: the scoring limit applies from here, not the method's
        rows = score_sample(sample, truth, forecast, res.metrics, res.execution, keep_bins if record else None,
                            protocol=res.builder.protocol, truths=truths,
                            context_cls=metrics_backend.context_class(res.metrics_backend))
    except DataError:
        raise
    except Exception as exc:  # a method (or metric) failing on one sample is recorded, the run goes on
        return [
            {
                **base,
                "step": -1,
                "status": "failed",
                "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc(),
                "t_load": t1 - t0,
            }
        ]
    t3 = time.perf_counter()
    for row in rows:
        row.update(base, status="ok", t_load=t1 - t0, t_method=t2 - t1, t_metrics=t3 - t2)
        if record:
            row[RANGE_KEY] = bins[int(row["step"])]
    return rows


# -- workers (pcfbench.running.workers) ---------------------------------------------------------------
_WORKER: Resolved | None = None


class _Chosen:
    """A registry holding only what one cell uses, picklable so that a worker gets the very
    classes the driver resolved (a plugin registered in the driver's process included). An
    item that does not pickle (a metric with a lambda) travels by name and is looked up in
    the worker's own plugins."""

    def __init__(self, kind: str, items: dict[str, Any]) -> None:
        import pickle  # only to test that an item travels; nothing here is ever unpickled

        self.kind = kind
        self.items: dict[str, Any] = {}
        self.by_name: set[str] = set()
        self.failed_plugins: dict[str, str] = {}
        for name, obj in items.items():
            try:
                pickle.dumps(obj)
                self.items[name] = obj
            except Exception:  # noqa: BLE001 - any pickling failure: send the name instead
                self.by_name.add(name)

    def get(self, name: str) -> Any:
        if name in self.items:
            return self.items[name]
        return getattr(get_plugins(), f"{self.kind}s").get(name)

    def names(self) -> list[str]:
        return sorted({*self.items, *self.by_name})

    def __contains__(self, name: str) -> bool:
        return name in self.items or name in self.by_name


class CellPlugins:
    """What :func:`resolve` needs of the plugins for one cell (``_Chosen`` registries)."""

    def __init__(self, spec: CellSpec, plugins: Plugins) -> None:
        self.datasets = _Chosen("dataset", {spec.dataset: plugins.datasets.get(spec.dataset)})
        self.methods = _Chosen("method", {spec.method: plugins.methods.get(spec.method)})
        self.metrics = _Chosen("metric", {m: plugins.metrics.get(m) for m in spec.metrics})
        settings = {spec.setting: plugins.settings.get(spec.setting)} if spec.setting in plugins.settings else {}
        self.settings = _Chosen("setting", settings)


def _worker_init(spec: CellSpec, execution: ExecutionContext, plugins: CellPlugins | None = None,
                 forecast_ratio: float | None = FORECAST_RATIO, backend: str = "auto") -> None:
    """Pin this worker process to its share of the threads (before resolving, so that what
    the method imports starts within it), then resolve the cell and hand the share on."""
    global _WORKER
    apply_execution(execution)
    _WORKER = resolve(spec, plugins)  # type: ignore[arg-type]
    _WORKER.bind(execution)
    _WORKER.forecast_ratio = forecast_ratio
    _WORKER.metrics_backend = backend


def _worker_task(key: tuple[str, int]) -> list[dict[str, Any]]:
    assert _WORKER is not None
    return process_sample(_WORKER, key)


def _failure_row(key: tuple[str, int], kind: str, reason: str) -> list[dict[str, Any]]:
    """The one failure row of a sample whose worker crashed, ran out of time (the method's, or
    the scoring's: ``kind`` "timeout" or "scoring-timeout") or went over the memory limit."""
    sequence, ref_index = key
    sid = sample_id(sequence, ref_index)
    name, note = _FAILURES[kind]
    error = f"{name}: sample {sid}: {reason}"
    return [{"sample_id": sid, "sequence": sequence, "ref_index": ref_index, "step": -1, "status": "failed",
             "error": error, "traceback": f"{error}\n({note})", "t_load": float("nan")}]


#: per failure kind of pcfbench.running.workers: the error's name and what to do about it
_FAILURES = {
    "timeout": ("SampleTimeout", "the method hung or is too slow (on Ray the limit covers its scoring too): raise "
                                 "the limit with --timeout SECONDS (0: none)"),
    "scoring-timeout": ("ScoringTimeout", "the metrics took too long on this forecast (the method had returned it): "
                                          "raise the limit with --scoring-timeout SECONDS (0: none)"),
    "memory": ("SampleMemory", "the worker went over --max-memory GIB (raise it, or 0: no limit)"),
    "crash": ("SampleCrash", "a native crash, os._exit() or the out-of-memory killer; no Python traceback"),
}


@dataclass
class CellResult:
    spec: CellSpec
    path: Path
    status: str
    samples: int
    done_before: int
    processed: int
    failed: int
    seconds: float


@dataclass(frozen=True)
class RunOptions:
    """How :func:`run_cell` computes a cell. None of it changes a row; ``allow_train_split``
    decides whether a trained method's cell on its own training data runs at all.

    ``jobs``: worker processes; 0 picks a pool of one worker per CPU when the samples are
    isolated (a worker is started for them either way, and the workers start side by side) or
    there are enough of them to pay for starting it, else runs serially. A pool never has more
    workers than samples. ``threads``: the run's thread budget
    (default: every CPU this process may use); a serial run keeps all of it, each of N
    workers gets ``max(1, threads // N)`` (:mod:`pcfbench.execution`).

    ``executor`` (:class:`pcfbench.running.ray_executor.RayExecutor`) computes the samples
    elsewhere instead: its tasks write the rows to the store themselves, a shard of samples
    per chunk.

    ``isolate`` (default: when a ``timeout`` is given) runs even a serial cell's samples in a
    worker process; a pool (``jobs`` > 1) always does. There a sample whose worker crashes (a
    native crash, ``os._exit``), runs past ``timeout`` seconds (loading and the method's
    forecast) or ``scoring_timeout`` seconds (scoring the forecast, timed on its own), or holds
    more than ``max_memory_gb`` GiB, is recorded failed and the cell goes on
    (:mod:`pcfbench.running.workers`). Unisolated, the method runs in this process, unlimited.
    ``forecast_ratio``: the forecast size cap, in either case
    (:func:`pcfbench.protocol.validate.check_forecast_size`; None: none).

    ``metrics_backend``: where the metrics' searches run (:mod:`pcfbench.metrics.backend`:
    ``auto``, the GPU through torch when there is one; ``numpy``; ``torch``); the rows are the same.

    ``wait``: a cell another process is computing (it holds the cell's lock) is waited for,
    else refused at once with :class:`pcfbench.store.cells.CellLocked`. ``progress_label``:
    the progress bar's text (default: the cell's label), e.g. ``cell 3/10 ...``.
    """

    jobs: int = 1
    force: bool = False
    progress: bool = True
    threads: int | None = None
    allow_train_split: bool = False
    executor: Any = None
    timeout: float | None = None
    isolate: bool | None = None
    wait: bool = True
    progress_label: str | None = None
    scoring_timeout: float | None = None
    max_memory_gb: float | None = None
    forecast_ratio: float | None = FORECAST_RATIO
    metrics_backend: str = "auto"

    def __post_init__(self) -> None:
        if self.metrics_backend not in metrics_backend.BACKENDS:
            raise PcfbenchError(f"the metrics backend must be one of {', '.join(metrics_backend.BACKENDS)}, "
                                f"not {self.metrics_backend!r}")
        for what, t, unit in (("per-sample time limit", self.timeout, "a number of seconds"),
                              ("scoring time limit", self.scoring_timeout, "a number of seconds"),
                              ("per-sample memory limit", self.max_memory_gb, "a number of GiB"),
                              ("forecast size cap", self.forecast_ratio, "a multiple of the ground truth's points")):
            if t is not None and not (isinstance(t, (int, float)) and not isinstance(t, bool) and 0 < t < float("inf")):
                raise PcfbenchError(f"the {what} must be {unit} > 0 (or None: none), not {t!r}")

    @property
    def isolated(self) -> bool:
        return self.timeout is not None if self.isolate is None else self.isolate

    def execution(self) -> ExecutionContext:
        return ExecutionContext() if self.threads is None else ExecutionContext(self.threads)

    def workers(self, todo: int) -> int:
        if self.jobs == 0:
            # isolated, one worker with every thread scored 4 samples of the default run's 9
            # methods in 94 s, two with one thread each in 76 s (journal/performance-tuning-2026-11.md)
            return (os.cpu_count() or 1) if self.isolated or todo >= AUTO_POOL_MIN_SAMPLES else 1
        return self.jobs


def run_cell(spec: CellSpec, store_root: Path, options: RunOptions | None = None, *,
             plugins: Plugins | None = None) -> CellResult:
    """Run (or resume) one cell. Returns at once if the cell is already complete.

    The cell is resolved once (:func:`resolve`): its samples, its identity (what the rows
    depend on: versions, protocol, data, checkpoint) and the rows still to compute. A cell
    whose stored identity differs is refused, naming the field (:func:`check_identity`).

    A trained method's cell is refused on the very data its checkpoint was trained on (same
    dataset, split and file fingerprint) unless ``options.allow_train_split``; cell.json then
    says so.
    """
    options = options or RunOptions()
    start = time.perf_counter()
    try:
        res = resolve(spec, plugins)
        keys = sample_keys(res, spec, plugins)
    except DataError as exc:  # the root may be another dataset's: say so, as `datasets check` would
        hint = _layout_hint(spec, plugins)
        if not hint:
            raise
        raise DataError(f"{exc}{hint}") from None
    ids = [sample_id(s, i) for s, i in keys]
    fingerprint = res.builder.adapter.fingerprint(spec.split)
    cell = Cell(store_root, spec, wait=options.wait)
    with cell:
        meta, done, todo = open_cell(cell, res, spec, keys, ids, fingerprint, options)
        if meta is None:
            return CellResult(spec, cell.dir, "complete", len(ids), len(done), 0, 0, 0.0)
        failed = _compute(res, spec, cell, keys, todo, done, options, plugins)
        elapsed = close_cell(cell, res, spec, meta, fingerprint, len(ids), start)
    return CellResult(spec, cell.dir, "complete", len(ids), len(done), len(todo), failed, elapsed)


def open_cell(cell: Cell, res: Resolved, spec: CellSpec, keys: list[tuple[str, int]], ids: list[str], fingerprint: Any,
              options: RunOptions) -> tuple[dict[str, Any] | None, set[str], list[tuple[str, int]]]:
    """(running meta, done sample ids, samples to do) of a locked ``cell``, its identity checked
    and its running ``cell.json`` written; the meta is None when the cell is complete already."""
    if options.force:  # whatever is there, a cut-short cell.json or a damaged chunk included
        cell.clear()
    meta = cell.read_meta()
    identity = cell_identity(res, spec, ids_hash(ids), fingerprint.digest, options.allow_train_split, fingerprint)
    if meta is not None:
        check_identity(cell.dir, meta, identity, fingerprint, _code_meta(res.method)["method_code_files"])
    done = cell.done_ids()
    todo = [k for k, sid in zip(keys, ids) if sid not in done]
    if not todo and meta is not None and meta.get("status") == "complete":
        return None, done, []
    meta = _running_meta(meta, spec, res, identity, fingerprint, len(ids))
    meta["metrics_backend"] = _with_backend(meta.get("metrics_backend"), scoring_backend(options))
    cell.write_meta(meta)
    return meta, done, todo


def close_cell(cell: Cell, res: Resolved, spec: CellSpec, meta: dict[str, Any], fingerprint: Any, samples: int,
               start: float) -> float:
    """Mark a computed ``cell`` complete (its data unchanged since ``fingerprint``, else it stays
    incomplete and this raises); returns the seconds since ``start``."""
    after = res.builder.adapter.fingerprint(spec.split)
    if after.digest != fingerprint.digest:  # rows from both versions of the data: never complete
        raise PcfbenchError(
            f"the files of {spec.dataset}:{spec.split} changed while cell {cell.dir} was computed "
            f"({after.changes_since(fingerprint.summary())}); it stays incomplete: rerun with --force to recompute it"
        )
    elapsed = time.perf_counter() - start
    cell.write_meta(_complete_meta(meta, cell.read_rows(), samples, elapsed))
    return elapsed


def sample_keys(res: Resolved, spec: CellSpec, plugins: Plugins | None = None) -> list[tuple[str, int]]:
    """The cell's samples, ``(sequence, reference index)``: :func:`cell_keys` of
    :func:`policy_keys`."""
    return cell_keys(policy_keys(res, spec, plugins), spec)


def cell_keys(keys: list[tuple[str, int]], spec: CellSpec) -> list[tuple[str, int]]:
    """The cell's share of its policy's samples ``keys``: ``spec.subset`` of them evenly spaced
    when it is set, then the first ``spec.limit`` of those."""
    if spec.subset is not None:
        keys = [keys[i] for i in evenly_spaced(len(keys), spec.subset)]
    return keys if spec.limit is None else keys[: spec.limit]


def policy_keys(res: Resolved, spec: CellSpec, plugins: Plugins | None = None) -> list[tuple[str, int]]:
    """Every sample of the cell's split under its setting and policy, ``(sequence, reference
    index)``; none is an error that says why (the split's sequences are elsewhere, too short for
    the setting, or absent) and the option that fixes it (:mod:`pcfbench.protocol.nosamples`)."""
    from pcfbench.errors import unknown_name
    from pcfbench.protocol.nosamples import explain

    builder = res.builder
    adapter = builder.adapter
    try:
        keys = builder.sample_keys(spec.split)
    except DataError:
        # the adapter refuses a split it does not know; name the known ones and the option. A
        # split it accepts without listing (an alias) is not refused here
        if spec.split not in adapter.splits():
            raise unknown_name(f"split of dataset {spec.dataset}", spec.split, adapter.splits(),
                               "pick one with --split NAME") from None
        raise
    if not keys:
        settings = [get_setting(name, plugins) for name in type(adapter).default_settings]
        raise DataError(explain(builder, spec.split, settings=settings).message)
    return keys


def _layout_hint(spec: CellSpec, plugins: Plugins | None) -> str:
    """``; ROOT holds the kitti layout: pass --dataset kitti=ROOT`` when the cell's root is
    not its dataset's layout and another registered adapter recognises it (``detect``, what
    ``pcfbench datasets check`` uses); else ""."""
    root = Path(config.split_root_options(spec.dataset_root)[0])
    try:
        datasets = (plugins or get_plugins()).datasets
        if not root.exists() or datasets.get(spec.dataset).detect(root):
            return ""
        found = [name for name in datasets.names() if name != spec.dataset and datasets.get(name).detect(root)]
    except Exception:  # noqa: BLE001 - a hint, never a second error
        return ""
    if not found:
        return ""
    return f"; {root} holds the {found[0]} layout: pass --dataset {found[0]}={root}"


def cell_identity(res: Resolved, spec: CellSpec, id_hash: str, digest: str, allow_train_split: bool,
                  fingerprint: Any = None) -> dict[str, Any]:
    """What a cell's rows depend on (its ``cell.json`` identity): the method's, dataset's and
    metrics' versions, the hash of the method's source (:func:`method_code`), the samples,
    the protocol, the dataset's options and files (by content), and a trained method's
    checkpoint and training data."""
    return {
        "method_version": res.method.version,
        "method_code": method_code(res.method)["sha256"] or NO_SOURCE,
        "dataset_version": res.builder.adapter.version,
        "metric_versions": {m.name: m.version for m in res.metrics},
        "sample_ids_hash": id_hash,
        **res.builder.identity(),  # protocol version, ROI, minimum range, setting, policy, ego box
        "dataset_options": options_identity(res.builder.adapter, config.split_root_options(spec.dataset_root)[1]),
        "data_fingerprint": digest,
        "data_fingerprint_kind": FINGERPRINT_KIND,
        **_trained_identity(spec, res.method, digest, allow_train_split, fingerprint),
    }


#: ``method_code`` of a method whose class has no source file (made at run time): its code
#: cannot be told apart, only its version.
NO_SOURCE = "no source file"


def method_code(method: Method) -> dict[str, Any]:
    """The identity of the code of ``method``'s class (:func:`pcfbench.provenance.code_identity`):
    the hash of its package's sources, each file's hash, its distribution and version."""
    return code_identity(code_unit(type(method).__module__))


def _running_meta(meta: dict | None, spec: CellSpec, res: Resolved, identity: dict[str, Any], fingerprint: Any,
                  samples: int) -> dict[str, Any]:
    """``cell.json`` while the cell computes: its identity, the data files, the code and
    environment, the metrics' units and directions (what a report needs of them)."""
    meta = {
        **(meta or {}),
        "spec": spec_to_meta(spec),
        **identity,
        "data_files": fingerprint.summary(),
        **_code_meta(res.method),
        **_claims_meta(res.method, fingerprint),
        "status": "running",
        "partial": spec.partial,
        "harness_version": pcfbench.__version__,
        "git_commit": git_commit(),
        "environment": environment(),
        "samples": samples,
        "metric_units": {m.name: m.unit for m in res.metrics},
        "metric_higher_is_better": {m.name: m.higher_is_better for m in res.metrics},
        "created": (meta or {}).get("created", time.time()),
    }
    if ranges.records(m.name for m in res.metrics):  # its rows' range bins are stored beside them (pcfbench.store.ranges)
        meta["range_bins"] = ranges.meta()
    return meta


def scoring_backend(options: RunOptions) -> dict[str, Any]:
    """How this run scores its samples (``cell.json``'s ``metrics_backend``): the backend asked
    for, the one it resolves to and its device (:mod:`pcfbench.metrics.backend`). Under an
    executor whose tasks run elsewhere (Ray) ``auto`` resolves on each worker, so only the request
    is known here."""
    requested = options.metrics_backend
    if options.executor is not None:
        return {"requested": requested, "backend": None, "device": None, "resolved": "on each worker"}
    backend = metrics_backend.resolve(requested)
    device = "cpu"
    if backend == "torch":
        from pcfbench.metrics.torch_nn import default_device

        device = default_device()
    return {"requested": requested, "backend": backend, "device": device}


def _with_backend(recorded: Any, entry: dict[str, Any]) -> list[dict[str, Any]]:
    """The backends a cell's rows were scored with, each once, in the order first used (a
    resumed cell may be scored with another than its first rows were)."""
    out = [e for e in recorded if isinstance(e, dict)] if isinstance(recorded, list) else []
    return out if entry in out else out + [entry]


def _code_meta(method: Method) -> dict[str, Any]:
    """What cell.json records of the method's code beside its hash: the package hashed, each
    of its files' hashes (to name the files a later change touches) and its distribution."""
    code = method_code(method)
    return {"method_code_unit": code["unit"], "method_code_files": code["files"],
            "method_distribution": {"name": code["distribution"], "version": code["version"]}}


def _claims_meta(method: Method, fingerprint: Any) -> dict[str, Any]:
    """A trained method's checkpoint claims as checked (``pcfbench.training.claims``): steps
    trained of planned, its training data verified by content or not; {} for other methods."""
    ck = getattr(method, "checkpoint", None)
    if ck is None:
        return {}
    from pcfbench.training.claims import claims_meta

    return claims_meta(ck, fingerprint)


def _compute(res: Resolved, spec: CellSpec, cell: Cell, keys: list[tuple[str, int]], todo: list[tuple[str, int]],
             done: set[str], options: RunOptions, plugins: Plugins | None) -> int:
    """Compute the ``todo`` samples' rows into ``cell``, a chunk at a time (after
    ``CHUNK_SAMPLES`` samples or ``CHUNK_SECONDS``), keeping every finished sample's rows
    when interrupted; returns how many samples failed."""
    buffer: list[dict[str, Any]] = []
    last_flush = time.monotonic()
    buffered_samples = 0

    def flush() -> None:
        nonlocal buffer, last_flush, buffered_samples
        if buffer:
            cell.append_rows(buffer)
        buffer, buffered_samples, last_flush = [], 0, time.monotonic()

    bar = tqdm(
        total=len(keys), initial=len(keys) - len(todo), desc=options.progress_label or spec.label, unit="sample",
        disable=_progress_disabled() if options.progress else True, leave=True, dynamic_ncols=True,
    )
    failed = 0
    try:
        if options.executor is not None:  # its tasks write the rows, a shard at a time; nothing to buffer here
            return options.executor.run(spec, cell, keys, done, bar.update)
        for rows in _execute(res, spec, todo, options.workers(len(todo)), options.execution(), options.timeout,
                             options.isolated, plugins, options):
            buffer.extend(rows)
            buffered_samples += 1
            failed += rows[0]["status"] == "failed"
            bar.update(1)
            if buffered_samples >= CHUNK_SAMPLES or time.monotonic() - last_flush > CHUNK_SECONDS:
                flush()
        return failed
    finally:
        # Rows in the buffer belong to finished samples: keep them even when interrupted.
        flush()
        bar.close()


def _complete_meta(meta: dict[str, Any], df: Any, samples: int, elapsed: float) -> dict[str, Any]:
    """``cell.json`` of a complete cell: its counts (samples, ok, failed, scored sweeps) and
    timings (this run's, the total, the per-sample medians)."""
    sample_status = df.groupby("sample_id")["status"].first() if len(df) else None
    n_failed = int((sample_status == "failed").sum()) if sample_status is not None else 0
    return {
        **meta,
        "status": "complete",
        "counts": {
            "samples": samples,
            "ok": samples - n_failed,
            "failed": n_failed,
            "sweeps": int((df["status"] == "ok").sum()) if len(df) else 0,
        },
        "timings": {
            "last_run_seconds": elapsed,
            "total_seconds": meta.get("timings", {}).get("total_seconds", 0.0) + elapsed,
            **_median_timings(df),
        },
        "updated": time.time(),
    }


def _trained_identity(spec: CellSpec, method: Method, digest: str, allow_train_split: bool,
                      fingerprint: Any = None) -> dict[str, Any]:
    """A trained method's part of the cell identity: the checkpoint's sha256, its training
    data and whether this cell evaluates on that very data (refused unless allowed): by name
    and fingerprint, or by content (``pcfbench.training.claims.overlap``: the evaluated files
    found among the training files, a renamed copy included)."""
    from pcfbench.training.claims import OVERLAP_FRACTION, overlap

    ck = getattr(method, "checkpoint", None)
    if not spec.checkpoint_sha256 or ck is None:
        return {}
    t = ck.train_on
    # A shipped checkpoint was trained on its dataset's split as made elsewhere: its recorded
    # fingerprint (of a manifest from before content fingerprints, or of a generated split
    # whose bytes differ by CPU) need not equal this machine's, so the same dataset and split
    # is taken for that data.
    by_name = (t.get("dataset") == spec.dataset and t.get("split") == spec.split
               and (t.get("fingerprint") == digest or bool(getattr(ck, "shipped", False))))
    shared = overlap(ck, fingerprint) if fingerprint is not None else None
    by_content = shared is not None and shared["files"] > 0 and shared["bytes_fraction"] >= OVERLAP_FRACTION
    on_train = by_name or by_content
    if on_train and not allow_train_split:
        how = (f"{shared['files']} of its {shared['of']} files, {100 * shared['bytes_fraction']:.0f} % of its bytes, "
               f"are in the training data {ck.train_on_label}" if by_content else f"fingerprint {digest}")
        raise PcfbenchError(
            f"{spec.label}: checkpoint {ck.manifest_path} was trained on this very data ({spec.dataset}:{spec.split}, "
            f"{how}); evaluate another split, or pass --allow-train-split to score it anyway "
            "(the cell and the leaderboard then mark it)")
    return {"checkpoint_sha256": ck.sha256, "train_on": t, "evaluated_on_training_data": on_train}


def _median_timings(df) -> dict[str, float]:
    out = {}
    if not len(df):
        return out
    per_sample = df.drop_duplicates("sample_id")
    for col in ("t_load", "t_method", "t_metrics"):
        values = per_sample[col].to_numpy(dtype=float) if col in per_sample else np.zeros(0)
        if np.isfinite(values).any():  # a cell whose samples all failed in their workers has no timings
            out[f"median_{col}"] = float(np.nanmedian(values))
    return out


def _execute(res: Resolved, spec: CellSpec, keys: list[tuple[str, int]], jobs: int,
             execution: ExecutionContext, timeout: float | None = None, isolate: bool = False,
             plugins: Plugins | None = None, options: RunOptions | None = None) -> Iterable[list[dict[str, Any]]]:
    """Yield each sample's rows: in this process within ``execution`` (``isolate`` false,
    serial), else from ``jobs`` supervised worker processes (``pcfbench.running.workers``), each
    pinned to its share of ``execution``, where a sample whose worker crashes or runs past
    ``timeout`` seconds (or ``options``' scoring time or memory limit) is one failure row."""
    options = options or RunOptions()
    if not isolate and (jobs <= 1 or len(keys) < 2):
        with applied(execution):
            res.bind(execution)
            res.forecast_ratio = options.forecast_ratio
            res.metrics_backend = options.metrics_backend
            for key in keys:
                yield process_sample(res, key)
        return
    from pcfbench.running.workers import run_supervised

    jobs = max(1, min(jobs, len(keys)))
    init_args = (spec, execution.share(jobs), CellPlugins(spec, plugins or get_plugins()), options.forecast_ratio,
                 options.metrics_backend)
    memory = None if options.max_memory_gb is None else int(options.max_memory_gb * 2**30)
    yield from run_supervised(keys, jobs, _worker_init, init_args, _worker_task, _failure_row, timeout,
                              options.scoring_timeout, memory)


def default_metrics(plugins: Plugins) -> tuple[str, ...]:
    """Every registered metric that loads; a broken metric plugin only loses its own metrics."""
    names = []
    for name in plugins.metrics.names():
        try:
            plugins.metrics.get(name)
        except PcfbenchError as exc:
            print(f"pcfbench: warning: {exc}", file=sys.stderr)
            continue
        names.append(name)
    return tuple(names)
