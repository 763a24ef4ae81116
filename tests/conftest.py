"""Shared fixtures: tiny datasets written in their real on-disk layouts."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("PCFBENCH_NO_PROGRESS", "1")


def write_tiny_kitti(root: Path, sequences=("08",), num_sweeps: int = 24, beams: int = 16, azimuths: int = 360) -> Path:
    """A KITTI Odometry tree (velodyne .bin, calib.txt, times.txt, poses/NN.txt) of the toy world."""
    from bench.testing import toy_world_sweeps
    from datasets.kitti import write_kitti_sequence

    for i, name in enumerate(sequences):
        pts, poses, times = toy_world_sweeps(num_sweeps, beams=beams, azimuths=azimuths, seed=i)
        write_kitti_sequence(root, name, pts, poses, times)
    return root


@pytest.fixture
def tiny_kitti(tmp_path: Path) -> Path:
    return write_tiny_kitti(tmp_path / "kitti")


@pytest.fixture
def store(tmp_path: Path) -> Path:
    return tmp_path / "store"
