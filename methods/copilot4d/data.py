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


@dataclass
class Batch:
    points: torch.Tensor  # (N, 3) encoder input, sensor frame
    point_batch: torch.Tensor  # (N,)
    origins: torch.Tensor  # (R, 3) ray origins (the sensor, zeros)
    dirs: torch.Tensor  # (R, 3) unit directions
    depth: torch.Tensor  # (R,) ground-truth ranges
    ray_batch: torch.Tensor  # (R,)
    size: int

    def to(self, device) -> "Batch":
        return Batch(*(getattr(self, f).to(device) for f in ("points", "point_batch", "origins", "dirs", "depth", "ray_batch")), self.size)


def in_box(cfg: TokenizerConfig, pts: np.ndarray) -> np.ndarray:
    return ((pts[:, 0] >= cfg.x_range[0]) & (pts[:, 0] < cfg.x_range[1]) & (pts[:, 1] >= cfg.y_range[0])
            & (pts[:, 1] < cfg.y_range[1]) & (pts[:, 2] >= cfg.z_range[0]) & (pts[:, 2] < cfg.z_range[1]))


def make_batch(cfg: TokenizerConfig, clouds: list[np.ndarray], rays: int | None, rng: np.random.Generator,
               min_range: float = 0.5) -> Batch:
    """Encoder input: every point inside the grid. Rays: ``rays`` random returns per sweep inside
    the grid (all of them when ``rays`` is None), from the sensor origin."""
    pts, pb, dirs, depth, rb = [], [], [], [], []
    for b, p in enumerate(clouds):
        p = p[in_box(cfg, p)]
        pts.append(p)
        pb.append(np.full(len(p), b))
        r = np.linalg.norm(p, axis=1)
        ok = np.nonzero(r > min_range)[0]
        if rays is not None and len(ok) > rays:
            ok = rng.choice(ok, rays, replace=False)
        dirs.append(p[ok] / r[ok, None])
        depth.append(r[ok])
        rb.append(np.full(len(ok), b))
    t = lambda a, dt=torch.float32: torch.from_numpy(np.concatenate(a)).to(dt)  # noqa: E731
    d = t(dirs)
    return Batch(t(pts), t(pb, torch.long), torch.zeros_like(d), d, t(depth), t(rb, torch.long), len(clouds))
