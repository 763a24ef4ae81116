"""Checks on what crosses a boundary: a method's forecast, an adapter's sweep."""

from __future__ import annotations

import numpy as np
from pcfbench.data import FLOAT32_MAX, Forecast, GroundTruth, Sample
from pcfbench.datacheck import check_points, check_rigid, validate_sweep
from pcfbench.errors import DataError, ForecastError

#: the sweep checks live in pcfbench.datacheck (the dataset layer reads them too); named here
#: as well, where the adapters and plugins have imported them from
__all__ = ["FORECAST_FLOOR", "FORECAST_RATIO", "GAP_PERIODS", "RATE_TOLERANCE", "check_forecast_size", "check_rigid",
           "check_sweep_times", "forecast_cap", "validate_forecast", "validate_sweep"]


def validate_forecast(sample: Sample, forecast: Forecast) -> Forecast:
    """Return the forecast with float32 arrays, or raise ForecastError naming sample and sweep."""
    if not isinstance(forecast, Forecast):
        raise ForecastError(f"sample {sample.sample_id}: method returned {type(forecast).__name__}, not a Forecast")
    F = sample.num_future
    if forecast.points_ref is None and forecast.depths is None:
        raise ForecastError(f"sample {sample.sample_id}: forecast has neither points nor depths")
    points = depths = None
    if forecast.points_ref is not None:
        if len(forecast.points_ref) != F:
            raise ForecastError(
                f"sample {sample.sample_id}: forecast has {len(forecast.points_ref)} point clouds, expected {F} future sweeps"
            )
        points = tuple(
            check_points(p, f"sample {sample.sample_id}, future sweep {k}", err=ForecastError)
            for k, p in enumerate(forecast.points_ref)
        )
    if forecast.depths is not None:
        if len(forecast.depths) != F:
            raise ForecastError(
                f"sample {sample.sample_id}: forecast has {len(forecast.depths)} depth arrays, expected {F} future sweeps"
            )
        checked = []
        for k, (d, q) in enumerate(zip(forecast.depths, sample.queries)):
            where = f"sample {sample.sample_id}, future sweep {k}"
            d = np.asarray(d)
            if d.dtype.kind not in "fiu":
                raise ForecastError(f"{where}: depths must be numeric, got dtype {d.dtype}")
            if d.shape != (len(q),):
                raise ForecastError(f"{where}: depths have shape {d.shape}, expected ({len(q)},) (one per query ray)")
            if not np.all(np.isfinite(d)):
                raise ForecastError(f"{where}: {int((~np.isfinite(d)).sum())} depth(s) are NaN or inf")
            if d.size and d.min() < 0:
                raise ForecastError(f"{where}: {int((d < 0).sum())} depth(s) are negative")
            if d.size and d.max() > FLOAT32_MAX:
                raise ForecastError(f"{where}: depths outside float32 range")
            checked.append(d.astype(np.float32, copy=False))
        depths = tuple(checked)
    return Forecast(points_ref=points, depths=depths)


#: the most points a forecast sweep may hold, as a multiple of its ground truth's point count
#: (``pcfbench run --max-forecast-ratio``): scoring time and memory grow with the forecast
FORECAST_RATIO = 8.0
#: ... but never fewer than this many points, so a sparse ground-truth sweep leaves room
FORECAST_FLOOR = 200_000


def forecast_cap(n_gt: int, ratio: float = FORECAST_RATIO) -> int:
    """The most points a forecast sweep whose ground truth has ``n_gt`` points may hold."""
    return max(int(ratio * n_gt), FORECAST_FLOOR)


def check_forecast_size(sample: Sample, truth: GroundTruth, forecast: Forecast, method: str,
                        ratio: float | None = FORECAST_RATIO) -> None:
    """Refuse (:class:`~pcfbench.errors.ForecastError`) a point forecast with a sweep over
    :func:`forecast_cap` points, naming the method, sample, sweep, count and cap, before it
    is scored. ``ratio`` None: no cap. Depth forecasts have one depth per query ray already."""
    if ratio is None or forecast.points_ref is None:
        return
    for k, (pred, gt) in enumerate(zip(forecast.points_ref, truth.future_points_ref)):
        cap = forecast_cap(int(gt.shape[0]), ratio)
        if pred.shape[0] > cap:
            raise ForecastError(
                f"method {method}, sample {sample.sample_id}, future sweep {k}: the forecast has {pred.shape[0]:,} "
                f"points, over the cap of {cap:,} ({ratio:g} x the ground truth's {gt.shape[0]:,} points, at least "
                f"{FORECAST_FLOOR:,}); scoring time grows with it. Raise the cap with --max-forecast-ratio "
                "(0: no cap)")


#: A gap between consecutive sweeps longer than this many nominal periods means at least one
#: sweep is missing: the sequence is refused (``check_sweep_times``).
GAP_PERIODS = 1.5
#: The median sweep period may differ from the nominal ``1 / rate_hz`` by this fraction.
RATE_TOLERANCE = 0.25


def check_sweep_times(timestamps_ns: np.ndarray, rate_hz: float, where: str) -> None:
    """Refuse sweep timestamps that would put a sample's sweeps at the wrong times.

    ``where`` names the file or sequence. Raises one ``DataError`` when the timestamps do not
    strictly increase, when the median period is not within ``RATE_TOLERANCE`` of
    ``1 / rate_hz`` (a 1 Hz ``times.txt`` read as a 10 Hz dataset), or when two consecutive
    sweeps are more than ``GAP_PERIODS`` periods apart (a sweep missing: every later sweep
    would be taken one step too early). A sequence with a gap is refused, never split: its
    sample ids would otherwise depend on where the gaps fall. Fewer than two sweeps pass.
    """
    ts = np.asarray(timestamps_ns, dtype=np.int64)
    if ts.size < 2:
        return
    dt = np.diff(ts)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0)) + 1
        raise DataError(f"{where}: sweep {i} has timestamp {ts[i]} ns, not after sweep {i - 1}'s {ts[i - 1]} ns "
                        "(expected strictly increasing timestamps)")
    period = 1.0 / float(rate_hz)
    median = float(np.median(dt)) / 1e9
    if abs(median / period - 1.0) > RATE_TOLERANCE:
        raise DataError(f"{where}: sweeps are {median:.4g} s apart ({1.0 / median:.3g} Hz), but the dataset is read at "
                        f"{rate_hz:g} Hz (expected a median period within {RATE_TOLERANCE:.0%} of {period:.4g} s)")
    gaps = np.flatnonzero(dt > GAP_PERIODS * period * 1e9)
    if gaps.size:
        i = int(gaps[0])
        more = f" (and {gaps.size - 1} more gap(s))" if gaps.size > 1 else ""
        raise DataError(f"{where}: {dt[i] / 1e9:.4g} s between sweep {i} ({ts[i]} ns) and sweep {i + 1} ({ts[i + 1]} ns), "
                        f"more than {GAP_PERIODS:g} periods at {rate_hz:g} Hz: a sweep is missing{more}. The sequence is "
                        "refused rather than read with its later sweeps shifted in time; restore the sweep, or cut the "
                        "sequence at the gap")
