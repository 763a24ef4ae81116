"""The world model's ceiling (issue 42): a perfect prediction of its training target for the
ground-truth future, rendered exactly as ``copilot4d`` renders, scored by the harness beside
``copilot4d-token-copy`` of the same tokenizer and copy-last on the same samples. If the
ceiling does not beat copying, no training will. ``pcfbench tokenizer-report --ceiling``.

Above :mod:`.evaluate`, :mod:`.token_copy` and :mod:`.forecaster`, whose pieces it puts
together; it calls the tokenizer's functions through :mod:`.evaluate` (tests replace them)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from pcfbench.methods.copilot4d import evaluate as ev
from pcfbench.methods.copilot4d.model import Tokenizer
from pcfbench.methods.copilot4d.forecaster import sample_seed
from pcfbench.methods.copilot4d.token_copy import TokenCopy, TokenCopyOptions


def evaluate_ceiling(model: Tokenizer, adapter, split: str, setting: str, *, frame: str = "t0",
                     threshold: float = 0.02, noise: bool = False, readout: str = "median",
                     max_samples: int | None = None, log=print) -> dict:
    """The ceiling of a world model on this tokenizer: a perfect prediction of its training
    target, rendered exactly as ``copilot4d`` renders, scored beside ``copilot4d-token-copy``
    (this very tokenizer) and copy-last on the same samples by every registered metric, as the
    runner scores them (``score_sample``). It sees the future: a bound, never a method.

    The target of each future sweep k of the protocol's samples (``setting`` on ``split``):
    ``frame="t0"``: its points (ego returns removed) moved into the t=0 sensor frame and
    tokenized there, rendered from the future sensor's origin in that frame; ``frame="own"``:
    tokenized in its own sensor frame and rendered from its own origin (relative poses tell
    the model where that is). Rendering: :func:`.evaluate.render_queries` with ``threshold``, ``noise``
    and ``readout`` (the options of ``copilot4d``), spatial skipping seeded as ``copilot4d``
    seeds it. Also per future sweep, the share of target tokens that differ from the last past
    sweep's (token-copy's tokens): what a world model has to change.

    Returns per-entry flat means over (sample, future sweep), ``changed`` (mean share, per step
    and per ring of distance from the sensor at the grid's centre, :func:`.evaluate.changed_by_ring`) and the
    per-sample rows (``rows``) for paired comparisons."""
    from pcfbench.data import Forecast
    from pcfbench.methods.copy_last import CopyLast

    if frame not in ev.CEILING_FRAMES:
        from pcfbench.errors import PcfbenchError

        raise PcfbenchError(f"ceiling frame {frame!r}: expected one of {', '.join(ev.CEILING_FRAMES)}")
    model.eval()
    render = {"threshold": threshold, "noise": noise, "readout": readout}
    token_copy = TokenCopy(TokenCopyOptions(**render))
    token_copy.model = model
    copy_last = CopyLast()
    changed: list[list[float]] = []
    ring_changed = ring_tokens = 0

    def ceiling(sample, builder, seq_name: str, ref: int):
        nonlocal ring_changed, ring_tokens
        last = ev.tokenize_sweep(model, builder.points_sensor(builder.sequence(seq_name), ref))
        codes, frames = future_targets(model, sample, builder, seq_name, ref, frame)
        changed.append([ev.changed_share(c, last) for c in codes])
        for c in codes:
            ch, n = ev.changed_by_ring(model.cfg, c, last)
            ring_changed, ring_tokens = ring_changed + ch, ring_tokens + n
        gen = torch.Generator().manual_seed(sample_seed(sample.sample_id, 0) ^ 1)
        return Forecast.from_depths(sample, ev.render_queries(model, codes, sample, frames, generator=gen, **render))

    res = score_beside(adapter, split, setting, {
        "ceiling": ceiling,
        "copilot4d-token-copy": lambda sample, *_: token_copy.forecast(sample.for_method()),
        "copy-last": lambda sample, *_: copy_last.forecast(sample.for_method())},
        max_samples=max_samples, log=log, label=f"ceiling ({frame})")
    ch = np.asarray(changed, np.float64)
    return {"setting": setting, "split": split, "dataset": adapter.name, "frame": frame, "samples": res["samples"],
            "of_samples": res["of_samples"],
            "sweeps": len(res["rows"]["ceiling"]), **render, "eval_s": res["eval_s"], "means": res["means"],
            "changed": {"mean": float(ch.mean()), "per_step": [float(v) for v in ch.mean(axis=0)],
                        "by_ring": dict(zip(ev.ring_labels(), (float(v) for v in ring_changed / ring_tokens)))},
            "rows": res["rows"]}


def future_targets(model: Tokenizer, sample, builder, seq_name: str, ref: int, frame: str):
    """The world model's training target for the ground-truth future of ``sample`` (built by
    ``builder`` from sweep ``ref`` of ``seq_name``): one token map per future sweep k, its points
    (ego returns removed) moved into the t=0 sensor frame and tokenized there (``frame="t0"``) or
    tokenized in their own sensor frame (``"own"``), and per map the frame it is rendered from
    (``T_g_ref``: the t=0 sensor's, or the future sensor's own)."""
    seq = builder.sequence(seq_name)
    stride = builder.setting.stride
    T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
    codes, frames = [], []
    for k in range(sample.num_future):
        pts = builder.points_sensor(seq, ref + (k + 1) * stride)
        if frame == "t0":
            T_s0_sk = T_s0_ref @ sample.future_T_ref_sensor[k]
            pts = (pts.astype(np.float64) @ T_s0_sk[:3, :3].T + T_s0_sk[:3, 3]).astype(np.float32)
            frames.append(T_s0_ref)
        else:
            frames.append(np.linalg.inv(sample.future_T_ref_sensor[k]))
        codes.append(ev.tokenize_sweep(model, pts))
    return codes, frames


def score_beside(adapter, split: str, setting: str, forecasters: dict, *, max_samples: int | None = None,
                 log=print, label: str = "ceiling") -> dict:
    """Score every entry of ``forecasters`` (name -> ``fn(sample, builder, seq_name, ref)``
    returning a ``Forecast``; ``sample`` is the full one, a bound may read the future through
    ``builder``) on the protocol's samples of ``setting`` on ``split`` (``max_samples`` evenly
    spaced ones; None: all), by every registered metric as the runner scores them
    (``score_sample``), in one loop. Returns ``samples`` (of ``of_samples`` in the split), per-entry
    flat means over (sample, future sweep) (``means``), the per-sample rows (``rows``) and ``eval_s``."""
    from pcfbench.metrics.base import score_sample
    from pcfbench.plugins import get_plugins, get_setting
    from pcfbench.protocol import SampleBuilder
    from pcfbench.protocol.validate import validate_forecast
    from pcfbench.running.runner import default_metrics

    plugins = get_plugins()
    metrics = [plugins.metrics.get(n) for n in default_metrics(plugins)]
    builder = SampleBuilder(adapter, get_setting(setting, plugins))
    keys = builder.sample_keys(split)
    if not keys:
        from pcfbench.errors import PcfbenchError
        from pcfbench.protocol.nosamples import Options, explain

        settings = [get_setting(name, plugins) for name in type(adapter).default_settings]
        why = explain(builder, split, settings=settings, options=Options(setting="--ceiling {}", policy=None))
        raise PcfbenchError(f"the ceiling: {why.message}")
    of_samples = len(keys)
    if max_samples:
        keys = [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, min(max_samples, len(keys))).round().astype(int))]
    rows: dict[str, list[dict]] = {name: [] for name in forecasters}
    t0 = time.monotonic()
    for n, (seq_name, ref) in enumerate(keys):
        sample, truth = builder.build(seq_name, ref)
        for name, fn in forecasters.items():
            fc = fn(sample, builder, seq_name, ref)
            for r in score_sample(sample, truth, validate_forecast(sample, fc), metrics):
                rows[name].append({"sample_id": sample.sample_id, **r})
        if (n + 1) % 5 == 0:
            log(f"{label}: {n + 1}/{len(keys)} samples, {time.monotonic() - t0:.0f} s")

    def mean(values: list[float]) -> float:  # flat over the sweeps that could be scored
        v = np.asarray(values, dtype=np.float64)
        return float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else float("nan")

    means = {name: {m.name: mean([r[m.name] for r in rs]) for m in metrics} for name, rs in rows.items()}
    return {"samples": len(keys), "of_samples": of_samples, "means": means, "rows": rows, "eval_s": time.monotonic() - t0}


def write_beside(result: dict, meta: dict, out_dir: Path, stem: str, *, copy: str, target: str, head: list[str],
                 issue: int, columns: tuple[str, ...] = ()) -> tuple[Path, Path]:
    """A ceiling scored by :func:`score_beside` as Markdown and CSV, for every world model: the
    ceiling's means (``target`` labels it), the copy baseline ``copy``'s and copy-last's from the
    same loop, the ceiling's ratios to both and whether it beats ``copy`` on the bar's three
    columns (issue ``issue``). ``head``: the Markdown lines before the table (title, what the
    target is, the samples); ``columns``: extra ``result`` keys written on every CSV row. A ceiling
    of some of the split's samples (``samples`` < ``of_samples``) is written beside the whole
    split's, never over it: ``<stem>-<samples>-samples``."""
    import csv

    if result["samples"] < result.get("of_samples", result["samples"]):
        stem = f"{stem}-{result['samples']}-samples"
    out_dir.mkdir(parents=True, exist_ok=True)
    m = result["means"]
    o, cp, c = m["ceiling"], m[copy], m["copy-last"]
    names = [n for n in o if all(np.isfinite(v[n]) for v in (o, cp, c))]
    ratio = lambda a, b: (a / b) if b else float("nan")  # noqa: E731
    table = [(f"ceiling: {target} for the ground-truth future (sees the future)", o), (copy, cp), ("copy-last", c),
             (f"ratio ceiling / {copy}", {n: ratio(o[n], cp[n]) for n in names}),
             ("ratio ceiling / copy-last", {n: ratio(o[n], c[n]) for n in names})]
    keys = ("dataset", "split", "setting", "frame", *columns, "samples", "sweeps")
    csv_path = out_dir / f"{stem}.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["entry", *keys, *names])
        for entry, vals in table:
            w.writerow([entry, *(result[k] for k in keys), *(f"{vals[n]:.6g}" for n in names)])
    beats = {n: o[n] < cp[n] for n in ("chamfer_nf", "l1_mean", "l1_median") if n in names}
    lines = [
        *head,
        "| entry | " + " | ".join(names) + " |",
        "|---|" + "---:|" * len(names),
        *("| " + entry.split(":")[0] + " | " + " | ".join(f"{vals[n]:.3f}" if "ratio" not in entry else f"{vals[n]:.2f}"
                                                          for n in names) + " |" for entry, vals in table),
        "",
        f"Bar (issue {issue}: the ceiling beats {copy} on chamfer_nf, l1_mean and l1_median): "
        + ", ".join(f"{n} {'met' if ok else 'NOT met'}" for n, ok in beats.items()) + ".",
        "",
        *(f"- {k}: {v}" for k, v in meta.items()),
    ]
    md = out_dir / f"{stem}.md"
    md.write_text("\n".join(lines) + "\n")
    return md, csv_path


