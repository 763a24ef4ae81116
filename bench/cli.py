"""The ``pcfbench`` command line."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

import pcfbench
from pcfbench import config
from pcfbench.errors import PcfbenchError
from pcfbench.plugins import get_plugins, warn_failed
from pcfbench.plugins import all_settings, get_setting
from pcfbench.protocol import SAMPLE_POLICIES

#: ``pcfbench run --timeout``: ten minutes per sample, far above any built-in method's CPU time
#: per sample (seconds), so that only a hung or runaway method meets it.
DEFAULT_TIMEOUT_S = 600.0
#: ``pcfbench run --scoring-timeout``: scoring a sample's forecast, timed apart from the method
#: (a KITTI-sized sample scores in about a second; docs/performance.md)
DEFAULT_SCORING_TIMEOUT_S = 120.0

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.method import MethodSpec


class Group(click.Group):
    """Turns PcfbenchError into one clear line and a non-zero exit, and Ctrl-C into one line and
    exit status 130 (128 + SIGINT)."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except PcfbenchError as exc:
            click.echo(f"pcfbench: error: {exc}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:  # one a command does not answer itself (click would say "Aborted!", exit 1)
            from pcfbench.interrupts import exit_interrupted

            exit_interrupted()


@click.group(cls=Group)
@click.version_option(pcfbench.__version__, prog_name="pcfbench")
def cli() -> None:
    """Benchmark LiDAR point-cloud forecasting methods under one exact protocol."""


def _selected_methods(plugins, requested: tuple[str, ...]) -> list[MethodSpec]:
    """The methods of ``--method`` (resolved now: an unknown name or option fails before any
    work), else every registered method that is ready to run, with each option set of its
    ``default_run_options`` (its defaults, unless it names more): a trained method is ready when
    its checkpoint for its default training data exists."""
    from pcfbench.method import resolve_method

    if requested:
        return [resolve_method(m, plugins) for m in requested]
    out = []
    for name in plugins.methods.names():
        try:
            cls = plugins.methods.get(name)
            methods = [resolve_method((name, dict(opts)), plugins) for opts in getattr(cls, "default_run_options", ({},))]
        except PcfbenchError as exc:
            click.echo(f"pcfbench: warning: skipping {exc}", err=True)
            continue
        seen: dict[str, MethodSpec] = {}
        for method in methods:
            if method.options_hash in seen:  # two option sets of one meaning: one cell, scored once
                click.echo(f"pcfbench: warning: {name}'s default_run_options give {method.text()} the options of "
                           f"{seen[method.options_hash].text()}; scored once", err=True)
                continue
            seen[method.options_hash] = method
            if _ready_by_default(method, plugins):
                out.append(method)
    return out


def _ready_by_default(method: MethodSpec, plugins) -> bool:
    """Whether a run of the default method set scores ``method``: it needs no input of its own,
    and a trained one has a checkpoint for its default training data (else a note says how to
    train it)."""
    from pcfbench.training import find_checkpoint, is_trained, open_training_data
    from pcfbench.training.checkpoints import may_have_checkpoint, ready_shipped, shipped_mismatch

    name = method.text()
    # the command that trains it names its training options only (the same checkpoint)
    train = method.text(drop=getattr(method.cls, "inference_options", ()))
    if not getattr(method.cls, "in_default_runs", True):  # needs an input of its own (a submission file)
        return False
    if is_trained(method.cls):
        data = method.cls.default_train_on
        try:
            if ready_shipped(method, data, plugins=plugins) is not None:  # no training data needed
                return True
            train_on = (open_training_data(data, plugins=plugins, progress=False).train_on
                        if may_have_checkpoint(method, data) else None)
            if train_on is None or find_checkpoint(method, train_on) is None:
                why = None if train_on is None else shipped_mismatch(method, train_on)
                if why:
                    click.echo(f"pcfbench: warning: {name}'s shipped checkpoint is not for this machine's "
                               f"{data}:train: {why} (`pcfbench train {train} --dataset {data}` trains one "
                               f"here); left out", err=True)
                else:
                    click.echo(f"pcfbench: note: {name} is not trained on {data}:train yet "
                               f"(`pcfbench train {train} --dataset {data}`); left out", err=True)
                return False
        except PcfbenchError as exc:
            click.echo(f"pcfbench: warning: skipping {name}: {exc}", err=True)
            return False
    return True


def _dataset_roots(plugins, dataset_args: tuple[str, ...], progress: bool) -> list[tuple[str, str]]:
    names, cli_roots = config.parse_dataset_args(dataset_args)
    if not names:
        names = [n for n in plugins.datasets.names() if getattr(plugins.datasets.get(n), "embedded", False)]
        if not names:
            raise PcfbenchError("no dataset named and no embedded dataset registered: use --dataset NAME=ROOT")
    return [(name, config.resolve_root(name, plugins.datasets.get(name), cli_roots, progress)) for name in names]


def executor_options(command):
    """The options that choose where samples are computed: this machine's processes or Ray."""
    options = [
        click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True,
                     help="local: this process or a pool of --jobs processes; ray: shards of samples as Ray tasks "
                          "(docs/cluster.md)."),
        click.option("--address", default=None, metavar="auto|HOST:PORT",
                     help="Ray: the cluster to run on (default: start Ray on this machine)."),
        click.option("--shard-samples", type=click.IntRange(min=1), default=16, show_default=True,
                     help="Ray: samples per task (and per chunk of rows in the store)."),
        click.option("--cpus-per-task", type=click.IntRange(min=1), default=1, show_default=True,
                     help="Ray: CPUs reserved for each task, its thread budget."),
        click.option("--gpus-per-task", type=click.FloatRange(min=0), default=0.0, show_default=True,
                     help="Ray: GPUs reserved for each task of a trained method's cell."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def limit_options(command):
    """The per-sample limits besides --timeout (scoring time, memory, forecast size) and where the
    scoring's searches run."""
    from pcfbench.protocol.validate import FORECAST_FLOOR, FORECAST_RATIO

    options = [
        click.option("--scoring-timeout", type=click.FloatRange(min=0), default=DEFAULT_SCORING_TIMEOUT_S,
                     show_default=True, metavar="SECONDS",
                     help="Time limit for scoring one sample's forecast, apart from the method's --timeout; a sample "
                          "over it is a scoring failure (ScoringTimeout), not the method's timeout (0: no limit)."),
        click.option("--max-memory", type=click.FloatRange(min=0), default=0.0, show_default=True, metavar="GIB",
                     help="Per-sample memory limit: a worker process holding more resident memory is stopped and its "
                          "sample recorded failed (SampleMemory) (0: no limit)."),
        click.option("--max-forecast-ratio", type=click.FloatRange(min=0), default=FORECAST_RATIO, show_default=True,
                     metavar="RATIO",
                     help=f"A forecast sweep with more than RATIO x its ground truth's points (at least "
                          f"{FORECAST_FLOOR:,}) is refused as the method's failure, before scoring (0: no cap)."),
        click.option("--metrics-backend", type=click.Choice(["auto", "numpy", "torch"]), default="auto",
                     show_default=True,
                     help="Where the metrics' nearest-neighbour searches run: torch (the GPU; the CPU when there is "
                          "none), numpy (k-d trees and grids on the CPU); auto: torch when a CUDA GPU is there. "
                          "Same values."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def _limits(executor: str, scoring_timeout: float, max_memory: float, max_forecast_ratio: float,
            metrics_backend: str = "auto") -> dict:
    """RunOptions' limit fields from limit_options' values (0: none); the Ray executor times the
    method and the scoring apart as the local one does, but keeps the default forecast cap, has
    no memory limit and scores where each task finds a GPU (auto), so it refuses those three."""
    from pcfbench.protocol.validate import FORECAST_RATIO

    if executor == "ray" and (max_memory or max_forecast_ratio != FORECAST_RATIO or metrics_backend != "auto"):
        raise click.UsageError("--max-memory, --max-forecast-ratio and --metrics-backend apply to the local executor "
                               "only; the Ray executor limits a sample by --timeout and --scoring-timeout and scores on "
                               "a task's GPU when it has one (docs/cluster.md)")
    return {"scoring_timeout": scoring_timeout or None, "max_memory_gb": max_memory or None,
            "forecast_ratio": max_forecast_ratio or None, "metrics_backend": metrics_backend}


def _executor(executor, address, shard_samples, cpus_per_task, gpus_per_task, jobs, threads, timeout=None,
              scoring_timeout=None):
    """The Ray executor for ``--executor ray`` (None: the local one); options of the other
    executor are refused rather than ignored."""
    if executor == "local":
        given = [name for name, value, default in (("--address", address, None), ("--shard-samples", shard_samples, 16),
                 ("--cpus-per-task", cpus_per_task, 1), ("--gpus-per-task", gpus_per_task, 0.0)) if value != default]
        if given:
            raise PcfbenchError(f"{', '.join(given)} apply to --executor ray only")
        return None
    if jobs or threads:
        raise PcfbenchError("--jobs and --threads are the local executor's: with --executor ray, Ray runs as many "
                            "tasks at once as the cluster has CPUs for (--cpus-per-task each)")
    from pcfbench.running.ray_executor import RayExecutor

    return RayExecutor(address=address, shard_samples=shard_samples, cpus_per_task=cpus_per_task,
                       gpus_per_task=gpus_per_task, timeout=timeout, scoring_timeout=scoring_timeout)


@cli.command()
@click.option("--dataset", "-d", "datasets", multiple=True, metavar="NAME[=ROOT]", help="Dataset (repeatable).")
@click.option("--setting", "-s", "settings", multiple=True, help="Setting, e.g. kitti-1s (repeatable).")
@click.option("--split", "splits", multiple=True, help="Split (repeatable); default: the dataset's evaluation split.")
@click.option("--method", "-m", "methods", multiple=True, metavar="NAME[:k=v,...]", help="Method (repeatable).")
@click.option("--metric", "metrics", multiple=True, help="Metric (repeatable); default: every registered metric.")
@click.option("--policy", type=click.Choice(SAMPLE_POLICIES), default=None,
              help="Sample policy of the protocol file, e.g. subsample-4000 (Copilot4D's Argoverse 2 Table 2); "
                   "default: each dataset's own (full-context; synthetic-town-realistic: every-third).")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first N samples (partial: kept out of leaderboards).")
@click.option("--subset", type=click.IntRange(min=0), default=None, metavar="N",
              help="At most N of the policy's samples per cell, evenly spaced: a documented subset, ranked beside "
                   "the other cells with its sample count (not partial). Default: without --method, each method's "
                   "own (the costliest learned methods score 8; docs/protocol.md); 0: every sample for every method.")
@click.option("--jobs", "-j", type=click.IntRange(min=0), default=0, show_default=True,
              help="Worker processes; 0: one per CPU for cells with enough samples, else serial.")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="Thread budget of the run (default: every CPU); each of N workers gets threads // N, at least 1.")
@click.option("--force", is_flag=True, help="Recompute cells that are already complete.")
@click.option("--store", type=click.Path(file_okay=False), default=None, help="Results store (default: <reports>/store).")
@click.option("--reports", type=click.Path(file_okay=False), default=None, help="Reports folder (default: ./reports).")
@click.option("--no-report", is_flag=True, help="Do not regenerate the leaderboard afterwards.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
@click.option("--train-on", "train_on", default=None, metavar="NAME[=ROOT]",
              help="Trained methods: the checkpoint trained on this dataset (default: each method's own default).")
@click.option("--train-split", default="train", show_default=True, help="Trained methods: the split it was trained on.")
@click.option("--checkpoint", type=click.Path(exists=True), default=None,
              help="Trained methods: evaluate this checkpoint (folder, manifest.json or weights file).")
@click.option("--allow-train-split", is_flag=True,
              help="Score a trained method on the very data it was trained on (marked in cell.json and the leaderboard).")
@click.option("--keep-going", is_flag=True,
              help="Exit 0 even when samples failed (their cells are reported incomplete and not ranked either way).")
@click.option("--timeout", type=click.FloatRange(min=0), default=DEFAULT_TIMEOUT_S, show_default=True, metavar="SECONDS",
              help="Per-sample time limit of loading and the method's forecast; a sample over it is recorded failed "
                   "and the run goes on (0: no limit).")
@limit_options
@executor_options
def run(datasets, settings, splits, methods, metrics, policy, limit, subset, jobs, threads, force, store, reports, no_report, quiet,
        train_on, train_split, checkpoint, allow_train_split, keep_going, timeout, scoring_timeout, max_memory,
        max_forecast_ratio, metrics_backend, executor, address, shard_samples, cpus_per_task, gpus_per_task):
    """Run (or resume) every cell of method x dataset x split x setting.

    Exits 1 when any sample of the run's cells failed (now or in an earlier run of a reused
    cell); ``--keep-going`` exits 0. A cell with failed samples is never ranked. Samples run
    in worker processes: one that crashes or exceeds ``--timeout`` is a failed sample."""
    from pcfbench.reporting.report import collect, summary, write_reports
    from pcfbench.running.runner import RunOptions

    plugins = get_plugins()
    warn_failed(plugins)
    ray_executor = _executor(executor, address, shard_samples, cpus_per_task, gpus_per_task, jobs, threads, timeout or None,
                             scoring_timeout or None)
    cells = _plan_cells(plugins, datasets, settings, splits, methods, metrics, policy, limit, train_on, train_split,
                        checkpoint, progress=not quiet, warm=executor == "local", subset=subset)
    reports_path = config.reports_dir(reports)
    store_path = config.store_dir(store, reports_path)
    options = RunOptions(jobs=jobs, force=force, progress=not quiet, threads=threads, allow_train_split=allow_train_split,
                         executor=ray_executor, timeout=timeout or None, isolate=True,
                         **_limits(executor, scoring_timeout, max_memory, max_forecast_ratio, metrics_backend))
    failures, failed_cells = _run_cells(cells, store_path, options, plugins)
    if not no_report:
        board = collect(store_path)
        # a --limit run's report goes beside the leaderboard, never over it (a complete one may be there)
        out = reports_path if limit is None else config.partial_reports_dir(reports_path)
        paths = write_reports(store_path, out, leaderboard=board)
        click.echo(summary(store_path, leaderboard=board))
        click.echo(f"leaderboard: {paths['md']}")
        if limit is not None:
            click.echo(f"(a --limit run writes its report under {out}; {reports_path / 'leaderboard.md'} is written "
                       "only by a run without --limit or by pcfbench report)")
    if failures:
        click.echo(f"pcfbench: {failures} sample(s) failed in {failed_cells} cell(s), which are incomplete and not "
                   "ranked; their tracebacks are in the cells' rows", err=True)
        if not keep_going:
            sys.exit(1)


def _plan_cells(plugins, datasets, settings, splits, methods, metrics, policy, limit, train_on, train_split, checkpoint,
                progress: bool, warm: bool, subset: int | None = None) -> list:
    """The run's cells (method x dataset x split x setting), every name checked and every
    trained method's checkpoint found before any work. ``subset``: N (every cell scores at most
    N evenly spaced samples of its policy), 0 (every sample) or None: without ``methods`` (the
    default method set) each method's ``default_run_subset``, with them every sample."""
    from pcfbench.running.runner import default_metrics
    from pcfbench.running.warmup import warm_while_preparing
    from pcfbench.store.cells import CellSpec

    for s in settings:
        get_setting(s)
    metric_names = tuple(metrics) or default_metrics(plugins)
    for m in metric_names:
        plugins.metrics.get(m)
    # data generated now (the embedded dataset's splits) leaves a core idle: the methods' and
    # metrics' numba kernels compile there meanwhile, not in every worker of the first cells
    warmup = warm_while_preparing(methods or None, metric_names) if warm else contextlib.nullcontext()
    with warmup:
        # named methods resolve first and a bad dataset root fails next, before the default
        # methods' readiness generates their training data
        method_specs = _selected_methods(plugins, methods) if methods else None
        roots = _dataset_roots(plugins, datasets, progress)
        if method_specs is None:
            method_specs = _selected_methods(plugins, methods)
        checkpoints = _checkpoints(plugins, method_specs, checkpoint, train_on, train_split, progress)
    cells = []
    for name, root in roots:
        cls = plugins.datasets.get(name)
        ds_settings = settings or cls.default_settings
        if not ds_settings:
            raise PcfbenchError(f"dataset {name!r} declares no default settings: pass --setting")
        ds_policy = policy or cls.default_policy
        for split, setting, method in itertools.product(splits or (cls.default_split,), ds_settings, method_specs):
            cells.append(
                CellSpec(method.name, dict(method.raw), method.options_hash, name, root, split, setting, ds_policy, limit,
                         metric_names, **checkpoints.get((method.name, method.options_hash), {}),
                         subset=_subset(method, subset, default_set=not methods))
            )
    return cells


def _subset(method, subset: int | None, default_set: bool) -> int | None:
    """A cell's ``CellSpec.subset``: ``--subset N`` for every method (0: none), else the
    method's ``default_run_subset`` in a run of the default method set (no ``--method``)."""
    if subset is not None:
        return subset or None
    return getattr(method.cls, "default_run_subset", None) if default_set else None


def _run_cells(cells, store_path, options, plugins) -> tuple[int, int]:
    """Run every cell in turn (a cell another process holds goes last and is then waited
    for: its rows are the other run's, computed once; docs/trust.md); Ctrl-C says how to
    resume. Cells that differ only in the method share one pass over their samples
    (``pcfbench.running.group``; one by one when another process holds one of them). Returns
    the failed samples of the run's cells, now or in an earlier run of a reused cell, and how
    many cells have any."""
    from pcfbench.running.group import group_key, run_group, shares
    from pcfbench.running.runner import run_cell
    from pcfbench.store.cells import Cell, CellLocked

    failures = failed_cells = 0
    finished = 0

    def report(i, spec, result) -> None:
        nonlocal failures, failed_cells, finished
        where = f"cell {i}/{len(cells)}: {cell_label(spec)}"  # the grid's position, the variant's options
        finished += 1
        if result.processed == 0 and result.done_before == result.samples:
            click.echo(f"{where}: complete, nothing to do ({result.samples} samples)")
        else:
            click.echo(
                f"{where}: {result.samples} samples ({result.processed} now, {result.failed} failed) "
                f"in {result.seconds:.1f} s -> {result.path}"
            )
        # this cell's failed samples, from this run or an earlier one (a reused cell keeps them)
        cell_failed = int(((Cell(store_path, spec).read_meta() or {}).get("counts") or {}).get("failed", 0))
        failures += cell_failed
        failed_cells += cell_failed > 0

    by_samples: dict = {}
    for i, spec in enumerate(cells, 1):
        by_samples.setdefault(group_key(spec), []).append((i, spec))
    queue = []
    with interrupted_note(store_path, lambda: finished, len(cells)):
        for members in by_samples.values():
            if len(members) < 2 or not shares(options):
                queue += [(i, spec, False) for i, spec in members]
                continue
            first = members[0][1]
            where = (f"cells {', '.join(str(i) for i, _ in members)}/{len(cells)}: {len(members)} methods | "
                     f"{first.dataset}:{first.split} | {first.setting}")
            try:
                results = run_group([spec for _, spec in members], store_path,
                                    dataclasses.replace(options, wait=False, progress_label=where), plugins=plugins)
            except CellLocked:
                click.echo(f"{where}: another pcfbench process is computing one of them; running them one by one",
                           err=True)
                queue += [(i, spec, False) for i, spec in members]
                continue
            for (i, spec), result in zip(members, results):
                report(i, spec, result)
        while queue:
            i, spec, wait = queue.pop(0)
            where = f"cell {i}/{len(cells)}: {cell_label(spec)}"
            if wait:
                click.echo(f"{where}: waiting for the other pcfbench process computing it", err=True)
            try:
                result = run_cell(spec, store_path, dataclasses.replace(options, wait=wait, progress_label=where),
                                  plugins=plugins)
            except CellLocked:
                click.echo(f"{where}: another pcfbench process is computing it; doing the other cells first", err=True)
                queue.append((i, spec, True))
                continue
            report(i, spec, result)
    return failures, failed_cells


def cell_label(spec) -> str:
    """``raycast-voxel (voxel=0.4) | synthetic-town:test | kitti-1s``: the cell with its options."""
    from pcfbench.reporting.labels import cell_label as label

    return label(spec)


@contextlib.contextmanager
def interrupted_note(store_path, finished, total: int):
    """On Ctrl-C: say what is kept and how to resume, and exit 130 (128 + SIGINT).

    ``finished()``: how many of the ``total`` cells are complete (None: not counted). The runner has written the
    rows of every finished sample before the interrupt reached here."""
    import shlex

    from pcfbench.interrupts import exit_interrupted

    try:
        yield
    except KeyboardInterrupt:
        again = "pcfbench " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        done = f"{finished()} of {total} cell(s) complete, and " if finished is not None else ""
        exit_interrupted(f"pcfbench: interrupted: the finished work is kept in the store {store_path} "
                         f"({done}every sample finished in the interrupted cell); "
                         f"run the same command again to resume:\n  {again}")


def _checkpoints(plugins, method_specs, checkpoint, train_on, train_split, progress) -> dict[tuple[str, str], dict]:
    """Per trained method variant of the run (name, options hash: two variants of one method are
    two checkpoints), the CellSpec fields of its checkpoint (one error for a missing, altered or
    mismatched one before any work)."""
    from pcfbench.training import checkpoint_for, is_trained

    trained = [m for m in method_specs if is_trained(m.cls)]
    if checkpoint and len(trained) != 1:
        raise PcfbenchError(f"--checkpoint {checkpoint}: the run must have exactly one trained method "
                            f"(it has {len(trained)}: {', '.join(m.name for m in trained) or 'none'})")
    out = {}
    for m in trained:
        ck = checkpoint_for(m, checkpoint=checkpoint, train_on=train_on, split=train_split, plugins=plugins,
                            progress=progress)
        out[m.name, m.options_hash] = {"checkpoint": str(ck.dir.resolve()), "checkpoint_sha256": ck.sha256,
                                       "train_on": ck.train_on_label}
    return out


@cli.command()
@click.argument("method_spec", metavar="METHOD[:k=v,...]")
@click.option("--dataset", "-d", "dataset", required=True, metavar="NAME[=ROOT]", help="Training data.")
@click.option("--split", default="train", show_default=True)
@click.option("--max-minutes", type=click.FloatRange(min=0), default=None,
              help="Stop (with a checkpoint) after this much training time; rerun to continue.")
@click.option("--fresh", is_flag=True, help="Start over instead of resuming the checkpoint.")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="CPU threads of the training (default: every CPU); recorded in the manifest, and a resumed "
                   "training must keep the count it started with (the weights' rounding depends on it).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--ship", is_flag=True, help="Then copy the complete checkpoint into the method's package (float16 "
              "weights, docs/training.md#shipped-checkpoints).")
def train(method_spec, dataset, split, max_minutes, fresh, threads, quiet, ship):
    """Train (or resume) a trained method; its checkpoint goes to the cache, keyed by method,
    version, options and training data."""
    from pcfbench.method import resolve_method
    from pcfbench.interrupts import exit_interrupted
    from pcfbench.training import TrainingInterrupted, open_training_data, retrain_command
    from pcfbench.training import ship as ship_checkpoint, train as train_method

    plugins = get_plugins()
    warn_failed(plugins)
    spec = resolve_method(method_spec, plugins)
    try:
        ck = train_method(spec, dataset, split=split, max_minutes=max_minutes, fresh=fresh, progress=not quiet,
                          plugins=plugins, threads=threads, log=click.echo)
    except TrainingInterrupted as stop:
        exit_interrupted(_training_interrupted(stop, _resume_command(method_spec, dataset, split, max_minutes,
                                                                     threads, quiet, ship)))
    except KeyboardInterrupt:  # while opening (or making) the training data: no step was trained
        exit_interrupted("pcfbench: interrupted before training began: nothing was trained or saved")
    state = "complete" if ck.manifest.get("complete") else "not finished: rerun the same command to continue"
    click.echo(f"{spec.name}: {ck.steps} steps on {ck.train_on_label} in {ck.manifest['wall_s']:.0f} s ({state})")
    click.echo(f"checkpoint: {ck.manifest_path} (weights sha256 {ck.sha256[:16]})")
    if ship:
        retrain = retrain_command(spec, dataset, split, ck.manifest)
        ship_checkpoint(spec, ck, open_training_data(dataset, split, plugins, progress=False).train_on, retrain,
                        log=click.echo)


def _resume_command(method_spec, dataset, split, max_minutes, threads, quiet, ship) -> str:
    """The ``pcfbench train`` command that resumes this one: its options but ``--fresh`` (which
    would throw the kept checkpoint away); ``--threads`` as given (a resumed training must keep
    its thread count)."""
    import shlex

    args = ["pcfbench", "train", method_spec, "--dataset", dataset]
    if split != "train":
        args += ["--split", split]
    if max_minutes is not None:
        args += ["--max-minutes", f"{max_minutes:g}"]
    if threads is not None:
        args += ["--threads", str(threads)]
    args += ["--quiet"] * bool(quiet) + ["--ship"] * bool(ship)
    return shlex.join(args)


def _training_interrupted(stop, resume: str) -> str:
    """What Ctrl-C in ``pcfbench train`` says: where it stopped, the checkpoint kept and the
    command that resumes from it."""
    at = "" if stop.step is None else f" at step {stop.step}" + (f" of {stop.total}" if stop.total else "")
    if stop.saved_step is None:
        return (f"pcfbench: training interrupted{at}, before its first checkpoint: nothing is kept in {stop.dir}; "
                f"start again with:\n  {resume}")
    redo = (f" (steps {stop.saved_step + 1}..{stop.step} are trained again)"
            if stop.step is not None and stop.step > stop.saved_step else "")
    return (f"pcfbench: training interrupted{at}: the checkpoint of step {stop.saved_step} is kept, "
            f"{stop.manifest_path}; resume it{redo} with:\n  {resume}")


@cli.command()
@click.option("--store", type=click.Path(file_okay=False), default=None)
@click.option("--reports", type=click.Path(file_okay=False), default=None)
@click.option("--preset", default="paper", show_default=True, help="Table preset of leaderboard.* (see tables.toml).")
@click.option("--tables", "tables_file", type=click.Path(dir_okay=False), default=None,
              help="A TOML file of extra table presets ([presets.NAME]).")
@click.option("--reference", default=None, metavar="NAME[:k=v,...]",
              help="Method every cell is compared with: by name, its cell of the shortest label in each table; "
                   "with options (as -m takes them), its cell of exactly those options (default: copy-last where "
                   "present).")
@click.option("--ci", type=click.Choice(["pm", "interval", "none"]), default="pm", show_default=True,
              help="Intervals shown as ±half-width, as [lo, hi], or not at all.")
@click.option("--resample", default="sample", show_default=True, metavar="sample|sequence|block:N",
              help="Bootstrap unit: samples, whole sequences, or blocks of N consecutive samples.")
@click.option("--resamples", type=click.IntRange(min=100), default=2000, show_default=True)
@click.option("--seed", type=int, default=17, show_default=True, help="Bootstrap seed (output is deterministic).")
@click.option("--no-figures", is_flag=True, help="Leave out reports/figures/ (and the page's figures).")
@click.option("--gallery", is_flag=True, help="Also draw the gallery of forecasts (reports/figures/gallery-*), "
              "which re-runs every method on 2 samples per group: the one figure not drawn from the store.")
@click.option("--dataset", "-d", "datasets", multiple=True, metavar="PATTERN",
              help="Only cells of these datasets (repeatable; shell-style patterns, e.g. 'kitti*').")
@click.option("--setting", "-s", "settings", multiple=True, metavar="PATTERN",
              help="Only cells of these settings (repeatable; patterns).")
@click.option("--method", "-m", "methods", multiple=True, metavar="PATTERN",
              help="Only cells of these methods (repeatable; patterns, e.g. 'raycast-*').")
@click.option("--verbose", "-v", is_flag=True, help="List every file written.")
def report(store, reports, preset, tables_file, reference, ci, resample, resamples, seed, no_figures, gallery,
           datasets, settings, methods, verbose):
    """Regenerate the leaderboard tables (reports/leaderboard.*, reports/tables/) and figures
    from the store alone: no method runs (but with --gallery). --dataset/--setting/--method
    report only the cells they match, and every page says so; a figure whose data did not
    change is not drawn again."""
    from pcfbench.reporting.report import ReportOptions, collect, summary, write_reports, written_summary
    from pcfbench.reporting.select import Selection
    from pcfbench.reporting.stats import Resampling

    options = ReportOptions(preset, tables_file, reference, ci, Resampling.parse(resample, resamples=resamples, seed=seed),
                            gallery=gallery, select=Selection(datasets, settings, methods))
    if no_figures:  # otherwise the default: figures unless PCFBENCH_FIGURES=0, as for run and sweep
        options = dataclasses.replace(options, figures=False)
    reports_path = config.reports_dir(reports)
    store_path = config.store_dir(store, reports_path)
    if not store_path.is_dir():  # a mistyped --store would otherwise replace the leaderboard with an empty one
        raise PcfbenchError(f"results store {store_path} does not exist{'' if store else ' (the default, <reports>/store)'}: "
                            "nothing to report and nothing written; pass the folder `pcfbench run --store` wrote")
    board = collect(store_path, options.resampling, options.reference, select=options.select)
    paths = write_reports(store_path, reports_path, options, leaderboard=board)
    click.echo(summary(store_path, options, leaderboard=board))
    if board.scope:
        click.echo(board.scope)
    for note in paths.range_gaps:  # with figures only
        click.echo(f"pcfbench: note: {note}", err=True)
    if verbose:
        for p in paths.values():
            click.echo(str(p))
    click.echo(written_summary(paths, reports_path))
    click.echo(paths["tex"].read_text().splitlines()[0].lstrip("% "))


@cli.command("backfill-ranges")
@click.option("--store", type=click.Path(file_okay=False), default=None, help="Results store (default: <reports>/store).")
@click.option("--reports", type=click.Path(file_okay=False), default=None, help="Reports folder (default: ./reports).")
def backfill_ranges(store, reports):
    """Recompute the range bins of the error-by-range figure for the complete cells made before
    the store kept them, by re-running their methods (a cell whose re-run does not give back
    its stored rows is named and left as it is); then `pcfbench report` draws them."""
    from pcfbench.running.backfill import backfill

    store_path = config.store_dir(store, config.reports_dir(reports))
    if not store_path.is_dir():
        raise PcfbenchError(f"results store {store_path} does not exist (pcfbench run writes it)")
    plugins = get_plugins()
    warn_failed(plugins)
    done = backfill(store_path, plugins, log=lambda line: click.echo(line))
    n = sum(r["status"].startswith("recomputed") for r in done)
    refused = sum(r["status"].startswith("not recomputed") for r in done)
    click.echo(f"{n} cell(s) recomputed, {refused} left as they are, {len(done) - n - refused} had their range bins")
    if refused:
        sys.exit(1)


@cli.command()
@click.argument("store", required=False, type=click.Path(file_okay=False))
@click.option("--traceback", "tracebacks", is_flag=True, help="Print each failure's full traceback.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object per failed sample.")
def failures(store, tracebacks, as_json):
    """List the failed samples of STORE (default: the results store) with their errors."""
    from pcfbench.reporting.report import failures as failed_samples

    store_path = Path(store) if store else config.store_dir(None, config.reports_dir(None))
    if not store_path.is_dir():
        raise PcfbenchError(f"results store {store_path} does not exist (pcfbench run writes it)")
    df = failed_samples(store_path)
    if as_json:
        for r in df.to_dict("records"):
            click.echo(json.dumps(r if tracebacks else {k: v for k, v in r.items() if k != "traceback"}))
        return
    if not len(df):
        click.echo(f"no failed samples in {store_path}")
        return
    for (cell, cell_dir), g in df.groupby(["cell", "cell_dir"], sort=False):
        click.echo(f"{cell}: {len(g)} failed sample(s) ({cell_dir})")
        for _, r in g.iterrows():
            click.echo(f"  {r['sample_id']}: {r['error']}")
            if tracebacks:
                click.echo("    " + r["traceback"].rstrip().replace("\n", "\n    "))
    cells = df["cell_dir"].nunique()
    click.echo(f"{len(df)} failed sample(s) in {cells} cell(s)" + ("" if tracebacks else "; --traceback prints the tracebacks"))


@cli.command()
@click.argument("experiment", type=click.Path(dir_okay=False))
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first N samples (overrides the file's limit).")
@click.option("--jobs", "-j", type=click.IntRange(min=0), default=None, help="Worker processes (overrides the file's jobs).")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="Thread budget of the sweep (as for run).")
@click.option("--force", is_flag=True, help="Recompute cells that are already complete.")
@click.option("--store", type=click.Path(file_okay=False), default=None, help="Results store (default: <reports>/store).")
@click.option("--reports", type=click.Path(file_okay=False), default=None, help="Reports folder (default: ./reports).")
@click.option("--dry-run", is_flag=True, help="Check the experiment file and list its cells as they are planned; run nothing.")
@click.option("--max-cells", type=click.IntRange(min=1), default=None, metavar="N",
              help="The most cells the grid may have (default: the file's max_cells, else 1000).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
@click.option("--timeout", type=click.FloatRange(min=0), default=DEFAULT_TIMEOUT_S, show_default=True, metavar="SECONDS",
              help="Per-sample time limit, as for run (0: no limit).")
@click.option("--keep-going", is_flag=True,
              help="Exit 0 even when samples failed (their cells are incomplete and not in the tables either way).")
@limit_options
@executor_options
def sweep(experiment, limit, jobs, threads, force, store, reports, dry_run, max_cells, quiet, timeout, keep_going,
          scoring_timeout, max_memory, max_forecast_ratio, metrics_backend, executor, address, shard_samples,
          cpus_per_task, gpus_per_task):
    """Run (or resume) the grid of EXPERIMENT.toml and write its ablation tables
    (<reports>/sweeps/STEM.{md,csv,tex,html}); docs/experiments.md describes the file."""
    from pcfbench.reporting.labels import cell_label
    from pcfbench.experiments.sweep import count_cells, iter_plan, load_experiment, run_sweep

    plugins = get_plugins()
    warn_failed(plugins)
    exp = load_experiment(experiment, plugins, max_cells=max_cells)
    ray_executor = _executor(executor, address, shard_samples, cpus_per_task, gpus_per_task, jobs, threads, timeout or None,
                             scoring_timeout or None)
    reports_path = config.reports_dir(reports)
    store_path = config.store_dir(store, reports_path)
    if dry_run:  # each cell as it is planned
        n = count_cells(exp, plugins)
        for i, spec in enumerate(iter_plan(exp, limit=limit, plugins=plugins, progress=not quiet), 1):
            click.echo(f"cell {i}/{n}: {cell_label(spec)} -> {store_path / spec.relpath()}")
        where = reports_path if (exp.limit if limit is None else limit) is None else config.partial_reports_dir(reports_path)
        click.echo(f"tables: {', '.join(str(where / 'sweeps' / t.stem) + '.{md,csv,tex,html}' for t in exp.tables)}")
        return
    with interrupted_note(store_path, None, 0):
        result = run_sweep(exp, store_path, reports_path, limit=limit, jobs=jobs, threads=threads, force=force,
                           progress=not quiet, plugins=plugins, echo=click.echo, executor=ray_executor,
                           timeout=timeout or None, isolate=True,
                           limits=_limits(executor, scoring_timeout, max_memory, max_forecast_ratio, metrics_backend))
    failed = sum(r.failed for r in result.results)
    for text in result.summaries:
        click.echo(text)
    for path in result.paths.values():
        click.echo(str(path))
    if failed:
        click.echo(f"pcfbench: {failed} sample(s) failed; `pcfbench failures` lists them, their tracebacks are in the "
                   "cells' rows", err=True)
        if not keep_going:  # as run: a sweep with failed samples is not a clean result
            sys.exit(1)


@cli.command(name="ls")
@click.argument("what", type=click.Choice(["methods", "datasets", "metrics", "settings", "samples"]))
@click.argument("dataset", required=False, metavar="[DATASET[=ROOT]]")
@click.option("--json", "as_json", is_flag=True)
@click.option("--options", "with_options", is_flag=True,
              help="Methods and datasets: each option (NAME:key=value / ROOT?key=value) with its type, default and help.")
@click.option("--setting", "-s", default=None, help="samples: the setting (required).")
@click.option("--split", default=None, help="samples: the split (default: the dataset's evaluation split).")
@click.option("--policy", type=click.Choice(SAMPLE_POLICIES), default=None,
              help="samples: the sample policy (default: the dataset's own).")
def ls_cmd(what, dataset, as_json, with_options, setting, split, policy):
    """List registered methods, datasets, metrics or the protocol's settings; ``ls samples
    DATASET --setting S`` lists the valid sample ids (what ``export --sample`` takes)."""
    if what == "samples":
        return _ls_samples(dataset, setting, split, policy, as_json)
    if dataset or setting or split:
        raise PcfbenchError(f"DATASET, --setting and --split apply to `pcfbench ls samples`, not to ls {what}")
    if with_options and what not in ("methods", "datasets"):
        raise PcfbenchError(f"--options lists the options of methods and datasets; {what} have none")
    if what == "settings":
        rows = [
            {"name": s.name, "rate_hz": s.rate_hz, "past": s.past, "future": s.future, "stride": s.stride,
             "horizon_s": s.horizon_s, "description": s.description}
            for s in all_settings().values()
        ]
    else:
        plugins = get_plugins()
        registry = getattr(plugins, what)
        rows = [{"name": e.name, "plugin": e.plugin, "description": e.description} for e in registry.entries.values()]
        rows.sort(key=lambda r: r["name"])
        if with_options:
            for r in rows:
                r["options"], r["error"] = _options_of(registry, r["name"])
        if what == "methods":
            for r in rows:
                r.update(_checkpoints_of(plugins, r["name"]))
    if as_json:
        click.echo(json.dumps(rows, indent=2, default=str))
        return
    opts = [o for r in rows for o in r.get("options", ())]
    widths = [max((len(f) for f in fs), default=0) for fs in zip(*((o["name"], o["type"], repr(o["default"])) for o in opts))]
    for r in rows:
        if what == "settings":
            click.echo(f"{r['name']:<14} {r['rate_hz']:>4g} Hz  past {r['past']}  future {r['future']}  stride {r['stride']}  {r['description']}")
            continue
        click.echo(f"{r['name']:<22} {r['plugin']:<22} {r['description']}")
        for line in _checkpoint_lines(r):
            click.echo(f"    {line}")
        if not with_options:
            continue
        if r["error"]:
            click.echo(f"    (options unavailable: {r['error']})")
        elif not r["options"]:
            click.echo("    (no options)")
        for o in r["options"]:
            valid = f" (valid: {o['range']})" if o.get("range") else ""
            click.echo(f"    {o['name']:<{widths[0]}}  {o['type']:<{widths[1]}}  {o['default']!r:<{widths[2]}}  {o['help']}{valid}")


def _checkpoints_of(plugins, name: str) -> dict:
    """``ls methods``' fields of a trained method: its default training data and every
    checkpoint it has (:func:`pcfbench.training.checkpoints.list_checkpoints`); nothing for another."""
    from pcfbench.method import resolve_method
    from pcfbench.training import is_trained
    from pcfbench.training.checkpoints import list_checkpoints

    try:
        spec = resolve_method((name, {}), plugins)
    except PcfbenchError:
        return {}
    if not is_trained(spec.cls):
        return {}
    return {"default_train_on": spec.cls.default_train_on, "checkpoints": list_checkpoints(spec)}


def _checkpoint_lines(row: dict) -> list[str]:
    """``checkpoint kitti:train (root /data/kitti): 1200 steps, complete; <manifest>`` per
    checkpoint of a trained method, or how to train one."""
    if "checkpoints" not in row:
        return []
    lines = []
    for c in row["checkpoints"]:
        if "error" in c:
            lines.append(f"checkpoint {c['manifest']}: {c['error']}")
            continue
        data = c["train_on"] + "".join(f"?{k}={v}" if i == 0 else f"&{k}={v}"
                                       for i, (k, v) in enumerate(sorted(c["dataset_options"].items())))
        origin = "shipped" if c["where"] == "shipped" else f"root {c['root']}" if c["root"] else "trained here"
        opts = f", options {','.join(f'{k}={v}' for k, v in sorted(c['options'].items()))}" if c["options"] else ""
        state = "complete" if c["complete"] else "unfinished (rerun its pcfbench train to continue)"
        lines.append(f"checkpoint {data} ({origin}{opts}): {c['steps']} steps, {state}; {c['manifest']}")
    if not row["checkpoints"]:
        lines.append(f"no checkpoint: `pcfbench train {row['name']} --dataset {row['default_train_on']}` trains the "
                     "checkpoint it uses by default")
    return lines


def _ls_samples(dataset, setting, split, policy, as_json) -> None:
    from pcfbench.protocol import SampleBuilder, check_compatible, sample_id

    if not dataset or not setting:
        raise PcfbenchError("usage: pcfbench ls samples DATASET[=ROOT] --setting SETTING [--split SPLIT]")
    plugins = get_plugins()
    ((name, root),) = _dataset_roots(plugins, (dataset,), progress=True)
    cls = plugins.datasets.get(name)
    adapter = config.open_adapter(name, cls, root)
    s = get_setting(setting)
    check_compatible(s, adapter)
    split = split or cls.default_split
    policy = policy or cls.default_policy
    if split not in adapter.splits():
        from pcfbench.errors import unknown_name

        raise unknown_name(f"split of dataset {name}", split, adapter.splits())
    builder = SampleBuilder(adapter, s, policy)
    ids = [sample_id(seq, i) for seq, i in builder.sample_keys(split)]
    if not ids:  # why, and the option that fixes it (pcfbench.protocol.nosamples), beside the empty list
        from pcfbench.protocol.nosamples import explain

        settings = [get_setting(n) for n in cls.default_settings]
        click.echo(f"pcfbench: note: {explain(builder, split, settings=settings).message}", err=True)
    if as_json:
        click.echo(json.dumps(ids))
        return
    for i in ids:
        click.echo(i)
    click.echo(f"{len(ids)} samples of {name}:{split} for {setting} ({policy})", err=True)


def _options_of(registry, name: str) -> tuple[list[dict], str | None]:
    """The option fields of registry item ``name`` (a method or adapter class), or the error
    that stopped its class from loading."""
    from pcfbench.options import describe_options

    try:
        cls = registry.get(name)
        fields = describe_options(cls.Options, f"{registry.kind} {name}")
    except PcfbenchError as exc:
        return [], str(exc)
    return [{"name": f.name, "type": f.type, "default": f.default, "help": f.help, "range": f.range} for f in fields], None


@cli.command()
@click.option("--json", "as_json", is_flag=True)
def plugins(as_json):
    """Installed plugins, what each registered, and any load errors."""
    state = get_plugins()
    rows = [
        {"name": i.name, "source": i.source, "registered": i.registered, "error": i.error}
        for i in sorted(state.info.values(), key=lambda i: i.name)
    ]
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    for r in rows:
        click.echo(f"{r['name']} ({r['source']})")
        for kind, names in r["registered"].items():
            click.echo(f"  {kind}: {', '.join(names)}")
        if r["error"]:
            click.echo(f"  ERROR: {r['error']}")


@cli.group()
def datasets():
    """Inspect dataset folders."""


@datasets.command()
@click.argument("root")
@click.option("--layout", default=None, help="Adapter name; default: detect it.")
def check(root, layout):
    """Say which layout ROOT is, what it holds and every problem found.

    ROOT may carry adapter options: PATH?key=value&key=value.
    """
    state = get_plugins()
    path = config.split_root_options(root)[0]
    if not Path(path).exists():
        raise PcfbenchError(f"{path} does not exist")
    if layout is None:
        found = [n for n in state.datasets.names() if state.datasets.get(n).detect(Path(path))]
        if not found:
            raise PcfbenchError(f"{path}: no known layout recognised (known: {', '.join(state.datasets.names())})")
        layout = found[0]
    adapter = config.open_adapter(layout, state.datasets.get(layout), root)
    rep = adapter.check()
    click.echo(f"layout: {rep.layout}  (adapter {layout} v{adapter.version})")
    click.echo(f"root: {rep.root}")
    for k, v in rep.found.items():
        click.echo(f"  {k}: {v}")
    if rep.problems:
        click.echo(f"{len(rep.problems)} problem(s):")
        for p in rep.problems:
            click.echo(f"  - {p}")
        sys.exit(1)
    click.echo("no problems found")


def build_cli() -> click.Group:
    from pcfbench.exchange.commands import add_commands

    add_commands(cli)  # queries, score, challenge (docs/bring-your-own-method.md)
    get_plugins().add_commands(cli)
    return cli


def main() -> None:
    from pcfbench.interrupts import redeliver_swallowed_interrupts

    redeliver_swallowed_interrupts()  # a Ctrl-C that lands in a finalizer still stops the command
    build_cli()(prog_name="pcfbench")
