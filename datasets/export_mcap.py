"""Write samples (past sweeps, forecasts, ground truth, ego trajectory) to an MCAP for Foxglove.

Every cloud is a ``foxglove.PointCloud`` in the frame ``sensor`` at its own timestamp; a
``foxglove.FrameTransform`` world -> sensor on ``/tf`` at each of those timestamps places it
in the world, so Foxglove's 3D panel shows past, forecast and ground truth where they belong
as the timeline plays. Topics:

- ``/past/points``: the past sweeps (t <= 0), oldest first;
- ``/ground_truth/points``: the future sweeps;
- ``/forecast/<method>[/<option>_<value>...][/ck_<sha>]/points``: each method variant's
  forecast of the future sweeps, one topic per variant (``raycast-voxel:voxel=0.4`` ->
  ``/forecast/raycast_voxel/voxel_0p4/points``), with a float32 field ``error`` per point:
  its distance (m) to the nearest ground-truth point of that sweep (NaN when the sweep has no
  ground truth). Topic names hold only letters, digits, ``_`` and ``/`` (:func:`forecast_topic`),
  so Foxglove's message paths take them unquoted; the ``pcfbench.topics`` record maps each
  back to its exact method spec;
- ``/ego/trajectory``: ``foxglove.PosesInFrame`` with every past and future sensor pose (world);
- ``/ego/pose``: ``foxglove.PoseInFrame`` of the sensor at each timestamp;
- ``/pcfbench/sample``: a ``foxglove.Log`` at each sample's first timestamp naming it.

Past and ground-truth clouds carry a float32 field ``intensity`` when the dataset stores one
(KITTI's reflectance, nuScenes' intensity: :meth:`pcfbench.dataset.Sequence.load_intensity`).

Several samples share one file on one timeline: each on its own time span, the first at its
recorded times, each next one shifted to start ``SAMPLE_GAP_NS`` after the previous one ends
(samples of one sequence overlap in time; shifted, they never do). Message times and every
header timestamp are the shifted ones; the ``pcfbench.samples`` record gives each sample's
shift, so a recorded time is ``log_time - offset_ns``.

Metadata records (string -> string; JSON where a value is structured):

- ``pcfbench.export``: what the file holds (dataset, split, setting, policy, metric
  versions, pcfbench version, the source: a results store or a recomputation);
- ``pcfbench.topics``: forecast topic -> JSON of its method, options, spec and, from a store,
  its cell and checkpoint;
- ``pcfbench.samples``: sample id -> JSON ``{sequence, ref_index, offset_ns, start_ns, end_ns}``
  (``start_ns``/``end_ns``: its span of message times in this file);
- ``pcfbench.scores``: sample id -> JSON ``{topic: [one metric row per future sweep]}`` as the
  results store's rows hold them, or ``{topic: {"failed": error}}`` for a method that failed
  on that sample in the run.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from pcfbench.data import Forecast, GroundTruth, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.geometry import invert, rotation_to_quat_wxyz, transform_points
from pcfbench.datasets.mcap_writer import foxglove_pointcloud, foxglove_transform

WORLD = "world"
SENSOR = "sensor"
#: Time between one sample's last message and the next sample's first in a file of several.
SAMPLE_GAP_NS = 1_000_000_000
#: What a topic name may hold: ROS 2's topic characters, none of which Foxglove makes you quote.
TOPIC_CHARS = re.compile(r"^(/[A-Za-z0-9_]+)+$")


def _slug(text: str) -> str:
    """``text`` in letters, digits and ``_``: a decimal point between digits becomes ``p``
    (``0.4`` -> ``0p4``), a minus sign before a digit ``m``, every other run of characters ``_``."""
    text = re.sub(r"(?<=\d)\.(?=\d)", "p", str(text))
    text = re.sub(r"(?:(?<=^)|(?<=[^A-Za-z0-9]))-(?=\d)", "m", text)
    return re.sub(r"[^A-Za-z0-9_]+", "_", text).strip("_") or "_"


def forecast_topic(method: str, options: dict[str, Any] | None = None, checkpoint_sha256: str | None = None) -> str:
    """The forecast topic of a method variant: ``/forecast/<method>/<key>_<value>.../points``,
    options sorted by key, a trained method's checkpoint as ``ck_<first 8 of its sha256>``."""
    parts = [_slug(method)] + [_slug(f"{k}_{v}") for k, v in sorted((options or {}).items())]
    if checkpoint_sha256:
        parts.append(f"ck_{checkpoint_sha256[:8]}")
    return "/forecast/" + "/".join(parts) + "/points"


