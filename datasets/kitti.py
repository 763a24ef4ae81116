"""KITTI Odometry: ``sequences/NN/velodyne/NNNNNN.bin``, ``calib.txt``, ``times.txt``, poses.

Poses come from ``poses/NN.txt`` (the odometry ground truth, left-camera frame) or from
SemanticKITTI's ``sequences/NN/poses.txt``; both are converted to LiDAR-frame poses
``T_world_velo = inv(Tr) @ P @ Tr`` where ``Tr`` (calib.txt) is ``T_cam0_velo``.

A sequence of a split is read whole or refused with one ``DataError`` naming the file: a
sequence folder without poses, velodyne/ missing sweeps (inside or at the end: ``times.txt``
and the poses have one line per sweep), an empty ``.bin``, a ``Tr`` that is not rigid, or
``times.txt`` whose sweeps are not 10 Hz apart or have a gap (``pcfbench.protocol.validate.check_sweep_times``:
a sequence with a missing sweep is refused, not split).
"""

from __future__ import annotations

import dataclasses
import os

from pathlib import Path

import numpy as np

from pcfbench.dataset import DatasetAdapter, Sequence
from pcfbench.errors import DataError
from pcfbench.boxes import EgoBox
from pcfbench.protocol.validate import check_rigid, check_sweep_times

SPLITS = {
    "train": ("00", "01", "02", "03", "04", "05"),
    "val": ("06", "07"),
    "test": ("08", "09", "10"),
}


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """Parse ``key: 12 numbers`` lines into (3, 4) float64 arrays; errors name file and line."""
    if not path.is_file():
        raise DataError(f"KITTI calib file {path} is missing (expected 'P0: ...' .. 'Tr: ...' lines)")
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        try:
            values = [float(v) for v in rest.split()]
        except ValueError:
            values = []
        if not sep or len(values) != 12:
            raise DataError(f"KITTI calib file {path} line {lineno}: expected 'KEY: 12 numbers', got {line.strip()[:80]!r}")
        out[key.strip()] = np.asarray(values, dtype=np.float64).reshape(3, 4)
    if "Tr" not in out:
        raise DataError(f"KITTI calib file {path} has no 'Tr:' line (velodyne -> camera 0 transform)")
    return out


def read_poses(path: Path) -> np.ndarray:
    """(T, 4, 4) float64 from lines of 12 numbers (row-major 3x4)."""
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            values = []
        if len(values) != 12 or not np.all(np.isfinite(values)):
            raise DataError(f"KITTI poses file {path} line {lineno}: expected 12 finite numbers, got {line.strip()[:80]!r}")
        rows.append(values)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    if rows:
        T[:, :3, :] = np.asarray(rows).reshape(-1, 3, 4)
    return T


def pose_line(path: Path, index: int) -> int:
    """The line number (from 1) of pose ``index`` in ``path``, as :func:`read_poses` counts them
    (blank lines skipped); read only to word an error."""
    numbered = [n for n, line in enumerate(path.read_text().splitlines(), 1) if line.strip()]
    return numbered[index]


def read_times(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"KITTI times file {path} is missing (expected one timestamp in seconds per sweep)")
    values = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            values.append(float(line))
        except ValueError:
            raise DataError(f"KITTI times file {path} line {lineno}: expected seconds, got {line.strip()[:80]!r}") from None
    return np.round(np.asarray(values, dtype=np.float64) * 1e9).astype(np.int64)


