"""Chamfer distances (docs/protocol.md section 4): CD on whole sweeps, NFCD on ROI crops."""

from __future__ import annotations

import numpy as np

from pcfbench.metrics.base import NN, Metric, SweepContext
from pcfbench.metrics.nn import nn_sq_dist

__all__ = ["CHAMFER", "CHAMFER_NF", "CHAMFER_NF_4DOCC", "chamfer_value", "nn_sq_dist"]


def chamfer_value(pred: np.ndarray, gt: np.ndarray) -> float:
    """0.5 * (mean_p min_g |p-g|^2 + mean_g min_p |g-p|^2); NaN if either cloud is empty."""
    if pred.shape[0] == 0 or gt.shape[0] == 0:
        return float("nan")
    return 0.5 * (float(nn_sq_dist(pred, gt).mean()) + float(nn_sq_dist(gt, pred).mean()))


def _chamfer(ctx: SweepContext) -> float:
    if ctx.pred_points.shape[0] == 0 or ctx.gt_points.shape[0] == 0:
        return float("nan")
    return 0.5 * (float(ctx.nn_pred_to_gt[0].mean()) + float(ctx.nn_gt_to_pred[0].mean()))


def _chamfer_nf_or_none(ctx: SweepContext) -> float | None:
    """NFCD, or None when the crop of P or of G is empty."""
    if not ctx.crops_hold_points:
        return None
    return 0.5 * (float(ctx.nn_pred_to_gt_roi.mean()) + float(ctx.nn_gt_to_pred_roi.mean()))


def _chamfer_nf(ctx: SweepContext) -> float:
    v = _chamfer_nf_or_none(ctx)
    return float("nan") if v is None else v


def _chamfer_nf_4docc(ctx: SweepContext) -> float:
    if ctx.gt_points.shape[0] == 0:
        return float("nan")  # sweeps without ground truth are skipped by every metric
    v = _chamfer_nf_or_none(ctx)
    return 0.0 if v is None else v


CHAMFER = Metric(
    name="chamfer",
    version="1",
    fn=_chamfer,
    description="Chamfer distance (CD): mean squared NN distance each way, the two means averaged; no crop",
    reference="4D-Occ (Khurana et al. 2023), docs/protocol.md section 4",
    unit="m^2",
    higher_is_better=False,
    searches={NN},
    empty_policy="empty prediction: sweep skipped (NaN, counted)",
)

CHAMFER_NF = Metric(
    name="chamfer_nf",
    version="1",
    fn=_chamfer_nf,
    description="Near-field Chamfer (NFCD): CD after cropping P and G to the ROI independently",
    reference="published tables' 'Chamfer' column (4D-Occ, Copilot4D); corrected empty policy",
    unit="m^2",
    higher_is_better=False,
    searches={NN},
    empty_policy="empty crop of P or G: sweep skipped (NaN, counted)",
)

CHAMFER_NF_4DOCC = Metric(
    name="chamfer_nf@4docc",
    version="1",
    fn=_chamfer_nf_4docc,
    description="NFCD as the 4D-Occ reference code averages it: an empty crop scores 0 and counts",
    reference="4D-Occ reference evaluation code (Khurana et al. 2023)",
    unit="m^2",
    higher_is_better=False,
    searches={NN},
    empty_policy="empty crop of P or G: 0, counted in the mean",
)
