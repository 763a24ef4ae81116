"""``pcfbench queries``, ``pcfbench score`` and ``pcfbench challenge queries|export``."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import click

from pcfbench.errors import PcfbenchError

_DATASET = click.option("--dataset", "-d", "dataset", required=True, metavar="NAME[=ROOT]",
                        help="The dataset (ROOT may carry ?key=value options), as `pcfbench run` takes it.")
_SETTING = click.option("--setting", "-s", "setting", required=True, help="The setting, e.g. kitti-1s.")
_SPLIT = click.option("--split", default=None, help="The split (default: the dataset's evaluation split).")
_POLICY = click.option("--policy", default=None, help="The sample policy (default: the dataset's).")
_QUIET = click.option("--quiet", "-q", is_flag=True, help="No progress bars.")


def _questions(dataset: str, setting: str, split: str | None, policy: str | None, quiet: bool):
    from pcfbench import config
    from pcfbench.exchange.questions import open_questions
    from pcfbench.plugins import get_plugins

    plugins = get_plugins()
    (name,), roots = config.parse_dataset_args((dataset,))
    cls = plugins.datasets.get(name)
    root = config.resolve_root(name, cls, roots, progress=not quiet)
    return open_questions(name, root, split or cls.default_split, setting, policy or cls.default_policy, plugins)


def _bar(total: int, desc: str, quiet: bool):
    from tqdm import tqdm

    from pcfbench.running.runner import _progress_disabled

    return tqdm(total=total, desc=desc, unit="sample", disable=True if quiet else _progress_disabled(), leave=False)


@click.command("queries")
@_DATASET
@_SETTING
@_SPLIT
@_POLICY
@click.option("--out", "-o", type=click.Path(dir_okay=False), required=True, help="The query file to write (.npz).")
@_QUIET
def queries(dataset, setting, split, policy, out, quiet):
    """Write every sample a method must answer (past sweeps and poses, future poses, query
    rays; never the ground truth) to a query file: docs/bring-your-own-method.md."""
    from pcfbench.exchange.queries import write_queries

    q = _questions(dataset, setting, split, policy, quiet)
    with _bar(len(q.keys), f"queries {q.dataset}:{q.split} {q.setting}", quiet) as bar:
        write_queries(q, Path(out), bar.update)
    click.echo(f"{len(q.keys)} samples of {q.dataset}:{q.split} {q.setting} ({q.policy}) -> {out}")


@click.command("score")
@click.argument("submission", type=click.Path(dir_okay=False))
@click.option("--name", required=True, help="The submission's name: its leaderboard label.")
@_DATASET
@_SETTING
@_SPLIT
@_POLICY
@click.option("--partial", is_flag=True,
              help="Score a submission that misses samples: its cell is marked partial and never ranked.")
@click.option("--metric", "metrics", multiple=True, help="Metric (repeatable); default: every registered metric.")
@click.option("--store", type=click.Path(file_okay=False), default=None, help="Results store (default: <reports>/store).")
@click.option("--reports", type=click.Path(file_okay=False), default=None, help="Reports folder (default: ./reports).")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=1, show_default=True, help="Worker processes.")
@_QUIET
def score(submission, name, dataset, setting, split, policy, partial, metrics, store, reports, jobs, quiet):
    """Score a forecast file made elsewhere (.npz, or the AV2 challenge's .json) into the
    store as its own cell, after checking it whole: docs/bring-your-own-method.md."""
    from pcfbench import config

    q = _questions(dataset, setting, split, policy, quiet)
    result, checked = score_submission(Path(submission), name, q, config.store_dir(store, config.reports_dir(reports)),
                                       metrics, partial, jobs, not quiet)
    what = f"{checked.answered} of {checked.answered + len(checked.missing)} samples" if checked.missing else \
        f"{checked.answered} samples"
    click.echo(f"submission {name}: {what} scored -> {result.path}" + (" (PARTIAL: never ranked)" if checked.missing else ""))
    if result.failed > len(checked.missing):
        click.echo(f"pcfbench: {result.failed - len(checked.missing)} sample(s) failed; see `pcfbench failures`", err=True)
        sys.exit(1)


def score_submission(path: Path, name: str, q: Any, store: Path, metrics=(), partial: bool = False, jobs: int = 1,
                     progress: bool = False):
    """Check the submission at ``path`` against the questions ``q`` whole, then score it as a
    cell of the ``submission`` method (its name, file and sha256 in the options) into ``store``.
    A partial submission's cell is marked partial. Returns (CellResult, Checked)."""
    from pcfbench.exchange.check import check_submission, open_submission
    from pcfbench.exchange.submission import file_sha256
    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.running.runner import RunOptions, default_metrics, run_cell
    from pcfbench.store.cells import Cell, CellSpec

    plugins = get_plugins()
    if not name or any(c in name for c in ",=") or name != name.strip():
        raise PcfbenchError(f"--name {name!r}: a submission's name is non-empty, without commas, '=' or edge spaces")
    path = path.resolve()
    sha = file_sha256(path)
    sub = open_submission(path)
    with _bar(len(q.keys), f"checking {path.name}", not progress) as bar:
        checked = check_submission(sub, q, partial, bar.update)
    if file_sha256(path) != sha:
        raise PcfbenchError(f"submission {path} changed while it was checked: score it again")
    method = resolve_method(("submission", {"name": name, "path": str(path), "sha256": sha}), plugins)
    metric_names = tuple(metrics) or default_metrics(plugins)
    spec = CellSpec(method.name, dict(method.raw), method.options_hash, q.dataset, q.dataset_root, q.split, q.setting,
                    q.policy, None, metric_names)
    result = run_cell(spec, store, RunOptions(jobs=jobs, progress=progress), plugins=plugins)
    with Cell(store, spec, wait=True) as cell:  # what the file was, and a partial one marked so
        meta = cell.read_meta() or {}
        meta["submission"] = {"name": name, "file": str(path), "sha256": sha, "layout": sub.layout,
                              "answered": checked.answered, "missing": len(checked.missing)}
        if checked.missing:
            meta["partial"] = True
        cell.write_meta(meta)
    return result, checked


@click.group("challenge")
def challenge():
    """The Argoverse 2 4D occupancy forecasting challenge's JSON files (docs/bring-your-own-method.md)."""


@challenge.command("queries")
@_DATASET
@_SETTING
@_SPLIT
@_POLICY
@click.option("--out", "-o", type=click.Path(dir_okay=False), required=True, help="The query-ray JSON to write.")
@_QUIET
def challenge_queries(dataset, setting, split, policy, out, quiet):
    """Write the challenge's query-ray JSON (origin and unit direction per ray) of a split."""
    from pcfbench.exchange.challenge import write_challenge_queries

    q = _questions(dataset, setting, split, policy, quiet)
    with _bar(len(q.keys), "challenge queries", quiet) as bar:
        n = write_challenge_queries(q, Path(out), bar.update)
    click.echo(f"{n['samples']} samples, {n['rays']} rays of {q.dataset}:{q.split} {q.setting} -> {out}")


@challenge.command("export")
@click.option("--method", "-m", "method_spec", required=True, metavar="NAME[:key=value,...]", help="The method to run.")
@_DATASET
@_SETTING
@_SPLIT
@_POLICY
@click.option("--out", "-o", type=click.Path(dir_okay=False), required=True, help="The submission JSON to write.")
@_QUIET
def challenge_export(method_spec, dataset, setting, split, policy, out, quiet):
    """Run a method (no trained ones) and write its forecasts as a challenge submission: a
    depth per query ray (a points forecast's depth: its point nearest the ray in angle)."""
    from pcfbench.exchange.challenge import export_challenge
    from pcfbench.method import resolve_method
    from pcfbench.training import is_trained

    method = resolve_method(method_spec)
    if is_trained(method.cls):
        raise PcfbenchError(f"method {method.name} is a trained method: export its checkpoint's forecasts with a "
                            "query file (`pcfbench queries`) instead")
    q = _questions(dataset, setting, split, policy, quiet)
    with _bar(len(q.keys), f"{method.name} -> challenge", quiet) as bar:
        n = export_challenge(q, method.create(), Path(out), bar.update)
    click.echo(f"{method.name}: {n['samples']} samples, {n['rays']} depths -> {out}")


def add_commands(cli: click.Group) -> None:
    for command in (queries, score, challenge):
        cli.add_command(command)
