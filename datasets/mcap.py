"""MCAP recordings: ROS 2 ``sensor_msgs/msg/PointCloud2`` or ``foxglove.PointCloud`` with TF poses.

One ``.mcap`` file, or a folder of them, is a dataset; each file is a sequence (named by its
path relative to the root, without ``.mcap``), all in the split ``all``. Clouds come from
ROS 2 PointCloud2 (CDR: ``fields``, ``point_step``, ``row_step`` and ``is_bigendian`` honoured;
NaN points of non-dense clouds dropped) or ``foxglove.PointCloud`` (protobuf or JSON; its
``pose`` applied). Poses come from ``tf2_msgs/msg/TFMessage`` (``/tf``, ``/tf_static``) or
``foxglove.FrameTransform`` messages: ``T_world_sensor`` is the chain of transforms from the
world frame to the cloud's frame at the cloud's own timestamp (dynamic links interpolated).

Options (keyword arguments, or root syntax ``rec.mcap?topic=/points&world_frame=map``):
``topic`` (default: the only point-cloud topic), ``world_frame`` (default: the root of the
TF tree), ``sensor_frame`` (default: the cloud's frame_id), ``rate_hz`` (default: measured and
snapped to 2 or 10 Hz within 2 %; a lower rate that divides the recorded one keeps every
k-th sweep), ``ego_box`` (``xmin,xmax,ymin,ymax`` metres in the sensor frame) and
``tf_tolerance_ms`` (how far outside a dynamic link's samples a cloud may be; default 60).

Refused with one ``DataError`` naming the file: two clouds logged at the same time (a cloud is
loaded by its log time), a cloud frame that is its own world frame (no transforms to it, or
the cloud frame is the root of the TF tree: every pose would be the identity), and a sweep
missing (two clouds more than 1.5 periods of the recorded rate apart,
``pcfbench.protocol.validate.check_sweep_times``): such a recording is refused, not split.
"""

from __future__ import annotations

import base64
import inspect
import json
import weakref
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import mcap  # the mcap library, not this module (absolute import)
import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader

from pcfbench.dataset import CheckReport, DatasetAdapter, Sequence
from pcfbench.errors import DataError, PcfbenchError
from pcfbench.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz
from pcfbench.options import option
from pcfbench.boxes import EgoBox
from pcfbench.protocol.validate import check_sweep_times

assert hasattr(mcap, "reader"), "pcfbench.datasets.mcap must import the mcap library"

CLOUD_SCHEMAS = ("sensor_msgs/msg/PointCloud2", "foxglove.PointCloud")
TF_SCHEMAS = ("tf2_msgs/msg/TFMessage", "foxglove.FrameTransform", "foxglove.FrameTransforms")
#: ROS PointField datatypes and foxglove PackedElementField numeric types, as NumPy codes.
ROS_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FOXGLOVE_TYPES = {1: "u1", 2: "i1", 3: "u2", 4: "i2", 5: "u4", 6: "i4", 7: "f4", 8: "f8"}
SNAP_RATES = (2.0, 10.0)


@lru_cache(maxsize=1)
def _factories():
    from mcap_protobuf.decoder import DecoderFactory as ProtobufFactory
    from mcap_ros2.decoder import DecoderFactory as Ros2Factory

    return (Ros2Factory(), ProtobufFactory())


class _Decoder:
    """Decodes raw messages by schema (ROS 2 CDR, protobuf, JSON); caches one decoder per schema."""

    def __init__(self) -> None:
        self._cache: dict[int, object] = {}

    def __call__(self, schema, channel, message):
        fn = self._cache.get(schema.id if schema else -1)
        if fn is None:
            if channel.message_encoding == "json":
                fn = lambda data: json.loads(data)  # noqa: E731
            else:
                fn = next((f for f in (fac.decoder_for(channel.message_encoding, schema) for fac in _factories()) if f), None)
                if fn is None:
                    raise DataError(
                        f"topic {channel.topic}: cannot decode message encoding {channel.message_encoding!r} "
                        f"with schema {schema.name if schema else None!r}"
                    )
            self._cache[schema.id if schema else -1] = fn
        return fn(message.data)


