"""Named settings, sample policies and the construction of samples (docs/protocol.md section 2)."""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from pcfbench.data import GroundTruth, RayQuery, Sample
from pcfbench.dataset import DatasetAdapter, Sequence
from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.geometry import invert, rotate_vectors, transform_points
from pcfbench.validate import validate_sweep

#: Ground-truth points closer than this to their sensor are ignored by the metrics.
MIN_RANGE_M = 0.01


@dataclass(frozen=True)
class Setting:
    """How many past / future sweeps a sample has and how far apart (in source sweeps)."""

    name: str
    rate_hz: float
    past: int  # including t=0
    future: int
    stride: int
    description: str = ""

    @property
    def horizon_s(self) -> float:
        return self.future * self.stride / self.rate_hz

    def step_seconds(self, step: int) -> float:
        """Time of future sweep ``step`` (0-based) after t=0, in seconds."""
        return (step + 1) * self.stride / self.rate_hz


SETTINGS: dict[str, Setting] = {
    s.name: s
    for s in (
        Setting("kitti-1s", 10.0, 5, 5, 2, "KITTI 10 Hz: 5 past (-0.8..0 s), 5 future (+0.2..+1.0 s)"),
        Setting("kitti-3s", 10.0, 5, 5, 6, "KITTI 10 Hz: 5 past (-2.4..0 s), 5 future (+0.6..+3.0 s)"),
        Setting("nuscenes-1s", 2.0, 2, 2, 1, "nuScenes 2 Hz keyframes: 2 past, 2 future (+0.5, +1.0 s)"),
        Setting("nuscenes-3s", 2.0, 6, 6, 1, "nuScenes 2 Hz keyframes: 6 past, 6 future (+0.5..+3.0 s)"),
        Setting("av2-1s", 10.0, 5, 5, 2, "Argoverse 2 10 Hz: as kitti-1s"),
        Setting("av2-3s", 10.0, 5, 5, 6, "Argoverse 2 10 Hz: as kitti-3s"),
    )
}

SAMPLE_POLICIES = ("full-context", "every-frame")


def get_setting(name: str) -> Setting:
    if name not in SETTINGS:
        import difflib

        close = difflib.get_close_matches(name, SETTINGS, n=2)
        hint = f"; did you mean {' or '.join(map(repr, close))}?" if close else ""
        raise UnknownNameError(f"unknown setting {name!r}{hint} (known: {', '.join(SETTINGS)})")
    return SETTINGS[name]


def check_compatible(setting: Setting, adapter: DatasetAdapter) -> None:
    if abs(setting.rate_hz - adapter.rate_hz) > 1e-6:
        raise PcfbenchError(
            f"setting {setting.name!r} expects {setting.rate_hz:g} Hz sweeps but dataset {adapter.name!r} "
            f"has {adapter.rate_hz:g} Hz (its settings: {', '.join(adapter.default_settings) or 'none'})"
        )


def anchors(num_sweeps: int, setting: Setting, policy: str) -> list[int]:
    """Reference-sweep indices of one sequence that count as samples under ``policy``."""
    if policy == "full-context":
        first = (setting.past - 1) * setting.stride
        last = num_sweeps - 1 - setting.future * setting.stride
        return list(range(first, last + 1))
    if policy == "every-frame":
        return list(range(num_sweeps))
    raise UnknownNameError(f"unknown sample policy {policy!r} (known: {', '.join(SAMPLE_POLICIES)})")


def sample_id(sequence: str, ref_index: int) -> str:
    return f"{sequence}/{ref_index:06d}"


def ids_hash(ids: list[str]) -> str:
    """A stable hash of the evaluated sample ids (order-independent)."""
    h = hashlib.sha256()
    for i in sorted(ids):
        h.update(i.encode())
        h.update(b"\n")
    return h.hexdigest()[:16]