def unique_topics(variants: dict[str, str]) -> dict[str, str]:
    """``variants`` (exact label -> topic from :func:`forecast_topic`) with every topic unique:
    labels whose topics coincide (``m:a=x-y`` and ``m:a=x_y`` both give ``/forecast/m/a_x_y/points``)
    each get ``_h`` and 8 hex digits of their label's sha256 on the topic's last variant part."""
    by_topic: dict[str, list[str]] = {}
    for label, topic in variants.items():
        by_topic.setdefault(topic, []).append(label)
    out = {}
    for label, topic in variants.items():
        if len(by_topic[topic]) > 1:
            h = hashlib.sha256(label.encode()).hexdigest()[:8]
            topic = topic[: -len("/points")] + f"_h{h}/points"
        out[label] = topic
    if len(set(out.values())) != len(out):  # two labels of one sha256 prefix: never quietly merged
        raise PcfbenchError(f"forecast topics collide even with a hash suffix: {sorted(out.items())}")
    return out


@dataclass(frozen=True, eq=False)
class SampleExport:
    """One sample and what to show with it.

    forecasts: topic -> forecast; scores: topic -> its metric rows (one per future sweep);
    failed: topic -> the error of a method that failed on this sample (no forecast shown);
    past_intensity / future_intensity: per cloud (N_k,) float32, aligned with
    ``sample.past_points_ref`` / ``truth.future_points_ref``; None: the dataset has none.
    """

    sample: Sample
    truth: GroundTruth | None = None
    forecasts: dict[str, Forecast] = field(default_factory=dict)
    scores: dict[str, list[dict]] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    past_intensity: tuple[np.ndarray, ...] | None = None
    future_intensity: tuple[np.ndarray, ...] | None = None

    @property
    def clouds(self) -> int:
        """How many point clouds this sample writes."""
        future = len(self.truth.future_points_ref) if self.truth is not None else 0
        return len(self.sample.past_points_ref) + future * (1 + len(self.forecasts))


def _pose_msg(pose, T: np.ndarray) -> None:
    w, x, y, z = rotation_to_quat_wxyz(T[:3, :3])
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = float(x), float(y), float(z), float(w)


def point_errors(pred_points: np.ndarray, gt_points: np.ndarray) -> np.ndarray:
    """(K,) float32 distance (m) of each predicted point to the nearest ground-truth point (NaN
    without ground truth): the nearest-neighbour pass of the Chamfer metrics."""
    from pcfbench.metrics.nn import Index

    if len(gt_points) == 0:
        return np.full(len(pred_points), np.nan, np.float32)
    if len(pred_points) == 0:
        return np.zeros(0, np.float32)
    d2, _ = Index(np.ascontiguousarray(gt_points, np.float64)).query(np.ascontiguousarray(pred_points, np.float64))
    return np.sqrt(d2).astype(np.float32)


def _stamps(item: SampleExport) -> list[int]:
    s = item.sample
    return [int(t) for t in s.past_timestamps_ns] + [int(t) for t in s.future_timestamps_ns]


def _sample_messages(item: SampleExport, offset: int) -> list[tuple[int, int, str, object]]:
    """(shifted time, order, topic, message) of one sample's messages."""
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

    sample, truth = item.sample, item.truth
    T_world_ref = np.asarray(sample.T_world_ref, np.float64)
    stamps = [t + offset for t in _stamps(item)]
    T_world_sensor = [T_world_ref @ T for T in (*sample.past_T_ref_sensor, *sample.future_T_ref_sensor)]
    msgs: list[tuple[int, int, str, object]] = []

    def cloud(topic: str, k: int, points_ref: np.ndarray, order: int, extra: dict | None = None) -> None:
        pts_sensor = transform_points(invert(T_world_sensor[k]) @ T_world_ref, np.asarray(points_ref, np.float32))
        msgs.append((stamps[k], order, topic, foxglove_pointcloud(pts_sensor, stamps[k], SENSOR, extra)))

    log = Log(level=Log.INFO, name="pcfbench", message=f"sample {sample.sample_id} ({sample.dataset} sequence "
              f"{sample.sequence}, reference sweep {sample.ref_index}); times shifted by {offset} ns")
    log.timestamp.FromNanoseconds(stamps[0])
    msgs.append((stamps[0], 0, "/pcfbench/sample", log))
    trajectory = PosesInFrame(frame_id=WORLD)
    trajectory.timestamp.FromNanoseconds(stamps[0])
    for k, T in enumerate(T_world_sensor):
        msgs.append((stamps[k], 0, "/tf", foxglove_transform(WORLD, SENSOR, T, stamps[k])))
        pose = PoseInFrame(frame_id=WORLD)
        pose.timestamp.FromNanoseconds(stamps[k])
        _pose_msg(pose.pose, T)
        msgs.append((stamps[k], 1, "/ego/pose", pose))
        _pose_msg(trajectory.poses.add(), T)
    msgs.append((stamps[0], 1, "/ego/trajectory", trajectory))
    P = len(sample.past_points_ref)
    for k, pts in enumerate(sample.past_points_ref):
        cloud("/past/points", k, pts, 2, {"intensity": item.past_intensity[k]} if item.past_intensity is not None else None)
    if truth is not None:
        for j, pts in enumerate(truth.future_points_ref):
            extra = {"intensity": item.future_intensity[j]} if item.future_intensity is not None else None
            cloud("/ground_truth/points", P + j, pts, 2, extra)
    for topic, fc in item.forecasts.items():
        clouds = fc.points_ref if fc.points_ref is not None else Forecast.from_depths(sample, fc.depths).points_ref
        for j, pts in enumerate(clouds):
            gt = truth.future_points_ref[j] if truth is not None else np.zeros((0, 3), np.float32)
            cloud(topic, P + j, pts, 3, {"error": point_errors(pts, gt)})
    return msgs


