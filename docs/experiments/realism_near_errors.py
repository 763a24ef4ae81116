"""Where the casters' l1_median differs, on a generated domain and on real sweeps (docs/realism.md,
"Physics 7"): for evenly spaced kitti-1s samples, every query ray's depth error (the forecast
depth on that ray minus the true return's range from the future sensor), and per group of the
true return (range from the future sensor 0-10 / 10-20 / 20-40 / 40+ m, above the ground or more
than 1.3 m below the sensor) the share of all of a sweep's rays that err by more than 0.1 m,
averaged over sweeps. With ``--labels`` (a generated root) the rays 0-10 m away above the
ground are also split by the labelled class of the true return (the label of its nearest raw
point), into too long and too short. Those near rays are also split, on both sides and
without labels, by the true return's height above or below the sensor (from -1.3 m, bands at
-1.0, -0.6, -0.3 and 0 m): each method's share of all rays too long by more than 0.1 m, by more
than 1 m (through or past what the ray meets), and too short by more than 0.1 m.

    .venv/bin/python docs/experiments/realism_near_errors.py \\
        --synthetic FOLDER --real ../shared/realdata/kitti-seq00-frames040-099 --samples 8 --labels

FOLDER: a generated test split (e.g. ``generate_domain(get_domain("synthetic-town-realistic"),
FOLDER, splits=("test",))``).
"""

from __future__ import annotations

import numpy as np

from realism_chamfer_split import (  # this folder is on the path when a script here runs
    GROUPS, evenly_spaced, forecasts_of, group_of, nearest_labels, run_sides,
)

METHODS = ("raycast-4docc", "raycast-freespace", "raycast-voxel", "raycast-zbuffer")
THRESHOLD_M = 0.1
FAR_M = 1.0
N_CLASSES = 16
HEIGHTS = (-1.0, -0.6, -0.3, 0.0)  # m, of the true return above the future sensor (near rays: >= -1.3)
HEIGHT_NAMES = tuple(f"{a} .. {b}" for a, b in zip((-1.3,) + HEIGHTS[:-1], HEIGHTS)) + ("above 0",)


def near_errors(dataset: str, root: str, split_name: str, samples: int, labels: bool) -> None:
    ad, setting, builder, keys, methods = evenly_spaced(dataset, root, split_name, samples, METHODS)
    share = np.zeros(len(GROUPS))
    wrong = {m: np.zeros(len(GROUPS)) for m in methods}
    cls_share = np.zeros(N_CLASSES)
    long_ = {m: np.zeros(N_CLASSES) for m in methods}
    short = {m: np.zeros(N_CLASSES) for m in methods}
    n_h = len(HEIGHT_NAMES)
    h_share = np.zeros(n_h)
    h_err = {m: np.zeros((3, n_h)) for m in methods}  # too long, far too long, too short
    sweeps = 0
    for seq, ref, sample, truth, forecasts in forecasts_of(builder, keys, methods):
        sequence = ad.sequence(seq)
        for k in range(setting.future):
            G = truth.future_points_ref[k]
            o = sample.queries[k].origin_ref
            true_range = np.linalg.norm(G - o, axis=1)
            T = np.eye(4)
            T[:3, 3] = o
            g = group_of(G, T)
            share += np.bincount(g, minlength=len(GROUPS)) / len(G)
            near = g == 0
            band = np.digitize(G[near, 2] - o[2], HEIGHTS)
            h_share += np.bincount(band, minlength=n_h) / len(G)
            cls = None
            if labels:
                j = ref + (k + 1) * setting.stride
                cls = np.minimum(nearest_labels(sequence, root, seq, ref, j, G[near]), N_CLASSES - 1)
                cls_share += np.bincount(cls, minlength=N_CLASSES) / len(G)
            for m, fc in forecasts.items():
                e = np.asarray(fc.depths[k], np.float64) - true_range
                wrong[m] += np.bincount(g, weights=np.abs(e) > THRESHOLD_M, minlength=len(GROUPS)) / len(G)
                for row, hit in enumerate((e[near] > THRESHOLD_M, e[near] > FAR_M, e[near] < -THRESHOLD_M)):
                    h_err[m][row] += np.bincount(band, weights=hit, minlength=n_h) / len(G)
                if cls is not None:
                    long_[m] += np.bincount(cls, weights=e[near] > THRESHOLD_M, minlength=N_CLASSES) / len(G)
                    short[m] += np.bincount(cls, weights=e[near] < -THRESHOLD_M, minlength=N_CLASSES) / len(G)
            sweeps += 1
    print(f"== {dataset} ({root}), {len(keys)} samples, {sweeps} sweeps; shares of all rays, mean over sweeps")
    print(f"all rays erring > {THRESHOLD_M} m: " + " | ".join(f"{m[8:]} {wrong[m].sum() / sweeps:.3f}" for m in methods))
    for gi, name in enumerate(GROUPS):
        print(f"  {name:13s} rays {share[gi] / sweeps:.3f} | "
              + " | ".join(f"{m[8:]} {wrong[m][gi] / sweeps:.3f}" for m in methods))
    print(f"rays 0-10 m away by the true return's height above the sensor (m): share, then each method's "
          f"too long by > {THRESHOLD_M} m / by > {FAR_M} m / too short by > {THRESHOLD_M} m")
    for hi, name in enumerate(HEIGHT_NAMES):
        print(f"  {name:13s} rays {h_share[hi] / sweeps:.3f} | "
              + " | ".join(f"{m[8:]} " + " / ".join(f"{v / sweeps:.3f}" for v in h_err[m][:, hi]) for m in methods))
    if labels:
        from pcfbench.datasets.synthetic.world import CLASS_NAMES

        print("rays 0-10 m above the ground by labelled class: share, then each method's too long / too short")
        for c in range(N_CLASSES):
            if cls_share[c] / sweeps < 0.002:
                continue
            name = CLASS_NAMES[c] if c < len(CLASS_NAMES) else str(c)
            print(f"  {name:15s} rays {cls_share[c] / sweeps:.3f} | "
                  + " | ".join(f"{m[8:]} {long_[m][c] / sweeps:.3f} / {short[m][c] / sweeps:.3f}" for m in methods))


def main() -> None:
    run_sides(__doc__, near_errors)


if __name__ == "__main__":
    main()
