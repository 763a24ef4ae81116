"""Argoverse 2 (Sensor and LiDAR datasets): ``<root>/<split>/<log_id>/sensors/lidar/<ts_ns>.feather``.

Sweeps are feather tables (x, y, z float16 in the real files, intensity uint8, laser_number
uint8, offset_ns int32) with points in the **ego-vehicle frame** (x forward, y left, z up), so
this adapter's sensor frame is the ego frame and ``T_world_sensor`` is the log's
``city_SE3_egovehicle`` pose at the sweep's timestamp. ``calibration/egovehicle_SE3_sensor.feather``
must be present (it is checked; the up_lidar mounting is reported by ``datasets check``).
Both the Sensor dataset (with annotations and cameras) and the LiDAR dataset share this layout.
pyarrow only; no av2 dependency.

A log with a sweep missing (two sweeps more than 1.5 periods apart at 10 Hz) is refused with
one ``DataError`` naming the log and the gap, never read with its later sweeps shifted in time
(``pcfbench.protocol.validate.check_sweep_times``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pyarrow.ipc as ipc

from pcfbench.dataset import CheckReport, DatasetAdapter, Sequence
from pcfbench.errors import DataError
from pcfbench.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz
from pcfbench.boxes import EgoBox
from pcfbench.protocol.validate import check_sweep_times
from pcfbench.datasets.layout import SequenceData

SPLITS = ("train", "val", "test")
POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
LIDAR_COLUMNS = {"x": "float", "y": "float", "z": "float"}


def _kind_ok(arrow_type: pa.DataType, kind: str) -> bool:
    if kind == "float":
        return pa.types.is_floating(arrow_type)
    if kind == "int":
        return pa.types.is_integer(arrow_type)
    if kind == "str":
        return pa.types.is_string(arrow_type) or pa.types.is_large_string(arrow_type)
    return True


def read_feather(path: Path, columns: dict[str, str], what: str, only: bool = False) -> pa.Table:
    """Read a feather file, checking ``columns`` (name -> 'float' | 'int' | 'str'); errors name the file.

    ``only``: read just those columns (the schema is checked first from the file footer).
    """
    if not path.is_file():
        raise DataError(f"Argoverse 2 {what} {path} is missing")
    try:
        with pa.memory_map(str(path)) as source:
            schema = ipc.open_file(source).schema
        for name, kind in columns.items():
            if name not in schema.names:
                raise DataError(f"Argoverse 2 {what} {path} has no column {name!r} (expected columns {', '.join(columns)}; found {', '.join(schema.names)})")
            if not _kind_ok(schema.field(name).type, kind):
                raise DataError(f"Argoverse 2 {what} {path}: column {name!r} has type {schema.field(name).type}, expected {kind}")
        return feather.read_table(path, columns=list(columns) if only else None, memory_map=True)
    except (pa.ArrowException, OSError) as exc:
        raise DataError(f"Argoverse 2 {what} {path} is not a readable feather file ({exc}): truncated?") from None


def read_lidar(path: Path) -> np.ndarray:
    """(N, 3) float32 ego-frame points of one sweep (float16 in the file, cast first)."""
    t = read_feather(path, LIDAR_COLUMNS, "LiDAR sweep", only=True)
    out = np.empty((t.num_rows, 3), np.float32)
    for j, c in enumerate("xyz"):
        start = 0
        for chunk in t.column(c).chunks:  # float16 chunks cast on assignment, no concatenation
            out[start:start + len(chunk), j] = chunk.to_numpy(zero_copy_only=False)
            start += len(chunk)
    return out


def read_lidar_intensity(path: Path) -> np.ndarray:
    """(N,) float32 intensity (0..255 as stored, uint8 in the real files) of one sweep's points, in order."""
    t = read_feather(path, {"intensity": "int"}, "LiDAR sweep", only=True)
    return t.column("intensity").to_numpy(zero_copy_only=False).astype(np.float32)


