"""Is the forecasting task real? Copy-last's error on moving agents vs on static structure.

The generator knows every point's class, so the ground-truth -> prediction half of the Chamfer
distance can be split by class: for each future ground-truth point, the squared distance to
the nearest point of copy-last's forecast (the t=0 sweep). A static world would make the two
groups alike apart from the ego motion's disocclusions; moving agents make theirs larger.

    python -m pcfbench.datasets.synthetic.analysis [synthetic-town] [kitti-1s] [--limit N]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from scipy.spatial import cKDTree

from pcfbench.geometry import transform_points
from pcfbench.plugins import get_setting
from pcfbench.protocol import MIN_RANGE_M, SampleBuilder
from pcfbench.datasets.synthetic.world import CLASS_NAMES, MOVING_CLASSES, STATIC_CLASSES

#: range bins (m, from the future sensor) for the range-matched comparison
RANGE_BINS = (0.0, 10.0, 20.0, 30.0, 50.0, 80.0, 130.0)


def read_labels(root, sequence: str, index: int) -> np.ndarray:
    from pathlib import Path

    return np.fromfile(Path(root) / "sequences" / sequence / "labels" / f"{index:06d}.label", dtype=np.uint32) & 0xFFFF


def copy_last_error_by_class(adapter, setting: str, split: str = "test", limit: int | None = None) -> dict:
    """Mean squared NN distance (m^2) of future GT points to copy-last's forecast, per class group."""
    s = get_setting(setting)
    builder = SampleBuilder(adapter, s)
    keys = builder.sample_keys(split)[:limit]
    nc = len(CLASS_NAMES)
    sums = np.zeros(nc)
    counts = np.zeros(nc)
    # per (range bin, class): to compare moving and static points at the same range
    bsums = np.zeros((len(RANGE_BINS) - 1, nc))
    bcounts = np.zeros((len(RANGE_BINS) - 1, nc))
    moving_d, static_d = [], []  # NN distances (static: every 10th point) for robust statistics
    is_moving = np.isin(np.arange(nc), MOVING_CLASSES)
    is_static = np.isin(np.arange(nc), STATIC_CLASSES)
    for seq_name, ref in keys:
        sample, _ = builder.build(seq_name, ref)
        tree = cKDTree(sample.past_points_ref[-1].astype(np.float64))
        seq = builder.sequence(seq_name)
        for j in range(s.future):
            i = ref + (j + 1) * s.stride
            pts = seq.load_points(i)
            lab = read_labels(adapter.root, seq_name, i)
            keep = ~adapter.ego_box.inside(pts) & (np.linalg.norm(pts, axis=1) > MIN_RANGE_M)
            gt = transform_points(sample.future_T_ref_sensor[j], pts[keep])
            d, _ = tree.query(gt.astype(np.float64), workers=-1)
            sums += np.bincount(lab[keep], weights=d * d, minlength=nc)
            counts += np.bincount(lab[keep], minlength=nc)
            moving_d.append(d[is_moving[lab[keep]]].astype(np.float32))
            static_d.append(d[is_static[lab[keep]]][::10].astype(np.float32))
            b = np.digitize(np.linalg.norm(pts[keep], axis=1), RANGE_BINS) - 1
            ok = (b >= 0) & (b < len(RANGE_BINS) - 1)
            flat = b[ok] * nc + lab[keep][ok].astype(np.int64)
            bsums += np.bincount(flat, weights=(d * d)[ok], minlength=bsums.size).reshape(bsums.shape)
            bcounts += np.bincount(flat, minlength=bsums.size).reshape(bsums.shape)

    def group(classes):
        n = counts[list(classes)].sum()
        return float(sums[list(classes)].sum() / n) if n else float("nan"), int(n)

    moving, n_moving = group(MOVING_CLASSES)
    static, n_static = group(STATIC_CLASSES)
    mv, st = list(MOVING_CLASSES), list(STATIC_CLASSES)
    bins = {}
    for k in range(len(RANGE_BINS) - 1):
        nm, ns = bcounts[k, mv].sum(), bcounts[k, st].sum()
        if nm and ns:
            bins[f"{RANGE_BINS[k]:g}-{RANGE_BINS[k + 1]:g} m"] = {
                "moving_m2": float(bsums[k, mv].sum() / nm), "static_m2": float(bsums[k, st].sum() / ns),
                "moving_points": int(nm)}
    # range-matched: static error re-weighted to the moving points' range distribution
    w = np.array([b["moving_points"] for b in bins.values()], float)
    matched_static = float(np.sum(w * [b["static_m2"] for b in bins.values()]) / w.sum()) if w.size else float("nan")
    matched_moving = float(np.sum(w * [b["moving_m2"] for b in bins.values()]) / w.sum()) if w.size else float("nan")
    per = {CLASS_NAMES[c]: float(sums[c] / counts[c]) for c in range(nc) if counts[c]}
    md = np.concatenate(moving_d) if moving_d else np.zeros(0)
    sd = np.concatenate(static_d) if static_d else np.zeros(0)

    def robust(x):
        return {"median_m": float(np.median(x)) if x.size else float("nan"),
                "frac_over_0.5m": float(np.mean(x > 0.5)) if x.size else float("nan")}
    return {
        "dataset": adapter.name, "setting": setting, "split": split, "samples": len(keys),
        "moving_m2": moving, "static_m2": static, "ratio": moving / static if static else float("nan"),
        "moving_points": n_moving, "static_points": n_static,
        "range_matched": {"moving_m2": matched_moving, "static_m2": matched_static,
                          "ratio": matched_moving / matched_static if matched_static else float("nan")},
        "moving_robust": robust(md), "static_robust": robust(sd),
        "vehicle_vs_parked_ratio": per.get("vehicle", np.nan) / per.get("parked-vehicle", np.nan),
        "per_class_m2": per,
        "per_range": bins,
    }


def main(argv: list[str] | None = None) -> None:
    from pcfbench.plugins import get_plugins

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", nargs="?", default="synthetic-town")
    p.add_argument("settings", nargs="*")
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--split", default="test")
    args = p.parse_args(argv)
    cls = get_plugins().datasets.get(args.dataset)
    adapter = cls(cls.default_root(progress=True))
    for setting in args.settings or cls.default_settings:
        print(json.dumps(copy_last_error_by_class(adapter, setting, args.split, args.limit), indent=1))


if __name__ == "__main__":
    main()
