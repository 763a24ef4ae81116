"""A kit for plugin authors: a toy world, an in-memory dataset and contract checks.

    from pcfbench.testing import check_method, check_adapter
    check_method(MyMethod())              # raises AssertionError with what is wrong
    check_adapter(MyAdapter(root), "val")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.dataset import DatasetAdapter, Sequence
from pcfbench.geometry import transform_points, yaw_transform
from pcfbench.method import Method
from pcfbench.protocol import SETTINGS, SampleBuilder, Setting
from pcfbench.boxes import EgoBox
from pcfbench.protocol.validate import validate_forecast


def spinning_directions(beams: int = 16, azimuths: int = 360, fov_deg: tuple[float, float] = (-24.0, 2.0)) -> np.ndarray:
    """(beams * azimuths, 3) unit ray directions of a toy spinning LiDAR, sensor frame."""
    el = np.deg2rad(np.linspace(fov_deg[0], fov_deg[1], beams))
    az = np.linspace(-np.pi, np.pi, azimuths, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)


def toy_world_sweeps(
    num_sweeps: int = 30, beams: int = 16, azimuths: int = 360, speed_mps: float = 8.0, rate_hz: float = 10.0,
    sensor_height: float = 1.73, seed: int = 0,
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """A corridor street (ground, two building walls, a far wall, a few posts) seen by a toy LiDAR.

    Returns sensor-frame points per sweep (float32), poses T_world_sensor (T, 4, 4) and
    timestamps in seconds. Analytic ray casting: exact and dependency-free.
    """
    rng = np.random.default_rng(seed)
    dirs = spinning_directions(beams, azimuths)
    posts = rng.uniform([5, -9], [200, 9], size=(12, 2))
    points, poses = [], []
    for k in range(num_sweeps):
        yaw = 0.02 * np.sin(0.3 * k)
        T_world_sensor = yaw_transform(yaw, (k * speed_mps / rate_hz, 0.3 * np.sin(0.1 * k), sensor_height))
        R = T_world_sensor[:3, :3]
        o = T_world_sensor[:3, 3]
        d = dirs @ R.T
        t = np.full(len(d), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis, value in ((2, 0.0), (1, 12.0), (1, -12.0), (0, 260.0)):
                ti = (value - o[axis]) / d[:, axis]
                t = np.where((ti > 0) & (ti < t), ti, t)
            for px, py in posts:  # vertical cylinders of radius 0.3 m, 4 m tall
                a = d[:, 0] ** 2 + d[:, 1] ** 2
                b = 2 * (d[:, 0] * (o[0] - px) + d[:, 1] * (o[1] - py))
                c = (o[0] - px) ** 2 + (o[1] - py) ** 2 - 0.09
                disc = b * b - 4 * a * c
                ti = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
                z = o[2] + ti * d[:, 2]
                hit = (disc > 0) & (ti > 0) & (ti < t) & (z < 4.0)
                t = np.where(hit, ti, t)
        keep = np.isfinite(t) & (t < 120.0)
        pts_world = o + d[keep] * t[keep, None]
        pts_world += rng.normal(0, 0.01, pts_world.shape)
        points.append(transform_points(np.linalg.inv(T_world_sensor), pts_world).astype(np.float32))
        poses.append(T_world_sensor)
    return points, np.stack(poses), np.arange(num_sweeps) / rate_hz


class InMemoryDataset(DatasetAdapter):
    """A dataset adapter over the toy world, for contract tests; root is ignored."""

    name = "toy"
    version = "1"
    rate_hz = 10.0
    ego_box = EgoBox(-2.0, 3.5, -1.55, 1.55)
    default_settings = ("kitti-1s",)

    def __init__(self, root: str | Path | None = None, num_sweeps: int = 30, **kw) -> None:
        super().__init__(root)
        self._points, self._poses, times = toy_world_sweeps(num_sweeps, **kw)
        self._times = np.round(times * 1e9).astype(np.int64)

    def splits(self) -> tuple[str, ...]:
        return ("test",)

    def sequence_names(self, split: str) -> list[str]:
        return ["00"]

    def sequence(self, name: str) -> Sequence:
        return Sequence(name, self._poses, self._times, self._load)

    def _load(self, sequence: str, index: int) -> np.ndarray:
        return self._points[index]


def toy_sample(setting: Setting | str = "kitti-1s", index: int = 8) -> tuple[Sample, object]:
    """One (Sample, GroundTruth) pair from the toy world."""
    setting = SETTINGS[setting] if isinstance(setting, str) else setting
    builder = SampleBuilder(InMemoryDataset(), setting)
    return builder.build("00", index)


def check_method(method: Method, setting: str = "kitti-1s") -> Forecast:
    """Assert that ``method`` returns a valid forecast for a toy sample (and give it back)."""
    assert isinstance(method, Method), f"{method!r} is not a pcfbench.method.Method"
    assert getattr(method, "name", None), "a method needs a class attribute 'name'"
    sample, _ = toy_sample(setting)
    forecast = method.forecast(sample.for_method())  # read-only arrays, as the runner gives them
    checked = validate_forecast(sample, forecast)  # raises ForecastError with what is wrong
    return checked


def check_adapter(adapter: DatasetAdapter, split: str, max_sweeps: int = 5) -> None:
    """Assert that ``adapter`` lists sequences of ``split`` and yields valid sweeps and poses
    (each sweep read through ``Sequence.checked_sweep``, the check ``pcfbench run`` makes)."""
    from pcfbench.errors import DataError

    for attr in ("name", "version", "rate_hz", "ego_box"):
        assert getattr(adapter, attr, None) is not None, f"adapter is missing class attribute {attr!r}"
    names = adapter.sequence_names(split)
    assert names, f"adapter {adapter.name!r} has no sequences in split {split!r}"
    for name in names:
        seq = adapter.sequence(name)
        n = len(seq)
        assert seq.T_world_sensor.shape == (n, 4, 4), f"{name}: poses shape {seq.T_world_sensor.shape}"
        assert seq.timestamps_ns.dtype == np.int64, f"{name}: timestamps must be int64 ns"
        assert np.all(np.diff(seq.timestamps_ns) > 0), f"{name}: timestamps must increase"
        for i in range(min(n, max_sweeps)):
            try:
                seq.checked_sweep(i, adapter.name)
            except DataError as exc:
                raise AssertionError(str(exc)) from None
            pts = seq.load_points(i)
            assert pts.dtype == np.float32, f"{seq.where_points(i, adapter.name)}: points are {pts.dtype}, not float32"