class SampleBuilder:
    """Turns a dataset's sequences into (Sample, GroundTruth) pairs for one setting.

    Sensor-frame sweeps (ego box removed, validated) are cached, since neighbouring samples
    share most of their sweeps.
    """

    def __init__(self, adapter: DatasetAdapter, setting: Setting, policy: str = "full-context", cache_sweeps: int = 32):
        if policy not in SAMPLE_POLICIES:
            raise UnknownNameError(f"unknown sample policy {policy!r} (known: {', '.join(SAMPLE_POLICIES)})")
        self.adapter = adapter
        self.setting = setting
        self.policy = policy
        self._sequences: dict[str, Sequence] = {}
        self._cache: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()
        self._cache_size = cache_sweeps

    def sequence(self, name: str) -> Sequence:
        if name not in self._sequences:
            self._sequences[name] = self.adapter.sequence(name)
        return self._sequences[name]

    def sample_keys(self, split: str) -> list[tuple[str, int]]:
        """(sequence, reference index) of every sample of ``split``, in a stable order."""
        keys = []
        for name in self.adapter.sequence_names(split):
            seq = self.sequence(name)
            keys.extend((name, i) for i in anchors(len(seq), self.setting, self.policy))
        return keys

    def points_sensor(self, seq: Sequence, index: int) -> np.ndarray:
        """(N, 3) float32 sensor-frame points of one sweep, ego returns removed."""
        key = (seq.name, index)
        cached = self._cache.get(key)
        if cached is not None:
            self._cache.move_to_end(key)
            return cached
        where = f"{self.adapter.name} sequence {seq.name} sweep {index}"
        pts = validate_sweep(seq.sweep(index), where).points_sensor
        pts = self.adapter.ego_box.remove(pts)
        self._cache[key] = pts
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return pts

    def build(self, sequence: str, ref_index: int) -> tuple[Sample, GroundTruth]:
        seq = self.sequence(sequence)
        n = len(seq)
        s = self.setting
        past_idx = [ref_index - k * s.stride for k in range(s.past - 1, -1, -1)]
        future_idx = [ref_index + k * s.stride for k in range(1, s.future + 1)]
        T_world_ref = seq.T_world_sensor[ref_index]
        T_ref_world = invert(T_world_ref)

        def pose(i: int) -> np.ndarray:
            # every-frame: a missing sweep takes the nearest existing pose (its points are empty).
            return T_ref_world @ seq.T_world_sensor[min(max(i, 0), n - 1)]

        def stamp(i: int) -> int:
            if 0 <= i < n:
                return int(seq.timestamps_ns[i])
            # outside the sequence: extrapolate at the nominal rate
            edge = 0 if i < 0 else n - 1
            return int(seq.timestamps_ns[edge] + (i - edge) * 1e9 / self.adapter.rate_hz)

        empty = np.zeros((0, 3), np.float32)
        past_T = np.stack([pose(i) for i in past_idx])
        past_points = tuple(
            transform_points(T, self.points_sensor(seq, i)) if 0 <= i < n else empty for T, i in zip(past_T, past_idx)
        )
        future_T = np.stack([pose(i) for i in future_idx])
        queries, truths = [], []
        for T, i in zip(future_T, future_idx):
            pts = self.points_sensor(seq, i) if 0 <= i < n else empty
            rng = np.linalg.norm(pts.astype(np.float64), axis=1)
            keep = rng > MIN_RANGE_M
            pts, rng = pts[keep], rng[keep]
            dirs_sensor = (pts.astype(np.float64) / rng[:, None]) if len(pts) else np.zeros((0, 3))
            queries.append(RayQuery(origin_ref=T[:3, 3].copy(), directions_ref=rotate_vectors(T, dirs_sensor).astype(np.float32)))
            truths.append(transform_points(T, pts))
        sid = sample_id(sequence, ref_index)
        sample = Sample(
            sample_id=sid,
            dataset=self.adapter.name,
            sequence=sequence,
            ref_index=ref_index,
            past_points_ref=past_points,
            past_T_ref_sensor=past_T,
            past_timestamps_ns=np.array([stamp(i) for i in past_idx], dtype=np.int64),
            future_T_ref_sensor=future_T,
            future_timestamps_ns=np.array([stamp(i) for i in future_idx], dtype=np.int64),
            queries=tuple(queries),
            T_world_ref=T_world_ref,
        )
        return sample, GroundTruth(sample_id=sid, future_points_ref=tuple(truths))
