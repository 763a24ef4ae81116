"""Named synthetic domains: which sensor, town style, rate, seed and splits each one has.

Domains differ the way real datasets differ: ``synthetic-town`` is KITTI-like (64 beams,
1.73 m, 10 Hz, dense town with busy traffic), ``synthetic-suburb`` is nuScenes-like (32 beams,
1.84 m, 2 Hz keyframes, wide curvy roads, low houses set back behind fences and trees, light
traffic). Each sequence is its own town (seeded by domain seed and sequence index), so the
test towns are never seen in training.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from pcfbench.errors import unknown_name
from pcfbench.datasets.synthetic.realism import REALISM, Realism
from pcfbench.datasets.synthetic.sensor import HDL32, HDL64, LidarConfig
from pcfbench.datasets.synthetic.world import SUBURB, TOWN, TownStyle

#: Bumped whenever the generated data would change; part of the cache folder name.
GENERATOR_VERSION = "2"


@dataclass(frozen=True)
class Domain:
    name: str
    sensor: LidarConfig
    style: TownStyle
    rate_hz: float
    seed: int
    #: split -> ((sequence name, number of sweeps), ...)
    splits: dict
    settings: tuple[str, ...]
    description: str
    #: None: world physics version 1 (clean surfaces, instant sweeps); else the version its
    #: knobs name (``pcfbench.datasets.synthetic.realism``)
    realism: Realism | None = None

    @property
    def physics(self) -> int:
        return 1 if self.realism is None else self.realism.version

    def sequences(self) -> list[tuple[str, str, int]]:
        """(split, sequence name, sweeps) of every sequence, in generation order."""
        return [(split, name, n) for split, seqs in self.splits.items() for name, n in seqs]

    def sequence_index(self, name: str) -> int:
        return [s for _, s, _ in self.sequences()].index(name)


DOMAINS: dict[str, Domain] = {
    d.name: d
    for d in (
        Domain(
            name="synthetic-town",
            sensor=HDL64,
            style=TOWN,
            rate_hz=10.0,
            seed=20240611,
            splits={
                "train": (("00", 90), ("01", 90), ("02", 90), ("03", 90)),
                "val": (("04", 70),),
                "test": (("05", 60), ("06", 60)),
            },
            settings=("kitti-1s", "kitti-3s"),
            description="KITTI-like: 64-beam HDL-64E-like LiDAR at 1.73 m, 10 Hz, dense town, busy traffic",
        ),
        Domain(
            name="synthetic-suburb",
            sensor=HDL32,
            style=SUBURB,
            rate_hz=2.0,
            seed=7771,
            splits={
                "train": (("00", 40), ("01", 40), ("02", 40), ("03", 40)),
                "val": (("04", 30),),
                "test": (("05", 30), ("06", 30)),
            },
            settings=("nuscenes-1s", "nuscenes-3s"),
            description="nuScenes-like: 32-beam HDL-32E-like LiDAR at 1.84 m, 2 Hz keyframes, suburb, light traffic",
        ),
    )
}

# Physics version 10 of the town (realism.REALISM.version): the same towns, splits and seed,
# seen by a sensor and surfaces like real ones, its stored poses drifting from the scans as
# KITTI's do, with as much moving traffic as SemanticKITTI has (0.085 of the town style's),
# narrower sidewalks, hedged yards with trees in them, mixed pixels at the real rate and shallow foliage
# (docs/realism.md). The embedded dataset of the default run.
_town = DOMAINS["synthetic-town"]
DOMAINS["synthetic-town-realistic"] = dataclasses.replace(
    _town, name="synthetic-town-realistic",
    sensor=dataclasses.replace(HDL64, name="hdl64-realistic", azimuth_steps=2048),
    realism=REALISM,
    description="synthetic-town with world physics v10: 2048 columns (~0.18 deg, ~110k points), beam calibration and "
                "jitter, rough surfaces, shallow vegetation volumes with solid trunks, mixed pixels at the real rate, "
                "reflectance-dependent ray drop, street furniture off the road, stored poses drifting 1.6 cm/s upwards "
                "from the scans, 0.085 of the town's moving traffic (SemanticKITTI's share of moving points), 2 m "
                "sidewalks, hedged yards with trees behind the buildings (motion distortion available, off: KITTI's "
                "scans are de-skewed)",
)


def get_domain(name: str) -> Domain:
    if name not in DOMAINS:
        raise unknown_name("synthetic domain", name, DOMAINS)
    return DOMAINS[name]
