"""Far views that close (docs/realism.md, "Reproduce"; the measurements that chose physics 10:
docs/journal/realism-2026-11.md, "Far views that close"): where copy-last's and 4docc's
near-field Chamfer comes from, and why the far points they keep are not seen a second later.

    # the split of chamfer_nf (every kitti-1s sample of the named sequences; all when none named)
    .venv/bin/python docs/experiments/realism_far_views.py split \\
        --dataset synthetic-town-realistic --split test --sequence 06
    .venv/bin/python docs/experiments/realism_far_views.py split \\
        --dataset kitti=../shared/realdata/kitti-seq00-frames040-099 --split train
    # why the far points of every second sweep pair 1 s apart close (--labels: a generated root)
    .venv/bin/python docs/experiments/realism_far_views.py why --dataset synthetic-town-realistic --split test --labels
    # a probe: the test split regenerated with town-style fields changed, into FOLDER
    .venv/bin/python docs/experiments/realism_far_views.py probe FOLDER --style '{"fence_prob": 1.0}'
    .venv/bin/python docs/experiments/realism_far_views.py probe FOLDER --yard-trees 12
    # physics 9's bare yards in physics 10's town: --yard-trees 0

``split`` prints, per method (copy-last, raycast-4docc, raycast-freespace), chamfer_nf as the
sum of three parts: forecast -> true for forecast points 40 m or more from the future sensor
and above z = -1.3 m in its frame, forecast -> true for the rest, and true -> forecast (each a
mean over sweeps of the ROI crops' mean squared distances, halved as the metric halves them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
from scipy.spatial import cKDTree

from pcfbench.datasets.realism import compare as C
from pcfbench.geometry import transform_points
from pcfbench.method import resolve_method
from pcfbench.plugins import get_setting
from pcfbench.protocol import SampleBuilder
from pcfbench.protocol import ROI
from pcfbench.protocol.validate import validate_forecast

METHODS = ("copy-last", "raycast-4docc", "raycast-freespace")


def forecasts_of(builder, keys, methods):
    """Per sample key: (sequence name, reference index, the sample, its truth, each method's
    validated forecast)."""
    for seq, ref in keys:
        sample, truth = builder.build(seq, ref)
        yield seq, ref, sample, truth, {m: validate_forecast(sample, x.forecast(sample.for_method()))
                                        for m, x in methods.items()}


def far_part(points_ref: np.ndarray, T_ref_future: np.ndarray) -> np.ndarray:
    """(N,) bool: 40 m or more horizontally from the future sensor, above z = -1.3 m in its frame."""
    p = transform_points(np.linalg.inv(T_ref_future), points_ref)
    return (np.hypot(p[:, 0], p[:, 1]) >= C.FAR_M) & (p[:, 2] > C.DRIFT_BELOW_M)


def split(spec: str, split_name: str, sequences: list[str]) -> None:
    name, root, ad = C.open_side(spec, progress=False)
    setting = get_setting("kitti-1s")
    builder = SampleBuilder(ad, setting)
    keys = [k for k in builder.sample_keys(split_name) if not sequences or k[0] in sequences]
    methods = {m: resolve_method(m).create() for m in METHODS}
    parts = {m: np.zeros(3) for m in METHODS}
    sweeps = 0
    for _, _, sample, truth, forecasts in forecasts_of(builder, keys, methods):
        for k in range(setting.future):
            G = ROI.crop(truth.future_points_ref[k])
            for m, fc in forecasts.items():
                P = ROI.crop(fc.points_ref[k])
                d_pg = cKDTree(G).query(P)[0] ** 2
                far = far_part(P, sample.future_T_ref_sensor[k])
                parts[m] += 0.5 * np.array([d_pg[far].sum() / len(P), d_pg[~far].sum() / len(P),
                                            (cKDTree(P).query(G)[0] ** 2).mean()])
            sweeps += 1
    print(f"== {name} {split_name} {','.join(sequences) or 'all'}: {len(keys)} samples, {sweeps} sweeps")
    print("method: chamfer_nf = forecast->true far + forecast->true rest + true->forecast (m^2)")
    for m, v in parts.items():
        v = v / sweeps
        print(f"{m:18s} {v.sum():.3f} = {v[0]:.3f} + {v[1]:.3f} + {v[2]:.3f}")


def why(spec: str, split_name: str, labels: bool) -> None:
    name, root, ad = C.open_side(spec, progress=False)
    if labels:
        from pcfbench.datasets.synthetic.world import CLASS_NAMES

        def lab(q, i, keep):
            return (np.fromfile(f"{root}/sequences/{q}/labels/{i:06d}.label", np.uint32) & 0xFFFF)[keep]
    kinds = dict.fromkeys(("occluded", "nothing in the bin", "farther", "about as far"), 0)
    occ_range, closing_cls, occ_cls = [], {}, {}
    by_azimuth = np.zeros(8)  # closing points by azimuth from the later sensor, 45-degree bins from -180
    judged = closing = 0
    for sp in C.split_list(split_name):
        for q in ad.sequence_names(sp):
            seq = ad.sequence(q)
            W = seq.T_world_sensor
            for i in range(0, len(seq) - 10, 2):
                j = C._sweep_at(seq.timestamps_ns, i, C.DRIFT_GAP_S)
                if j is None:
                    continue
                a_raw = np.asarray(seq.load_points(i), np.float64)
                ka = C._kept(ad, a_raw)
                a = a_raw[ka]
                b_raw = np.asarray(seq.load_points(j), np.float64)
                kb = ~ad.ego_box.inside(b_raw)
                T = np.linalg.inv(W[i]) @ W[j]
                b = transform_points(T, b_raw[kb])
                o = T[:3, 3]
                far = ROI.contains(a) & (np.hypot(a[:, 0] - o[0], a[:, 1] - o[1]) >= C.FAR_M) & (a[:, 2] > C.DRIFT_BELOW_M)
                d = cKDTree(b).query(a[far], distance_upper_bound=C.FAR_GONE_M)[0]
                gone = np.flatnonzero(far)[np.isinf(d)]
                judged += int(far.sum())
                closing += len(gone)
                # directions from the later sensor, in its frame: the later sweep's nearest return there
                R = T[:3, :3].T

                def angles(p):
                    v = (p - o) @ R.T
                    return (np.degrees(np.arctan2(v[:, 1], v[:, 0])) / C.FREE_AZ_DEG,
                            np.degrees(np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))) / C.FREE_EL_DEG,
                            np.linalg.norm(v, axis=1))
                az_b, el_b, r_b = angles(b)
                az_c, el_c, r_c = angles(a[gone])
                by_azimuth += np.histogram(az_c * C.FREE_AZ_DEG, bins=8, range=(-180.0, 180.0))[0]
                dist, idx = cKDTree(np.stack([az_b, el_b], 1)).query(np.stack([az_c, el_c], 1), k=4,
                                                                     distance_upper_bound=1.5)
                lb = lab(q, j, kb) if labels else None
                if labels:
                    for c in lab(q, i, ka)[gone]:
                        closing_cls[CLASS_NAMES[c]] = closing_cls.get(CLASS_NAMES[c], 0) + 1
                for row_d, row_i, rc in zip(dist, idx, r_c):
                    ok = np.isfinite(row_d)
                    if not ok.any():
                        kinds["nothing in the bin"] += 1
                        continue
                    nearest = row_i[ok][np.argmin(r_b[row_i[ok]])]
                    if r_b[nearest] < rc - C.FAR_GONE_M:
                        kinds["occluded"] += 1
                        occ_range.append(r_b[nearest])
                        if labels:
                            occ_cls[CLASS_NAMES[lb[nearest]]] = occ_cls.get(CLASS_NAMES[lb[nearest]], 0) + 1
                    else:
                        kinds["farther" if r_b[nearest] > rc + C.FAR_GONE_M else "about as far"] += 1
    print(f"== {name} {split_name}: far points {judged}, closing {closing} ({closing / max(judged, 1):.3f})")
    print("  why:", {k: round(v / max(closing, 1), 3) for k, v in kinds.items()})
    if occ_range:
        print("  occluder range, 10/50/90 %:", np.quantile(occ_range, [0.1, 0.5, 0.9]).round(1))
    print("  closing points by azimuth from the later sensor (0 ahead, 90 left; 45-degree bins from -180):",
          (by_azimuth / max(closing, 1)).round(2))
    for title, counts in (("closing points' class", closing_cls), ("occluders' class", occ_cls)):
        if counts:
            tot = sum(counts.values())
            print(f"  {title}:", {k: round(v / tot, 3) for k, v in sorted(counts.items(), key=lambda x: -x[1])})


def probe(out: str, style: dict, trees: float | None = None, splits: tuple[str, ...] = ("test",)) -> None:
    """The realistic town's ``splits`` regenerated into ``out`` with town-style fields changed
    and, where ``trees`` is given, that many yard trees per 100 m of frontage (physics 10's
    ``yard_trees_per_100m``; 0: physics 9's bare yards). The manifest names the domain's own
    physics version: read the folder as a probe, not as that physics."""
    from pcfbench.datasets.synthetic.domains import get_domain
    from pcfbench.datasets.synthetic.generate import generate_domain

    d = get_domain("synthetic-town-realistic")
    d = dataclasses.replace(d, style=dataclasses.replace(
        d.style, **{k: tuple(v) if isinstance(v, list) else v for k, v in style.items()}))
    if trees is not None:
        d = dataclasses.replace(d, realism=dataclasses.replace(d.realism, yard_trees_per_100m=trees))
    m = generate_domain(d, out, progress=False, splits=splits)
    print(f"generated {out} in {m['seconds']:.1f} s; read it as synthetic-town-realistic={out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("split")
    a.add_argument("--dataset", required=True, help="NAME[=ROOT]")
    a.add_argument("--split", required=True)
    a.add_argument("--sequence", action="append", default=[])
    b = sub.add_parser("why")
    b.add_argument("--dataset", required=True, help="NAME[=ROOT]")
    b.add_argument("--split", required=True)
    b.add_argument("--labels", action="store_true")
    c = sub.add_parser("probe")
    c.add_argument("out")
    c.add_argument("--style", default="{}", help="JSON of TownStyle fields")
    c.add_argument("--yard-trees", type=float, default=None,
                   help="trees per 100 m of frontage in the yards behind (default: the physics's own; 0: none)")
    c.add_argument("--splits", default="test", help="splits to generate, comma-separated (train,val,test: every town)")
    args = ap.parse_args()
    if args.cmd == "split":
        split(args.dataset, args.split, args.sequence)
    elif args.cmd == "why":
        why(args.dataset, args.split, args.labels)
    else:
        probe(args.out, json.loads(args.style), args.yard_trees, tuple(args.splits.split(",")))


if __name__ == "__main__":
    main()
