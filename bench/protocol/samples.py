"""Samples under a protocol (docs/protocol.md 2): which reference sweeps a policy anchors a
sample on, and the construction of each (Sample, GroundTruth) pair from a dataset's sequences.

A :class:`SampleBuilder` carries the :class:`~pcfbench.protocol.settings.Protocol` it builds
under and hands its ROI and minimum range on to what scores the samples; its
:meth:`SampleBuilder.identity` is what a cell records of the protocol.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Any

import numpy as np
from pcfbench.data import GroundTruth, RayQuery, Sample
from pcfbench.dataset import DatasetAdapter, Sequence
from pcfbench.geometry import invert, rotate_vectors, transform_points
from pcfbench.kinds import PolicyKind
from pcfbench.protocol.settings import Protocol, SamplePolicy, Setting, active_protocol


def _policy(policy: str | SamplePolicy) -> SamplePolicy:
    return policy if isinstance(policy, SamplePolicy) else active_protocol().policy(policy)


def anchors(num_sweeps: int, setting: Setting, policy: str | SamplePolicy) -> list[int]:
    """Candidate reference-sweep indices of one sequence under ``policy``.

    For a ``subsample`` policy these are the candidates of the policy it thins; the thinning
    itself spans the whole split (:meth:`SampleBuilder.sample_keys`).
    """
    p = _policy(policy)
    if p.rule == PolicyKind.FULL_CONTEXT:
        first = (setting.past - 1) * setting.stride
        last = num_sweeps - 1 - setting.future * setting.stride
        return list(range(first, last + 1))
    return list(range(num_sweeps))  # every-frame (SamplePolicy admits no other rule)


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

    def __init__(self, adapter: DatasetAdapter, setting: Setting, policy: str = "full-context", cache_sweeps: int = 32,
                 protocol: Protocol | None = None):
        #: the protocol the samples are made under, handed on to what scores them (ROI, minimum
        #: range; :func:`pcfbench.metrics.base.score_sample`); default: the active one
        self.protocol = protocol or active_protocol()
        self.sample_policy = policy if isinstance(policy, SamplePolicy) else self.protocol.policy(policy)
        self.adapter = adapter
        self.setting = setting
        self.policy = self.sample_policy.name
        self._sequences: dict[str, Sequence] = {}
        self._cache: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()
        self._cache_size = cache_sweeps

    def identity(self) -> dict[str, Any]:
        """The protocol's part of a cell's identity (JSON-ready): protocol version, ROI, minimum
        range, the setting's parameters, the sample policy and the adapter's ego box."""
        ego = self.adapter.ego_box
        return {
            **self.protocol.identity(),
            "setting_params": self.setting.params(),
            "sample_policy": self.sample_policy.params(),
            "ego_box": {k: float(getattr(ego, k)) for k in ("x_min", "x_max", "y_min", "y_max")},
        }

    def sequence(self, name: str) -> Sequence:
        if name not in self._sequences:
            self._sequences[name] = self.adapter.sequence(name)
        return self._sequences[name]

    def sample_keys(self, split: str) -> list[tuple[str, int]]:
        """(sequence, reference index) of every sample of ``split``, in a stable order."""
        keys = []
        for name in self.adapter.sequence_names(split):
            seq = self.sequence(name)
            keys.extend((name, i) for i in anchors(len(seq), self.setting, self.sample_policy))
        if self.sample_policy.kind == PolicyKind.SUBSAMPLE:
            keys = [keys[i] for i in self.sample_policy.thin(len(keys))]
        return keys

    def points_sensor(self, seq: Sequence, index: int) -> np.ndarray:
        """(N, 3) float32 sensor-frame points of one sweep, ego returns removed."""
        key = (seq.name, index)
        cached = self._cache.get(key)
        if cached is not None:
            self._cache.move_to_end(key)
            return cached
        pts = seq.checked_sweep(index, self.adapter.name).points_sensor  # errors name the file (and line)
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
            keep = rng > self.protocol.min_range_m
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
