"""Registers the built-in dataset adapters through the same hook as third-party plugins."""

from bench.hookspecs import hookimpl


@hookimpl
def register_datasets(register):
    register("kitti", "datasets.kitti:KittiOdometry", "KITTI Odometry (velodyne .bin, calib, poses)")
