"""One pass over a sample for every method: the cells of a run that score several methods on
the same samples, computed together.

Cells that differ only in the method (and its options or checkpoint) share their samples: the
same dataset, root, split, setting, policy, limit and metrics; a cell that scores a subset of
them (``CellSpec.subset``) joins the pass and is given only its own. :func:`run_group` loads each
such sample once and builds its ground truth's structures once (the k-d tree, the angles, the
ROI masks and clamps: :class:`~pcfbench.metrics.base.SweepTruth`), then runs and scores every
method that still needs the sample on it, one after the other, in the same process
(:class:`~pcfbench.running.runner.SharedSample`). The store is as before: one cell per method,
each locked, checked, appended to a chunk at a time and completed on its own, with the same
rows (the shared structures are the values each method's scoring would compute); only the
``t_load`` timing is the one shared loading's.

What a sample's task is does not change either: one method on one sample, under the same
per-sample limits, its failure that method's failure row. In worker processes
(``RunOptions.isolated``) the tasks of one sample go to one worker in turn
(``run_supervised``'s ``affinity``), so that the worker keeps the sample between them; a worker
that crashes or is stopped takes only its task down, and the sample's other methods are done by
the next worker, which loads the sample again.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Iterable

from tqdm import tqdm

from pcfbench.execution import ExecutionContext, applied
from pcfbench.execution import apply as apply_execution
from pcfbench.plugins import Plugins, get_plugins
from pcfbench.protocol import sample_id
from pcfbench.running import runner
from pcfbench.running.runner import CellPlugins, CellResult, Resolved, RunOptions, SharedSample
from pcfbench.store.cells import Cell, CellSpec


def group_key(spec: CellSpec) -> tuple:
    """What cells must share to share their samples: everything but the method's part."""
    return (spec.dataset, spec.dataset_root, spec.split, spec.setting, spec.policy, spec.limit, tuple(spec.metrics))


def groups(specs: Iterable[CellSpec]) -> list[list[CellSpec]]:
    """``specs`` in groups of :func:`group_key`, in the order each group first appears."""
    out: dict[tuple, list[CellSpec]] = {}
    for spec in specs:
        out.setdefault(group_key(spec), []).append(spec)
    return list(out.values())


def shares(options: RunOptions) -> bool:
    """Whether cells computed under ``options`` can share a pass: the local executor's (a Ray
    executor's tasks are shards of one cell)."""
    return options.executor is None


def run_group(specs: list[CellSpec], store_root, options: RunOptions | None = None, *,
              plugins: Plugins | None = None) -> list[CellResult]:
    """Run (or resume) the cells ``specs`` (one :func:`groups` group) in one pass over their
    samples; returns each cell's result, in the order of ``specs``.

    Each cell is resolved, locked, checked and completed as :func:`~pcfbench.running.runner.run_cell`
    does it (a complete cell is left alone; ``CellLocked`` when another process holds one and
    ``options.wait`` is false, before any work). Every method needing a sample runs on it while
    it is loaded; each cell's rows are appended to its own store, a chunk at a time. One cell, or
    an executor whose tasks are one cell's shards (Ray): ``run_cell`` for each."""
    options = options or RunOptions()
    specs = list(specs)
    if len({group_key(s) for s in specs}) != 1:
        raise ValueError("run_group: the cells must share dataset, root, split, setting, policy, limit and metrics")
    if len(specs) == 1 or not shares(options):
        return [runner.run_cell(spec, store_root, options, plugins=plugins) for spec in specs]
    start = time.perf_counter()
    resolved = [runner.resolve(spec, plugins) for spec in specs]
    builder = resolved[0].builder
    if any(res.builder.identity() != builder.identity() for res in resolved):  # a method's own protocol would differ
        return [runner.run_cell(spec, store_root, options, plugins=plugins) for spec in specs]
    for res in resolved:
        res.builder = builder  # one builder: its sweep cache serves every method
    # each cell's own samples (a subset cell's are some of the others'); the pass goes over
    # their union in the policy's order
    every = runner.policy_keys(resolved[0], specs[0], plugins)
    own = [runner.cell_keys(every, spec) for spec in specs]
    wanted = {key for keys in own for key in keys}
    keys = [key for key in every if key in wanted]
    fingerprint = builder.adapter.fingerprint(specs[0].split)
    results: list[CellResult | None] = [None] * len(specs)
    with contextlib.ExitStack() as stack:
        open_: list[tuple[int, Cell, dict, set, list]] = []
        # locked in the order of their folders, as any other group holding some of them locks them
        order = sorted(range(len(specs)), key=lambda j: str(specs[j].relpath()))
        cells = {j: stack.enter_context(Cell(store_root, specs[j], wait=options.wait)) for j in order}
        for j, (spec, res) in enumerate(zip(specs, resolved)):
            cell = cells[j]
            ids = [sample_id(s, i) for s, i in own[j]]
            meta, done, todo = runner.open_cell(cell, res, spec, own[j], ids, fingerprint, options)
            if meta is None:
                results[j] = CellResult(spec, cell.dir, "complete", len(ids), len(done), 0, 0, 0.0)
            else:
                open_.append((j, cell, meta, done, todo))
        if open_:
            failed = _compute(specs, resolved, open_, keys, options, plugins)
            for j, cell, meta, done, todo in open_:
                n = len(own[j])
                elapsed = runner.close_cell(cell, resolved[j], specs[j], meta, fingerprint, n, start)
                results[j] = CellResult(specs[j], cell.dir, "complete", n, len(done), len(todo), failed[j], elapsed)
    return results  # type: ignore[return-value]


