"""The five baselines ranked town by town, and over every town at once, beside the real drive
(docs/realism.md, "Seven towns"): which rankings are the world's and which are the scene's.

Each ``--side`` is a generated root and the splits of it to take; each split's baseline cells
run (or resume) in ``--store`` exactly as ``pcfbench synthetic compare`` runs them, so a store
that compare filled is read, not rerun:

    .venv/bin/python docs/experiments/realism_towns.py --store STORE \\
        --real ../shared/realdata/kitti-seq00-frames040-099 --side FOLDER=train,val,test

Prints each town's (sequence's) flat means and Kendall tau against the real drive, the towns'
taus against each other, and the flat means and taus of every town pooled (each sample
weighs the same).
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np

from pcfbench.datasets.synthetic.compare import BASELINES, RANK_METRICS, baseline_means, kendall_tau


def flat_means(base: dict, keep=lambda sample_id: True) -> dict:
    """metric -> [each method's mean over the samples ``keep`` takes] (per-sample means weigh
    alike: every sample has as many future sweeps)."""
    out = {}
    for k in RANK_METRICS:
        out[k] = []
        for m in BASELINES:
            ps = base[m]["per_sample"]
            out[k].append(float(np.mean([v for i, v in zip(ps["sample_id"], ps[k]) if keep(i)])))
    return out


def towns_of(base: dict) -> list[str]:
    return sorted({i.split("/")[0] for i in base[BASELINES[0]]["per_sample"]["sample_id"]})


def line(name: str, means: dict, real: dict) -> str:
    return f"{name:8s} " + " | ".join(
        f"{k} " + " ".join(f"{x:.3f}" for x in means[k]) + f" tau {kendall_tau(real[k], means[k]):+.1f}"
        for k in RANK_METRICS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True, type=Path)
    ap.add_argument("--real", required=True, help="a KITTI root (split train)")
    ap.add_argument("--domain", default="synthetic-town-realistic")
    ap.add_argument("--side", action="append", required=True, help="FOLDER=split[,split...]")
    a = ap.parse_args()
    real = flat_means(baseline_means("kitti", a.real, "train", "kitti-1s", a.store, None))
    towns, pooled = {}, {k: [[] for _ in BASELINES] for k in RANK_METRICS}
    for side in a.side:
        root, splits = side.split("=")
        for split in splits.split(","):
            base = baseline_means(a.domain, root, split, "kitti-1s", a.store, None)
            for t in towns_of(base):
                towns[t] = flat_means(base, lambda i, t=t: i.split("/")[0] == t)
            for k in RANK_METRICS:
                for j, m in enumerate(BASELINES):
                    pooled[k][j] += base[m]["per_sample"][k]
    print("methods: " + ", ".join(BASELINES))
    print(line("real", real, real))
    for t, means in towns.items():
        print(line(f"town {t}", means, real))
    pooled = {k: [float(np.mean(v)) for v in pooled[k]] for k in RANK_METRICS}
    print(line("pooled", pooled, real) + f"  ({len(towns)} towns)")
    print("within 1.5x of real (pooled): " + ", ".join(
        f"{k} " + " ".join(f"{s / r:.2f}" for s, r in zip(pooled[k], real[k])) for k in RANK_METRICS))
    for k in RANK_METRICS:
        pairs = [kendall_tau(towns[x][k], towns[y][k]) for x, y in itertools.combinations(towns, 2)]
        print(f"{k}: town against town, mean tau {np.mean(pairs):.2f} (lowest {min(pairs):+.1f}); "
              f"order of each town: " + "; ".join(
                  " < ".join(BASELINES[j].replace("raycast-", "") for j in np.argsort(towns[t][k])) for t in towns))


if __name__ == "__main__":
    main()
