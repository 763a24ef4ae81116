"""What a world model's changes are worth (``pcfbench world-changes``; issue 42).

In the t=0 frame the last past token map is a forecast already (``copilot4d-token-copy``): a
world model beats it only through the tokens it changes. This scores, by the harness's
metrics on the protocol's samples, the world model's forecast beside bounds that take the
t=0 map and change some of its tokens to the real future's (the training target, as the
ceiling builds it):

- *its right changes only*: the target where the forecast changed a token and got it right,
  the t=0 map everywhere else: all the world model's changes could add without its errors;
- *right on a share p of the changes*: the target on a random share p of the tokens the real
  future changes (seeded per sample), the t=0 map everywhere else: what a forecast right on
  that share, and wrong nowhere, would score; p = 1 is the ceiling;

and ``copilot4d-token-copy`` and copy-last in the same loop, every entry rendered as
``copilot4d`` renders (the forecast's entry is the method's forecast, token for token). It
also counts the forecast's tokens against the target (``token_report.score_tokens``) per
future step. It sees the future: a measurement, never a method.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import torch

from pcfbench.errors import PcfbenchError
from pcfbench.methods.copilot4d import evaluate as ev
from pcfbench.methods.copilot4d.ceiling import future_targets, score_beside
from pcfbench.methods.copilot4d.evaluate import RING_EDGES, ring_labels, token_rings
from pcfbench.methods.copilot4d.forecaster import sample_seed, transform
from pcfbench.methods.copilot4d.token_copy import TokenCopy, TokenCopyOptions
from pcfbench.methods.copilot4d.token_report import COUNTS, score_tokens, shares

#: the shares of the real changes the bound entries get right, by default
CHANGE_SHARES = (0.1, 0.25, 0.5)
#: the columns the report compares (issue 42's bar)
COLUMNS = ("chamfer_nf", "l1_mean", "l1_median")
FORECAST, HITS, COPY = "world model", "its right changes only", "copilot4d-token-copy"
def share_entry(p: float) -> str:
    return f"right on {p:g} of the changes"


def with_changes(last: torch.Tensor, target: torch.Tensor, take: torch.Tensor) -> torch.Tensor:
    """``last`` with ``target``'s token wherever ``take`` holds (a change only where the two differ)."""
    if not last.shape == target.shape == take.shape:
        raise ValueError(f"maps of shapes {tuple(last.shape)}, {tuple(target.shape)}, {tuple(take.shape)}")
    return torch.where(take, target, last)


def random_changes(last: torch.Tensor, target: torch.Tensor, p: float, generator: torch.Generator) -> torch.Tensor:
    """``last`` with ``target``'s token on a random share ``p`` of the tokens where they differ
    (each such token independently, drawn from ``generator``), nowhere else."""
    return with_changes(last, target, (target != last) & (torch.rand(target.shape, generator=generator) < p))


def check_shares(values) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    bad = [v for v in out if not 0.0 < v <= 1.0]
    if bad:
        raise PcfbenchError(f"shares {', '.join(f'{v:g}' for v in bad)}: each must lie in (0, 1]")
    return out