def _compute(specs: list[CellSpec], resolved: list[Resolved], open_: list, keys: list[tuple[str, int]],
             options: RunOptions, plugins: Plugins | None) -> dict[int, int]:
    """Compute the open cells' samples, sample by sample (every method needing it in turn),
    each cell's rows buffered and appended as ``runner._compute`` does; returns the failed
    samples per cell."""
    todo = {j: set(t) for j, _, _, _, t in open_}
    tasks = [(key, j) for key in keys for j, *_ in open_ if key in todo[j]]
    cells = {j: cell for j, cell, *_ in open_}
    buffers: dict[int, list] = {j: [] for j in cells}
    counts = dict.fromkeys(cells, 0)
    failed = dict.fromkeys(cells, 0)
    last_flush = time.monotonic()

    def flush() -> None:
        nonlocal last_flush
        for j, rows in buffers.items():
            if rows:
                cells[j].append_rows(rows)
            buffers[j], counts[j] = [], 0
        last_flush = time.monotonic()

    label = options.progress_label or f"{len(cells)} methods | {specs[0].dataset}:{specs[0].split} | {specs[0].setting}"
    bar = tqdm(total=len(tasks), desc=label, unit="task", disable=runner._progress_disabled() if options.progress else True,
               leave=True, dynamic_ncols=True)
    try:
        for j, rows in _execute(specs, resolved, tasks, options, plugins):
            buffers[j].extend(rows)
            counts[j] += 1
            failed[j] += rows[0]["status"] == "failed"
            bar.update(1)
            if max(counts.values()) >= runner.CHUNK_SAMPLES or time.monotonic() - last_flush > runner.CHUNK_SECONDS:
                flush()
        return failed
    finally:
        flush()  # rows in the buffers belong to finished samples: keep them even when interrupted
        bar.close()


def _execute(specs: list[CellSpec], resolved: list[Resolved], tasks: list[tuple[tuple[str, int], int]],
             options: RunOptions, plugins: Plugins | None) -> Iterable[tuple[int, list[dict[str, Any]]]]:
    """Yield (cell number, rows) per task, in this process (serial, unisolated) or from
    supervised workers, a sample's tasks to one worker in turn."""
    execution = options.execution()
    samples = len({key for key, _ in tasks})
    jobs = options.workers(samples)
    if not options.isolated and (jobs <= 1 or len(tasks) < 2):
        shared = SharedSample()
        with applied(execution):
            for res in resolved:
                res.bind(execution)
                res.forecast_ratio = options.forecast_ratio
                res.metrics_backend = options.metrics_backend
            for key, j in tasks:
                yield j, runner.process_sample(resolved[j], key, shared)
        return
    from pcfbench.running.workers import run_supervised

    jobs = max(1, min(jobs, samples))
    chosen = [CellPlugins(spec, plugins or get_plugins()) for spec in specs]
    init_args = (specs, execution.share(jobs), chosen, options.forecast_ratio, options.metrics_backend)
    memory = None if options.max_memory_gb is None else int(options.max_memory_gb * 2**30)
    yield from run_supervised(tasks, jobs, _worker_init, init_args, _worker_task, _failure, options.timeout,
                              options.scoring_timeout, memory, affinity=_sample_of)


# -- workers (pcfbench.running.workers) ---------------------------------------------------------------
_GROUP: list[Resolved] | None = None
_SHARED = SharedSample()


def _worker_init(specs: list[CellSpec], execution: ExecutionContext, plugins: list[CellPlugins],
                 forecast_ratio: float | None, backend: str = "auto") -> None:
    """As ``runner._worker_init``, for every cell of the group, with one builder."""
    global _GROUP
    apply_execution(execution)
    group = [runner.resolve(spec, chosen) for spec, chosen in zip(specs, plugins)]  # type: ignore[arg-type]
    for res in group:
        res.builder = group[0].builder
        res.bind(execution)
        res.forecast_ratio = forecast_ratio
        res.metrics_backend = backend
    _GROUP = group


def _worker_task(task: tuple[tuple[str, int], int]) -> tuple[int, list[dict[str, Any]]]:
    assert _GROUP is not None
    key, j = task
    return j, runner.process_sample(_GROUP[j], key, _SHARED)


def _failure(task: tuple[tuple[str, int], int], kind: str, reason: str) -> tuple[int, list[dict[str, Any]]]:
    key, j = task
    return j, runner._failure_row(key, kind, reason)


def _sample_of(task: tuple[tuple[str, int], int]) -> tuple[str, int]:
    return task[0]
