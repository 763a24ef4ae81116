"""The baselines' rankings on like-for-like samples (docs/realism.md, "Moving evidence"): each
kitti-1s sample's moving evidence (``compare.sweep_moving_evidence`` at its reference sweep:
the share of its points in space the sweeps 0.5 s before and after both saw empty, with no
return near them then; label-free, so the same on both sides), and the flat means, Kendall
taus and ratios of the five baselines over every sample and over the synthetic samples with
no more moving evidence than the busiest real sample. The numbers are read from the store of
a ``pcfbench synthetic compare`` run with the same arguments (cells missing there are run).

    .venv/bin/python docs/experiments/realism_moving_strata.py --store STORE \\
        --synthetic synthetic-town-realistic=FOLDER --split train,val,test \\
        --real kitti=../shared/realdata/kitti-seq00-frames040-099 --real-split train

With labels (a generated side) it also gives the share of each stratum's points on labelled
moving objects.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pcfbench.datasets.synthetic import compare as C


def side(spec: str, split: str, store: Path, setting: str):
    """(dataset name, {method: its ok rows}, {(sequence, reference index): (moving evidence,
    judged points, share of the sweep's points on labelled moving objects or None)}, the
    number of samples in the rows; a sample without sweeps 0.5 s before and after has no
    evidence)."""
    name, root, ad = C.open_side(spec, False)
    rows = {m: C.baseline_rows(name, str(root), split, setting, store, None, m)[0] for m in C.BASELINES}
    keys = sorted({(str(s), int(r)) for s, r in zip(rows[C.BASELINES[0]]["sequence"], rows[C.BASELINES[0]]["ref_index"])})
    evidence, seqs = {}, {}
    for seq_name, ref in keys:
        seq = seqs.setdefault(seq_name, ad.sequence(seq_name))
        got = C.sweep_moving_evidence(ad, seq, ref)
        if got is None:
            continue
        judged, moving = got
        raw_n = len(seq.load_points(ref))
        mask = C._moving_mask(ad, seq_name, ref, raw_n)
        evidence[(seq_name, ref)] = (int(moving.sum()), int(judged.sum()), None if mask is None else float(mask.mean()))
    return name, rows, evidence, len(keys)


def means(rows: dict, keep: set | None) -> np.ndarray:
    """(methods, metrics) flat means over the rows of the samples in ``keep`` (all if None)."""
    out = []
    for m in C.BASELINES:
        df = rows[m]
        if keep is not None:
            sel = np.array([(str(s), int(r)) in keep for s, r in zip(df["sequence"], df["ref_index"])])
            df = df[sel]
        out.append([float(np.nanmean(df[k].to_numpy(float))) for k in C.RANK_METRICS])
    return np.array(out)


def show(label: str, syn: np.ndarray, real: np.ndarray, n_syn: int, n_real: int) -> None:
    taus = [C.kendall_tau(real[:, k], syn[:, k]) for k in range(len(C.RANK_METRICS))]
    ratio = syn / real
    within = int(((ratio <= 1.5) & (ratio >= 1 / 1.5)).sum())
    print(f"\n{label}: {n_syn} synthetic samples against {n_real} real; tau "
          + " / ".join(f"{t:.1f}" for t in taus) + f" ({' / '.join(C.RANK_METRICS)}); {within} of {ratio.size} "
          f"within 1.5x (largest ratio {ratio.max():.2f}, smallest {ratio.min():.2f})")
    print("| method | " + " | ".join(f"{k} synthetic | real" for k in C.RANK_METRICS) + " |")
    for i, m in enumerate(C.BASELINES):
        print(f"| {m} | " + " | ".join(f"{syn[i, k]:.3f} | {real[i, k]:.3f}" for k in range(len(C.RANK_METRICS))) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", type=Path, required=True)
    ap.add_argument("--synthetic", required=True, help="NAME=ROOT of the generated side")
    ap.add_argument("--split", default="test")
    ap.add_argument("--real", required=True, help="NAME=ROOT of the real side")
    ap.add_argument("--real-split", default="train")
    ap.add_argument("--setting", default="kitti-1s")
    a = ap.parse_args()
    s_name, s_rows, s_ev, s_n = side(a.synthetic, a.split, a.store, a.setting)
    r_name, r_rows, r_ev, r_n = side(a.real, a.real_split, a.store, a.setting)

    def share(ev):  # a sample without judged points has no evidence either way: left out of the strata
        return {k: m / j for k, (m, j, _) in ev.items() if j}
    s_share, r_share = share(s_ev), share(r_ev)
    for label, n, sh in ((s_name, s_n, s_share), (r_name, r_n, r_share)):
        if len(sh) < n:
            print(f"{label}: {n - len(sh)} of {n} samples without moving evidence either way, left out of the strata")
    top = max(r_share.values())
    for label, sh, ev in ((s_name, s_share, s_ev), (r_name, r_share, r_ev)):
        v = np.array(list(sh.values()))
        print(f"{label}: {len(v)} samples; moving evidence per sample median {np.median(v):.5f}, p90 "
              f"{np.quantile(v, 0.9):.5f}, max {v.max():.5f}; pooled {sum(m for m, _, _ in ev.values()) / sum(j for _, j, _ in ev.values()):.5f}; "
              f"above the busiest real sample ({top:.5f}): {(v > top).mean():.0%}")
    real = means(r_rows, None)
    show("every sample", means(s_rows, None), real, s_n, r_n)
    quiet = {k for k, v in s_share.items() if v <= top}
    show(f"synthetic samples with no more moving evidence than the busiest real sample ({top:.5f})",
         means(s_rows, quiet), real, len(quiet), r_n)
    labelled = [(k, f) for k, (_, _, f) in s_ev.items() if f is not None]
    if labelled:
        q = [f for k, f in labelled if k in quiet]
        b = [f for k, f in labelled if k not in quiet]
        print(f"\nlabelled moving points at the reference sweep: {np.mean(q) if q else float('nan'):.4f} in the quiet "
              f"samples, {np.mean(b) if b else float('nan'):.4f} in the others")


if __name__ == "__main__":
    main()