def evaluate_changes(method, adapter, split: str, setting: str, *, change_shares=CHANGE_SHARES,
                     max_samples: int | None = None, log=print) -> dict:
    """Score ``method`` (a loaded ``Copilot4D`` trained in frame t0) beside the bounds above on
    ``setting``'s samples of ``split`` (``max_samples`` evenly spaced; None: all). Returns
    ``score_beside``'s result (``means``, ``rows``, ``samples``...) with ``counts``: per future
    step the token counts of the forecast against the target (``token_report.COUNTS``), and
    ``by_ring``: the same over every step, per ring of ``token_rings``.

    The t=0 map is tokenized from the points the world model is given (``sample.for_method()``),
    the targets from the builder's sweeps (as the ceiling builds them): the two are the same
    points for the t=0 sweep (a test holds them so), or every token would count as changed."""
    if method.options.frame != "t0":
        raise PcfbenchError(f"{method.name}: frame={method.options.frame}; the changes of a forecast are measured "
                            "against the t=0 map in the frame that map is in: frame=t0 only")
    change_shares = check_shares(change_shares)
    tok = method.tokenizer
    render = dict(method.render)
    token_copy = TokenCopy(TokenCopyOptions(**render))
    token_copy.model = tok
    counts: list[dict[str, int]] = []
    by_ring = [dict.fromkeys(COUNTS, 0) for _ in range(len(RING_EDGES) + 1)]
    memo: dict[str, tuple] = {}

    def tokens(sample, builder, seq_name, ref):
        """The t=0 map (as the world model is given it), the targets and the forecast, once a sample."""
        if sample.sample_id not in memo:
            memo.clear()
            seen = sample.for_method()
            T_s0_ref = np.linalg.inv(seen.past_T_ref_sensor[-1])
            last = ev.tokenize_sweep(tok, transform(seen.past_points_ref[-1], T_s0_ref)).cpu()
            target, _ = future_targets(tok, sample, builder, seq_name, ref, "t0")
            pred = [p.cpu() for p in method.forecast_tokens(seen)[0]]
            target = [t.cpu() for t in target]
            rings = token_rings(tok.cfg, tuple(last.shape))
            ln = last.numpy()
            while len(counts) < len(pred):
                counts.append(dict.fromkeys(COUNTS, 0))
            for step, p, t in zip(counts, pred, target):
                pn, tn = p.numpy(), t.numpy()
                for into, where in [(step, slice(None)), *((r, rings == i) for i, r in enumerate(by_ring))]:
                    for key, v in score_tokens(pn[where], tn[where], ln[where]).items():
                        into[key] += v
            memo[sample.sample_id] = (last, target, pred, T_s0_ref)
        return memo[sample.sample_id]

    def entry(maps):
        def forecast(sample, builder, seq_name, ref):
            from pcfbench.data import Forecast

            last, target, pred, T_s0_ref = tokens(sample, builder, seq_name, ref)
            gen = torch.Generator().manual_seed(sample_seed(sample.sample_id, method.options.seed) ^ 1)
            codes = maps(sample, last, target, pred)
            return Forecast.from_depths(sample, ev.render_queries(tok, codes, sample, T_s0_ref, generator=gen,
                                                                  **render))
        return forecast

    def share(p: float):
        def maps(sample, last, target, pred):
            g = torch.Generator().manual_seed(sample_seed(sample.sample_id, 7) ^ int(p * 1_000_000))
            return [random_changes(last, t, p, g) for t in target]
        return maps

    forecasters = {
        FORECAST: entry(lambda s, last, target, pred: pred),
        HITS: entry(lambda s, last, target, pred: [with_changes(last, t, p == t) for t, p in zip(target, pred)]),
        **{share_entry(p): entry(share(p)) for p in change_shares},
        "ceiling": entry(lambda s, last, target, pred: target),
        COPY: lambda sample, *_: token_copy.forecast(sample.for_method()),
        "copy-last": lambda sample, *_: _copy_last().forecast(sample.for_method()),
    }
    res = score_beside(adapter, split, setting, forecasters, max_samples=max_samples, log=log,
                       label=f"{method.name} changes")
    return {**res, "counts": counts, "by_ring": by_ring, "setting": setting, "split": split, "dataset": adapter.name}


def _copy_last():
    from pcfbench.methods.copy_last import CopyLast

    return CopyLast()


