"""Helpers importable by test modules (conftest fixtures cover the common cases)."""

from conftest import write_tiny_kitti


def write_kitti_tree(root, sequences=("08",), num_sweeps=24):
    return write_tiny_kitti(root, sequences=sequences, num_sweeps=num_sweeps)
