"""Registers the built-in dataset adapters through the same hook as third-party plugins."""

from bench.hookspecs import hookimpl


@hookimpl
def register_datasets(register):
    register("kitti", "datasets.kitti:KittiOdometry", "KITTI Odometry (velodyne .bin, calib, poses)")
    register("nuscenes", "datasets.nuscenes:NuScenes", "nuScenes LIDAR_TOP keyframes (JSON tables, .pcd.bin)")
    register("av2", "datasets.av2:Argoverse2", "Argoverse 2 Sensor / LiDAR datasets (feather sweeps and poses)")
    register("mcap", "datasets.mcap:McapRecording", "MCAP recordings: ROS 2 PointCloud2 or foxglove.PointCloud + TF")


@hookimpl
def register_commands(cli):
    from datasets.commands import add_commands

    add_commands(cli)
