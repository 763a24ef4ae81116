"""Where the casters' Chamfer comes from, on a generated domain and on real sweeps (docs/realism.md,
"Mixed pixels"): for evenly spaced kitti-1s samples, each future sweep's squared nearest-neighbour
distances (true -> forecast and forecast -> true, inside the ROI) summed by the point's range from
the future sensor (0-10, 10-20, 20-40, 40+ m) and whether it lies more than 1.3 m below the sensor
(ground), as a share of that sweep's points, then averaged over sweeps. With ``--labels`` (a
generated root), the true -> forecast half is also split by the labelled class of each true point
(the label of its nearest raw point of that sweep).

    .venv/bin/python docs/experiments/realism_chamfer_split.py \\
        --synthetic FOLDER --real ../shared/realdata/kitti-seq00-frames040-099 --samples 12 --labels

FOLDER: a generated test split (e.g. ``generate_domain(get_domain("synthetic-town-realistic"),
FOLDER, splits=("test",))``). It runs raycast-voxel, raycast-zbuffer and raycast-freespace.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

from pcfbench import roi as roimod
from pcfbench.geometry import transform_points
from pcfbench.method import resolve_method
from pcfbench.plugins import get_plugins
from pcfbench.protocol import SampleBuilder, get_setting
from pcfbench.validate import validate_forecast

METHODS = ("raycast-voxel", "raycast-zbuffer", "raycast-freespace")
BANDS = (10.0, 20.0, 40.0)
GROUPS = [f"{b} {g}" for b in ("0-10", "10-20", "20-40", "40+") for g in ("above", "ground")]


def group_of(points_ref: np.ndarray, T_ref_future: np.ndarray) -> np.ndarray:
    p = transform_points(np.linalg.inv(T_ref_future), points_ref)
    band = np.digitize(np.linalg.norm(p[:, :2], axis=1), BANDS)
    return band * 2 + (p[:, 2] < -1.3)


def evenly_spaced(dataset: str, root: str, split_name: str, samples: int, method_names=METHODS):
    """(adapter, the kitti-1s setting, its sample builder, ``samples`` sample keys spread evenly
    over the split, the methods by name): what each of these realism scripts starts from."""
    ad = get_plugins().datasets.get(dataset)(root)
    setting = get_setting("kitti-1s")
    builder = SampleBuilder(ad, setting)
    keys = builder.sample_keys(split_name)
    keys = [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, samples).round().astype(int))]
    return ad, setting, builder, keys, {m: resolve_method(m).create() for m in method_names}


def forecasts_of(builder, keys, methods):
    """Per sample key: (sequence name, reference index, the sample, its truth, each method's
    validated forecast)."""
    for seq, ref in keys:
        sample, truth = builder.build(seq, ref)
        yield seq, ref, sample, truth, {m: validate_forecast(sample, x.forecast(sample.for_method()))
                                        for m, x in methods.items()}


def nearest_labels(sequence, root: str, seq: str, ref: int, j: int, points_ref: np.ndarray) -> np.ndarray:
    """The label (class id) of the raw point of generated sweep ``j`` nearest to each of
    ``points_ref`` (in sweep ``ref``'s frame)."""
    raw = transform_points(np.linalg.inv(sequence.T_world_sensor[ref]) @ sequence.T_world_sensor[j],
                           np.asarray(sequence.load_points(j), np.float64))
    lab = np.fromfile(f"{root}/sequences/{seq}/labels/{j:06d}.label", np.uint32) & 0xFFFF
    return lab[cKDTree(raw).query(points_ref)[1]]


def run_sides(doc: str, measure) -> None:
    """Parse the shared command line and run ``measure(dataset, root, split, samples, labels)``
    on the generated side (split test) and the real one (split train, no labels)."""
    a = parse_sides(doc, labels=True)
    if a.synthetic:
        measure(a.domain, a.synthetic, "test", a.samples, a.labels)
    if a.real:
        measure("kitti", a.real, "train", a.samples, False)


def split(dataset: str, root: str, split_name: str, samples: int, labels: bool) -> None:
    ad, setting, builder, keys, methods = evenly_spaced(dataset, root, split_name, samples)
    gp = {m: np.zeros(len(GROUPS)) for m in methods}
    pg = {m: np.zeros(len(GROUPS)) for m in methods}
    n_cls = 16
    by_cls = {m: np.zeros((n_cls, len(BANDS) + 1)) for m in methods}
    share_cls = np.zeros((n_cls, len(BANDS) + 1))
    sweeps = 0
    for seq, ref, sample, truth, forecasts in forecasts_of(builder, keys, methods):
        sequence = ad.sequence(seq)
        for k in range(setting.future):
            T_f = sample.future_T_ref_sensor[k]
            G = roimod.ROI.crop(truth.future_points_ref[k])
            g_of_G = group_of(G, T_f)
            cls = None
            if labels:
                j = ref + (k + 1) * setting.stride
                cls = np.minimum(nearest_labels(sequence, root, seq, ref, j, G), n_cls - 1)
                np.add.at(share_cls, (cls, g_of_G // 2), 1.0 / len(G))
            for m, fc in forecasts.items():
                P = roimod.ROI.crop(fc.points_ref[k])
                d_gp = cKDTree(P).query(G)[0] ** 2
                d_pg = cKDTree(G).query(P)[0] ** 2
                gp[m] += np.bincount(g_of_G, weights=d_gp, minlength=len(GROUPS)) / len(G)
                pg[m] += np.bincount(group_of(P, T_f), weights=d_pg, minlength=len(GROUPS)) / len(P)
                if cls is not None:
                    np.add.at(by_cls[m], (cls, g_of_G // 2), d_gp / len(G))
            sweeps += 1
    print(f"== {dataset} ({root}), {len(keys)} samples, {sweeps} sweeps; m^2, mean over sweeps")
    print("groups: " + ", ".join(GROUPS))
    for m in methods:
        print(f"{m:18s} sum {(gp[m].sum() + pg[m].sum()) / sweeps:.3f}")
        print("  true -> forecast " + " ".join(f"{v / sweeps:.3f}" for v in gp[m]))
        print("  forecast -> true " + " ".join(f"{v / sweeps:.3f}" for v in pg[m]))
    if labels:
        from pcfbench.datasets.synthetic.world import CLASS_NAMES

        print("true -> forecast by labelled class, range bands 0-10 / 10-20 / 20-40 / 40+ m "
              "(share of the true points, then each method's m^2)")
        for c in range(n_cls):
            if share_cls[c].sum() / sweeps < 0.002:
                continue
            name = CLASS_NAMES[c] if c < len(CLASS_NAMES) else str(c)
            print(f"{name:15s} points " + " ".join(f"{v / sweeps:.3f}" for v in share_cls[c]) + " | "
                  + " | ".join(f"{m[8:]} " + " ".join(f"{v / sweeps:.3f}" for v in by_cls[m][c]) for m in methods))


def parse_sides(doc: str, labels: bool = False) -> argparse.Namespace:
    """The command line these realism scripts share: a generated split and / or a KITTI root."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--synthetic", help="a generated synthetic-town-realistic test split (folder)")
    ap.add_argument("--domain", default="synthetic-town-realistic")
    ap.add_argument("--real", help="a KITTI root (split train)")
    ap.add_argument("--samples", type=int, default=12)
    if labels:
        ap.add_argument("--labels", action="store_true", help="also split the generated side by labelled class")
    return ap.parse_args()


def main() -> None:
    run_sides(__doc__, split)


if __name__ == "__main__":
    main()
