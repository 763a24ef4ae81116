"""Slow, obviously-correct float64 references of every metric, for tests only.

Brute force everywhere: no spatial index, nearest neighbours by scanning all candidates in
chunks (O(N*M) time, bounded memory), the ROI clamp by a per-ray scalar slab walk written
independently of pcfbench.boxes. Each function takes plain arrays and returns the per-sweep value
with the same empty-input policy as the fast metric (NaN = skipped).
"""

from __future__ import annotations

import math

import numpy as np

from pcfbench.protocol import ROI
from pcfbench.boxes import Box

MIN_RANGE = 0.01
NAN = float("nan")
_CHUNK = 256


def nn_sq_dists(query: np.ndarray, target: np.ndarray) -> np.ndarray:
    """min over target of |q - t|^2 for each query (float64, brute force)."""
    q = np.asarray(query, np.float64)
    t = np.asarray(target, np.float64)
    out = np.empty(len(q))
    for i in range(0, len(q), _CHUNK):
        d = q[i : i + _CHUNK, None, :] - t[None, :, :]
        out[i : i + _CHUNK] = (d * d).sum(axis=2).min(axis=1)
    return out


def chamfer(pred: np.ndarray, gt: np.ndarray) -> float:
    if len(pred) == 0 or len(gt) == 0:
        return NAN
    return 0.5 * (nn_sq_dists(pred, gt).mean() + nn_sq_dists(gt, pred).mean())


def in_box(points: np.ndarray, box: Box = ROI) -> np.ndarray:
    p = np.asarray(points, np.float64)
    keep = np.ones(len(p), bool)
    for a in range(3):
        keep &= (p[:, a] >= box.lo[a]) & (p[:, a] <= box.hi[a])
    return keep


def chamfer_nf(pred: np.ndarray, gt: np.ndarray, box: Box = ROI, empty_scores_zero: bool = False) -> float:
    if len(gt) == 0:
        return NAN
    p, g = pred[in_box(pred, box)], gt[in_box(gt, box)]
    if len(p) == 0 or len(g) == 0:
        return 0.0 if empty_scores_zero else NAN
    return chamfer(p, g)


def segment_in_box(o, u, box: Box = ROI) -> tuple[float, float] | None:
    """[t0, t1] of the ray o + t u (t >= 0) inside the box, by a scalar slab walk; None if it misses."""
    t0, t1 = 0.0, math.inf
    for a in range(3):
        lo, hi = box.lo[a], box.hi[a]
        if u[a] == 0.0:
            if o[a] < lo or o[a] > hi:
                return None
            continue
        ta, tb = (lo - o[a]) / u[a], (hi - o[a]) / u[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return (t0, t1) if t0 <= t1 else None


def _angle_4docc(v) -> tuple[float, float]:
    return math.atan2(v[0], v[1]), math.atan2(v[2], v[1])


def _angle_az_el(v) -> tuple[float, float]:
    return math.atan2(v[1], v[0]), math.atan2(v[2], math.hypot(v[0], v[1]))


def nearest_in_angle(pred_rel: np.ndarray, gt_rel: np.ndarray, space: str) -> np.ndarray:
    """Index of the predicted point nearest to each ground-truth ray, brute force."""
    f = _angle_4docc if space == "4docc" else _angle_az_el
    pa = np.array([f(v) for v in pred_rel], np.float64).reshape(-1, 2)
    ga = np.array([f(v) for v in gt_rel], np.float64).reshape(-1, 2)
    out = np.empty(len(ga), np.int64)
    for i, (a, e) in enumerate(ga):
        da = np.abs(pa[:, 0] - a)
        if space != "4docc":
            da = np.minimum(da, 2 * math.pi - da)
        out[i] = int(np.argmin(da * da + (pa[:, 1] - e) ** 2))
    return out


def ray_errors(gt, origin, pred=None, depths=None, space="wrapped", box: Box = ROI):
    """(errors, absrels, n_gt_rays_over_1cm) of the kept rays; None errors for an empty prediction."""
    g = np.asarray(gt, np.float64)
    o = np.asarray(origin, np.float64)
    rel = g - o
    rng = np.sqrt((rel * rel).sum(axis=1))
    n_denom = int((rng > MIN_RANGE).sum())
    if depths is not None:
        d_pred = np.asarray(depths, np.float64)
    else:
        p_rel = np.asarray(pred, np.float64) - o
        if len(p_rel) == 0:
            return None, None, n_denom
        idx = nearest_in_angle(p_rel, rel, space)
        d_pred = np.sqrt((p_rel * p_rel).sum(axis=1))[idx]
    errs, rels = [], []
    for i in range(len(g)):
        if rng[i] == 0:
            continue
        u = rel[i] / rng[i]
        seg = segment_in_box(o, u, box)
        if seg is None:
            continue
        t0, t1 = seg
        gc = min(max(rng[i], t0), t1)
        pc = min(max(d_pred[i], t0), t1)
        if gc - t0 <= MIN_RANGE:
            continue
        g_point, p_point, o_point = o + gc * u, o + pc * u, o + t0 * u
        err = float(np.linalg.norm(g_point - p_point))
        errs.append(err)
        rels.append(err / float(np.linalg.norm(g_point - o_point)))
    return np.array(errs), np.array(rels), n_denom


def depth_metrics(gt, origin, pred=None, depths=None) -> dict[str, float]:
    """Every L1/AbsRel metric of one sweep, by name."""
    out: dict[str, float] = {}
    if len(gt) == 0:
        return {k: NAN for k in ("l1@4docc", "absrel@4docc", "l1_mean", "absrel_mean", "l1_median",
                                 "absrel_median", "l1_ray", "absrel_ray")}
    e4, r4, n = ray_errors(gt, origin, pred, depths, "4docc")
    out["l1@4docc"] = NAN if e4 is None or n == 0 else float(e4.sum()) / n
    out["absrel@4docc"] = NAN if e4 is None or n == 0 else float(r4.sum()) / n
    e, r, _ = ray_errors(gt, origin, pred, depths, "wrapped")
    ok = e is not None and len(e) > 0
    out["l1_mean"] = float(np.mean(e)) if ok else NAN
    out["absrel_mean"] = float(np.mean(r)) if ok else NAN
    out["l1_median"] = float(np.median(e)) if ok else NAN
    out["absrel_median"] = float(np.median(r)) if ok else NAN
    if depths is None:
        out["l1_ray"] = out["absrel_ray"] = NAN
    else:
        d_gt = np.linalg.norm(np.asarray(gt, np.float64) - np.asarray(origin, np.float64), axis=1)
        err = np.abs(d_gt - np.asarray(depths, np.float64))
        out["l1_ray"] = float(err.mean())
        out["absrel_ray"] = float((err[d_gt > 0] / d_gt[d_gt > 0]).mean()) if (d_gt > 0).any() else NAN
    return out


def all_metrics(gt, origin, pred=None, depths=None) -> dict[str, float]:
    """Every registered metric of one sweep; ``pred`` may be derived from depths by the caller."""
    out = {
        "chamfer": NAN if len(gt) == 0 else chamfer(pred, gt),
        "chamfer_nf": chamfer_nf(pred, gt),
        "chamfer_nf@4docc": chamfer_nf(pred, gt, empty_scores_zero=True),
    }
    out.update(depth_metrics(gt, origin, pred=None if depths is not None else pred, depths=depths))
    return out
