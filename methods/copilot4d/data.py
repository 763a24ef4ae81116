"""Sweeps for the tokenizer, loaded through the registered dataset adapters."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pcfbench.methods.copilot4d.config import TokenizerConfig


def open_dataset(name: str, root: str | Path | None = None, progress: bool = True):
    """The registered adapter ``name`` on ``root`` (else the configured root, else the
    adapter's default root, which embedded datasets generate)."""
    from pcfbench import config
    from pcfbench.plugins import get_plugins

    cls = get_plugins().datasets.get(name)
    if root is None:
        root = config.dataset_root(name, {})
    if root is None:
        root = cls.default_root(progress=progress)
    return cls(root)


class SweepSource:
    """All sweeps of one split of an adapter, in the sensor frame, ego returns removed."""

    def __init__(self, adapter, split: str, stride: int = 1, limit: int | None = None) -> None:
        self.adapter = adapter
        self.split = split
        self.sequences = {n: adapter.sequence(n) for n in adapter.sequence_names(split)}
        keys = [(n, i) for n, s in self.sequences.items() for i in range(len(s))]
        keys = keys[::stride]
        self.keys = keys[:limit] if limit else keys
        if not self.keys:
            from pcfbench.errors import DataError

            raise DataError(f"dataset {adapter.name!r} has no sweeps in split {split!r} under {adapter.root}")

    def __len__(self) -> int:
        return len(self.keys)

    def points(self, k: int) -> np.ndarray:
        name, i = self.keys[k]
        pts = self.sequences[name].load_points(i)
        return self.adapter.ego_box.remove(pts)

    def window_sensor(self, cfg: TokenizerConfig, k: int, rng: np.random.Generator) -> np.ndarray:
        """``T_grid_sensor`` (4, 4) of sweep ``k`` seen as a world-model window holds it
        (``cfg.sensor_moves == "window"``): with probability ``cfg.sensor_moved_share`` the sweep
        is frame j (uniform over ``window_past + window_future``) of a window of stride s (uniform
        over ``window_strides``), and the grid is that window's t=0 sensor frame, anchor
        a = i - (j - (window_past - 1)) s clipped to the sequence: ``inv(T_world_a) @ T_world_i``;
        else the identity."""
        T = np.eye(4)
        if cfg.sensor_moved_share <= 0 or rng.random() >= cfg.sensor_moved_share:
            return T
        name, i = self.keys[k]
        poses = self.sequences[name].T_world_sensor
        j = int(rng.integers(0, cfg.window_past + cfg.window_future))
        s = int(cfg.window_strides[int(rng.integers(0, len(cfg.window_strides)))])
        a = min(max(i - (j - (cfg.window_past - 1)) * s, 0), len(poses) - 1)
        return np.linalg.inv(poses[a]) @ poses[i]

    def window_pair(self, cfg: TokenizerConfig, k: int, rng: np.random.Generator):
        """Two views of one world-model window, for ``cfg.view_consistency``: sweep ``k`` (index i
        of its sequence) as frame j of a window of stride s (both uniform, as
        :meth:`window_sensor` draws them; anchor a = i - (j - (window_past - 1)) s clipped to the
        sequence) and another frame j2 != j of the same window (sweep a + (j2 - (window_past - 1)) s,
        clipped), both seen from the window's t=0 sensor. Returns ``[(points, T_grid_sensor)] * 2``,
        the points in their own sensor frame (ego returns removed), as :func:`make_batch` takes them."""
        name, i = self.keys[k]
        seq = self.sequences[name]
        poses = seq.T_world_sensor
        n = cfg.window_past + cfg.window_future
        j = int(rng.integers(0, n))
        j2 = int(rng.integers(0, n - 1))
        j2 += j2 >= j  # uniform over the other frames
        s = int(cfg.window_strides[int(rng.integers(0, len(cfg.window_strides)))])
        clip = lambda v: min(max(v, 0), len(poses) - 1)  # noqa: E731
        a = clip(i - (j - (cfg.window_past - 1)) * s)
        i2 = clip(a + (j2 - (cfg.window_past - 1)) * s)
        T_a = np.linalg.inv(poses[a])
        return [(self.points(k), T_a @ poses[i]),
                (self.adapter.ego_box.remove(seq.load_points(i2)), T_a @ poses[i2])]


@dataclass
class Batch:
    points: torch.Tensor  # (N, 3) encoder input, sensor frame
    point_batch: torch.Tensor  # (N,)
    origins: torch.Tensor  # (R, 3) ray origins: the sensor (zeros unless moved: make_batch)
    dirs: torch.Tensor  # (R, 3) unit directions
    depth: torch.Tensor  # (R,) ground-truth ranges
    ray_batch: torch.Tensor  # (R,)
    size: int

    def to(self, device) -> "Batch":
        return Batch(*(getattr(self, f).to(device) for f in ("points", "point_batch", "origins", "dirs", "depth", "ray_batch")), self.size)


def in_box(cfg: TokenizerConfig, pts: np.ndarray) -> np.ndarray:
    return ((pts[:, 0] >= cfg.x_range[0]) & (pts[:, 0] < cfg.x_range[1]) & (pts[:, 1] >= cfg.y_range[0])
            & (pts[:, 1] < cfg.y_range[1]) & (pts[:, 2] >= cfg.z_range[0]) & (pts[:, 2] < cfg.z_range[1]))


def moved_sensor(cfg: TokenizerConfig, rng: np.random.Generator) -> np.ndarray:
    """``T_grid_sensor`` (4, 4) for one training sweep: the identity, or with probability
    ``cfg.sensor_moved_share`` a turn about z by up to ``cfg.sensor_turn`` degrees and a shift
    by up to ``cfg.sensor_shift`` m in the ground plane (radius and direction uniform). Draws
    nothing from ``rng`` when the share is 0 (the built-in configurations train as before)."""
    T = np.eye(4)
    if cfg.sensor_moved_share <= 0 or rng.random() >= cfg.sensor_moved_share:
        return T
    yaw = np.radians(rng.uniform(-cfg.sensor_turn, cfg.sensor_turn))
    radius, heading = rng.uniform(0.0, cfg.sensor_shift), rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = radius * np.cos(heading), radius * np.sin(heading)
    return T


def make_batch(cfg: TokenizerConfig, clouds: list[np.ndarray], rays: int | None, rng: np.random.Generator,
               min_range: float = 0.5, sensors: list[np.ndarray] | None = None) -> Batch:
    """Encoder input: every point inside the grid. Rays: ``rays`` random returns per sweep inside
    the grid (all of them when ``rays`` is None), from the sensor origin. With moved sensors
    (``cfg.sensor_moved_share``), a sweep is first moved into a grid frame where its sensor sits
    at ``T_grid_sensor``'s origin (``sensors[b]`` when given, else :func:`moved_sensor`), and its
    rays start there."""
    # BEVWorld's tokenizer configuration has the moved-sensor fields but the window moves
    if sensors is None and getattr(cfg, "sensor_moves", "disc") == "window":
        raise ValueError(f"tokenizer config {cfg.name!r} moves sensors as windows do: make_batch needs their sensors "
                         "(SweepSource.window_sensor)")
    pts, pb, origins, dirs, depth, rb = [], [], [], [], [], []
    for b, p in enumerate(clouds):
        T_grid_sensor = sensors[b] if sensors is not None else moved_sensor(cfg, rng)
        moved = not np.array_equal(T_grid_sensor, np.eye(4))
        if moved:
            p = (p.astype(np.float64) @ T_grid_sensor[:3, :3].T + T_grid_sensor[:3, 3]).astype(np.float32)
        p = p[in_box(cfg, p)]
        pts.append(p)
        pb.append(np.full(len(p), b))
        o = T_grid_sensor[:3, 3].astype(np.float32)
        v = p - o if moved else p
        r = np.linalg.norm(v, axis=1)
        ok = np.nonzero(r > min_range)[0]
        if rays is not None and len(ok) > rays:
            ok = rng.choice(ok, rays, replace=False)
        dirs.append(v[ok] / r[ok, None])
        depth.append(r[ok])
        origins.append(np.broadcast_to(o, (len(ok), 3)))
        rb.append(np.full(len(ok), b))
    t = lambda a, dt=torch.float32: torch.from_numpy(np.concatenate(a)).to(dt)  # noqa: E731
    return Batch(t(pts), t(pb, torch.long), t(origins), t(dirs), t(depth), t(rb, torch.long), len(clouds))
