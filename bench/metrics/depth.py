"""Depth errors along the ground-truth rays (docs/protocol.md section 4): L1 and AbsRel.

Every ground-truth ray from the sweep origin ``o`` to a point ``g`` gets a predicted depth (the
forecast's per-ray depth, or the range of the predicted point nearest in angle space), both
points are clamped to the ROI along the ray, and ``err = |g_c - p_c|``,
``absrel = err / |g_c - o_c|``. Rays missing the ROI or with clamped ground-truth range
<= 1 cm are dropped. The shared work lives in SweepContext (bench/metrics/base.py).
"""

from __future__ import annotations

import numpy as np

from pcfbench.kinds import Needs
from pcfbench.metrics.base import ANGLES, Metric, SweepContext

NAN = float("nan")


def _denominator_4docc(ctx: SweepContext) -> int:
    """The reference code's denominator: ground-truth rays with range > 1 cm, before dropping."""
    return int(np.count_nonzero(ctx.gt_ranges > ctx.min_range_m))


def _sum_4docc(ctx: SweepContext, which: int) -> float:
    errs = ctx.ray_errors_4docc
    n = _denominator_4docc(ctx)
    if errs is None or n == 0:
        return NAN
    return float(np.sum(errs[which])) / n


def _mean(ctx: SweepContext, which: int) -> float:
    errs = ctx.ray_errors_wrapped
    if errs is None or errs[which].size == 0:
        return NAN
    return float(np.mean(errs[which]))


def _median(ctx: SweepContext, which: int) -> float:
    medians = ctx.ray_error_medians
    return NAN if medians is None else medians[which]


def _ray(ctx: SweepContext, relative: bool) -> float:
    if ctx.pred_depths is None or ctx.gt_points.shape[0] == 0:
        return NAN
    d_gt = ctx.gt_ranges
    err = np.abs(d_gt - ctx.pred_depths.astype(np.float64))
    if not relative:
        return float(np.mean(err))
    pos = d_gt > 0
    return float(np.mean(err[pos] / d_gt[pos])) if pos.any() else NAN


_REF_4DOCC = "4D-Occ reference evaluation code (Khurana et al. 2023), docs/protocol.md section 4"
_REF = "docs/protocol.md section 4 (corrected: true azimuth/elevation, azimuth wrap-around)"
_EMPTY = "empty prediction: sweep skipped (NaN, counted)"

L1_4DOCC = Metric(
    name="l1@4docc", version="1", fn=lambda c: _sum_4docc(c, 0), unit="m", reference=_REF_4DOCC,
    higher_is_better=False, searches={ANGLES},
    description="L1 depth error, NN in angle space (atan2(x,y), atan2(z,y)), ROI-clamped; sum over kept rays "
    "/ number of GT rays with range > 1 cm",
    empty_policy=_EMPTY + "; no kept ray: 0",
)
ABSREL_4DOCC = Metric(
    name="absrel@4docc", version="1", fn=lambda c: _sum_4docc(c, 1), unit="fraction", reference=_REF_4DOCC,
    higher_is_better=False, searches={ANGLES},
    description="AbsRel |g_c - p_c| / |g_c - o_c|, as l1@4docc",
    empty_policy=_EMPTY + "; no kept ray: 0",
)
L1_MEAN = Metric(
    name="l1_mean", version="1", fn=lambda c: _mean(c, 0), unit="m", reference=_REF,
    higher_is_better=False, searches={ANGLES},
    description="L1 depth error, NN in (azimuth, elevation) with wrap-around, ROI-clamped; mean over kept rays",
    empty_policy=_EMPTY + "; no kept ray: skipped",
)
ABSREL_MEAN = Metric(
    name="absrel_mean", version="1", fn=lambda c: _mean(c, 1), unit="fraction", reference=_REF,
    higher_is_better=False, searches={ANGLES},
    description="AbsRel, as l1_mean",
    empty_policy=_EMPTY + "; no kept ray: skipped",
)
L1_MEDIAN = Metric(
    name="l1_median", version="1", fn=lambda c: _median(c, 0), unit="m", reference=_REF,
    higher_is_better=False, searches={ANGLES},
    description="L1 depth error as l1_mean, median over the kept rays of the sweep ('L1 Med')",
    empty_policy=_EMPTY + "; no kept ray: skipped",
)
ABSREL_MEDIAN = Metric(
    name="absrel_median", version="1", fn=lambda c: _median(c, 1), unit="fraction", reference=_REF,
    higher_is_better=False, searches={ANGLES},
    description="AbsRel as absrel_mean, median over the kept rays of the sweep ('AbsRel Med')",
    empty_policy=_EMPTY + "; no kept ray: skipped",
)
L1_RAY = Metric(
    name="l1_ray", version="1", fn=lambda c: _ray(c, False), unit="m", needs=Needs.DEPTHS,
    higher_is_better=False,
    reference="Argoverse 2 LiDAR forecasting challenge kit, docs/protocol.md section 4",
    description="ray-query mode: mean |d_gt - d_pred| over all query rays, no clamping",
    empty_policy="forecast without depths: skipped (NaN, counted)",
)
ABSREL_RAY = Metric(
    name="absrel_ray", version="1", fn=lambda c: _ray(c, True), unit="fraction", needs=Needs.DEPTHS,
    higher_is_better=False,
    reference="Argoverse 2 LiDAR forecasting challenge kit, docs/protocol.md section 4",
    description="ray-query mode: mean |d_gt - d_pred| / d_gt over all query rays, no clamping",
    empty_policy="forecast without depths: skipped (NaN, counted)",
)
