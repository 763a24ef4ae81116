"""Write sequences as MCAP recordings: ROS 2 PointCloud2 + /tf, or foxglove.PointCloud + FrameTransform.

The layouts ``pcfbench.datasets.mcap`` reads: a cloud topic in the sensor frame and transforms
world -> base_link (dynamic, one per sweep) and base_link -> sensor (static), so the reader
must chain links exactly as with a real robot's TF tree.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

from pcfbench.geometry import invert, rotation_to_quat_wxyz
from pcfbench.datasets.layout import SequenceData

POINTCLOUD2_MSGDEF = """std_msgs/Header header
uint32 height
uint32 width
sensor_msgs/PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: sensor_msgs/PointField
uint8 INT8=1
uint8 UINT8=2
uint8 INT16=3
uint8 UINT16=4
uint8 INT32=5
uint8 UINT32=6
uint8 FLOAT32=7
uint8 FLOAT64=8
string name
uint32 offset
uint8 datatype
uint32 count
"""

TFMESSAGE_MSGDEF = """geometry_msgs/TransformStamped[] transforms
================================================================================
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
geometry_msgs/Transform transform
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: geometry_msgs/Transform
geometry_msgs/Vector3 translation
geometry_msgs/Quaternion rotation
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
================================================================================
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
"""

#: base_link -> sensor mounting used by the writers (1.8 m up, 0.5 m forward).
DEFAULT_T_BASE_SENSOR = np.array([[1.0, 0, 0, 0.5], [0, 1.0, 0, 0], [0, 0, 1.0, 1.8], [0, 0, 0, 1.0]])


def _time(ns: int) -> dict:
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


def _xyzw(T: np.ndarray) -> tuple[dict, dict]:
    w, x, y, z = rotation_to_quat_wxyz(T[:3, :3])
    return {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])}, {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}


def pointcloud2_message(points: np.ndarray, stamp_ns: int, frame_id: str, big_endian: bool = False,
                        extra_bytes: int = 4, row_padding: int = 0, height: int = 1) -> dict:
    """A PointCloud2 dict with x, y, z float32 and an intensity field (plus padding bytes)."""
    pts = np.asarray(points, np.float32)
    n = len(pts)
    if n % height:
        raise ValueError(f"{n} points do not split into {height} rows")
    width = n // height
    order = ">" if big_endian else "<"
    step = 16 + extra_bytes
    rec = np.zeros(n, dtype=np.dtype({"names": ["x", "y", "z", "intensity"], "formats": [order + "f4"] * 4, "offsets": [0, 4, 8, 12], "itemsize": step}))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rows = rec.tobytes()
    row_step = width * step + row_padding
    if row_padding:
        rows = b"".join(rows[r * width * step:(r + 1) * width * step] + b"\0" * row_padding for r in range(height))
    fields = [{"name": c, "offset": 4 * k, "datatype": 7, "count": 1} for k, c in enumerate(("x", "y", "z", "intensity"))]
    return {"header": {"stamp": _time(stamp_ns), "frame_id": frame_id}, "height": height, "width": width, "fields": fields,
            "is_bigendian": big_endian, "point_step": step, "row_step": row_step, "data": rows, "is_dense": True}


def _tf(parent: str, child: str, T: np.ndarray, stamp_ns: int) -> dict:
    tr, rot = _xyzw(T)
    return {"header": {"stamp": _time(stamp_ns), "frame_id": parent}, "child_frame_id": child, "transform": {"translation": tr, "rotation": rot}}


def write_ros2_recording(path: str | Path, seq: SequenceData, topic: str = "/lidar/points", world_frame: str = "map",
                         sensor_frame: str = "lidar", base_frame: str = "base_link", T_base_sensor: np.ndarray = DEFAULT_T_BASE_SENSOR,
                         **cloud_kw) -> Path:
    """A ROS 2 MCAP: PointCloud2 on ``topic``, /tf world->base (per sweep), /tf_static base->sensor."""
    from mcap_ros2.writer import Writer

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    T_sensor_base = invert(T_base_sensor)
    with open(path, "wb") as f:
        w = Writer(f)
        cloud_schema = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        tf_schema = w.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE_MSGDEF)
        t0 = int(seq.timestamps_ns[0]) if len(seq) else 0
        w.write_message("/tf_static", tf_schema, {"transforms": [_tf(base_frame, sensor_frame, T_base_sensor, t0)]}, log_time=t0)
        for i in range(len(seq)):
            ts = int(seq.timestamps_ns[i])
            T_world_base = seq.T_world_sensor[i] @ T_sensor_base
            w.write_message("/tf", tf_schema, {"transforms": [_tf(world_frame, base_frame, T_world_base, ts)]}, log_time=ts)
            w.write_message(topic, cloud_schema, pointcloud2_message(np.asarray(seq.load(i))[:, :3], ts, sensor_frame, **cloud_kw), log_time=ts)
        w.finish()
    return path


def foxglove_pointcloud(points: np.ndarray, stamp_ns: int, frame_id: str, extra: dict[str, np.ndarray] | None = None):
    """A foxglove.PointCloud protobuf message with x, y, z float32 (little-endian), then one
    float32 field per entry of ``extra`` (name -> (N,) values, e.g. a per-point error)."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    pts = np.asarray(points, np.float32)[:, :3]
    names = list(extra or {})
    cols = [pts] + [np.asarray(extra[n], np.float32).reshape(-1, 1) for n in names]
    data = np.ascontiguousarray(np.hstack(cols) if names else pts).astype("<f4")
    msg = PointCloud(frame_id=frame_id, point_stride=4 * (3 + len(names)), data=data.tobytes())
    msg.timestamp.FromNanoseconds(int(stamp_ns))
    msg.pose.orientation.w = 1.0
    for k, c in enumerate(["x", "y", "z"] + names):
        msg.fields.append(PackedElementField(name=c, offset=4 * k, type=PackedElementField.FLOAT32))
    return msg


