"""A look-up table of the `tiny-window` tokenizer's future codes (issue 42, 2026-12-02, stop 76).

Fitted on the training windows of `copilot4d:config=tiny-window,anchor_every=1` (frame t0, strides
2 and 6): for every future token, the key (its t=0 code; the distance and bearing bins of the
token's centre seen from that future frame's sensor; the token's ring of distance from the t=0
sensor) counts the future codes. The table's forecast of a future map is the t=0 map with, at every
token whose key was seen at least 5 times, the key's most frequent code where that code's share of
the key passes a bar (bar 0: wherever it is not the t=0 code). Not a method: a measurement of what
the t=0 code and where the future sensor sees a token from say about its future code.

    .venv/bin/python docs/experiments/copilot4d_token_table.py tokens            # held-out windows
    .venv/bin/python docs/experiments/copilot4d_token_table.py score --split test  # kitti-1s, rendered

    .venv/bin/python docs/experiments/copilot4d_token_table.py rings --split test  # where the ceiling's gain is
    .venv/bin/python docs/experiments/copilot4d_token_table.py rings --split test --setting kitti-3s

`tokens` scores the forecast tokens of the held-out (test) windows against the real ones, per stride,
over every future step and within 20 m of the t=0 sensor; `score` renders the table's forecasts of
kitti-1s's every-third samples as `copilot4d` renders and scores them by the harness beside
`copilot4d-token-copy:config=tiny-window` in one loop (about 11 min on 2 CPU cores for test's 28);
`rings` scores, the same way, the t=0 map with the real future's tokens (the training target, as the
ceiling builds it) within one ring of distance from the t=0 sensor only, for each ring, and everywhere
(the ceiling): which ring's changes each column's gain over token-copy is made of; and the real changes
within 20 m of each future frame's own sensor only, and farther from it only (the near field the future
sensor sees from close up, which the t=0 sensor saw from afar). `--setting kitti-3s` scores that
setting's samples instead of kitti-1s's.
Needs `pcfbench train copilot4d-token-copy:config=tiny-window --dataset synthetic-town-realistic`
(the windows are tokenized here when the world model's training has not cached them).
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
import torch

from pcfbench.methods.copilot4d import evaluate as ev
from pcfbench.methods.copilot4d.forecaster import sample_seed, transform

DATASET, TOKENIZER = "synthetic-town-realistic", "copilot4d-token-copy:config=tiny-window"
BARS = (0.0, 0.4, 0.5, 0.6)
NEAR_FUTURE_M = 20.0
MIN_COUNT = 5


class Grid:
    """The tokenizer's BEV token grid: ``tokens`` x ``tokens`` over [-extent, extent]^2 of the t=0
    sensor frame, token [i, j] centred at (x_i, y_j)."""

    def __init__(self, extent: float, tokens: int) -> None:
        centres = -extent + (np.arange(tokens) + 0.5) * (2 * extent / tokens)
        self.X, self.Y = np.meshgrid(centres, centres, indexing="ij")
        self.r0 = np.hypot(self.X, self.Y)
        self.ring0 = np.digitize(self.r0, [5, 10, 15, 20, 30, 40, 60])

    def keys(self, c0: np.ndarray, T_s0_sensor: np.ndarray) -> np.ndarray:
        """(H, W) keys of a t=0 map ``c0`` for a future sensor at ``T_s0_sensor`` (its pose in the t=0 frame)."""
        t, yaw = T_s0_sensor[:2, 3], np.arctan2(T_s0_sensor[1, 0], T_s0_sensor[0, 0])
        dx, dy = self.X - t[0], self.Y - t[1]
        lx, ly = np.cos(yaw) * dx + np.sin(yaw) * dy, -np.sin(yaw) * dx + np.cos(yaw) * dy
        dist = np.digitize(np.hypot(lx, ly), [2.5, 5, 7.5, 10, 15, 20, 30, 40, 60])
        bearing = ((np.arctan2(ly, lx) + np.pi) / (2 * np.pi) * 8).astype(np.int64) % 8
        return c0.astype(np.int64) * 1000 + dist * 100 + bearing * 10 + self.ring0


def fit(grid: Grid, w: dict, n_past: int = 5) -> dict[int, tuple[int, float, int]]:
    """key -> (most frequent future code, its share of the key, the key's count), over the future
    frames of the windows ``w`` (``build_windows`` output; the t=0 map is frame ``n_past`` - 1)."""
    counts: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)
    for a in range(len(w["tokens"])):
        for j in range(n_past, w["tokens"].shape[1]):
            k = grid.keys(w["tokens"][a, n_past - 1], w["poses"][a, j]).ravel()
            u, n = np.unique(k * 1024 + w["tokens"][a, j].ravel().astype(np.int64), return_counts=True)
            for x, m in zip(u.tolist(), n.tolist()):
                counts[x // 1024][x % 1024] += m
    table = {}
    for k, c in counts.items():
        (code, n) = c.most_common(1)[0]
        table[k] = (code, n / sum(c.values()), sum(c.values()))
    return table


def forecast(grid: Grid, table, c0: np.ndarray, T_s0_sensor: np.ndarray, bar: float) -> np.ndarray:
    out = c0.astype(np.int64).copy()
    for (i, j), k in np.ndenumerate(grid.keys(c0, T_s0_sensor)):
        hit = table.get(int(k))
        if hit is not None and hit[1] > bar and hit[2] >= MIN_COUNT:
            out[i, j] = hit[0]
    return out


def token_stats(grid: Grid, table, w: dict, bars=BARS, n_past: int = 5) -> list[str]:
    """Per bar, stride and (whole map, within 20 m): the table's forecast tokens of the windows ``w``
    against their real future tokens."""
    lines = []
    for bar in bars:
        st = collections.Counter()
        for a in range(len(w["tokens"])):
            s, c0 = int(w["stride"][a]), w["tokens"][a, n_past - 1].astype(np.int64)
            for j in range(n_past, w["tokens"].shape[1]):
                pred, truth = forecast(grid, table, c0, w["poses"][a, j], bar), w["tokens"][a, j].astype(np.int64)
                for where, sel in (("all", np.ones_like(grid.r0, bool)), ("0-20 m", grid.r0 < 20)):
                    moved, changed = (pred != c0) & sel, (truth != c0) & sel
                    st[s, where, "tokens"] += int(sel.sum())
                    st[s, where, "changed"] += int(changed.sum())
                    st[s, where, "moved"] += int(moved.sum())
                    st[s, where, "hit"] += int((moved & (pred == truth)).sum())
                    st[s, where, "right"] += int(((pred == truth) & sel).sum())
                    st[s, where, "copy"] += int(((c0 == truth) & sel).sum())
        for s in sorted({k[0] for k in st}):
            for where in ("all", "0-20 m"):
                g = lambda k: st[s, where, k]  # noqa: E731
                lines.append(f"bar {bar:g}, stride {s}, {where}: moved {100 * g('moved') / g('tokens'):.1f} %, "
                             f"precision {100 * g('hit') / max(g('moved'), 1):.1f} %, changes right "
                             f"{100 * g('hit') / max(g('changed'), 1):.1f} %, accuracy {100 * g('right') / g('tokens'):.1f} % "
                             f"(copying {100 * g('copy') / g('tokens'):.1f} %)")
    return lines


class Measurement:
    """The trained `tiny-window` tokenizer, its grid and the windows it tokenizes (loaded when made)."""

    def __init__(self) -> None:
        from pcfbench.methods.copilot4d.plugin import _loaded
        from pcfbench.methods.copilot4d.token_copy import TokenCopy

        self.tc, self.ck = _loaded(TOKENIZER, TokenCopy, "tokenizer", DATASET, "train", None)
        self.tok = self.tc.model
        self.grid = Grid(self.tok.cfg.x_range[1], self.tok.cfg.bev_tokens)

    def windows(self, split: str) -> dict:
        from pcfbench.methods.copilot4d.forecaster import build_windows, window_cache_dir
        from pcfbench.training import open_training_data

        source = open_training_data(DATASET, split, split_option="--split {}")
        return build_windows(self.tok, source.adapter, split, 5, 5, (2, 6), 1,
                             window_cache_dir(self.ck.sha256, source.train_on.key), log=print)

    def fit(self) -> dict:
        w = self.windows("train")
        table = fit(self.grid, w)
        print(f"{len(table)} keys from {len(w['tokens'])} training windows")
        return table


def every_third(m: Measurement, split: str, forecasters: dict, setting: str = "kitti-1s") -> dict:
    """``score_beside`` on ``setting``'s samples under the every-third policy (the ones `pcfbench run` scores)."""
    import pcfbench.protocol as protocol
    from pcfbench.methods.copilot4d.ceiling import score_beside
    from pcfbench.training import open_training_data

    builder = protocol.SampleBuilder

    class EveryThird(builder):
        def __init__(self, adapter, setting, policy="every-third", **kw):
            super().__init__(adapter, setting, policy, **kw)

    protocol.SampleBuilder = EveryThird
    try:
        return score_beside(open_training_data(DATASET, split, split_option="--split {}").adapter, split, setting,
                            {"copilot4d-token-copy": lambda sample, *_: m.tc.forecast(sample.for_method()), **forecasters},
                            log=print, label="table")
    finally:
        protocol.SampleBuilder = builder


def print_beside(res: dict, split: str, setting: str = "kitti-1s") -> None:
    cols = ("chamfer_nf", "l1_mean", "l1_median")
    ref = res["means"]["copilot4d-token-copy"]
    print(f"{DATASET} {split} {setting}, {res['samples']} samples; chamfer_nf / l1_mean / l1_median, then / token-copy")
    per_sample = {}
    for name, rows in res["rows"].items():
        for r in rows:
            for c in cols:
                if r.get(c) is not None and np.isfinite(r[c]):
                    per_sample.setdefault((name, c, r["sample_id"]), []).append(r[c])
    for name, m in res["means"].items():
        line = " / ".join(f"{m[c]:.3f}" for c in cols) + "   " + " / ".join(f"{m[c] / ref[c]:.3f}" for c in cols)
        if name != "copilot4d-token-copy":  # paired over samples: better on how many, and a bootstrap interval
            for c in cols:
                d = np.array([np.mean(v) - np.mean(per_sample[("copilot4d-token-copy", c, sid)])
                              for (n, cc, sid), v in per_sample.items() if n == name and cc == c])
                boot = np.random.default_rng(0).choice(d, (2000, len(d))).mean(1)
                lo, hi = np.percentile(boot, [2.5, 97.5])
                line += f"; {c}: better on {int((d < 0).sum())}/{len(d)}, diff 95 % [{lo:+.4f}, {hi:+.4f}]"
        print(f"{name}: {line}")


def rings(m: Measurement, split: str, setting: str = "kitti-1s", near: float = NEAR_FUTURE_M) -> None:
    from pcfbench.data import Forecast
    from pcfbench.methods.copilot4d.ceiling import future_targets

    tok, render = m.tok, ev.rendering_kwargs(m.tc.options)
    ring = torch.from_numpy(ev.token_rings(tok.cfg, (tok.cfg.bev_tokens, tok.cfg.bev_tokens)))
    labels = ev.ring_labels()
    memo: dict[str, tuple] = {}

    def maps(sample, builder, seq_name, ref):
        if sample.sample_id not in memo:
            memo.clear()
            seen = sample.for_method()
            T_s0_ref = np.linalg.inv(seen.past_T_ref_sensor[-1])
            c0 = ev.tokenize_sweep(tok, transform(seen.past_points_ref[-1], T_s0_ref)).cpu()
            target = [t.cpu() for t in future_targets(tok, sample, builder, seq_name, ref, "t0")[0]]
            memo[sample.sample_id] = (c0, target, T_s0_ref)
        return memo[sample.sample_id]

    def entry(where):
        """``where``: a (H, W) bool map, or ``fn(k, T_s0_sk)`` giving one for future frame k."""
        def fn(sample, builder, seq_name, ref):
            c0, target, T_s0_ref = maps(sample, builder, seq_name, ref)
            pick = [where(k, T_s0_ref @ sample.future_T_ref_sensor[k]) if callable(where) else where
                    for k in range(len(target))]
            codes = [torch.where(w, t, c0) for w, t in zip(pick, target)]
            gen = torch.Generator().manual_seed(sample_seed(sample.sample_id, 0) ^ 1)
            return Forecast.from_depths(sample, ev.render_queries(tok, codes, sample, T_s0_ref, generator=gen,
                                                                  **render))
        return fn

    def near_future(k, T_s0_sk):  # tokens whose centre lies within `near` m of future frame k's sensor
        return torch.from_numpy(np.hypot(m.grid.X - T_s0_sk[0, 3], m.grid.Y - T_s0_sk[1, 3]) < near)

    entries = {f"the real changes at {labels[i]} only": entry(ring == i) for i in range(len(labels))}
    entries[f"the real changes within {near:g} m of each future sensor only"] = entry(near_future)
    entries[f"the real changes farther than {near:g} m from it only"] = entry(lambda k, T: ~near_future(k, T))
    entries["the ceiling (every change)"] = entry(torch.ones_like(ring, dtype=torch.bool))
    print_beside(every_third(m, split, entries, setting), split, setting)


def score(m: Measurement, table, split: str, bars=(0.0, 0.4, 0.5)) -> None:
    from pcfbench.data import Forecast

    tok, render = m.tok, ev.rendering_kwargs(m.tc.options)
    memo: dict[str, tuple] = {}

    def maps(sample):
        if sample.sample_id not in memo:
            memo.clear()
            seen = sample.for_method()
            T_s0_ref = np.linalg.inv(seen.past_T_ref_sensor[-1])
            c0 = ev.tokenize_sweep(tok, transform(seen.past_points_ref[-1], T_s0_ref)).cpu().numpy()
            memo[sample.sample_id] = ({bar: [torch.from_numpy(forecast(m.grid, table, c0, T_s0_ref @ T, bar))
                                             for T in seen.future_T_ref_sensor] for bar in bars}, T_s0_ref)
        return memo[sample.sample_id]

    def entry(bar):
        def fn(sample, *_):
            by_bar, T_s0_ref = maps(sample)
            gen = torch.Generator().manual_seed(sample_seed(sample.sample_id, 0) ^ 1)
            return Forecast.from_depths(sample, ev.render_queries(tok, by_bar[bar], sample, T_s0_ref, generator=gen,
                                                                  **render))
        return fn

    print_beside(every_third(m, split, {f"table, bar {b:g}": entry(b) for b in bars}), split)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=("tokens", "score", "rings"))
    p.add_argument("--split", default="test")
    p.add_argument("--setting", default="kitti-1s", help="rings only: the setting whose samples are scored")
    args = p.parse_args()
    m = Measurement()
    if args.what == "rings":
        rings(m, args.split, args.setting)
    elif args.what == "tokens":
        print("\n".join(token_stats(m.grid, m.fit(), m.windows("test"))))
    else:
        score(m, m.fit(), args.split)


if __name__ == "__main__":
    main()