def read_bin(path: Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, reflectance; errors name the file."""
    try:
        size = os.path.getsize(path)
    except OSError:
        raise DataError(f"KITTI sweep {path} is missing") from None
    if size % 16:
        raise DataError(f"KITTI sweep {path} has {size:,} bytes, not a multiple of 16 (x, y, z, reflectance float32)")
    if size == 0:
        raise DataError(f"KITTI sweep {path} is empty (0 bytes): a cut-short or placeholder file, not a sweep "
                        "(expected x, y, z, reflectance float32 per point)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


class KittiOdometry(DatasetAdapter):
    name = "kitti"
    version = "1"
    rate_hz = 10.0
    ego_box = EgoBox(-2.0, 3.5, -1.55, 1.55)
    default_settings = ("kitti-1s", "kitti-3s")
    default_split = "test"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return any(Path(root).glob("sequences/*/velodyne"))

    def splits(self) -> tuple[str, ...]:
        return tuple(SPLITS)

    def _seq_dir(self, name: str) -> Path:
        return self.root / "sequences" / name

    def _poses_path(self, name: str) -> Path | None:
        for p in (self.root / "poses" / f"{name}.txt", self._seq_dir(name) / "poses.txt"):
            if p.is_file():
                return p
        return None

    def _require_poses(self, name: str) -> Path:
        path = self._poses_path(name)
        if path is None:
            raise DataError(f"KITTI sequence {name}: poses file missing (looked for {self.root / 'poses' / f'{name}.txt'} "
                            f"and {self._seq_dir(name) / 'poses.txt'}); a sequence of the split is never left out")
        return path

    def sequence_names(self, split: str) -> list[str]:
        if split not in SPLITS:
            raise DataError(f"KITTI has no split {split!r} (known: {', '.join(SPLITS)})")
        if not (self.root / "sequences").is_dir():
            raise DataError(f"KITTI root {self.root} has no sequences/ folder (expected sequences/NN/velodyne/*.bin)")
        return [s for s in SPLITS[split] if self._seq_dir(s).is_dir()]

    def sequence(self, name: str) -> Sequence:
        seq = _open_sequence(str(self.root), name, self.rate_hz)
        velo, poses = self._seq_dir(name) / "velodyne", self._require_poses(name)
        return dataclasses.replace(
            seq,
            points_source=lambda i: f"KITTI sweep {velo / f'{i:06d}.bin'}",
            pose_source=lambda i: f"KITTI poses file {poses} line {pose_line(poses, i)} (pose of sweep {i:06d}.bin)",
        )

    def load_points(self, sequence: str, index: int) -> np.ndarray:
        path = self._seq_dir(sequence) / "velodyne" / f"{index:06d}.bin"
        return read_bin(path)[:, :3]

    def load_intensity(self, sequence: str, index: int) -> np.ndarray:
        """(N,) float32 reflectance of sweep ``index`` (the .bin's fourth column), points in order."""
        return read_bin(self._seq_dir(sequence) / "velodyne" / f"{index:06d}.bin")[:, 3]

    def data_files(self, split: str) -> list[Path]:
        """What ``split`` reads: each sequence's velodyne/*.bin, calib.txt, times.txt and poses."""
        files: list[Path] = []
        for name in self.sequence_names(split):
            seq_dir = self._seq_dir(name)
            files.extend(sorted((seq_dir / "velodyne").glob("*.bin")))
            files += [seq_dir / "calib.txt", seq_dir / "times.txt", self._require_poses(name)]
        return files



def _open_sequence(root: str, name: str, rate_hz: float = 10.0) -> Sequence:
    adapter = KittiOdometry(root)
    seq_dir = adapter._seq_dir(name)
    velo = seq_dir / "velodyne"
    if not velo.is_dir():
        raise DataError(f"KITTI sequence {seq_dir} has no velodyne/ folder")
    indices = sorted(int(p.stem) for p in velo.glob("*.bin") if p.stem.isdigit())
    n = indices[-1] + 1 if indices else 0
    if len(indices) != n:
        missing = sorted(set(range(n)) - set(indices))[:5]
        raise DataError(f"KITTI sequence {velo} is missing sweep(s) {', '.join(f'{i:06d}.bin' for i in missing)}")
    poses_path = adapter._require_poses(name)
    P = read_poses(poses_path)
    _check_count(f"KITTI poses file {poses_path}", "poses", len(P), n, velo)
    calib_path = seq_dir / "calib.txt"
    calib = read_calib(calib_path)
    Tr = np.eye(4)
    Tr[:3, :] = calib["Tr"]
    check_rigid(Tr, f"KITTI calib file {calib_path} Tr (velodyne -> camera 0)")
    T_world_velo = np.linalg.inv(Tr) @ P[:n] @ Tr
    times_path = seq_dir / "times.txt"
    times = read_times(times_path)
    _check_count(f"KITTI times file {times_path}", "timestamps", len(times), n, velo)
    if n > 1 and np.any(np.diff(times) <= 0):
        bad = int(np.argmax(np.diff(times) <= 0)) + 1
        raise DataError(f"KITTI times file {times_path}: timestamps not increasing at line {bad + 1}")
    check_sweep_times(times, rate_hz, f"KITTI times file {times_path}")
    return Sequence(name=name, T_world_sensor=T_world_velo, timestamps_ns=times, loader=adapter.load_points,
                    intensity_loader=adapter.load_intensity)


def _check_count(where: str, what: str, have: int, n: int, velo: Path) -> None:
    """One line per sweep: more lines than sweeps means sweeps missing at the end of velodyne/."""
    if have < n:
        raise DataError(f"{where} has {have} {what} for {n} sweeps in {velo} (expected one per sweep)")
    if have > n:
        first = f"{n:06d}.bin"
        raise DataError(f"{where} has {have} {what} but {velo} has {n} sweeps: sweep(s) {first} .. {have - 1:06d}.bin "
                        "missing (expected one sweep per line)")


# --- writer -------------------------------------------------------------------------------

#: A velodyne -> camera 0 transform in the shape of KITTI's (axes permuted, small offsets).
DEFAULT_TR = np.array(
    [
        [0.0, -1.0, 0.0, -0.012],
        [0.0, 0.0, -1.0, -0.054],
        [1.0, 0.0, 0.0, -0.292],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
_P0 = np.array([[718.856, 0.0, 607.1928, 0.0], [0.0, 718.856, 185.2157, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _fmt12(M: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(M)[:3, :4].reshape(-1))


def write_kitti_sequence(
    root: str | Path,
    name: str,
    points_sensor: list[np.ndarray],
    T_world_velo: np.ndarray,
    times_s: np.ndarray,
    Tr: np.ndarray = DEFAULT_TR,
    intensity: list[np.ndarray] | None = None,
    semantic_kitti_poses: bool = False,
) -> Path:
    """Write one sequence in the exact KITTI Odometry layout; returns its folder.

    points_sensor: T arrays (N, 3) in the velodyne frame; T_world_velo: (T, 4, 4) LiDAR poses.
    Poses are stored as the benchmark stores them: camera-0 poses ``Tr @ T_world_velo @ inv(Tr)``.
    """
    root = Path(root)
    seq_dir = root / "sequences" / name
    velo = seq_dir / "velodyne"
    velo.mkdir(parents=True, exist_ok=True)
    for i, pts in enumerate(points_sensor):
        pts = np.asarray(pts, dtype=np.float32)
        refl = np.zeros(len(pts), np.float32) if intensity is None else np.asarray(intensity[i], np.float32)
        tmp = velo / f".{i:06d}.bin.tmp"
        np.concatenate([pts, refl[:, None]], axis=1).astype(np.float32).tofile(tmp)
        os.replace(tmp, velo / f"{i:06d}.bin")
    P1 = _P0.copy()
    P1[0, 3] = -386.1448
    lines = [f"P0: {_fmt12(_P0)}", f"P1: {_fmt12(P1)}", f"P2: {_fmt12(_P0)}", f"P3: {_fmt12(_P0)}", f"Tr: {_fmt12(Tr)}"]
    (seq_dir / "calib.txt").write_text("\n".join(lines) + "\n")
    (seq_dir / "times.txt").write_text("".join(f"{t:.6e}\n" for t in np.asarray(times_s)))
    P = Tr @ np.asarray(T_world_velo) @ np.linalg.inv(Tr)
    pose_text = "".join(_fmt12(p) + "\n" for p in P)
    if semantic_kitti_poses:
        (seq_dir / "poses.txt").write_text(pose_text)
    else:
        (root / "poses").mkdir(parents=True, exist_ok=True)
        (root / "poses" / f"{name}.txt").write_text(pose_text)
    return seq_dir
