"""What every layout writer takes: sequences of sweeps with poses, loaded one sweep at a time.

Writers (``write_nuscenes``, ``write_av2``, ``write_mcap_dataset``, KITTI's
``write_kitti_sequence``) take :class:`SequenceData`, so tests, the synthetic generator and
``pcfbench convert`` share one path and a conversion never holds a whole dataset in memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from pcfbench.errors import DataError

#: Axis conventions the adapters declare, and the rotation R_conv_std mapping the standard
#: frame (x forward, y left, z up) into each one.
STANDARD_AXES = "x forward, y left, z up"
AXES_FROM_STANDARD: dict[str, np.ndarray] = {
    STANDARD_AXES: np.eye(3),
    # nuScenes LIDAR_TOP: x right, y forward -> x' = -y, y' = x
    "x right, y forward, z up": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


@dataclass(frozen=True, eq=False)
class SequenceData:
    """One sequence to write: poses (T, 4, 4) float64, timestamps (T,) int64 ns, points on demand.

    ``load(i)`` returns sweep i as (N, 3) float32 in the sensor frame (extra columns ignored).
    """

    name: str
    split: str
    T_world_sensor: np.ndarray
    timestamps_ns: np.ndarray
    load: Callable[[int], np.ndarray]

    def __len__(self) -> int:
        return int(len(self.timestamps_ns))

    @classmethod
    def from_arrays(cls, name: str, split: str, points: list[np.ndarray], T_world_sensor: np.ndarray, timestamps_ns) -> "SequenceData":
        ts = np.asarray(timestamps_ns, dtype=np.int64)
        if len(points) != len(ts) or len(T_world_sensor) != len(ts):
            raise ValueError(f"sequence {name}: {len(points)} sweeps, {len(T_world_sensor)} poses, {len(ts)} timestamps")
        return cls(name, split, np.asarray(T_world_sensor, np.float64), ts, lambda i: np.asarray(points[i], np.float32))


def change_axes(seq: SequenceData, from_axes: str, to_axes: str) -> SequenceData:
    """Re-express a sequence's sensor frame in another axis convention (same physical sensor)."""
    if from_axes == to_axes:
        return seq
    for a in (from_axes, to_axes):
        if a not in AXES_FROM_STANDARD:
            raise DataError(f"unknown axis convention {a!r} (known: {', '.join(AXES_FROM_STANDARD)})")
    # p_to = R_to_from @ p_from ; T_world_to = T_world_from @ T_from_to
    R_to_from = AXES_FROM_STANDARD[to_axes] @ AXES_FROM_STANDARD[from_axes].T
    T_from_to = np.eye(4)
    T_from_to[:3, :3] = R_to_from.T
    load = seq.load

    def load_to(i: int) -> np.ndarray:
        pts = np.asarray(load(i))[:, :3].astype(np.float64)
        return (pts @ R_to_from.T).astype(np.float32)

    return SequenceData(seq.name, seq.split, seq.T_world_sensor @ T_from_to, seq.timestamps_ns, load_to)