def write_changes(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """The entries' means on the bar's columns with their ratio to token-copy, and the forecast's
    token counts per future step, as Markdown and CSV (beside a whole split's, never over it)."""
    from pcfbench.reporting.escape import md_text

    if result["samples"] < result.get("of_samples", result["samples"]):
        stem = f"{stem}-{result['samples']}-samples"
    out_dir.mkdir(parents=True, exist_ok=True)
    means, ref = result["means"], result["means"][COPY]
    ratio = lambda a, b: a / b if b else float("nan")  # noqa: E731
    csv_path, md = out_dir / f"{stem}.csv", out_dir / f"{stem}.md"
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["entry", *COLUMNS, *(f"{c}_over_token_copy" for c in COLUMNS)])
        for name, m in means.items():
            w.writerow([name, *(f"{m[c]:.6g}" for c in COLUMNS), *(f"{ratio(m[c], ref[c]):.4g}" for c in COLUMNS)])
        w.writerow([])
        w.writerow(["future step", *COUNTS, *shares(dict.fromkeys(COUNTS, 0))])
        for k, c in enumerate(result["counts"]):
            w.writerow([k + 1, *(c[n] for n in COUNTS), *(f"{v:.6g}" for v in shares(c).values())])
        w.writerow([])
        w.writerow(["distance from the t=0 sensor", *COUNTS, *shares(dict.fromkeys(COUNTS, 0))])
        for label, c in zip(ring_labels(), result["by_ring"]):
            w.writerow([label, *(c[n] for n in COUNTS), *(f"{v:.6g}" for v in shares(c).values())])
    names = list(shares(dict.fromkeys(COUNTS, 0)))
    total = {n: sum(c[n] for c in result["counts"]) for n in COUNTS}
    lines = [
        f"# Copilot4D: what the world model's changes are worth ({md_text(meta.get('method', ''))}, "
        f"{result['dataset']} {result['split']}, {result['setting']})", "",
        "**Bounds that see the future beside the forecast.** Each entry is a token map per future sweep in the "
        "t=0 sensor frame, rendered as `copilot4d` renders: the world model's forecast; the t=0 map with only the "
        "forecast's right changes applied; the t=0 map with the real future's token on a random share of the tokens "
        "that change (and nowhere else); the real future's tokens (the ceiling). `copilot4d-token-copy` (the t=0 "
        "map) and copy-last are scored in the same loop on the same samples; means are flat over (sample, future "
        f"sweep). {result['samples']} samples, {result['eval_s']:.0f} s.", "",
        "| entry | " + " | ".join(COLUMNS) + " | " + " | ".join(f"{c} / token-copy" for c in COLUMNS) + " |",
        "|---|" + "---:|" * (2 * len(COLUMNS)),
        *(f"| {name} | " + " | ".join(f"{m[c]:.3f}" for c in COLUMNS) + " | "
          + " | ".join(f"{ratio(m[c], ref[c]):.2f}" for c in COLUMNS) + " |" for name, m in means.items()),
        "", "The forecast's tokens against the target's (*changed*: the target differs from the t=0 map; *moved*: "
        "the forecast does; *precision*: the share of its moved tokens that are right):", "",
        "| future step | " + " | ".join(n.replace("_", " ") for n in names) + " |",
        "|---:|" + "---:|" * len(names),
        *(f"| {k + 1} | " + " | ".join(f"{100 * v:.1f} %" for v in shares(c).values()) + " |"
          for k, c in enumerate(result["counts"])),
        "| all | " + " | ".join(f"**{100 * v:.1f} %**" for v in shares(total).values()) + " |",
        "", "The same counts by the token's distance from the t=0 sensor (all future steps):", "",
        "| distance | tokens | " + " | ".join(n.replace("_", " ") for n in names) + " |",
        "|---|---:|" + "---:|" * len(names),
        *(f"| {label} | {c['tokens']} | " + " | ".join(f"{100 * v:.1f} %" for v in shares(c).values()) + " |"
          for label, c in zip(ring_labels(), result["by_ring"])),
        "", *(f"- {k}: {md_text(v)}" for k, v in meta.items()),
    ]
    md.write_text("\n".join(lines) + "\n")
    return md, csv_path
