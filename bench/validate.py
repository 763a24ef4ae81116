"""Checks on what crosses a boundary: a method's forecast, an adapter's sweep."""

from __future__ import annotations

import numpy as np

from pcfbench.data import FLOAT32_MAX, Forecast, Sample, Sweep
from pcfbench.errors import DataError, ForecastError
from pcfbench.geometry import is_se3


def _check_points(arr, where: str, err=ForecastError) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype.kind != "f":
        raise err(f"{where}: points must be floating point, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise err(f"{where}: points must have shape (N, 3), got {arr.shape}")
    finite = np.isfinite(arr)
    if not finite.all():
        bad = int((~finite.all(axis=1)).sum())
        raise err(f"{where}: {bad} point(s) with NaN or inf coordinates")
    if arr.size and np.abs(arr).max() > FLOAT32_MAX:
        raise err(f"{where}: coordinates outside float32 range")
    return arr.astype(np.float32, copy=False)


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
            _check_points(p, f"sample {sample.sample_id}, future sweep {k}") for k, p in enumerate(forecast.points_ref)
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


def validate_sweep(sweep: Sweep, where: str | None = None) -> Sweep:
    """The sweep with float32 points, or DataError naming ``where`` (default: its source)
    when the points or the pose break the contract."""
    where = where or sweep.source or "sweep"
    pts = _check_points(sweep.points_sensor, where, err=DataError)
    if not is_se3(sweep.T_world_sensor, atol=1e-4):
        raise DataError(f"{where}: pose is not a finite rigid 4x4 transform")
    return sweep if pts is sweep.points_sensor else Sweep(pts, sweep.T_world_sensor, sweep.timestamp_ns, sweep.intensity, sweep.source)
