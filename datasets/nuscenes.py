"""nuScenes: ``<root>/<version>/*.json`` tables and ``samples/LIDAR_TOP/*.pcd.bin``, read directly.

A sequence is a scene; its sweeps are the LIDAR_TOP keyframes (2 Hz) of the scene's samples,
followed through the ``prev``/``next`` chain. Sensor pose ``T_world_sensor =
T_world_ego (ego_pose) @ T_ego_sensor (calibrated_sensor)``; quaternions are [w, x, y, z] and
timestamps microseconds. Point files are float32 x5 (x, y, z, intensity, ring) in the
LIDAR_TOP frame (x right, y forward, z up). No nuscenes-devkit dependency.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path

import numpy as np

from pcfbench.dataset import CheckReport, DatasetAdapter, Sequence
from pcfbench.errors import DataError
from pcfbench.geometry import invert, quat_wxyz_to_rotation, rotation_to_quat_wxyz
from pcfbench.options import option
from pcfbench.boxes import EgoBox
from pcfbench.datasets.layout import SequenceData

TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "log")
VERSIONS = ("v1.0-trainval", "v1.0-mini", "v1.0-test")
#: The splits of each release; "train"/"val" on v1.0-mini mean mini_train/mini_val.
VERSION_SPLITS = {
    "v1.0-trainval": ("train", "val"),
    "v1.0-mini": ("mini_train", "mini_val"),
    "v1.0-test": ("test",),
}
MINI_ALIASES = {"train": "mini_train", "val": "mini_val"}
POINT_COLUMNS = 5  # x, y, z, intensity, ring


def official_splits() -> dict[str, list[str]]:
    """The official scene lists (train 700, val 150, test 150, mini_train 8, mini_val 2)."""
    data = json.loads(resources.files(__package__).joinpath("nuscenes_splits.json").read_text())
    return {k: v for k, v in data.items() if isinstance(v, list)}


def read_pcd_bin(path: Path) -> np.ndarray:
    """(N, 5) float32 x, y, z, intensity, ring; errors name the file."""
    try:
        size = os.path.getsize(path)
    except OSError:
        raise DataError(f"nuScenes point file {path} is missing") from None
    if size % (4 * POINT_COLUMNS):
        raise DataError(
            f"nuScenes point file {path} has {size:,} bytes, not a multiple of 20 "
            "(x, y, z, intensity, ring float32): truncated?"
        )
    if size == 0:
        raise DataError(f"nuScenes point file {path} is empty (0 bytes): a cut-short or placeholder file, not a sweep "
                        "(expected x, y, z, intensity, ring float32 per point)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, POINT_COLUMNS)


def _pose(record: dict, table_path: Path) -> np.ndarray:
    try:
        q = np.asarray(record["rotation"], dtype=np.float64)
        t = np.asarray(record["translation"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise DataError(f"nuScenes table {table_path} token {record.get('token')}: expected 'rotation' [w, x, y, z] and 'translation' [x, y, z]") from None
    if q.shape != (4,) or t.shape != (3,) or not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise DataError(
            f"nuScenes table {table_path} token {record.get('token')}: rotation must be 4 finite numbers [w, x, y, z] "
            f"and translation 3, got {record['rotation']} / {record['translation']}"
        )
    if np.linalg.norm(q) < 1e-12:
        raise DataError(
            f"nuScenes table {table_path} token {record.get('token')}: rotation quaternion {list(q)} has zero norm "
            "(expected a unit quaternion [w, x, y, z])"
        )
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_rotation(q)
    T[:3, 3] = t
    return T


def _timestamp_us(sd: dict, path: Path, scene: str) -> int:
    """A sample_data record's ``timestamp``: whole microseconds (a JSON integer), else one
    error naming the record's token."""
    ts = sd.get("timestamp")
    if isinstance(ts, bool) or not isinstance(ts, int) or ts < 0:
        raise DataError(f"nuScenes table {path}: sample_data {sd.get('token')} (scene {scene}) has timestamp {ts!r}, "
                        "not a non-negative integer number of microseconds")
    return ts