def _get(msg, name, default=None):
    return msg.get(name, default) if isinstance(msg, dict) else getattr(msg, name, default)


def _stamp_ns(stamp) -> int:
    """builtin_interfaces/Time or google.protobuf.Timestamp or JSON {sec, nsec} -> int ns."""
    if stamp is None:
        return 0
    sec = _get(stamp, "sec", None)
    if sec is None:
        sec = _get(stamp, "seconds", 0)
    nsec = _get(stamp, "nanosec", None)
    if nsec is None:
        nsec = _get(stamp, "nsec", None)
    if nsec is None:
        nsec = _get(stamp, "nanos", 0)
    return int(sec) * 1_000_000_000 + int(nsec)


def _transform(translation, rotation_xyzw, where: str) -> np.ndarray:
    q = np.array([_get(rotation_xyzw, k, 0.0) for k in ("w", "x", "y", "z")], dtype=np.float64)
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-12:
        raise DataError(f"{where}: rotation quaternion (w, x, y, z) {list(q)} has zero norm or non-finite values (expected a unit quaternion)")
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_rotation(q)
    T[:3, 3] = [_get(translation, k, 0.0) for k in ("x", "y", "z")]
    return T


def _slerp_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    q0, q1 = rotation_to_quat_wxyz(T0[:3, :3]), rotation_to_quat_wxyz(T1[:3, :3])
    if np.dot(q0, q1) < 0:
        q1 = -q1
    d = float(np.clip(np.dot(q0, q1), -1.0, 1.0))
    theta = np.arccos(d)
    if theta < 1e-9:
        q = q0
    else:
        q = (np.sin((1 - a) * theta) * q0 + np.sin(a * theta) * q1) / np.sin(theta)
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_rotation(q)
    T[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
    return T


def cloud_points(msg, schema_name: str, where: str) -> np.ndarray:
    """(N, 3) float32 points of a decoded PointCloud2 / foxglove.PointCloud in its frame."""
    if schema_name == "sensor_msgs/msg/PointCloud2":
        fields = {
            _get(f, "name"): (int(_get(f, "offset")), ROS_TYPES.get(int(_get(f, "datatype"))), int(_get(f, "count", 1) or 1))
            for f in _get(msg, "fields")
        }
        step, width, height = int(_get(msg, "point_step")), int(_get(msg, "width")), int(_get(msg, "height"))
        row_step, data = int(_get(msg, "row_step")), _get(msg, "data")
        order = ">" if _get(msg, "is_bigendian") else "<"
        pose = None
    else:
        fields = {_get(f, "name"): (int(_get(f, "offset", 0)), FOXGLOVE_TYPES.get(int(_numeric(_get(f, "type")))), 1) for f in _get(msg, "fields")}
        step, data = int(_get(msg, "point_stride")), _get(msg, "data")
        if isinstance(data, str):
            data = base64.b64decode(data)
        width, height, order = (len(data) // step if step else 0), 1, "<"
        row_step = width * step
        pose = _get(msg, "pose")
    for name in ("x", "y", "z"):
        if name not in fields:
            raise DataError(f"{where}: point cloud has no field {name!r} (fields: {', '.join(fields)}); expected x, y, z")
    for name, (offset, code, count) in fields.items():
        if code is None:
            raise DataError(f"{where}: field {name!r} has an unknown datatype")
        size = np.dtype(code).itemsize * count
        if offset + size > step:
            raise DataError(
                f"{where}: point_step {step} is smaller than field {name!r} (offset {offset} + {size} bytes); "
                f"expected point_step >= {offset + size}"
            )
    if row_step < width * step:
        raise DataError(f"{where}: row_step {row_step} is smaller than width {width} x point_step {step}")
    data = bytes(data) if not isinstance(data, (bytes, bytearray, memoryview)) else data
    if len(data) < row_step * (height - 1) + width * step:
        raise DataError(f"{where}: data has {len(data):,} bytes, expected {row_step * height:,} (height {height} x row_step {row_step}): truncated cloud")
    dtype = np.dtype({"names": ["x", "y", "z"], "formats": [order + fields[c][1] for c in "xyz"],
                      "offsets": [fields[c][0] for c in "xyz"], "itemsize": step})
    buf = np.frombuffer(data, dtype=np.uint8, count=row_step * (height - 1) + width * step if height else 0)
    if height > 1 and row_step != width * step:
        padded = np.zeros(row_step * height, np.uint8)
        padded[: len(buf)] = buf
        buf = np.ascontiguousarray(padded.reshape(height, row_step)[:, : width * step]).reshape(-1)
    offsets = [fields[c][0] for c in "xyz"]
    if all(fields[c][1] == "f4" for c in "xyz") and offsets[1] == offsets[0] + 4 and offsets[2] == offsets[0] + 8 and step % 4 == 0 and offsets[0] % 4 == 0:
        # the common packed case: a strided float32 view, one copy
        flat = np.frombuffer(buf, dtype=order + "f4", count=width * height * step // 4).reshape(-1, step // 4)
        pts = flat[:, offsets[0] // 4: offsets[0] // 4 + 3].astype(np.float32)
    else:
        rec = np.frombuffer(buf, dtype=dtype, count=width * height)
        pts = np.empty((len(rec), 3), np.float32)
        for j, c in enumerate("xyz"):
            pts[:, j] = rec[c]
    if not np.isfinite(pts).all():  # non-dense clouds mark missing returns with NaN
        pts = pts[np.isfinite(pts).all(axis=1)]
    if pose is not None:
        T = _transform(_get(pose, "position") or {}, _get(pose, "orientation") or {"w": 1.0}, where)
        if not np.allclose(T, np.eye(4)):
            pts = (pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    return pts


def _numeric(value) -> int:
    if isinstance(value, str):  # JSON may spell the enum
        return {"UINT8": 1, "INT8": 2, "UINT16": 3, "INT16": 4, "UINT32": 5, "INT32": 6, "FLOAT32": 7, "FLOAT64": 8}.get(value, 0)
    return int(value)


class _Recording:
    """One scanned file: cloud topics, TF links, cloud stamps and log times."""

    def __init__(self, path: Path, topic: str | None) -> None:
        self.path = path
        self.cloud_topics: dict[str, str] = {}
        self.tf_topics: dict[str, str] = {}
        # child -> (parent, [(stamp_ns, T_parent_child)], static)
        self.links: dict[str, tuple[str, list, bool]] = {}
        self.clouds: list[tuple[int, int, str]] = []  # (stamp_ns, log_time, frame_id)
        decode = _Decoder()
        try:
            with open(path, "rb") as f:
                reader = make_reader(f)
                summary = reader.get_summary()
                if summary is None:
                    raise DataError(f"MCAP file {path} has no summary section: cut short? (expected a complete MCAP file)")
                for ch in summary.channels.values():
                    schema = summary.schemas.get(ch.schema_id)
                    name = schema.name if schema else ""
                    if name in CLOUD_SCHEMAS:
                        self.cloud_topics[ch.topic] = name
                    elif name in TF_SCHEMAS:
                        self.tf_topics[ch.topic] = name
                if not self.cloud_topics:
                    raise DataError(f"MCAP file {path} has no point-cloud topic (expected a channel with schema {' or '.join(CLOUD_SCHEMAS)})")
                if topic is None:
                    if len(self.cloud_topics) > 1:
                        raise DataError(
                            f"MCAP file {path} has several point-cloud topics ({', '.join(sorted(self.cloud_topics))}): "
                            "pick one with the option topic=..."
                        )
                    topic = next(iter(self.cloud_topics))
                elif topic not in self.cloud_topics:
                    raise DataError(f"MCAP file {path} has no point-cloud topic {topic!r} (found: {', '.join(sorted(self.cloud_topics)) or 'none'})")
                self.topic = topic
                self.schema_name = self.cloud_topics[topic]
                for schema, channel, message in reader.iter_messages(topics=[topic, *self.tf_topics]):
                    if channel.topic == topic:
                        head = self._cloud_header(decode(schema, channel, message))
                        self.clouds.append((head[0] or message.log_time, message.log_time, head[1]))
                    else:
                        self._add_tf(decode(schema, channel, message), channel.topic, schema.name, message.log_time)
        except McapError as exc:
            raise DataError(f"MCAP file {path} is not a readable MCAP file ({type(exc).__name__}: {exc}): cut short?") from None
        except (EOFError, ValueError, KeyError, IndexError, OSError) as exc:
            if isinstance(exc, DataError):
                raise
            raise DataError(f"MCAP file {path} could not be read ({type(exc).__name__}: {exc}): cut short or corrupt?") from None

    def _cloud_header(self, msg) -> tuple[int, str]:
        if self.schema_name == "sensor_msgs/msg/PointCloud2":
            header = _get(msg, "header")
            return _stamp_ns(_get(header, "stamp")), _get(header, "frame_id", "")
        return _stamp_ns(_get(msg, "timestamp")), _get(msg, "frame_id", "")

    def _add_tf(self, msg, topic: str, schema_name: str, log_time: int) -> None:
        static = topic.endswith("tf_static")
        if schema_name == "tf2_msgs/msg/TFMessage":
            items = [(_get(_get(t, "header"), "frame_id"), _get(t, "child_frame_id"), _stamp_ns(_get(_get(t, "header"), "stamp")),
                      _get(_get(t, "transform"), "translation"), _get(_get(t, "transform"), "rotation")) for t in _get(msg, "transforms")]
        else:
            many = _get(msg, "transforms") if schema_name == "foxglove.FrameTransforms" else [msg]
            items = [(_get(t, "parent_frame_id"), _get(t, "child_frame_id"), _stamp_ns(_get(t, "timestamp")),
                      _get(t, "translation"), _get(t, "rotation")) for t in many]
        for parent, child, stamp, tr, rot in items:
            stamp = stamp or log_time
            where = f"MCAP file {self.path} topic {topic} transform {parent} -> {child} at {stamp} ns"
            T = _transform(tr, rot, where)
            old = self.links.get(child)
            if old is not None and old[0] != parent:
                raise DataError(f"MCAP file {self.path} topic {topic}: frame {child!r} has two parents ({old[0]!r} and {parent!r}); expected a tree")
            if old is None:
                old = (parent, [], static)
                self.links[child] = old
            old[1].append((stamp, T))

    def frames(self) -> set[str]:
        return set(self.links) | {p for p, _, _ in self.links.values()}

    def root_of(self, frame: str) -> str:
        seen = {frame}
        while frame in self.links:
            frame = self.links[frame][0]
            if frame in seen:
                raise DataError(f"MCAP file {self.path}: the transform tree has a loop through {frame!r}")
            seen.add(frame)
        return frame

    @cached_property
    def _link_arrays(self) -> dict[str, tuple[str, np.ndarray, np.ndarray, bool]]:
        out = {}
        for child, (parent, samples, static) in self.links.items():
            samples = sorted(samples, key=lambda s: s[0])
            out[child] = (parent, np.array([s[0] for s in samples], np.int64), np.stack([s[1] for s in samples]), static or len(samples) == 1)
        return out

    def lookup(self, world: str, frame: str, stamp: int, tolerance_ns: int) -> np.ndarray:
        """T_world_frame at ``stamp``: the chain of links, dynamic ones interpolated."""
        T = np.eye(4)
        f = frame
        while f != world:
            link = self._link_arrays.get(f)
            if link is None:
                raise DataError(
                    f"MCAP file {self.path} topic {self.topic} cloud at {stamp} ns: no transform from {world!r} to {frame!r} "
                    f"(frame {f!r} has no parent; frames known: {', '.join(sorted(self.frames())) or 'none'})"
                )
            parent, times, Ts, static = link
            if static:
                T_link = Ts[-1]
            else:
                if stamp < times[0] - tolerance_ns or stamp > times[-1] + tolerance_ns:
                    raise DataError(
                        f"MCAP file {self.path} topic {self.topic} cloud at {stamp} ns: no transform {parent} -> {f} "
                        f"available at that time (samples from {times[0]} to {times[-1]} ns)"
                    )
                k = int(np.searchsorted(times, stamp))
                if k <= 0:
                    T_link = Ts[0]
                elif k >= len(times):
                    T_link = Ts[-1]
                else:
                    a = (stamp - times[k - 1]) / max(times[k] - times[k - 1], 1)
                    T_link = _slerp_pose(Ts[k - 1], Ts[k], float(a))
            T = T_link @ T
            f = parent
        return T


@dataclass(frozen=True)
class McapOptions:
    """Root options of ``mcap`` (``rec.mcap?topic=/points&world_frame=map``)."""

    topic: str | None = option(None, help="point-cloud topic (default: the recording's only point-cloud topic)")
    world_frame: str | None = option(None, help="TF frame the poses are expressed in (default: the root of the TF tree)")
    sensor_frame: str | None = option(None, help="TF frame of the sensor (default: the cloud's frame_id)")
    rate_hz: float | None = option(None, help="sweep rate, Hz; a lower rate that divides the recorded one keeps every "
                                              "k-th sweep (default: measured, snapped to 2 or 10 Hz within 2 %)")
    ego_box: tuple[float, ...] | None = option(None, help="xmin,xmax,ymin,ymax of the ego vehicle, metres in the sensor "
                                                          "frame (default: the adapter's ego_box)")
    tf_tolerance_ms: float = option(60.0, help="how far outside a dynamic TF link's samples a cloud may be, ms")

    def __post_init__(self) -> None:
        if self.ego_box is not None and len(self.ego_box) != 4:
            raise PcfbenchError(f"MCAP option ego_box={self.ego_box!r}: expected xmin,xmax,ymin,ymax")
        if self.rate_hz is not None and not float(self.rate_hz) > 0:
            raise PcfbenchError(f"MCAP option rate_hz={self.rate_hz!r}: expected a positive rate in Hz")
        if not float(self.tf_tolerance_ms) >= 0:
            raise PcfbenchError(f"MCAP option tf_tolerance_ms={self.tf_tolerance_ms!r}: expected milliseconds >= 0")


class McapRecording(DatasetAdapter):
    name = "mcap"
    version = "1"
    rate_hz = 10.0  # nominal; each instance measures its recording's rate
    ego_box = EgoBox(-2.0, 3.5, -1.55, 1.55)
    default_settings = ()
    default_split = "all"

    Options = McapOptions

    def __init__(self, root, options: McapOptions | None = None, **raw: object) -> None:
        super().__init__(root, options, **raw)
        o = self.options
        self.topic = o.topic or None
        self.world_frame = o.world_frame or None
        self.sensor_frame = o.sensor_frame or None
        self._wanted_rate = float(o.rate_hz) if o.rate_hz is not None else None
        self.tf_tolerance_ns = int(float(o.tf_tolerance_ms) * 1e6)
        if o.ego_box is not None:
            self.ego_box = EgoBox(*(float(v) for v in o.ego_box))
        self._recordings: dict[str, _Recording] = {}
        self.stride = 1
        try:  # the rate is the first recording's; a broken file is reported by check()/sequence()
            files = self._files()
            first = self.recording(files[0][0]) if files else None
        except DataError:
            first = None
        if first is not None:
            self.rate_hz, self.stride = self._rate(files[0][0])

    @classmethod
    def detect(cls, root: Path) -> bool:
        root = Path(root)
        return root.suffix == ".mcap" if root.is_file() else any(root.rglob("*.mcap"))

    def _files(self) -> list[tuple[str, Path]]:
        if self.root.is_file():
            return [(self.root.stem, self.root)]
        if not self.root.is_dir():
            raise DataError(f"MCAP root {self.root} is neither an .mcap file nor a folder")
        return [(str(p.relative_to(self.root).with_suffix("")), p) for p in sorted(self.root.rglob("*.mcap"))]

    def recording(self, name: str) -> _Recording:
        if name not in self._recordings:
            paths = dict(self._files())
            if name not in paths:
                raise DataError(f"MCAP root {self.root} has no recording {name!r} (found: {', '.join(paths) or 'none'})")
            self._recordings[name] = _Recording(paths[name], self.topic)
        return self._recordings[name]

    def _rate(self, name: str) -> tuple[float, int]:
        rec = self.recording(name)
        stamps = np.array(sorted(c[0] for c in rec.clouds), np.int64)
        if len(stamps) < 2:
            return (self._wanted_rate or type(self).rate_hz), 1
        native = 1e9 / float(np.median(np.diff(stamps)))
        target = self._wanted_rate
        if target is None:
            snap = [r for r in SNAP_RATES if abs(native - r) <= 0.02 * r]
            return (snap[0] if snap else round(native, 2)), 1
        stride = max(1, int(round(native / target)))
        if abs(native / stride - target) > 0.02 * target:
            raise DataError(
                f"MCAP file {rec.path} topic {rec.topic} is recorded at {native:.2f} Hz: "
                f"keeping every k-th sweep cannot give {target:g} Hz "
                f"(rates reachable: {', '.join(f'{native / k:.2f}' for k in range(1, 6))} Hz)"
            )
        return target, stride

    def splits(self) -> tuple[str, ...]:
        return ("all",)

    def sequence_names(self, split: str) -> list[str]:
        if split != "all":
            raise DataError(f"MCAP recordings have one split, 'all' (got {split!r})")
        return [name for name, _ in self._files()]

    def sequence(self, name: str) -> Sequence:
        rec = self.recording(name)
        stamps_all = np.array(sorted(c[0] for c in rec.clouds), np.int64)
        if len(stamps_all) > 1:
            native = 1e9 / float(np.median(np.diff(stamps_all)))
            if abs(native / self.stride - self.rate_hz) > 0.02 * self.rate_hz:
                raise DataError(
                    f"MCAP file {rec.path} topic {rec.topic} is recorded at {native:.2f} Hz, "
                    f"but this dataset runs at {self.rate_hz:g} Hz (every {self.stride} sweep(s), from its first recording): "
                    "one rate per dataset, or open the file alone"
                )
        logged: dict[int, int] = {}
        for k, (_stamp, log_time, _frame) in enumerate(rec.clouds):
            if log_time in logged:
                raise DataError(f"MCAP file {rec.path} topic {rec.topic}: clouds {logged[log_time]} and {k} have the same "
                                f"log time {log_time} ns (a cloud is read by its log time; expected one cloud per log time)")
            logged[log_time] = k
        clouds = rec.clouds[:: self.stride]
        stamps = np.array([c[0] for c in clouds], np.int64)
        bad = np.flatnonzero(np.diff(stamps) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataError(
                f"MCAP file {rec.path} topic {rec.topic}: cloud {i} has timestamp {stamps[i]} ns, "
                f"not after the previous cloud's {stamps[i - 1]} ns (expected increasing header stamps)"
            )
        if len(stamps_all) > 1:
            native = 1e9 / float(np.median(np.diff(stamps_all)))
            check_sweep_times(stamps_all, native, f"MCAP file {rec.path} topic {rec.topic} (header stamps)")
        poses = []
        for stamp, _log, frame in clouds:
            frame = self.sensor_frame or frame
            world = self.world_frame or rec.root_of(frame)
            if world == frame:
                raise DataError(
                    f"MCAP file {rec.path} topic {rec.topic} cloud at {stamp} ns: the cloud frame {frame!r} is its own world "
                    f"frame ({'it is the root of the TF tree' if frame in rec.frames() else 'no transform mentions it'}; "
                    f"frames known: {', '.join(sorted(rec.frames())) or 'none'}): every pose would be the identity. "
                    "Expected /tf (or foxglove.FrameTransform) from a world frame down to the cloud frame; "
                    "pick them with world_frame=... and sensor_frame=...")
            poses.append(rec.lookup(world, frame, int(stamp), self.tf_tolerance_ns))
        log_times = [c[1] for c in clouds]
        path, topic, schema_name = rec.path, rec.topic, rec.schema_name

        decode = _Decoder()
        state: dict[str, object] = {}  # one open reader per sequence: the summary is parsed once

        def load(_seq: str, index: int) -> np.ndarray:
            t = log_times[index]
            if "reader" not in state:
                state["file"] = open(path, "rb")  # noqa: SIM115 - kept open for the sequence's lifetime
                state["reader"] = make_reader(state["file"])
            for schema, channel, message in state["reader"].iter_messages(topics=[topic], **_time_window(state["reader"], t)):
                where = f"MCAP file {path} topic {topic} cloud at {clouds[index][0]} ns"
                return cloud_points(decode(schema, channel, message), schema_name, where)
            raise DataError(f"MCAP file {path} topic {topic}: no cloud at log time {t} ns")

        T = np.stack(poses) if poses else np.zeros((0, 4, 4))
        out = Sequence(name=name, T_world_sensor=T, timestamps_ns=stamps, loader=load,
                       points_source=lambda i: f"MCAP file {path} topic {topic} cloud at {clouds[i][0]} ns",
                       pose_source=lambda i: f"MCAP file {path}: transform to the frame of the cloud at {clouds[i][0]} ns")
        weakref.finalize(out, _close_state, state)  # the open reader goes with the sequence
        return out

    def check(self) -> CheckReport:
        report = CheckReport(layout="mcap", root=str(self.root))
        try:
            files = self._files()
        except DataError as exc:
            report.problems.append(str(exc))
            return report
        report.found["recordings"] = str(len(files))
        for name, _ in files:
            try:
                rec = self.recording(name)
            except DataError as exc:
                report.problems.append(str(exc))
                continue
            report.found[f"{name}: point-cloud topics"] = ", ".join(f"{t} ({s})" for t, s in sorted(rec.cloud_topics.items()))
            report.found[f"{name}: transform topics"] = ", ".join(f"{t} ({s})" for t, s in sorted(rec.tf_topics.items())) or "none"
            cloud_frames = sorted({c[2] for c in rec.clouds})
            report.found[f"{name}: frames"] = (
                f"clouds in {', '.join(cloud_frames) or '?'}; "
                f"tree roots {', '.join(sorted({rec.root_of(f) for f in rec.frames()})) or 'none'}; "
                f"all: {', '.join(sorted(rec.frames()))}"
            )
        base = DatasetAdapter.check(self)
        report.found.update(base.found)
        report.problems.extend(p for p in base.problems if p not in report.problems)
        report.found["rate"] = f"{self.rate_hz:g} Hz (every {self.stride} sweep(s)); settings at this rate: " + (
            ", ".join(n for n, s in _settings().items() if abs(s.rate_hz - self.rate_hz) < 1e-6) or "none (pass ?rate_hz=...)")
        return report


def _time_window(reader, t: int) -> dict[str, int]:
    """Messages logged exactly at ``t`` (newer mcap names the bounds starting_at / ending_at)."""
    if "starting_at" in inspect.signature(reader.iter_messages).parameters:
        return {"starting_at": t, "ending_at": t}
    return {"start_time": t, "end_time": t + 1}


def _close_state(state: dict) -> None:
    f = state.pop("file", None)
    state.pop("reader", None)
    if f is not None:
        f.close()


def _settings():
    from pcfbench.protocol import SETTINGS

    return SETTINGS
