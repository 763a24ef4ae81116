"""Chamfer distances (PROTOCOL.md section 4): CD on whole sweeps, NFCD on ROI crops."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bench.metrics.base import Metric, SweepContext


def nn_sq_dist(query: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Squared distance from each query point to its nearest target point (float64)."""
    tree = cKDTree(np.asarray(target, dtype=np.float64))
    d, _ = tree.query(np.asarray(query, dtype=np.float64), k=1, workers=-1)
    return d * d


def chamfer_value(pred: np.ndarray, gt: np.ndarray) -> float:
    """0.5 * (mean_p min_g |p-g|^2 + mean_g min_p |g-p|^2); NaN if either cloud is empty."""
    if pred.shape[0] == 0 or gt.shape[0] == 0:
        return float("nan")
    return 0.5 * (float(nn_sq_dist(pred, gt).mean()) + float(nn_sq_dist(gt, pred).mean()))


def _chamfer(ctx: SweepContext) -> float:
    return chamfer_value(ctx.pred_points, ctx.gt_points)


def _chamfer_nf(ctx: SweepContext) -> float:
    return chamfer_value(ctx.pred_roi, ctx.gt_roi)


CHAMFER = Metric(
    name="chamfer",
    version="1",
    fn=_chamfer,
    description="Chamfer distance (CD), m^2: mean squared NN distance each way, averaged; no crop",
    reference="4D-Occ (Khurana et al. 2023), PROTOCOL.md section 4",
    unit="m^2",
    empty_policy="empty prediction: sweep skipped (NaN, counted)",
)

CHAMFER_NF = Metric(
    name="chamfer_nf",
    version="1",
    fn=_chamfer_nf,
    description="Near-field Chamfer (NFCD), m^2: CD after cropping P and G to the ROI independently",
    reference="4D-Occ, Copilot4D tables' 'Chamfer' column; corrected empty policy",
    unit="m^2",
    empty_policy="empty crop of P or G: sweep skipped (NaN, counted)",
)