def _poses(table: pa.Table, path: Path, key: str) -> tuple[np.ndarray, np.ndarray]:
    """(keys, (K, 4, 4) float64) from the qw..tz_m columns; zero-norm quaternions are errors."""
    q = np.stack([table.column(c).to_numpy().astype(np.float64) for c in POSE_COLUMNS[:4]], axis=1)
    t = np.stack([table.column(c).to_numpy().astype(np.float64) for c in POSE_COLUMNS[4:]], axis=1)
    keys = table.column(key).to_numpy(zero_copy_only=False)
    norms = np.linalg.norm(q, axis=1)
    if (norms < 1e-12).any() or not (np.isfinite(q).all() and np.isfinite(t).all()):
        i = int(np.argmax((norms < 1e-12) | ~np.isfinite(norms) | ~np.isfinite(t).all(axis=1)))
        raise DataError(
            f"Argoverse 2 pose file {path} row {i} ({key} {keys[i]}): quaternion (qw, qx, qy, qz) {list(q[i])} "
            "has zero norm or a non-finite value (expected a unit quaternion)"
        )
    T = np.tile(np.eye(4), (len(q), 1, 1))
    T[:, :3, :3] = quat_wxyz_to_rotation(q)
    T[:, :3, 3] = t
    return keys, T


class Argoverse2(DatasetAdapter):
    name = "av2"
    version = "1"
    rate_hz = 10.0
    ego_box = EgoBox(-1.75, 3.75, -1.25, 1.25)
    default_settings = ("av2-1s", "av2-3s")
    default_split = "val"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return any(Path(root).glob("*/*/sensors/lidar")) and any(Path(root).glob("*/*/city_SE3_egovehicle.feather"))

    @property
    def layout(self) -> str:
        """'sensor' when logs carry annotations or cameras (Sensor dataset), else 'lidar'."""
        for log in self.root.glob("*/*"):
            if (log / "annotations.feather").is_file() or (log / "sensors" / "cameras").is_dir():
                return "sensor"
        return "lidar"

    def splits(self) -> tuple[str, ...]:
        return tuple(s for s in SPLITS if (self.root / s).is_dir()) or SPLITS

    def _log_dir(self, name: str) -> Path:
        split, _, log_id = name.partition("/")
        return self.root / split / log_id

    def sequence_names(self, split: str) -> list[str]:
        if split not in SPLITS:
            raise DataError(f"Argoverse 2 has no split {split!r} (known: {', '.join(SPLITS)})")
        d = self.root / split
        if not d.is_dir():
            raise DataError(f"Argoverse 2 root {self.root} has no {split}/ folder (expected {split}/<log_id>/sensors/lidar/<timestamp_ns>.feather)")
        return sorted(f"{split}/{p.name}" for p in d.iterdir() if (p / "sensors" / "lidar").is_dir())

    def sequence(self, name: str) -> Sequence:
        log = self._log_dir(name)
        lidar = log / "sensors" / "lidar"
        if not lidar.is_dir():
            raise DataError(f"Argoverse 2 log {log} has no sensors/lidar/ folder")
        stamps = []
        for p in lidar.glob("*.feather"):
            if not p.stem.isdigit():
                raise DataError(f"Argoverse 2 sweep {p}: file name must be the timestamp in nanoseconds (<ts_ns>.feather)")
            stamps.append(int(p.stem))
        ts = np.asarray(sorted(stamps), dtype=np.int64)
        check_sweep_times(ts, self.rate_hz, f"Argoverse 2 log {lidar} (sweep file names are timestamps in ns)")
        read_feather(log / "calibration" / "egovehicle_SE3_sensor.feather", {"sensor_name": "str", **{c: "float" for c in POSE_COLUMNS}}, "calibration file")
        pose_path = log / "city_SE3_egovehicle.feather"
        table = read_feather(pose_path, {"timestamp_ns": "int", **{c: "float" for c in POSE_COLUMNS}}, "pose file")
        keys, T = _poses(table, pose_path, "timestamp_ns")
        keys = keys.astype(np.int64)
        if np.any(np.diff(keys) <= 0):
            i = int(np.argmax(np.diff(keys) <= 0)) + 1
            raise DataError(
                f"Argoverse 2 pose file {pose_path}: timestamp_ns {keys[i]} at row {i} is not after {keys[i - 1]} "
                "(expected strictly increasing timestamps)"
            )
        idx = np.searchsorted(keys, ts)
        found = (idx < len(keys)) & (keys[np.minimum(idx, len(keys) - 1)] == ts) if len(keys) else np.zeros(len(ts), bool)
        if not found.all():
            missing = ts[~found][:3]
            raise DataError(
                f"Argoverse 2 pose file {pose_path} has no pose at timestamp_ns {', '.join(map(str, missing))} "
                f"(the sweeps {', '.join(f'{m}.feather' for m in missing)} need one each)"
            )
        files = [lidar / f"{t}.feather" for t in ts]
        return Sequence(name=name, T_world_sensor=T[idx], timestamps_ns=ts, loader=lambda _s, i: read_lidar(files[i]),
                        intensity_loader=lambda _s, i: read_lidar_intensity(files[i]),
                        points_source=lambda i: f"Argoverse 2 LiDAR sweep {files[i]}",
                        pose_source=lambda i: f"Argoverse 2 pose file {pose_path} row {idx[i]} (timestamp_ns {ts[i]})")

    def check(self) -> CheckReport:
        base = super().check()
        base.layout = f"av2 {self.layout} dataset"
        return base


