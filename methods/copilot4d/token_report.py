"""What a trained world model does with the tokens that change (``pcfbench world-report``).

Averages over all tokens flatter a model that only copies: most of a future token map equals
the last past frame's map at the same place (empty space, the ground). This report samples the
world model's forecast (Algorithm 2, the method's own sampler and options) on held-out windows
of the frame it was trained in, and scores it against the tokenizer's tokens of the real future
apart on the tokens that **changed** since the last past frame and on those that did not, per
future step. Copying the last past frame scores 0 on the changed and 1 on the unchanged ones by
definition; a model that learned the world's motion scores above 0 on the changed ones. It also
says how many of its own predictions differ from the last past frame ("moved") and how many
of those are right.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

#: the counts summed per (stride, future step); every share below is a ratio of two of them
COUNTS = ("tokens", "changed", "changed_hit", "unchanged_hit", "moved", "moved_hit")


def score_tokens(pred: np.ndarray, truth: np.ndarray, last: np.ndarray) -> dict[str, int]:
    """Counts for one forecast frame: ``pred``, ``truth`` and ``last`` (the last past frame's
    tokens) are integer maps of one shape."""
    if not pred.shape == truth.shape == last.shape:
        raise ValueError(f"token maps of shapes {pred.shape}, {truth.shape}, {last.shape}; expected one shape")
    changed = truth != last
    hit = pred == truth
    moved = pred != last
    return {"tokens": int(truth.size), "changed": int(changed.sum()), "changed_hit": int((hit & changed).sum()),
            "unchanged_hit": int((hit & ~changed).sum()), "moved": int(moved.sum()),
            "moved_hit": int((hit & moved).sum())}


def shares(c: dict[str, int]) -> dict[str, float]:
    """The report's ratios of one set of counts (NaN where a denominator is 0)."""
    div = lambda a, b: a / b if b else float("nan")  # noqa: E731
    return {"changed_share": div(c["changed"], c["tokens"]),
            "accuracy": div(c["changed_hit"] + c["unchanged_hit"], c["tokens"]),
            "changed_accuracy": div(c["changed_hit"], c["changed"]),
            "unchanged_accuracy": div(c["unchanged_hit"], c["tokens"] - c["changed"]),
            "moved_share": div(c["moved"], c["tokens"]),
            "moved_precision": div(c["moved_hit"], c["moved"])}


def world_token_report(method, windows: dict[str, np.ndarray], *, max_windows: int | None = None,
                       log=print) -> dict:
    """Forecast the future frames of each window (``build_windows`` output: its past frames and
    all poses given) with ``method`` (a loaded ``Copilot4D``: its world model, sampler options,
    variant), evenly spaced windows of each stride up to ``max_windows`` per stride. Returns
    ``{"rows": [{stride, step, windows, **counts}], "options": ...}``."""
    import torch

    from pcfbench.methods.copilot4d.diffusion import forecast_tokens
    from pcfbench.training import autocast

    cfg, opts = method.world_cfg, method.options
    P, F = cfg.n_past, cfg.n_future
    dev = next(method.world.parameters()).device
    rows = []
    for s in sorted(set(int(v) for v in windows["stride"])):
        idx = np.flatnonzero(windows["stride"] == s)
        if max_windows and len(idx) > max_windows:
            idx = idx[np.unique(np.linspace(0, len(idx) - 1, max_windows).round().astype(int))]
        acc = [dict.fromkeys(COUNTS, 0) for _ in range(F)]
        for n, a in enumerate(idx):
            toks = torch.from_numpy(windows["tokens"][a].astype(np.int64))
            poses = torch.from_numpy(windows["poses"][a].astype(np.float32))
            gen = torch.Generator(dev).manual_seed(int(opts.seed) * 1_000_003 + int(a))
            with autocast(dev):
                pred = forecast_tokens(method.world, toks[None, :P].to(dev), poses[None].to(dev), F,
                                       steps=opts.sampling_steps, guidance=opts.cfg_weight, top_k=opts.top_k,
                                       revise=method.variant.revise, generator=gen)[0].cpu().numpy()
            last = windows["tokens"][a, P - 1]
            for f in range(F):
                for k, v in score_tokens(pred[f], windows["tokens"][a, P + f], last).items():
                    acc[f][k] += v
            log(f"stride {s}: window {n + 1}/{len(idx)}")
        rows += [{"stride": s, "step": f + 1, "windows": len(idx), **acc[f]} for f in range(F)]
    return {"rows": rows}


def write_token_report(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """The report as CSV (counts and shares per stride and future step) and Markdown."""
    from pcfbench.reporting.escape import md_text

    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, md = out_dir / f"{stem}.csv", out_dir / f"{stem}.md"
    names = list(shares(dict.fromkeys(COUNTS, 0)))
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["stride", "step", "windows", *COUNTS, *names])
        for r in result["rows"]:
            w.writerow([r["stride"], r["step"], r["windows"], *(r[k] for k in COUNTS),
                        *(f"{v:.6g}" for v in shares(r).values())])
    lines = [f"# Copilot4D world model: its forecast tokens, changed and unchanged ({md_text(meta['method'])})", "",
             "Algorithm 2's forecast of each held-out window's future frames from its past frames and every pose, "
             "against the tokenizer's tokens of the real future. *Changed*: the real token differs from the last "
             "past frame's at its place (copying that frame scores 0 % on them and 100 % on the others). "
             "*Moved*: the forecast token differs from the last past frame's; *precision*: the share of those "
             "that are right.", "",
             *(f"- {k}: {md_text(v)}" for k, v in meta.items()), "",
             "| stride | future step | windows | changed share | accuracy | changed accuracy | unchanged accuracy "
             "| moved share | moved precision |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    by_stride: dict[int, dict[str, int]] = {}
    for r in result["rows"]:
        sh = shares(r)
        lines.append(f"| {r['stride']} | {r['step']} | {r['windows']} | "
                     + " | ".join(f"{100 * sh[n]:.1f} %" for n in names) + " |")
        tot = by_stride.setdefault(r["stride"], dict.fromkeys(COUNTS, 0))
        for k in COUNTS:
            tot[k] += r[k]
    for s, tot in by_stride.items():
        sh = shares(tot)
        lines.append(f"| {s} | all | | " + " | ".join(f"**{100 * sh[n]:.1f} %**" for n in names) + " |")
    md.write_text("\n".join(lines) + "\n")
    return md, csv_path
