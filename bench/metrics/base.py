"""The metric contract and the per-sweep context metrics share their work through."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np

from bench.data import Forecast, GroundTruth, RayQuery, Sample
from bench.roi import ROI, Box


@dataclass(frozen=True)
class Metric:
    """A per-(sample, future sweep) metric.

    ``fn(ctx)`` returns a float, or NaN when the sweep is skipped under the metric's empty
    policy (skipped sweeps are counted, never averaged). ``version`` changes whenever what
    the metric computes changes.
    """

    name: str
    version: str
    fn: Callable[["SweepContext"], float]
    description: str
    reference: str = ""
    unit: str = ""
    empty_policy: str = ""
    #: "points", "depths" or "either": what the forecast must carry for this metric.
    needs: str = "either"

    def __call__(self, ctx: "SweepContext") -> float:
        return float(self.fn(ctx))


class SweepContext:
    """One future sweep to score: prediction, ground truth and the query rays, reference frame.

    Derived quantities (crops, nearest-neighbour distances, clamped ranges) are cached, so a
    suite of metrics pays for each only once.
    """

    def __init__(
        self,
        gt_points: np.ndarray,
        query: RayQuery,
        pred_points: np.ndarray | None,
        pred_depths: np.ndarray | None,
        roi: Box = ROI,
    ) -> None:
        self.gt_points = gt_points  # (M, 3) float32, reference frame
        self.query = query
        self.origin = np.asarray(query.origin_ref, dtype=np.float64)
        self.pred_depths = pred_depths  # (M,) or None
        self._pred_points = pred_points  # (K, 3) or None
        self.roi = roi

    @cached_property
    def pred_points(self) -> np.ndarray:
        """Predicted points; from depths along the query rays when only depths were given."""
        if self._pred_points is not None:
            return self._pred_points
        d = self.pred_depths.astype(np.float64)[:, None]
        return (self.origin + self.query.directions_ref.astype(np.float64) * d).astype(np.float32)

    @cached_property
    def gt_ranges(self) -> np.ndarray:
        """(M,) float64 distance of each ground-truth point from the sweep origin."""
        return np.linalg.norm(self.gt_points.astype(np.float64) - self.origin, axis=1)

    @cached_property
    def gt_roi(self) -> np.ndarray:
        return self.roi.crop(self.gt_points)

    @cached_property
    def pred_roi(self) -> np.ndarray:
        return self.roi.crop(self.pred_points)


def score_sample(
    sample: Sample, truth: GroundTruth, forecast: Forecast, metrics: list[Metric]
) -> list[dict[str, float | int]]:
    """Score every future sweep of a validated forecast: one row per sweep with every metric."""
    rows = []
    for k, query in enumerate(sample.queries):
        gt = truth.future_points_ref[k]
        ctx = SweepContext(
            gt_points=gt,
            query=query,
            pred_points=forecast.points_ref[k] if forecast.points_ref is not None else None,
            pred_depths=forecast.depths[k] if forecast.depths is not None else None,
        )
        row: dict[str, float | int] = {"step": k, "n_gt": int(gt.shape[0]), "n_pred": int(ctx.pred_points.shape[0])}
        for metric in metrics:
            if gt.shape[0] == 0:
                row[metric.name] = float("nan")  # sweeps without ground truth are skipped
            elif metric.needs == "depths" and forecast.depths is None:
                row[metric.name] = float("nan")
            else:
                row[metric.name] = metric(ctx)
        rows.append(row)
    return rows
