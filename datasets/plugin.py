"""Registers the built-in dataset adapters through the same hook as third-party plugins."""

from bench.hookspecs import hookimpl


@hookimpl
def register_datasets(register):
    register("kitti", "datasets.kitti:KittiOdometry", "KITTI Odometry (velodyne .bin, calib, poses)")
    register("synthetic-town", "datasets.synthetic.adapter:SyntheticTown", "Generated town, 64-beam LiDAR, 10 Hz (embedded default)")
    register("synthetic-suburb", "datasets.synthetic.adapter:SyntheticSuburb", "Generated suburb, 32-beam LiDAR, 2 Hz keyframes")


@hookimpl
def register_commands(cli):
    from datasets.synthetic.cli import add_commands

    add_commands(cli)