def foxglove_transform(parent: str, child: str, T: np.ndarray, stamp_ns: int):
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

    tr, rot = _xyzw(T)
    msg = FrameTransform(parent_frame_id=parent, child_frame_id=child)
    msg.timestamp.FromNanoseconds(int(stamp_ns))
    msg.translation.x, msg.translation.y, msg.translation.z = tr["x"], tr["y"], tr["z"]
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = rot["x"], rot["y"], rot["z"], rot["w"]
    return msg


_JSON_SCHEMAS = {
    "foxglove.PointCloud": {"type": "object", "title": "foxglove.PointCloud", "properties": {
        "timestamp": {"type": "object"}, "frame_id": {"type": "string"}, "pose": {"type": "object"},
        "point_stride": {"type": "integer"}, "fields": {"type": "array"}, "data": {"type": "string", "contentEncoding": "base64"}}},
    "foxglove.FrameTransform": {"type": "object", "title": "foxglove.FrameTransform", "properties": {
        "timestamp": {"type": "object"}, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
        "translation": {"type": "object"}, "rotation": {"type": "object"}}},
}


def write_foxglove_recording(path: str | Path, seq: SequenceData, encoding: str = "protobuf", topic: str = "/lidar",
                             world_frame: str = "world", sensor_frame: str = "lidar", base_frame: str = "base_link",
                             T_base_sensor: np.ndarray = DEFAULT_T_BASE_SENSOR) -> Path:
    """A Foxglove MCAP: foxglove.PointCloud on ``topic`` and foxglove.FrameTransform on /tf."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    T_sensor_base = invert(T_base_sensor)
    t0 = int(seq.timestamps_ns[0]) if len(seq) else 0
    if encoding == "protobuf":
        from mcap_protobuf.writer import Writer

        with open(path, "wb") as f, Writer(f) as w:
            w.write_message("/tf", foxglove_transform(base_frame, sensor_frame, T_base_sensor, t0), log_time=t0, publish_time=t0)
            for i in range(len(seq)):
                ts = int(seq.timestamps_ns[i])
                w.write_message("/tf", foxglove_transform(world_frame, base_frame, seq.T_world_sensor[i] @ T_sensor_base, ts), log_time=ts, publish_time=ts)
                w.write_message(topic, foxglove_pointcloud(seq.load(i), ts, sensor_frame), log_time=ts, publish_time=ts)
        return path
    if encoding != "json":
        raise ValueError(f"encoding must be 'protobuf' or 'json', got {encoding!r}")
    from mcap.writer import Writer as McapWriter

    def tf_json(parent, child, T, ts):
        tr, rot = _xyzw(T)
        return {"timestamp": _time(ts), "parent_frame_id": parent, "child_frame_id": child, "translation": tr, "rotation": rot}

    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        ids = {name: w.register_schema(name=name, encoding="jsonschema", data=json.dumps(s).encode()) for name, s in _JSON_SCHEMAS.items()}
        cloud_ch = w.register_channel(topic=topic, message_encoding="json", schema_id=ids["foxglove.PointCloud"])
        tf_ch = w.register_channel(topic="/tf", message_encoding="json", schema_id=ids["foxglove.FrameTransform"])
        w.add_message(tf_ch, log_time=t0, publish_time=t0, data=json.dumps(tf_json(base_frame, sensor_frame, T_base_sensor, t0)).encode())
        for i in range(len(seq)):
            ts = int(seq.timestamps_ns[i])
            w.add_message(
                tf_ch, log_time=ts, publish_time=ts,
                data=json.dumps(tf_json(world_frame, base_frame, seq.T_world_sensor[i] @ T_sensor_base, ts)).encode(),
            )
            pts = np.ascontiguousarray(np.asarray(seq.load(i), np.float32)[:, :3]).astype("<f4")
            cloud = {"timestamp": _time(ts), "frame_id": sensor_frame,
                     "pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
                     "point_stride": 12, "fields": [{"name": c, "offset": 4 * k, "type": 7} for k, c in enumerate("xyz")],
                     "data": base64.b64encode(pts.tobytes()).decode()}
            w.add_message(cloud_ch, log_time=ts, publish_time=ts, data=json.dumps(cloud).encode())
        w.finish()
    return path


def write_mcap_dataset(root: str | Path, sequences: list[SequenceData], flavour: str = "ros2") -> Path:
    """A folder of recordings, one ``<name>.mcap`` per sequence (``flavour``: ros2, protobuf or json)."""
    root = Path(root)
    for seq in sequences:
        out = root / f"{seq.name}.mcap"
        if flavour == "ros2":
            write_ros2_recording(out, seq)
        else:
            write_foxglove_recording(out, seq, encoding=flavour)
    return root