def write_ceiling(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """The ceiling as Markdown and CSV: its metric means, token-copy's and copy-last's from the
    same loop, and the ceiling's ratios to both, labelled as a bound that sees the future."""
    frame = {"t0": "moved into the t=0 sensor frame and tokenized there, rendered from the future sensor's "
                   "origin in that frame",
             "own": "tokenized in its own sensor frame, rendered from its own origin"}[result["frame"]]
    ch = result["changed"]
    head = [
        f"# Copilot4D: the world model's ceiling ({meta.get('config')} tokenizer, {result['dataset']} "
        f"{result['split']}, {result['setting']}, frame {result['frame']})",
        "",
        "**A bound, not a method: it sees the future.** Each ground-truth future sweep is " + frame + " (the world "
        "model's training target, perfectly predicted), rendered as `copilot4d` renders (spatial skipping at "
        f"threshold {result['threshold']}, Logistic noise {'on' if result['noise'] else 'off'}, {result['readout']} "
        "depth). `copilot4d-token-copy` (the same tokenizer) and copy-last are scored in the same loop on the same "
        "samples by the same registered metrics; means are flat over (sample, future sweep).",
        "",
        f"{result['samples']} samples, {result['sweeps']} future sweeps; evaluation took {result['eval_s']:.0f} s. "
        f"Target tokens that differ from the last past sweep's: {ch['mean']:.1%} on average "
        f"({', '.join(f'{v:.0%}' for v in ch['per_step'])} by future step; by distance from the sensor at the grid's "
        f"centre: {', '.join(f'{k} {v:.0%}' for k, v in ch['by_ring'].items())}).",
        "",
    ]
    return write_beside(result, meta, out_dir, stem, copy="copilot4d-token-copy",
                        target="the world model's target", head=head, issue=42)