# --- writer -------------------------------------------------------------------------------

#: up_lidar mounted roughly as on the Argoverse 2 vehicles (metres, ego frame).
DEFAULT_T_EGO_UPLIDAR = np.array([[1.0, 0, 0, 1.35], [0, 1.0, 0, 0.0], [0, 0, 1.0, 1.64], [0, 0, 0, 1.0]])


def _pose_columns(T: np.ndarray) -> dict[str, np.ndarray]:
    q = np.stack([rotation_to_quat_wxyz(R) for R in T[:, :3, :3]])
    cols = {c: q[:, k] for k, c in enumerate(POSE_COLUMNS[:4])}
    cols.update({c: T[:, k, 3] for k, c in enumerate(POSE_COLUMNS[4:])})
    return cols


def write_av2_lidar(path: Path, points_ego: np.ndarray, intensity: np.ndarray | None = None) -> None:
    """One sweep file with the real columns and dtypes (x, y, z float16)."""
    n = len(points_ego)
    pts = np.asarray(points_ego, np.float32)
    table = pa.table({
        "x": pa.array(pts[:, 0].astype(np.float16)),
        "y": pa.array(pts[:, 1].astype(np.float16)),
        "z": pa.array(pts[:, 2].astype(np.float16)),
        "intensity": pa.array(np.zeros(n, np.uint8) if intensity is None else np.asarray(intensity, np.uint8)),
        "laser_number": pa.array((np.arange(n) % 64).astype(np.uint8)),
        "offset_ns": pa.array(np.zeros(n, np.int32)),
    })
    tmp = path.with_name(path.name + ".tmp")
    feather.write_feather(table, tmp)
    tmp.replace(path)


def write_av2(root: str | Path, sequences: list[SequenceData], layout: str = "lidar", T_ego_uplidar: np.ndarray = DEFAULT_T_EGO_UPLIDAR) -> Path:
    """Write logs in the Argoverse 2 layout: ``<root>/<split>/<log_id>/...``; returns root.

    Each SequenceData is one log (``name`` is the log id, or ``split/log_id``); its sensor frame
    is the ego frame. ``layout="sensor"`` also writes an (empty) ``annotations.feather`` with the
    Sensor dataset's columns, as the Sensor dataset has one per log.
    """
    if layout not in ("lidar", "sensor"):
        raise ValueError(f"layout must be 'lidar' or 'sensor', got {layout!r}")
    root = Path(root)
    for seq in sequences:
        log_id = seq.name.rpartition("/")[2]
        log = root / (seq.split or "val") / log_id
        lidar = log / "sensors" / "lidar"
        lidar.mkdir(parents=True, exist_ok=True)
        (log / "calibration").mkdir(exist_ok=True)
        for i in range(len(seq)):
            write_av2_lidar(lidar / f"{int(seq.timestamps_ns[i])}.feather", np.asarray(seq.load(i))[:, :3])
        poses = {"timestamp_ns": pa.array(np.asarray(seq.timestamps_ns, np.int64))}
        poses.update({k: pa.array(v) for k, v in _pose_columns(np.asarray(seq.T_world_sensor)).items()})
        feather.write_feather(pa.table(poses), log / "city_SE3_egovehicle.feather")
        down = T_ego_uplidar.copy()
        down[2, 3] -= 0.1
        calib = {"sensor_name": pa.array(["up_lidar", "down_lidar"])}
        calib.update({k: pa.array(v) for k, v in _pose_columns(np.stack([T_ego_uplidar, down])).items()})
        feather.write_feather(pa.table(calib), log / "calibration" / "egovehicle_SE3_sensor.feather")
        if layout == "sensor":
            ann = {"timestamp_ns": pa.array([], pa.int64()), "track_uuid": pa.array([], pa.string()), "category": pa.array([], pa.string())}
            for c in ("length_m", "width_m", "height_m", *POSE_COLUMNS):
                ann[c] = pa.array([], pa.float64())
            ann["num_interior_pts"] = pa.array([], pa.int64())
            feather.write_feather(pa.table(ann), log / "annotations.feather")
    return root