def write_mcap(path: str | Path, items: Iterable[SampleExport], topics: dict[str, dict] | None = None,
               record: dict[str, Any] | None = None) -> tuple[Path, int]:
    """Write ``items`` to ``path``, each sample on its own span of one timeline (the first at its
    recorded times, each next one ``SAMPLE_GAP_NS`` after the previous one's last message);
    returns the path and the number of point clouds.

    ``items`` may be a generator: each sample is written as it comes, so memory holds one
    sample's clouds, and the file appears (renamed into place) only once every sample is
    written: an error half-way leaves no file. ``topics``: forecast topic -> what it shows
    (method, options, spec, ...: ``pcfbench.topics``); every forecast topic needs an entry when
    given. ``record``: the ``pcfbench.export`` record's fields."""
    import os

    import pcfbench
    from mcap_protobuf.writer import Writer

    path = Path(path)
    for topic in sorted(topics or {}):
        if not TOPIC_CHARS.match(topic):
            raise PcfbenchError(f"{path}: topic {topic!r} holds characters Foxglove users must quote "
                                "(only letters, digits, _ and / are written)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    samples: dict[str, str] = {}
    scores: dict[str, str] = {}
    used: set[str] = set()
    end, clouds, dataset = None, 0, ""
    try:
        with open(tmp, "wb") as f, Writer(f) as w:
            for item in items:
                s = item.sample
                if s.sample_id in samples:
                    raise PcfbenchError(f"{path}: sample {s.sample_id} given twice")
                mine = set(item.forecasts) | set(item.scores) | set(item.failed)
                bad = sorted(t for t in mine if not TOPIC_CHARS.match(t) or (topics is not None and t not in topics))
                if bad:
                    raise PcfbenchError(f"{path}: forecast topic(s) {', '.join(bad)} are not in the topic record "
                                        "(or hold characters Foxglove users must quote)")
                used |= mine
                stamps = _stamps(item)
                offset = 0 if end is None else end + SAMPLE_GAP_NS - min(stamps)
                msgs = sorted(_sample_messages(item, offset), key=lambda m: (m[0], m[1]))
                for t, _, topic, msg in msgs:
                    w.write_message(topic, msg, log_time=t, publish_time=t)
                end = msgs[-1][0]
                samples[s.sample_id] = json.dumps({"sequence": s.sequence, "ref_index": int(s.ref_index),
                                                   "offset_ns": offset, "start_ns": msgs[0][0], "end_ns": end})
                per_topic: dict[str, Any] = dict(item.scores)
                per_topic.update({t: {"failed": err} for t, err in item.failed.items()})
                if per_topic:
                    scores[s.sample_id] = json.dumps(per_topic, allow_nan=True)
                clouds += item.clouds
                dataset = s.dataset
            if not samples:
                raise PcfbenchError(f"{path}: no sample to export")
            export = {"dataset": dataset, "samples": str(len(samples)), "pcfbench_version": pcfbench.__version__,
                      **(record or {})}
            w.add_metadata("pcfbench.export", {k: str(v) for k, v in export.items()})
            w.add_metadata("pcfbench.samples", samples)
            if topics:
                w.add_metadata("pcfbench.topics", {t: json.dumps(v, sort_keys=True) for t, v in topics.items() if t in used})
            if scores:
                w.add_metadata("pcfbench.scores", scores)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path, clouds


def per_sample_name(sample_id: str) -> str:
    """The file of one sample in a ``--per-sample`` folder: ``08/000010`` -> ``08_000010.mcap``."""
    return _slug(sample_id.replace("/", "_")) + ".mcap"