@dataclass(frozen=True)
class NuScenesOptions:
    """Root options of ``nuscenes`` (``ROOT?version=v1.0-mini``)."""

    version: str | None = option(None, help=f"release folder of the JSON tables, e.g. {VERSIONS[1]} (default: the "
                                            f"first of {', '.join(VERSIONS)} present, else the first v* folder)")
    channel: str = option("LIDAR_TOP", help="sensor channel whose keyframe sweeps are read")


class NuScenes(DatasetAdapter):
    name = "nuscenes"
    version = "1"
    rate_hz = 2.0
    ego_box = EgoBox(-0.8, 0.8, -1.5, 2.5)
    default_settings = ("nuscenes-1s", "nuscenes-3s")
    default_split = "val"
    axes = "x right, y forward, z up"

    Options = NuScenesOptions

    def __init__(self, root, options: NuScenesOptions | None = None, **raw: object) -> None:
        super().__init__(root, options, **raw)
        self.channel = self.options.channel
        self.release = self.options.version or self._find_version(self.root)

    @staticmethod
    def _find_version(root: Path) -> str:
        for v in VERSIONS:
            if (root / v).is_dir():
                return v
        found = sorted(p.name for p in root.glob("v*") if p.is_dir()) if root.is_dir() else []
        if found:
            return found[0]
        raise DataError(f"nuScenes root {root} has no version folder (expected one of {', '.join(VERSIONS)} with the JSON tables)")

    @classmethod
    def detect(cls, root: Path) -> bool:
        return any((Path(root) / v / "scene.json").is_file() for v in VERSIONS)

    @property
    def table_dir(self) -> Path:
        return self.root / self.release

    def _read_table(self, name: str) -> list[dict]:
        path = self.table_dir / f"{name}.json"
        if not path.is_file():
            raise DataError(f"nuScenes table {path} is missing (expected a JSON list of {name} records)")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise DataError(f"nuScenes table {path} is not valid JSON ({exc}): truncated?") from None
        if not isinstance(data, list) or any(not isinstance(r, dict) or "token" not in r for r in data):
            raise DataError(f"nuScenes table {path}: expected a JSON list of records with a 'token'")
        return data

    @cached_property
    def _tables(self) -> dict[str, dict[str, dict]]:
        return {name: {r["token"]: r for r in self._read_table(name)} for name in TABLES}

    def _path(self, table: str) -> Path:
        return self.table_dir / f"{table}.json"

    @cached_property
    def _keyframes(self) -> dict[str, dict]:
        """sample token -> the keyframe sample_data record of ``self.channel``."""
        t = self._tables
        channel_of_cs = {}
        for cs in t["calibrated_sensor"].values():
            sensor = t["sensor"].get(cs.get("sensor_token"))
            if sensor is not None:
                channel_of_cs[cs["token"]] = sensor.get("channel")
        out = {}
        for sd in t["sample_data"].values():
            if sd.get("is_key_frame") and channel_of_cs.get(sd.get("calibrated_sensor_token")) == self.channel:
                out[sd["sample_token"]] = sd
        return out

    @cached_property
    def _scenes_by_name(self) -> dict[str, dict]:
        return {s["name"]: s for s in self._tables["scene"].values()}

    def splits(self) -> tuple[str, ...]:
        return VERSION_SPLITS.get(self.release, ("all",))

    def sequence_names(self, split: str) -> list[str]:
        if self.release == "v1.0-mini":
            split = MINI_ALIASES.get(split, split)
        if split not in self.splits():
            raise DataError(f"nuScenes {self.release} has no split {split!r} (known: {', '.join(self.splits())})")
        present = self._scenes_by_name
        if split == "all":
            return sorted(present)
        return [s for s in official_splits()[split] if s in present]

    def sequence(self, name: str) -> Sequence:
        scene = self._scenes_by_name.get(name)
        if scene is None:
            raise DataError(f"nuScenes table {self._path('scene')} has no scene named {name!r}")
        t = self._tables
        sample_path = self._path("sample")
        token, prev, chain = scene.get("first_sample_token"), "", []
        while token:
            rec = t["sample"].get(token)
            if rec is None:
                raise DataError(
                    f"nuScenes table {sample_path}: scene {name} links to sample token {token} "
                    f"(next of {prev or 'first_sample_token'}) which does not exist: the prev/next chain is broken"
                )
            if rec.get("prev", "") != prev:
                raise DataError(
                    f"nuScenes table {sample_path}: sample {token} of scene {name} has prev {rec.get('prev')!r}, "
                    f"expected {prev!r}: the prev/next chain is broken"
                )
            if rec.get("scene_token") != scene["token"]:
                raise DataError(f"nuScenes table {sample_path}: sample {token} reached from scene {name} belongs to scene token {rec.get('scene_token')}")
            chain.append(rec)
            if len(chain) > len(t["sample"]):
                raise DataError(f"nuScenes table {sample_path}: the next chain of scene {name} loops")
            prev, token = token, rec.get("next", "")
        if not chain or chain[-1]["token"] != scene.get("last_sample_token"):
            raise DataError(
                f"nuScenes table {self._path('scene')}: scene {name}'s next chain ends at {prev or 'nothing'}, "
                f"expected last_sample_token {scene.get('last_sample_token')}"
            )
        if scene.get("nbr_samples") not in (None, len(chain)):
            raise DataError(f"nuScenes table {self._path('scene')}: scene {name} says nbr_samples {scene['nbr_samples']} but its chain has {len(chain)}")
        poses, stamps, files, egos = [], [], [], []
        for rec in chain:
            sd = self._keyframes.get(rec["token"])
            if sd is None:
                raise DataError(f"nuScenes table {self._path('sample_data')}: sample {rec['token']} of scene {name} has no {self.channel} keyframe")
            ego = t["ego_pose"].get(sd.get("ego_pose_token"))
            cs = t["calibrated_sensor"].get(sd.get("calibrated_sensor_token"))
            if cs is None:
                raise DataError(
                    f"nuScenes table {self._path('calibrated_sensor')} has no token {sd.get('calibrated_sensor_token')} "
                    f"(calibration of sample_data {sd['token']})"
                )
            if ego is None:
                raise DataError(f"nuScenes table {self._path('ego_pose')} has no token {sd.get('ego_pose_token')} (ego pose of sample_data {sd['token']})")
            poses.append(_pose(ego, self._path("ego_pose")) @ _pose(cs, self._path("calibrated_sensor")))
            stamps.append(_timestamp_us(sd, self._path("sample_data"), name) * 1000)
            files.append(self.root / sd["filename"])
            egos.append(ego["token"])
        ts = np.asarray(stamps, dtype=np.int64)
        bad = np.flatnonzero(np.diff(ts) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataError(
                f"nuScenes table {self._path('sample_data')}: scene {name} keyframe {chain[i]['token']} "
                f"has timestamp {ts[i] // 1000} us, not after the previous keyframe's {ts[i - 1] // 1000} us"
            )

        def load(_seq: str, index: int) -> np.ndarray:
            return read_pcd_bin(files[index])[:, :3]

        def intensity(_seq: str, index: int) -> np.ndarray:
            return read_pcd_bin(files[index])[:, 3]

        return Sequence(name=name, T_world_sensor=np.stack(poses), timestamps_ns=ts, loader=load, intensity_loader=intensity,
                        points_source=lambda i: f"nuScenes point file {files[i]}",
                        pose_source=lambda i: f"nuScenes table {self._path('ego_pose')} token {egos[i]}")

    def check(self) -> CheckReport:
        report = CheckReport(layout=f"nuscenes {getattr(self, 'release', '?')}", root=str(self.root))
        missing = [str(self._path(n)) for n in TABLES if not self._path(n).is_file()]
        if missing:
            report.problems.append(f"nuScenes tables missing: {', '.join(missing)}")
            return report
        try:
            self._tables
        except DataError as exc:
            report.problems.append(str(exc))
            return report
        base = super().check()
        report.found.update(base.found)
        report.problems.extend(base.problems)
        listed = {s for v in official_splits().values() for s in v}
        extra = sorted(set(self._scenes_by_name) - listed)
        if extra:
            report.found["scenes outside the official splits"] = ", ".join(extra[:10]) + (" ..." if len(extra) > 10 else "")
        return report


# --- writer -------------------------------------------------------------------------------

#: A LIDAR_TOP mounting in the shape of nuScenes' (1.84 m up, yawed -90 deg: x right, y forward).
DEFAULT_T_EGO_LIDAR = np.array(
    [[0.0, 1.0, 0.0, 0.94], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.84], [0.0, 0.0, 0.0, 1.0]]
)


