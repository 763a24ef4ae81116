"""What a trained world model does with the tokens that change (``pcfbench world-report``).

Averages over all tokens flatter a model that only copies: most of a future token map equals
the last past frame's map at the same place (empty space, the ground). This report samples the
world model's forecast (decoded as the method decodes a sample, by its options) on held-out windows
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
    all poses given) with ``method`` (a loaded ``Copilot4D``: its world model, decoded as its
    options say, :meth:`Copilot4D.decode_future`), evenly spaced windows of each stride up to ``max_windows`` per stride. Returns
    ``{"rows": [{stride, step, windows, **counts}], "rings": [{stride, ring, windows, **counts}]}``:
    per future step, and over every future step per ring of distance from the grid's centre (the t=0
    sensor in frame t0, each frame's own sensor in frame own; ``evaluate.token_rings`` of the method's
    tokenizer grid, ``ring`` its index into ``evaluate.ring_labels()``)."""
    import torch

    from pcfbench.methods.copilot4d.evaluate import RING_EDGES, token_rings

    cfg, opts = method.world_cfg, method.options
    P, F = cfg.n_past, cfg.n_future
    dev = next(method.world.parameters()).device
    rings = token_rings(method.tok_cfg, tuple(windows["tokens"].shape[-2:]))
    rows, ring_rows = [], []
    for s in sorted(set(int(v) for v in windows["stride"])):
        idx = np.flatnonzero(windows["stride"] == s)
        world = method.network_for_stride(s)  # with stride_models, the network that forecasts this stride
        if max_windows and len(idx) > max_windows:
            idx = idx[np.unique(np.linspace(0, len(idx) - 1, max_windows).round().astype(int))]
        acc = [dict.fromkeys(COUNTS, 0) for _ in range(F)]
        by_ring = [dict.fromkeys(COUNTS, 0) for _ in range(len(RING_EDGES) + 1)]
        for n, a in enumerate(idx):
            toks = torch.from_numpy(windows["tokens"][a].astype(np.int64))
            poses = torch.from_numpy(windows["poses"][a].astype(np.float32))
            gen = torch.Generator(dev).manual_seed(int(opts.seed) * 1_000_003 + int(a))
            # decoded as the method decodes a sample (one pass or Algorithm 2, by its options)
            pred = torch.stack(method.decode_future(world, toks[None, :P].to(dev), poses[None].to(dev), F, generator=gen,
                                                    name=f"window {a}"), 1)[0].cpu().numpy()
            last = windows["tokens"][a, P - 1]
            for f in range(F):
                for into, where in [(acc[f], slice(None)), *((r, rings == i) for i, r in enumerate(by_ring))]:
                    for k, v in score_tokens(pred[f][where], windows["tokens"][a, P + f][where], last[where]).items():
                        into[k] += v
            log(f"stride {s}: window {n + 1}/{len(idx)}")
        rows += [{"stride": s, "step": f + 1, "windows": len(idx), **acc[f]} for f in range(F)]
        ring_rows += [{"stride": s, "ring": i, "windows": len(idx), **r} for i, r in enumerate(by_ring)]
    return {"rows": rows, "rings": ring_rows}


