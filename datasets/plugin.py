"""Registers the built-in dataset adapters through the same hook as third-party plugins."""

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_datasets(register):
    register("kitti", "pcfbench.datasets.kitti:KittiOdometry", "KITTI Odometry (velodyne .bin, calib, poses)")
    register("nuscenes", "pcfbench.datasets.nuscenes:NuScenes", "nuScenes LIDAR_TOP keyframes (JSON tables, .pcd.bin)")
    register("av2", "pcfbench.datasets.av2:Argoverse2", "Argoverse 2 Sensor / LiDAR datasets (feather sweeps and poses)")
    register("mcap", "pcfbench.datasets.mcap:McapRecording", "MCAP recordings: ROS 2 PointCloud2 or foxglove.PointCloud + TF")
    register("synthetic-town", "pcfbench.datasets.synthetic.adapter:SyntheticTown",
             "Generated town, 64-beam LiDAR, 512 columns, clean surfaces (world physics v1), 10 Hz: fast, for tests")
    register("synthetic-town-realistic", "pcfbench.datasets.synthetic.adapter:SyntheticTownRealistic",
             "synthetic-town with a realistic sensor, surfaces, poses and traffic (world physics v10), 10 Hz (embedded default, every third sample)")
    register("synthetic-suburb", "pcfbench.datasets.synthetic.adapter:SyntheticSuburb", "Generated suburb, 32-beam LiDAR, 2 Hz keyframes")


@hookimpl
def register_commands(cli):
    from pcfbench.datasets.commands import add_commands
    from pcfbench.datasets.synthetic.cli import add_commands as add_synthetic_commands

    add_commands(cli)
    add_synthetic_commands(cli)
