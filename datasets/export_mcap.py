"""Export one sample (past sweeps, forecasts, ground truth, ego trajectory) to an MCAP for Foxglove.

Every cloud is a ``foxglove.PointCloud`` in the frame ``sensor`` at its own timestamp; a
``foxglove.FrameTransform`` world -> sensor on ``/tf`` at each of those timestamps places it
in the world, so Foxglove's 3D panel shows past, forecast and ground truth where they belong
as the timeline plays. Topics:

- ``/past/points``: the past sweeps (t <= 0), oldest first;
- ``/ground_truth/points``: the future sweeps;
- ``/forecast/<variant>/points``: each method variant's forecast of the future sweeps, one
  topic per variant (``/forecast/raycast-voxel:voxel=0.4/points``: the method spec as on the
  command line), with a float32 field ``error`` per point: its distance (m) to the nearest
  ground-truth point of that sweep (NaN when the sweep has no ground truth);
- ``/ego/trajectory``: ``foxglove.PosesInFrame`` with every past and future sensor pose (world);
- ``/ego/pose``: ``foxglove.PoseInFrame`` of the sensor at each timestamp.

Two MCAP metadata records: ``pcfbench.sample`` (sample id, dataset, split, setting, policy,
sequence, reference index, pcfbench version) and ``pcfbench.scores`` (per variant, a JSON list
of every future sweep's metric values, as the results store's rows hold them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, GroundTruth, Sample
from pcfbench.geometry import invert, rotation_to_quat_wxyz, transform_points
from pcfbench.datasets.mcap_writer import foxglove_pointcloud, foxglove_transform

WORLD = "world"
SENSOR = "sensor"


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


def export_sample(path: str | Path, sample: Sample, truth: GroundTruth | None = None,
                  forecasts: dict[str, Forecast] | None = None, metadata: dict[str, str] | None = None,
                  scores: dict[str, list[dict]] | None = None) -> Path:
    """Write ``sample`` (and ground truth and forecasts by topic name) to ``path``; returns it.

    ``metadata``: the ``pcfbench.sample`` record's extra string fields (split, setting, ...);
    ``scores``: per forecast name, its future sweeps' metric rows (``pcfbench.scores``)."""
    import json

    import pcfbench
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
    from mcap_protobuf.writer import Writer

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    T_world_ref = np.asarray(sample.T_world_ref, np.float64)
    stamps = [int(t) for t in sample.past_timestamps_ns] + [int(t) for t in sample.future_timestamps_ns]
    T_world_sensor = [T_world_ref @ T for T in (*sample.past_T_ref_sensor, *sample.future_T_ref_sensor)]
    msgs: list[tuple[int, int, str, object]] = []  # (time, order, topic, message)

    def cloud(topic: str, k: int, points_ref: np.ndarray, order: int, extra: dict | None = None) -> None:
        pts_sensor = transform_points(invert(T_world_sensor[k]) @ T_world_ref, np.asarray(points_ref, np.float32))
        msgs.append((stamps[k], order, topic, foxglove_pointcloud(pts_sensor, stamps[k], SENSOR, extra)))

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
        cloud("/past/points", k, pts, 2)
    if truth is not None:
        for j, pts in enumerate(truth.future_points_ref):
            cloud("/ground_truth/points", P + j, pts, 2)
    for name, fc in (forecasts or {}).items():
        clouds = fc.points_ref if fc.points_ref is not None else Forecast.from_depths(sample, fc.depths).points_ref
        for j, pts in enumerate(clouds):
            gt = truth.future_points_ref[j] if truth is not None else np.zeros((0, 3), np.float32)
            cloud(f"/forecast/{name}/points", P + j, pts, 3, {"error": point_errors(pts, gt)})
    msgs.sort(key=lambda m: (m[0], m[1]))
    record = {"sample_id": sample.sample_id, "dataset": sample.dataset, "sequence": sample.sequence,
              "ref_index": str(sample.ref_index), "pcfbench_version": pcfbench.__version__, **(metadata or {})}
    with open(path, "wb") as f, Writer(f) as w:
        for t, _, topic, msg in msgs:
            w.write_message(topic, msg, log_time=t, publish_time=t)
        w.add_metadata("pcfbench.sample", {k: str(v) for k, v in record.items()})
        if scores:
            w.add_metadata("pcfbench.scores", {name: json.dumps(rows, allow_nan=True) for name, rows in scores.items()})
    return path