def write_token_report(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """The report as CSV (counts and shares per stride and future step) and Markdown."""
    from pcfbench.methods.copilot4d.evaluate import ring_labels
    from pcfbench.reporting.escape import md_text

    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, md = out_dir / f"{stem}.csv", out_dir / f"{stem}.md"
    names = list(shares(dict.fromkeys(COUNTS, 0)))
    labels = ring_labels()
    ring_rows = result.get("rings", [])
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["stride", "step", "ring", "windows", *COUNTS, *names])
        for r in [*result["rows"], *ring_rows]:
            w.writerow([r["stride"], r.get("step", "all"), labels[r["ring"]] if "ring" in r else "all", r["windows"],
                        *(r[k] for k in COUNTS), *(f"{v:.6g}" for v in shares(r).values())])
    lines = [f"# Copilot4D world model: its forecast tokens, changed and unchanged ({md_text(meta['method'])})", "",
             "The method's forecast of each held-out window's future frames from its past frames and every pose "
             "(decoded as its options say: Algorithm 2 a frame at a time, or every frame in one pass), "
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
    if ring_rows:
        lines += ["", "Every future step, by the token's distance from the grid's centre (the t=0 sensor in frame t0; "
                  "in frame own, each frame's own sensor):", "",
                  "| stride | distance | windows | changed share | accuracy | changed accuracy | unchanged accuracy "
                  "| moved share | moved precision |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
        lines += [f"| {r['stride']} | {labels[r['ring']]} | {r['windows']} | "
                  + " | ".join(f"{100 * shares(r)[n]:.1f} %" for n in names) + " |" for r in ring_rows]
    md.write_text("\n".join(lines) + "\n")
    return md, csv_path


# --------------------------------------------------------------------------- the objective held out
#: the objectives :func:`objective_report` scores: Algorithm 1's mixture as trained, and its
#: "future" objective alone (past frames clean, every future frame masked at its own rate)
OBJECTIVE_MODES = ("mixture", "future")


def objective_report(model, sets: dict[str, dict[str, np.ndarray]], *, n_past: int, variant,
                     label_smoothing: float, draws: int, max_windows: int | None = None, batch: int = 4,
                     seed: int = 0, log=print) -> dict:
    """The training objective (:func:`~.diffusion.objective_sums`) of ``model`` on each set of
    windows in ``sets`` (name -> ``build_windows`` output, e.g. the training split's and a
    held-out one's): ``draws`` corruptions of each of up to ``max_windows`` evenly spaced
    windows, under each of :data:`OBJECTIVE_MODES`. Every set draws the same random sequence
    (one generator seeded by ``seed`` per set and mode), so a gap between two sets is the
    windows', not the draws'. Returns ``{"rows": [{set, objective, windows, draws, **sums}]}``."""
    import torch

    from pcfbench.methods.copilot4d.diffusion import OBJECTIVE_SUMS, objective_sums
    from pcfbench.training import autocast

    if draws < 1:
        raise ValueError(f"draws={draws}: expected at least one corruption per window")
    dev = next(model.parameters()).device
    was_training = model.training
    model.eval()
    rows = []
    try:
        for name, windows in sets.items():
            idx = np.arange(len(windows["tokens"]))
            if max_windows and len(idx) > max_windows:
                idx = idx[np.unique(np.linspace(0, len(idx) - 1, max_windows).round().astype(int))]
            for mode in OBJECTIVE_MODES:
                gen = torch.Generator(dev).manual_seed(seed)
                tot = dict.fromkeys(OBJECTIVE_SUMS, 0)
                order = np.tile(idx, draws)
                for b in range(0, len(order), batch):
                    pick = order[b: b + batch]
                    x0 = torch.from_numpy(windows["tokens"][pick].astype(np.int64)).to(dev)
                    poses = torch.from_numpy(windows["poses"][pick].astype(np.float32)).to(dev)
                    objective = None if mode == "mixture" else torch.zeros(len(pick), dtype=torch.long)
                    with autocast(dev):
                        sums = objective_sums(model, x0, poses, n_past, variant, label_smoothing, gen, objective)
                    for k, v in sums.items():
                        tot[k] += v
                    log(f"{name}, {mode}: {min(b + batch, len(order))}/{len(order)}")
                rows.append({"set": name, "objective": mode, "windows": len(idx), "draws": draws, **tot})
    finally:
        model.train(was_training)
    return {"rows": rows}


def objective_shares(r: dict) -> dict[str, float]:
    """The ratios of one :func:`objective_report` row (NaN where a denominator is 0)."""
    from pcfbench.methods.copilot4d.diffusion import objective_ratios

    ratios = objective_ratios(r)
    div = lambda a, b: a / b if b else float("nan")  # noqa: E731
    return {**{k: ratios[k] for k in CURVE_COLUMNS},
            **{f"{p}changed_accuracy_r{i}": div(r[f"{p}changed_hits_r{i}"], r[f"{p}changed_r{i}"])
               for p in ("", "first_") for i in range(len(mask_rate_labels()))}}


#: the objective's ratios the training curve logs too (:func:`curve_tail` averages them)
CURVE_COLUMNS = ("changed_share", "changed_loss", "changed_accuracy", "unchanged_loss", "unchanged_accuracy",
                 "masked_accuracy")


def mask_rate_labels() -> list[str]:
    """The bins of a frame's masked share (``MASK_RATE_EDGES``), as the report heads them."""
    from pcfbench.methods.copilot4d.diffusion import MASK_RATE_EDGES

    edges = [0.0, *MASK_RATE_EDGES, 1.0]
    return [f"{100 * a:g}-{100 * b:g} %" for a, b in zip(edges[:-1], edges[1:])]


def curve_tail(curve_csv: Path, last: int = 100, first_step: int = 0) -> dict[str, float] | None:
    """Means of the objective's columns over a training curve's last ``last`` steps (None
    without a curve): the model on the windows it learned from, as it learned. ``first_step``:
    the steps its weights had when this curve began (a training that went on from another's),
    added to the steps the result names."""
    if not curve_csv.is_file():
        return None
    with open(curve_csv, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return None
    end = int(rows[-1]["step"])
    tail = [r for r in rows if int(r["step"]) > end - last]
    out = {}
    for k in CURVE_COLUMNS:
        vals = [float(r[k]) for r in tail if r.get(k) not in (None, "", "nan")]
        out[k] = float(np.mean(vals)) if vals else float("nan")
    out["steps"] = f"{first_step + max(end - last, 0) + 1}-{first_step + end}"
    return out


def write_objective_report(result: dict, meta: dict, out_dir: Path, stem: str,
                           curve: dict | None = None) -> tuple[Path, Path]:
    """:func:`objective_report` as CSV (sums and ratios per set and objective) and Markdown,
    with the training curve's tail (``curve``, from :func:`curve_tail`) as the first row."""
    from pcfbench.methods.copilot4d.diffusion import OBJECTIVE_SUMS
    from pcfbench.reporting.escape import md_text

    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, md = out_dir / f"{stem}.csv", out_dir / f"{stem}.md"
    names = list(objective_shares(dict.fromkeys(OBJECTIVE_SUMS, 0)))
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["set", "objective", "windows", "draws", *OBJECTIVE_SUMS, *names])
        for r in result["rows"]:
            w.writerow([r["set"], r["objective"], r["windows"], r["draws"], *(r[k] for k in OBJECTIVE_SUMS),
                        *(f"{v:.6g}" for v in objective_shares(r).values())])

    def cells(sh):
        return (f"{100 * sh['changed_share']:.1f} % | {sh['changed_loss']:.2f} | {100 * sh['changed_accuracy']:.1f} % | "
                f"{sh['unchanged_loss']:.2f} | {100 * sh['unchanged_accuracy']:.1f} % | "
                f"{100 * sh['masked_accuracy']:.1f} %")

    lines = [f"# Copilot4D world model: its training objective on the windows it learned from and on held-out "
             f"ones ({md_text(meta['method'])})", "",
             "Algorithm 1's loss (cross entropy with label smoothing) and arg-max accuracy on the masked future "
             "tokens, apart on those that *changed* since the last past frame and those that did not, with the "
             "trained weights in evaluation mode; every set of windows draws the same corruptions. *mixture*: the "
             "objectives as trained; *future*: past frames clean, each future frame masked at its own rate. "
             "A held-out loss well above the training windows' says the model learned its windows rather than "
             "the world; the two alike, with the curve still falling, say it has not learned enough yet.", "",
             *(f"- {k}: {md_text(v)}" for k, v in meta.items()), "",
             "| windows | objective | windows (draws) | changed share | changed loss | changed accuracy | "
             "unchanged loss | unchanged accuracy | masked accuracy |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    if curve is not None:
        lines.append(f"| training curve, steps {curve['steps']} | mixture | | {cells(curve)} |")
    for r in result["rows"]:
        lines.append(f"| {md_text(r['set'])} | {r['objective']} | {r['windows']} ({r['draws']}) | "
                     f"{cells(objective_shares(r))} |")
    labels = mask_rate_labels()
    lines += ["", "Changed accuracy by the masked share of the token's frame (changed tokens scored), on every "
              "future frame and on the first alone: Algorithm 2 decides a frame's first tokens with all of it "
              "masked, and the first future frame's context is the past alone (a later one's, in training, holds "
              "the true tokens of the future frames before it; in a forecast, the model's own).", "",
              "| windows | objective | future frames | " + " | ".join(labels) + " |",
              "|---|---|---|" + "---:|" * len(labels)]
    for r in result["rows"]:
        sh = objective_shares(r)
        for p, which in (("", "all"), ("first_", "first")):
            lines.append(f"| {md_text(r['set'])} | {r['objective']} | {which} | "
                         + " | ".join(f"{100 * sh[f'{p}changed_accuracy_r{i}']:.1f} % ({r[f'{p}changed_r{i}']})"
                                      for i in range(len(labels))) + " |")
    md.write_text("\n".join(lines) + "\n")
    return md, csv_path
