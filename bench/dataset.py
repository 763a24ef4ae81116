"""The dataset-adapter contract: one on-disk layout, sequences of sweeps, loaded lazily."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, ClassVar

import numpy as np

from pcfbench.data import Sweep
from pcfbench.roi import EgoBox


@dataclass(frozen=True, eq=False)
class Sequence:
    """A time-ordered run of sweeps. Poses and timestamps are known up front; points load lazily.

    T_world_sensor: (T, 4, 4) float64; timestamps_ns: (T,) int64 strictly increasing.
    """

    name: str
    T_world_sensor: np.ndarray
    timestamps_ns: np.ndarray
    loader: Callable[[str, int], np.ndarray]

    def __len__(self) -> int:
        return int(self.timestamps_ns.shape[0])

    def load_points(self, index: int) -> np.ndarray:
        """(N, 3) float32 points of sweep ``index`` in its own sensor frame."""
        return self.loader(self.name, index)

    def sweep(self, index: int) -> Sweep:
        """Sweep ``index`` with its pose and timestamp (not validated: see pcfbench.validate)."""
        return Sweep(
            points_sensor=self.load_points(index),
            T_world_sensor=self.T_world_sensor[index],
            timestamp_ns=int(self.timestamps_ns[index]),
            source=f"sequence {self.name} sweep {index}",
        )


@dataclass
class CheckReport:
    """What ``pcfbench datasets check`` prints: what was found and every problem."""

    layout: str
    root: str
    found: dict[str, object] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


class DatasetAdapter(ABC):
    """Base class of every dataset plugin.

    Subclasses set ``name``, ``version``, ``rate_hz``, ``ego_box`` and ``default_settings``,
    take the dataset root (and keyword options) in ``__init__`` and implement ``splits``,
    ``sequence_names`` and ``sequence``. Axis convention: x forward, y left, z up unless the
    adapter says otherwise in ``axes``.
    """

    name: ClassVar[str]
    version: ClassVar[str] = "1"
    rate_hz: ClassVar[float]
    ego_box: ClassVar[EgoBox]
    default_settings: ClassVar[tuple[str, ...]] = ()
    default_split: ClassVar[str] = "test"
    axes: ClassVar[str] = "x forward, y left, z up"
    #: True for a dataset that makes its own data (generated on first use): the default of
    #: ``pcfbench run`` when no dataset is named.
    embedded: ClassVar[bool] = False

    @classmethod
    def default_root(cls, progress: bool = True) -> Path:
        """The root to use when none is configured (an embedded dataset prepares it here)."""
        from pcfbench.config import env_var_for
        from pcfbench.errors import PcfbenchError

        raise PcfbenchError(
            f"dataset {cls.name!r} needs a root: pass --dataset {cls.name}=/path/to/data, set "
            f"{env_var_for(cls.name)}, or add it under [datasets] in the config file"
        )

    @classmethod
    def detect(cls, root: Path) -> bool:
        """True when ``root`` looks like this adapter's layout (used by ``datasets check``)."""
        return False

    def __init__(self, root: str | Path | None, **options: object) -> None:
        self.root = Path(root) if root is not None else None
        if options:
            raise TypeError(f"dataset {self.name!r} takes no options, got {sorted(options)}")

    @abstractmethod
    def splits(self) -> tuple[str, ...]:
        """The split names this dataset knows."""

    @abstractmethod
    def sequence_names(self, split: str) -> list[str]:
        """Sequences of ``split`` present under the root, in a stable order."""

    @abstractmethod
    def sequence(self, name: str) -> Sequence:
        """Open one sequence: poses and timestamps now, points on demand."""

    def check(self) -> CheckReport:
        """Walk the whole dataset and report what was found and every problem (never raises)."""
        report = CheckReport(layout=self.name, root=str(self.root))
        for split in self.splits():
            try:
                names = self.sequence_names(split)
            except Exception as exc:  # noqa: BLE001 - a check collects every problem
                report.problems.append(f"split {split}: {exc}")
                continue
            report.found[f"split {split}"] = f"{len(names)} sequence(s)"
            for seq_name in names:
                try:
                    seq = self.sequence(seq_name)
                    n = len(seq)
                    dt = np.diff(seq.timestamps_ns) / 1e9
                    rate = f", {1.0 / np.median(dt):.2f} Hz" if dt.size else ""
                    report.found[f"sequence {seq_name}"] = f"{n} sweeps{rate}"
                    for i in range(n):
                        try:
                            seq.load_points(i)
                        except Exception as exc:  # noqa: BLE001
                            report.problems.append(str(exc))
                except Exception as exc:  # noqa: BLE001
                    report.problems.append(str(exc))
        return report
