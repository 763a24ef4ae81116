"""Dataset adapters of the synthetic domains: the generated KITTI layout, with its own splits.

Each domain is a dataset of its own (``synthetic-town``, ``synthetic-suburb``). With no root
configured, ``default_root`` generates the domain into the cache on first use and reuses it
afterwards. Only ``synthetic-town`` is ``embedded`` (the default of ``pcfbench run``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from pcfbench.errors import DataError
from pcfbench.boxes import EgoBox
from pcfbench.datasets.kitti import KittiOdometry
from pcfbench.datasets.synthetic.domains import GENERATOR_VERSION, get_domain
from pcfbench.datasets.synthetic.generate import MANIFEST, ensure_domain, is_managed, split_complete
from pcfbench.datasets.synthetic.lidar import EGO_SHAPE


def _ego_box(margin: float = 0.15) -> EgoBox:
    """The generator's ego body (sensor frame) plus a margin for range noise."""
    return EgoBox(EGO_SHAPE.x_min - margin, EGO_SHAPE.x_max + margin,
                  -EGO_SHAPE.half_width - margin, EGO_SHAPE.half_width + margin)


class SyntheticKitti(KittiOdometry):
    """A generated synthetic domain read through the KITTI layout."""

    domain: str
    version = GENERATOR_VERSION
    ego_box = _ego_box()
    default_split = "test"

    @classmethod
    def default_root(cls, progress: bool = True) -> Path:
        """The cache copy, with the evaluation split generated now; other splits on first use."""
        return ensure_domain(cls.domain, splits=(cls.default_split,), progress=progress)

    @classmethod
    def recipe(cls, split: str) -> dict | None:
        """The domain's definition that makes ``split`` (sensor, town style, world physics,
        seed, rate, the split's sequences), its name and the generator's version; its
        description and settings left out (they make no data). None for a split the domain
        does not have."""
        d = get_domain(cls.domain)
        if split not in d.splits:
            return None
        return {"domain": d.name, "generator_version": GENERATOR_VERSION, "physics": d.physics, "seed": d.seed,
                "rate_hz": d.rate_hz, "sensor": dataclasses.asdict(d.sensor), "style": dataclasses.asdict(d.style),
                "realism": None if d.realism is None else dataclasses.asdict(d.realism), "split": split,
                "sequences": [list(s) for s in d.splits[split]]}

    @classmethod
    def detect(cls, root: Path) -> bool:
        try:
            return json.loads((Path(root) / MANIFEST).read_text()).get("domain") == cls.name
        except (OSError, ValueError):
            return False

    def __init__(self, root, options=None, **raw):
        super().__init__(root, options, **raw)
        self._splits = {split: tuple(n for n, _ in seqs) for split, seqs in get_domain(self.domain).splits.items()}
        if self.root is not None and (self.root / MANIFEST).is_file():
            try:
                manifest = json.loads((self.root / MANIFEST).read_text())
            except ValueError as exc:
                raise DataError(f"synthetic manifest {self.root / MANIFEST} is not valid JSON: {exc}") from None
            if manifest.get("domain") != self.name:
                raise DataError(f"{self.root} holds synthetic domain {manifest.get('domain')!r}, not {self.name!r}")
            # A folder made by another generator or physics version is another dataset under the
            # same name: read as today's, its results would carry today's recipe.
            made = (str(manifest.get("generator_version")), manifest.get("physics", 1))
            today = (GENERATOR_VERSION, get_domain(self.domain).physics)
            if made != today:
                raise DataError(
                    f"{self.root / MANIFEST}: {self.name} made by generator version {made[0]}, world physics "
                    f"{made[1]}; this pcfbench makes version {today[0]}, physics {today[1]}, and would record "
                    f"results on it as that: generate it again (pcfbench generate {self.name} --out DIR) or "
                    "read it with the pcfbench that made it")

    def splits(self) -> tuple[str, ...]:
        return tuple(self._splits)

    def sequence_names(self, split: str) -> list[str]:
        if split not in self._splits:
            raise DataError(f"{self.name} has no split {split!r} (known: {', '.join(self._splits)})")
        if is_managed(self.root) and not split_complete(self.root, split):
            ensure_domain(self.domain, splits=(split,), root=self.root)
        if not (self.root / "sequences").is_dir():
            raise DataError(f"{self.name} root {self.root} has no sequences/ folder (expected the KITTI layout)")
        return [s for s in self._splits[split] if self._seq_dir(s).is_dir()]  # one without poses is an error

    def check(self):
        report = super().check()
        if self.root is not None and is_managed(self.root):
            report.found["cache"] = "managed by pcfbench (splits generated on first use)"
        return report


class SyntheticTown(SyntheticKitti):
    """World physics 1: clean surfaces, 512 columns (~28k points a sweep). Fast to generate and
    score, so the tests and sweeps use it; it ranks methods unlike real LiDAR (docs/realism.md),
    so the default run uses ``synthetic-town-realistic``."""

    name = "synthetic-town"
    domain = "synthetic-town"
    rate_hz = 10.0
    default_settings = ("kitti-1s", "kitti-3s")
    embedded = False  # generated on first use too, but not part of the no-argument default run


class SyntheticSuburb(SyntheticKitti):
    name = "synthetic-suburb"
    domain = "synthetic-suburb"
    rate_hz = 2.0
    default_settings = ("nuscenes-1s", "nuscenes-3s")
    embedded = False  # generated on first use too, but not part of the no-argument default run


class SyntheticTownRealistic(SyntheticKitti):
    """synthetic-town with the world physics of ``realism.REALISM`` (docs/realism.md): the
    default run's dataset. Its sweeps have ~110k points (a real HDL-64's count), so by default
    it is scored on every third sample (policy ``every-third``, which ranks the baselines as
    all of them do); ``--policy full-context`` scores all."""

    name = "synthetic-town-realistic"
    domain = "synthetic-town-realistic"
    rate_hz = 10.0
    default_settings = ("kitti-1s", "kitti-3s")
    default_policy = "every-third"
    embedded = True
