"""Where 4docc's l1_median differs from the fitted casters', on a generated domain and on real
sweeps (docs/realism.md, "Physics 8"): for evenly spaced kitti-1s samples, every query ray's
depth error (the forecast depth on that ray minus the true return's range from the future
sensor), grouped by the true return's azimuth from the future sensor in the reference frame
(0 deg: straight ahead, 180: straight behind; left and right alike), whether it lies more than
1.3 m below the sensor (ground) or not, and its range (0-10 / 10-20 / 20-40 / 40+ m). Per
group: its share of all rays and each method's median absolute error. Label-free, so it runs
on both sides. With ``--labels`` (a generated root), the rays of one group (``CELL``: the
rear quarter, 135-165 deg, above the ground, 10-20 m) are also split by the
labelled class of the true return (the label of its nearest raw point), those with at least 1 % of it: share, median error,
too long and too short by more than 0.1 m.

    .venv/bin/python docs/experiments/realism_sectors.py \\
        --synthetic FOLDER --real ../shared/realdata/kitti-seq00-frames040-099 --samples 8 --labels

FOLDER: a generated test split (e.g. ``generate_domain(get_domain("synthetic-town-realistic"),
FOLDER, splits=("test",))``).
"""

from __future__ import annotations

import numpy as np

from realism_chamfer_split import evenly_spaced, forecasts_of, nearest_labels, run_sides  # this folder is on the path

METHODS = ("raycast-4docc", "raycast-freespace", "raycast-zbuffer")
SECTORS = {"front 15-45": (15.0, 45.0), "side 45-135": (45.0, 135.0), "rear 135-165": (135.0, 165.0)}
RANGES = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, np.inf))
CELL = ("rear 135-165", False, (10.0, 20.0))  # sector, ground?, range: the class split's group
THRESHOLD_M = 0.1


def sectors(dataset: str, root: str, split_name: str, samples: int, labels: bool) -> None:
    ad, setting, builder, keys, methods = evenly_spaced(dataset, root, split_name, samples, METHODS)
    az, z, rng, cls = [], [], [], []
    err = {m: [] for m in methods}
    for seq, ref, sample, truth, forecasts in forecasts_of(builder, keys, methods):
        sequence = ad.sequence(seq)
        for k in range(setting.future):
            G = truth.future_points_ref[k]
            d = G - sample.queries[k].origin_ref
            true_range = np.linalg.norm(d, axis=1)
            az.append(np.degrees(np.abs(np.arctan2(d[:, 1], d[:, 0]))))
            z.append(d[:, 2])
            rng.append(true_range)
            if labels:
                cls.append(nearest_labels(sequence, root, seq, ref, ref + (k + 1) * setting.stride, G))
            for m, fc in forecasts.items():
                err[m].append(np.asarray(fc.depths[k], np.float64) - true_range)
    az, z, rng = np.concatenate(az), np.concatenate(z), np.concatenate(rng)
    err = {m: np.concatenate(v) for m, v in err.items()}
    print(f"== {dataset} ({root}), {len(keys)} samples, {len(az)} rays; per group: share of all rays, "
          f"then median |error| of " + " / ".join(m[8:] for m in methods))

    def group(sector: str, ground: bool, r: tuple[float, float]) -> np.ndarray:
        a0, a1 = SECTORS[sector]
        return (az >= a0) & (az < a1) & ((z < -1.3) == ground) & (rng >= r[0]) & (rng < r[1])

    for sector in SECTORS:
        for ground in (True, False):
            cells = []
            for r in RANGES:
                s = group(sector, ground, r)
                med = " / ".join(f"{np.median(np.abs(err[m][s])):.3f}" for m in methods) if s.any() else "-"
                cells.append(f"{r[0]:.0f}{f'-{r[1]:.0f}' if np.isfinite(r[1]) else '+'} m: {s.mean():.3f} {med}")
            print(f"  {sector:13s} {'ground' if ground else 'above':6s} | " + " | ".join(cells))
    if labels:
        from pcfbench.datasets.synthetic.world import CLASS_NAMES

        cls = np.concatenate(cls)
        s = group(*CELL)
        print(f"  {CELL[0]}, {'ground' if CELL[1] else 'above'}, {CELL[2][0]:.0f}-{CELL[2][1]:.0f} m by labelled class: "
              f"share of the group, then each method's median |error| / too long / too short by > {THRESHOLD_M} m")
        for c in np.unique(cls[s]):
            sc = s & (cls == c)
            if sc.sum() < 0.01 * s.sum():
                continue
            name = CLASS_NAMES[c] if c < len(CLASS_NAMES) else str(c)
            print(f"    {name:15s} {sc.sum() / s.sum():.3f} | " + " | ".join(
                f"{m[8:]} {np.median(np.abs(err[m][sc])):.3f} / {np.mean(err[m][sc] > THRESHOLD_M):.2f} / "
                f"{np.mean(err[m][sc] < -THRESHOLD_M):.2f}" for m in methods))


def main() -> None:
    run_sides(__doc__, sectors)


if __name__ == "__main__":
    main()
