"""Sweeps per second loaded by each adapter, beside the rate of just reading the same files' bytes.

Realistic sweep sizes (nuScenes ~35,000 points, Argoverse 2 ~100,000, KITTI ~120,000, an MCAP
PointCloud2 ~100,000) with ``PCFBENCH_BENCH_FULL=1``; small sweeps otherwise so the default
(disabled) run stays fast. Run::

    PCFBENCH_BENCH_FULL=1 .venv/bin/python -m pytest tests/benchmarks/test_bench_adapters.py --benchmark-enable

Each adapter's ``load`` benchmark and its ``bytes`` baseline (``Path.read_bytes`` of the
same files, page cache warm) load the same SWEEPS sweeps per round: sweeps/s = SWEEPS / mean.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pcfbench.datasets.layout import STANDARD_AXES, SequenceData, change_axes

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"
SWEEPS = 10
POINTS = {"nuscenes": 35_000, "av2": 100_000, "kitti": 120_000, "mcap": 100_000} if FULL else {k: 2_000 for k in ("nuscenes", "av2", "kitti", "mcap")}


def _sequence(n_points: int, name: str, split: str) -> SequenceData:
    rng = np.random.default_rng(0)
    sweeps = [rng.uniform([-70, -70, -3], [70, 70, 5], size=(n_points, 3)).astype(np.float32) for _ in range(SWEEPS)]
    poses = np.tile(np.eye(4), (SWEEPS, 1, 1))
    poses[:, 0, 3] = np.arange(SWEEPS) * 1.0
    ts = 1_600_000_000_000_000_000 + np.arange(SWEEPS, dtype=np.int64) * 100_000_000
    return SequenceData.from_arrays(name, split, sweeps, poses, ts)


def _write(kind: str, root: Path):
    """(adapter sequence, the files holding its sweeps)."""
    seq = _sequence(POINTS[kind], {"nuscenes": "scene-0003", "av2": "log0", "kitti": "08", "mcap": "drive"}[kind], "val")
    if kind == "nuscenes":
        from pcfbench.datasets.nuscenes import NuScenes, write_nuscenes

        write_nuscenes(root, [change_axes(seq, STANDARD_AXES, NuScenes.axes)])
        return NuScenes(root).sequence("scene-0003"), sorted((root / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    if kind == "av2":
        from pcfbench.datasets.av2 import Argoverse2, write_av2

        write_av2(root, [seq])
        return Argoverse2(root).sequence("val/log0"), sorted((root / "val" / "log0" / "sensors" / "lidar").glob("*.feather"))
    if kind == "kitti":
        from pcfbench.datasets.kitti import KittiOdometry, write_kitti_sequence

        write_kitti_sequence(root, "08", [seq.load(i) for i in range(SWEEPS)], seq.T_world_sensor, np.arange(SWEEPS) / 10)
        return KittiOdometry(root).sequence("08"), sorted((root / "sequences" / "08" / "velodyne").glob("*.bin"))
    from pcfbench.datasets.mcap import McapRecording
    from pcfbench.datasets.mcap_writer import write_ros2_recording

    write_ros2_recording(root / "drive.mcap", seq)
    return McapRecording(root / "drive.mcap").sequence("drive"), [root / "drive.mcap"]


@pytest.fixture(scope="module", params=["nuscenes", "av2", "kitti", "mcap"])
def written(request, tmp_path_factory):
    kind = request.param
    return kind, *_write(kind, tmp_path_factory.mktemp(f"bench_{kind}"))


def test_load_sweeps(benchmark, written):
    kind, seq, _files = written
    benchmark.group = f"adapters: {kind} ({POINTS[kind]:,} points/sweep, {SWEEPS} sweeps)"
    benchmark.extra_info.update(sweeps=SWEEPS, points=POINTS[kind], mode="load")
    counts = benchmark(lambda: [len(seq.load_points(i)) for i in range(len(seq))])
    assert counts == [POINTS[kind]] * SWEEPS


def test_read_bytes_baseline(benchmark, written):
    kind, seq, files = written
    benchmark.group = f"adapters: {kind} ({POINTS[kind]:,} points/sweep, {SWEEPS} sweeps)"
    benchmark.extra_info.update(sweeps=SWEEPS, points=POINTS[kind], mode="bytes")
    sizes = benchmark(lambda: [len(f.read_bytes()) for f in files])
    assert sum(sizes) >= SWEEPS * POINTS[kind] * 3 * 2  # at least x, y, z at float16
