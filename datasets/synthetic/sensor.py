"""A simulated spinning multi-beam LiDAR: beam tables, ray directions, range noise and ray drop.

Two beam tables are modelled on real sensors:

* ``HDL64``: 64 beams in two blocks like the Velodyne HDL-64E of KITTI: the upper block from
  +2.0 deg down to about -8.3 deg in 1/3 deg steps, the lower block from about -8.8 deg down
  to -24.8 deg in 1/2 deg steps; mounted 1.73 m above the ground; 120 m maximum range.
* ``HDL32``: 32 beams evenly spaced from +10.67 deg to -30.67 deg (1.33 deg), like the
  Velodyne HDL-32E of nuScenes; mounted 1.84 m above the ground; 70 m maximum range.

Ray drop (no return although the ray hit something) grows at grazing incidence and with
range, as real returns weaken; hits past the maximum range give no return at all.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def hdl64_elevations_deg() -> np.ndarray:
    """64 beam elevations, highest first: 32 upper (1/3 deg apart), 32 lower (1/2 deg apart)."""
    upper = 2.0 - np.arange(32) / 3.0  # +2.0 .. -8.33
    lower = -8.83 - np.arange(32) * 0.5  # -8.83 .. -24.33
    return np.concatenate([upper, lower - 0.47 * np.arange(32) / 31.0])  # lower block ends at -24.8


def hdl32_elevations_deg() -> np.ndarray:
    """32 beam elevations, highest first, 4/3 deg apart from +10.67 to -30.67 deg."""
    return np.linspace(10.67, -30.67, 32)


@dataclass(frozen=True)
class LidarConfig:
    """A spinning LiDAR: beams, mounting, resolution, range limits, noise and drop."""

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_steps: int  # rays per beam per revolution
    mount_height_m: float  # sensor origin above the ground under the ego vehicle
    max_range_m: float
    min_range_m: float = 0.9
    range_noise_m: float = 0.02  # 1-sigma Gaussian range noise
    drop_base: float = 0.02  # drop probability of a head-on, near return
    drop_grazing: float = 0.35  # extra drop probability at grazing incidence (cos -> 0)
    drop_range: float = 0.25  # extra drop probability at maximum range (quadratic in range)
    extra: dict = field(default_factory=dict, compare=False, hash=False)

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def num_rays(self) -> int:
        return self.beams * self.azimuth_steps

    def directions(self) -> np.ndarray:
        """(beams * azimuth_steps, 3) float32 unit directions in the sensor frame (x fwd, y left, z up).

        Beam-major: ray ``b * azimuth_steps + a`` is beam ``b`` at azimuth step ``a``.
        """
        el = np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))
        az = np.linspace(-np.pi, np.pi, self.azimuth_steps, endpoint=False)
        E, A = np.meshgrid(el, az, indexing="ij")
        d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
        return d.astype(np.float32)

    def drop_probability(self, ranges: np.ndarray, cos_incidence: np.ndarray) -> np.ndarray:
        """Probability that a hit at ``ranges`` with |cos(incidence)| gives no return."""
        grazing = (1.0 - np.clip(np.abs(cos_incidence), 0.0, 1.0)) ** 4
        far = np.clip(ranges / self.max_range_m, 0.0, 1.0) ** 2
        return np.clip(self.drop_base + self.drop_grazing * grazing + self.drop_range * far, 0.0, 0.95)


HDL64 = LidarConfig(
    name="hdl64",
    elevations_deg=tuple(float(v) for v in hdl64_elevations_deg()),
    # 0.3 deg: the real HDL-64E at 10 Hz fires ~0.09 deg apart. A third of its columns keeps a
    # sweep near 40k points, so the metrics (k-d trees over every sweep) stay fast enough for
    # the 10-minute default run; the beam table (what forecasting is sensitive to) is full.
    azimuth_steps=1200,
    mount_height_m=1.73,
    max_range_m=120.0,
    range_noise_m=0.02,
)

HDL32 = LidarConfig(
    name="hdl32",
    elevations_deg=tuple(float(v) for v in hdl32_elevations_deg()),
    azimuth_steps=1080,  # 0.33 deg, as the HDL-32E at 20 Hz
    mount_height_m=1.84,
    max_range_m=70.0,
    range_noise_m=0.03,
    drop_base=0.03,
)

SENSORS = {s.name: s for s in (HDL64, HDL32)}