def _token(*parts: object) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _rec_pose(T: np.ndarray) -> dict:
    return {"rotation": [float(v) for v in rotation_to_quat_wxyz(T[:3, :3])], "translation": [float(v) for v in T[:3, 3]]}


def write_nuscenes(
    root: str | Path,
    sequences: list[SequenceData],
    version: str = "v1.0-trainval",
    keyframe_every: int = 1,
    T_ego_lidar: np.ndarray = DEFAULT_T_EGO_LIDAR,
    logfile: str = "n015-2018-07-24-11-22-45+0800",
) -> Path:
    """Write scenes in the exact nuScenes layout; returns the version folder.

    Each SequenceData is one scene (its ``name`` should be an official ``scene-NNNN`` name for
    the splits to find it); every ``keyframe_every``-th sweep is a keyframe under
    ``samples/LIDAR_TOP``, the rest go to ``sweeps/LIDAR_TOP`` as non-key sample_data.
    Points are LIDAR_TOP-frame (x right, y forward); intensity and ring are written as 0.
    """
    root = Path(root)
    tables: dict[str, list[dict]] = {n: [] for n in TABLES}
    sensor_token = _token("sensor", "LIDAR_TOP")
    tables["sensor"].append({"token": sensor_token, "channel": "LIDAR_TOP", "modality": "lidar"})
    cs_token = _token("calibrated_sensor", "LIDAR_TOP")
    tables["calibrated_sensor"].append({"token": cs_token, "sensor_token": sensor_token, **_rec_pose(T_ego_lidar), "camera_intrinsic": []})
    T_lidar_ego = invert(T_ego_lidar)
    for d in ("samples", "sweeps"):
        (root / d / "LIDAR_TOP").mkdir(parents=True, exist_ok=True)
    for seq in sequences:
        log_token = _token("log", seq.name)
        tables["log"].append({"token": log_token, "logfile": logfile, "vehicle": "n015", "date_captured": logfile[5:15], "location": "singapore-onenorth"})
        scene_token = _token("scene", seq.name)
        samples, sds = [], []
        for i in range(len(seq)):
            ts_us = int(seq.timestamps_ns[i] // 1000)
            key = i % keyframe_every == 0
            sd_token = _token("sample_data", seq.name, i)
            folder = "samples" if key else "sweeps"
            filename = f"{folder}/LIDAR_TOP/{logfile}__LIDAR_TOP__{ts_us}.pcd.bin"
            pts = np.asarray(seq.load(i), np.float32)[:, :3]
            out = np.zeros((len(pts), POINT_COLUMNS), np.float32)
            out[:, :3] = pts
            tmp = root / (filename + ".tmp")
            out.tofile(tmp)
            os.replace(tmp, root / filename)
            T_world_ego = seq.T_world_sensor[i] @ T_lidar_ego
            # nuScenes gives each sample_data its own ego pose with the same token.
            tables["ego_pose"].append({"token": sd_token, "timestamp": ts_us, **_rec_pose(T_world_ego)})
            if key:
                samples.append({"token": _token("sample", seq.name, i), "timestamp": ts_us, "scene_token": scene_token})
            sds.append({
                "token": sd_token, "sample_token": samples[-1]["token"] if samples else "", "ego_pose_token": sd_token,
                "calibrated_sensor_token": cs_token, "timestamp": ts_us, "fileformat": "pcd", "is_key_frame": key,
                "height": 0, "width": 0, "filename": filename,
            })
        for chain in (samples, sds):
            for j, rec in enumerate(chain):
                rec["prev"] = chain[j - 1]["token"] if j else ""
                rec["next"] = chain[j + 1]["token"] if j + 1 < len(chain) else ""
        tables["sample"].extend(samples)
        tables["sample_data"].extend(sds)
        tables["scene"].append({
            "token": scene_token, "log_token": log_token, "nbr_samples": len(samples),
            "first_sample_token": samples[0]["token"] if samples else "", "last_sample_token": samples[-1]["token"] if samples else "",
            "name": seq.name, "description": "written by pcfbench",
        })
    vdir = root / version
    vdir.mkdir(parents=True, exist_ok=True)
    for name, records in tables.items():
        (vdir / f"{name}.json").write_text(json.dumps(records, indent=0))
    return vdir
