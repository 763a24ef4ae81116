"""Which way the baselines' depth errors lean on the near ground, on a generated domain and on
real sweeps (docs/realism.md, "What moved from physics 4 to 5"): for evenly spaced kitti-1s
samples, every query ray's signed depth error (forecast minus true, both clamped to the ROI as
the protocol's L1 does, nearest forecast point in azimuth / elevation) of copy-last and the
three ray casters, for the rays whose true return lies on the ground (more than 1.3 m below
the future sensor) 5-10 m from it: the 10th / 25th / 50th / 75th / 90th percentiles, the share
within 5 cm, and the median |error|; then the median |error| by range band and height for
every ray.

    .venv/bin/python docs/experiments/realism_ground_errors.py \\
        --synthetic FOLDER --real ../shared/realdata/kitti-seq00-frames040-099 --samples 12

FOLDER: a generated test split (e.g. ``generate_domain(get_domain("synthetic-town-realistic"),
FOLDER, splits=("test",))``).
"""

from __future__ import annotations

import numpy as np

from pcfbench.metrics.base import SweepContext
from realism_chamfer_split import evenly_spaced, forecasts_of, parse_sides  # this folder is on the path when a script here runs

METHODS = ("copy-last", "raycast-zbuffer", "raycast-freespace", "raycast-voxel")
RANGES = (5.0, 10.0, 20.0)  # bands 0-5, 5-10, 10-20, 20+ m from the future sensor
HEIGHTS = (-1.3, -0.5, 0.5)  # ground, low, middle, high: z relative to the future sensor


def signed_errors(dataset: str, root: str, split_name: str, samples: int):
    """(signed errors per method, range, height) over the kept rays of every future sweep."""
    _, setting, builder, keys, methods = evenly_spaced(dataset, root, split_name, samples, METHODS)
    errs = {m: [] for m in methods}
    ranges, heights = [], []
    for _, _, sample, truth, forecasts in forecasts_of(builder, keys, methods):
        for k in range(setting.future):
            gt = truth.future_points_ref[k]
            for m, fc in forecasts.items():
                ctx = SweepContext(gt, sample.queries[k], fc.points_ref[k] if fc.points_ref is not None else None,
                                   fc.depths[k] if fc.depths is not None else None)
                t_enter, t_exit, _ = ctx.ray_clamp
                kept = ctx.ray_kept
                errs[m].append(np.clip(ctx.ray_depth[kept], t_enter[kept], t_exit[kept]) - ctx.gt_clamped[kept])
            rel = np.asarray(gt, np.float64)[kept] - ctx.origin
            ranges.append(np.linalg.norm(rel, axis=1))
            heights.append(rel[:, 2])
    return {m: np.concatenate(v) for m, v in errs.items()}, np.concatenate(ranges), np.concatenate(heights)


def report(dataset: str, root: str, split_name: str, samples: int) -> None:
    errs, r, z = signed_errors(dataset, root, split_name, samples)
    print(f"== {dataset} ({root}), {samples} samples; metres")
    print("overall median |error|: " + ", ".join(f"{m} {np.median(np.abs(e)):.4f}" for m, e in errs.items()))
    near_ground = (r >= 5.0) & (r < 10.0) & (z < HEIGHTS[0])
    print(f"ground 5-10 m ({near_ground.mean():.3f} of the rays): signed error percentiles 10/25/50/75/90, "
          "share within 5 cm, median |error|")
    for m, e in errs.items():
        x = e[near_ground]
        print(f"  {m:18s} " + " ".join(f"{v:+.3f}" for v in np.percentile(x, [10, 25, 50, 75, 90]))
              + f" | {(np.abs(x) < 0.05).mean():.3f} | {np.median(np.abs(x)):.3f}")
    print("median |error| by range band and height (share of the rays | " + " ".join(METHODS) + ")")
    rb, hb = np.digitize(r, RANGES), np.digitize(z, HEIGHTS)
    for i, band in enumerate(("0-5", "5-10", "10-20", "20+")):
        for j, height in enumerate(("ground", "low", "middle", "high")):
            w = (rb == i) & (hb == j)
            if w.mean() >= 0.01:
                print(f"  {band:5s} {height:6s} {w.mean():.3f} | " + " ".join(f"{np.median(np.abs(errs[m][w])):.3f}"
                                                                        for m in METHODS))


def main() -> None:
    a = parse_sides(__doc__)
    if a.synthetic:
        report(a.domain, a.synthetic, "test", a.samples)
    if a.real:
        report("kitti", a.real, "train", a.samples)


if __name__ == "__main__":
    main()
