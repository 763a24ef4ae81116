"""Registers the built-in dataset adapters through the same hook as third-party plugins."""

from bench.hookspecs import hookimpl


@hookimpl
def register_datasets(register):
    register("kitti", "datasets.kitti:KittiOdometry", "KITTI Odometry (velodyne .bin, calib, poses)")
    register("nuscenes", "datasets.nuscenes:NuScenes", "nuScenes LIDAR_TOP keyframes (JSON tables, .pcd.bin)")
    register("av2", "datasets.av2:Argoverse2", "Argoverse 2 Sensor / LiDAR datasets (feather sweeps and poses)")
    register("mcap", "datasets.mcap:McapRecording", "MCAP recordings: ROS 2 PointCloud2 or foxglove.PointCloud + TF")
    register("synthetic-town", "datasets.synthetic.adapter:SyntheticTown", "Generated town, 64-beam LiDAR, 10 Hz (embedded default)")
    register("synthetic-suburb", "datasets.synthetic.adapter:SyntheticSuburb", "Generated suburb, 32-beam LiDAR, 2 Hz keyframes")


@hookimpl
def register_commands(cli):
    from datasets.commands import add_commands
    from datasets.synthetic.cli import add_commands as add_synthetic_commands

    add_commands(cli)
    add_synthetic_commands(cli)
