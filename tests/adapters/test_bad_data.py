"""Issue 15: broken data is one clear error naming the file, never a plausible wrong number,
and ``pcfbench datasets check`` reports each case. Every dataset here is written by the
project's own writers, then broken the way the issue found it broken."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pcfbench.cli import cli
from pcfbench.datasets.av2 import Argoverse2, write_av2
from pcfbench.datasets.kitti import DEFAULT_TR, KittiOdometry, write_kitti_sequence
from pcfbench.datasets.layout import SequenceData
from pcfbench.datasets.mcap import McapRecording
from pcfbench.datasets.mcap_writer import (POINTCLOUD2_MSGDEF, TFMESSAGE_MSGDEF, _tf, pointcloud2_message,
                                           write_ros2_recording)
from pcfbench.datasets.nuscenes import NuScenes, read_pcd_bin, write_nuscenes
from pcfbench.errors import DataError
from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.testing import toy_world_sweeps
from pcfbench.protocol.validate import check_rigid, check_sweep_times

N = 24


def _kitti(root: Path, names=("08",), times_scale: float = 1.0, Tr=DEFAULT_TR) -> Path:
    for i, name in enumerate(names):
        pts, poses, times = toy_world_sweeps(N, beams=8, azimuths=90, seed=i)
        write_kitti_sequence(root, name, pts, poses, times * times_scale, Tr=Tr)
    return root


def _check(root: Path, layout: str) -> tuple[int, str]:
    res = CliRunner().invoke(cli, ["datasets", "check", str(root), "--layout", layout])
    assert "Traceback" not in res.output, res.output
    return res.exit_code, res.output


# -- the checks themselves, against hand-made cases ------------------------------------------

def test_sweep_times_hand_made_cases():
    ten_hz = np.arange(10) * 100_000_000
    check_sweep_times(ten_hz, 10.0, "x")  # exact
    check_sweep_times(ten_hz + np.array([0, 3, -2, 4, 0, 1, -3, 2, 0, 5]) * 1_000_000, 10.0, "x")  # jitter of ms
    check_sweep_times(np.round(np.arange(10) * 103_639_300), 10.0, "x")  # KITTI's real 9.65 Hz
    check_sweep_times(ten_hz[:1], 10.0, "x")  # one sweep: nothing to check
    with pytest.raises(DataError, match=r"^x: sweeps are 1 s apart \(1 Hz\), but the dataset is read at 10 Hz"):
        check_sweep_times(ten_hz * 10, 10.0, "x")
    with pytest.raises(DataError, match=r"^x: 0.2 s between sweep 3 \(300000000 ns\) and sweep 4 \(500000000 ns\), "
                                        r"more than 1.5 periods at 10 Hz: a sweep is missing\."):
        check_sweep_times(np.delete(ten_hz, 4), 10.0, "x")
    check_sweep_times(np.array([0, 100, 200, 349]) * 1_000_000, 10.0, "x")  # 1.49 periods: within the tolerance
    with pytest.raises(DataError, match=r"and 1 more gap"):
        check_sweep_times(np.delete(ten_hz, [2, 6]), 10.0, "x")
    with pytest.raises(DataError, match=r"sweep 2 has timestamp 100000000 ns, not after sweep 1's 100000000 ns"):
        check_sweep_times(np.array([0, 1, 1, 2, 3]) * 100_000_000, 10.0, "x")


def test_rigid_hand_made_cases():
    check_rigid(DEFAULT_TR, "Tr")
    for bad, why in ((DEFAULT_TR * np.r_[2, 2, 2, 1][:, None], "singular values 2, 2, 2"),
                     (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant -1")):
        with pytest.raises(DataError, match=rf"^Tr: not a rigid transform \(.*{why}"):
            check_rigid(bad, "Tr")
    shear = np.eye(4)
    shear[0, 1] = 0.05
    with pytest.raises(DataError, match="not a rigid transform"):
        check_rigid(shear, "Tr")


# -- KITTI -----------------------------------------------------------------------------------

def test_kitti_zero_length_bin_is_an_error(tmp_path):
    root = _kitti(tmp_path / "k")
    empty = root / "sequences/08/velodyne/000005.bin"
    empty.write_bytes(b"")
    seq = KittiOdometry(root).sequence("08")
    with pytest.raises(DataError, match=rf"^KITTI sweep {empty} is empty \(0 bytes\)"):
        seq.load_points(5)
    code, out = _check(root, "kitti")
    assert code == 1 and f"KITTI sweep {empty} is empty (0 bytes)" in out


def test_kitti_sequence_without_poses_is_an_error_naming_the_file(tmp_path):
    root = _kitti(tmp_path / "k", names=("08", "09"))
    (root / "poses/09.txt").unlink()
    adapter = KittiOdometry(root)
    assert adapter.sequence_names("test") == ["08", "09"]  # never silently left out
    msg = rf"KITTI sequence 09: poses file missing \(looked for {root}/poses/09.txt and {root}/sequences/09/poses.txt\)"
    with pytest.raises(DataError, match=msg):
        adapter.sequence("09")
    with pytest.raises(DataError, match=msg):
        adapter.fingerprint("test")
    with pytest.raises(DataError, match=msg):
        SampleBuilder(adapter, SETTINGS["kitti-1s"]).sample_keys("test")
    code, out = _check(root, "kitti")
    assert code == 1 and "KITTI sequence 09: poses file missing" in out


def test_kitti_trailing_sweeps_missing_is_an_error(tmp_path):
    root = _kitti(tmp_path / "k")
    for i in (21, 22, 23):
        (root / f"sequences/08/velodyne/{i:06d}.bin").unlink()
    with pytest.raises(DataError, match=r"KITTI poses file .*/poses/08.txt has 24 poses but .*velodyne has 21 sweeps: "
                                        r"sweep\(s\) 000021.bin .. 000023.bin missing"):
        KittiOdometry(root).sequence("08")
    (root / "poses/08.txt").write_text("".join((root / "poses/08.txt").read_text().splitlines(True)[:21]))
    with pytest.raises(DataError, match=r"KITTI times file .*/times.txt has 24 timestamps but .* has 21 sweeps"):
        KittiOdometry(root).sequence("08")
    code, out = _check(root, "kitti")
    assert code == 1 and "has 24 timestamps but" in out


def test_kitti_non_rigid_calibration_is_refused(tmp_path):
    scaled = DEFAULT_TR.copy()
    scaled[:3, :3] *= 2.0
    root = _kitti(tmp_path / "k", Tr=scaled)
    with pytest.raises(DataError, match=r"KITTI calib file .*/sequences/08/calib.txt Tr \(velodyne -> camera 0\): not a "
                                        r"rigid transform \(rotation singular values 2, 2, 2, determinant 8"):
        KittiOdometry(root).sequence("08")
    code, out = _check(root, "kitti")
    assert code == 1 and "not a rigid transform" in out


def test_kitti_times_at_1hz_are_refused(tmp_path):
    root = _kitti(tmp_path / "k", times_scale=10.0)  # one sweep a second
    with pytest.raises(DataError, match=r"KITTI times file .*/times.txt: sweeps are 1 s apart \(1 Hz\), but the dataset is "
                                        r"read at 10 Hz"):
        KittiOdometry(root).sequence("08")
    code, out = _check(root, "kitti")
    assert code == 1 and "sweeps are 1 s apart (1 Hz)" in out


def test_kitti_times_with_a_gap_are_refused(tmp_path):
    root = _kitti(tmp_path / "k")
    path = root / "sequences/08/times.txt"
    t = np.array([float(v) for v in path.read_text().split()])
    t[10:] += 0.1  # the sweep between 9 and 10 missing from the recording
    path.write_text("".join(f"{v:.6e}\n" for v in t))
    with pytest.raises(DataError, match=r"KITTI times file .*: 0.2 s between sweep 9 .* and sweep 10 .*: a sweep is missing"):
        KittiOdometry(root).sequence("08")


def test_kitti_good_tree_still_checks_clean(tmp_path):
    root = _kitti(tmp_path / "k", names=("08", "09"))
    code, out = _check(root, "kitti")
    assert code == 0 and "no problems found" in out


def _nan_points(path: Path, rows=(3, 7)) -> None:
    """Set x of ``rows`` of a KITTI .bin to NaN (the file keeps its size)."""
    data = np.fromfile(path, np.float32).reshape(-1, 4)
    data[list(rows), 0] = np.nan
    data.tofile(path)


def _scaled_pose(path: Path, line: int, scale: float = 1.5) -> None:
    """Scale the rotation of the 3x4 pose on ``line`` (from 1) of a KITTI poses file."""
    lines = path.read_text().splitlines()
    P = np.array([float(v) for v in lines[line - 1].split()]).reshape(3, 4)
    P[:, :3] *= scale
    lines[line - 1] = " ".join(f"{v:.12e}" for v in P.reshape(-1))
    path.write_text("\n".join(lines) + "\n")


def _run_reads_every_sweep(root: Path) -> None:
    """Build every kitti-1s sample of the test split, as ``pcfbench run`` does."""
    builder = SampleBuilder(KittiOdometry(root), SETTINGS["kitti-1s"])
    for key in builder.sample_keys("test"):
        builder.build(*key)


def test_kitti_nan_points_are_refused_by_run_and_check_alike_naming_the_file(tmp_path):
    root = _kitti(tmp_path / "k")
    bad = root / "sequences/08/velodyne/000012.bin"
    _nan_points(bad)
    message = f"KITTI sweep {bad}: 2 point(s) with NaN or inf coordinates"
    with pytest.raises(DataError, match=rf"^{re.escape(message)}$"):
        _run_reads_every_sweep(root)
    code, out = _check(root, "kitti")
    assert code == 1 and f"1 problem(s):\n  - {message}\n" in out


def test_kitti_non_rigid_pose_is_refused_by_run_and_check_alike_naming_file_and_line(tmp_path):
    root = _kitti(tmp_path / "k")
    poses = root / "poses/08.txt"
    poses.write_text("\n" + poses.read_text())  # a blank first line: pose i is on line i + 2
    _scaled_pose(poses, 12)  # sweep 10's pose
    message = (f"KITTI poses file {poses} line 12 (pose of sweep 000010.bin): not a rigid transform (rotation singular "
               "values 1.5, 1.5, 1.5, determinant 3.375")
    with pytest.raises(DataError, match=rf"^{re.escape(message)}"):
        _run_reads_every_sweep(root)
    code, out = _check(root, "kitti")
    assert code == 1 and out.count("not a rigid transform") == 1 and f"  - {message}" in out


def test_check_lists_ten_bad_sweeps_of_a_sequence_and_counts_the_rest(tmp_path):
    root = _kitti(tmp_path / "k")
    for i in range(N):
        _nan_points(root / f"sequences/08/velodyne/{i:06d}.bin", rows=(0,))
    code, out = _check(root, "kitti")
    assert code == 1 and out.count("1 point(s) with NaN or inf coordinates") == 10
    assert f"sequence 08: {N - 10} more bad sweep(s) like the above" in out


def test_a_sequence_with_poses_of_the_wrong_shape_or_time_going_back_is_refused():
    from pcfbench.dataset import Sequence

    def load(_s, _i):
        return np.zeros((1, 3), np.float32)

    Sequence("s", np.tile(np.eye(4), (3, 1, 1)), np.array([0, 1, 2]), load)  # fine
    with pytest.raises(DataError, match=r"^sequence s: poses must have shape \(3, 4, 4\) \(one 4x4 per sweep\), got \(2, 4, 4\)"):
        Sequence("s", np.tile(np.eye(4), (2, 1, 1)), np.array([0, 1, 2]), load)
    with pytest.raises(DataError, match=r"^sequence s: sweep 2 has timestamp 1 ns, not after sweep 1's 1 ns"):
        Sequence("s", np.tile(np.eye(4), (3, 1, 1)), np.array([0, 1, 1]), load)
    with pytest.raises(DataError, match=r"^sequence s: timestamps must be a 1-D integer array of ns, got float64"):
        Sequence("s", np.tile(np.eye(4), (3, 1, 1)), np.array([0.0, 0.1, 0.2]), load)


# -- nuScenes --------------------------------------------------------------------------------

def _nuscenes_tree(tmp_path):
    """A v1.0-trainval tree of one 6-sweep scene; its root and its point files in order."""
    pts, poses, times = toy_world_sweeps(6, beams=8, azimuths=90, rate_hz=2.0)
    seq = SequenceData.from_arrays("scene-0003", "val", pts, poses,
                                   1_531_000_000_000_000_000 + np.round(times * 1e9).astype(np.int64))
    root = tmp_path / "nu"
    write_nuscenes(root, [seq], version="v1.0-trainval")
    return root, sorted((root / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))


def test_nuscenes_nan_points_are_reported_naming_the_point_file(tmp_path):
    root, files = _nuscenes_tree(tmp_path)
    data = read_pcd_bin(files[2])
    data[5, 2] = np.inf
    data.tofile(files[2])
    message = f"nuScenes point file {files[2]}: 1 point(s) with NaN or inf coordinates"
    with pytest.raises(DataError, match=rf"^{re.escape(message)}$"):
        NuScenes(root).sequence("scene-0003").checked_sweep(2)
    code, out = _check(root, "nuscenes")
    assert code == 1 and f"  - {message}\n" in out


def test_nuscenes_zero_length_pcd_bin_is_an_error(tmp_path):
    root, files = _nuscenes_tree(tmp_path)
    files[2].write_bytes(b"")
    with pytest.raises(DataError, match=rf"^nuScenes point file {re.escape(str(files[2]))} is empty \(0 bytes\)"):
        read_pcd_bin(files[2])
    code, out = _check(root, "nuscenes")
    assert code == 1 and "is empty (0 bytes)" in out


@pytest.mark.parametrize("bad", ["1531000000500000", 1531000000500000.5, None, True, -5])
def test_nuscenes_timestamp_that_is_not_an_integer_is_an_error_naming_the_token(tmp_path, bad):
    pts, poses, times = toy_world_sweeps(6, beams=8, azimuths=90, rate_hz=2.0)
    seq = SequenceData.from_arrays("scene-0003", "val", pts, poses,
                                   1_531_000_000_000_000_000 + np.round(times * 1e9).astype(np.int64))
    root = tmp_path / "nu"
    write_nuscenes(root, [seq], version="v1.0-trainval")
    table = root / "v1.0-trainval" / "sample_data.json"
    records = json.loads(table.read_text())
    records[2]["timestamp"] = bad
    table.write_text(json.dumps(records))
    token = records[2]["token"]
    with pytest.raises(DataError, match=rf"^nuScenes table {re.escape(str(table))}: sample_data {token} \(scene "
                                        rf"scene-0003\) has timestamp {re.escape(repr(bad))}, not a non-negative integer"):
        NuScenes(root).sequence("scene-0003")
    code, out = _check(root, "nuscenes")
    assert code == 1 and f"sample_data {token} (scene scene-0003) has timestamp" in out


def test_nuscenes_timestamps_out_of_order_are_an_error_naming_the_token(tmp_path):
    pts, poses, times = toy_world_sweeps(6, beams=8, azimuths=90, rate_hz=2.0)
    seq = SequenceData.from_arrays("scene-0003", "val", pts, poses,
                                   1_531_000_000_000_000_000 + np.round(times * 1e9).astype(np.int64))
    root = tmp_path / "nu"
    write_nuscenes(root, [seq], version="v1.0-trainval")
    table = root / "v1.0-trainval" / "sample_data.json"
    records = json.loads(table.read_text())
    records[3]["timestamp"] = records[1]["timestamp"]  # keyframe 3 goes back in time
    table.write_text(json.dumps(records))
    sample = records[3]["sample_token"]
    with pytest.raises(DataError, match=rf"scene scene-0003 keyframe {sample} has timestamp \d+ us, not after the "
                                        r"previous keyframe's \d+ us"):
        NuScenes(root).sequence("scene-0003")
    code, out = _check(root, "nuscenes")
    assert code == 1 and f"keyframe {sample} has timestamp" in out


# -- Argoverse 2 -----------------------------------------------------------------------------

LOG = "0c6e62d7-bdfa-3061-8d3d-03b13aa21f68"


def test_av2_log_with_a_sweep_missing_is_refused(tmp_path):
    pts, poses, times = toy_world_sweeps(12, beams=8, azimuths=90)
    ts = 315_967_376_859_506_000 + np.round(times * 1e9).astype(np.int64)
    root = write_av2(tmp_path / "av2", [SequenceData.from_arrays(LOG, "val", pts, poses, ts)])
    Argoverse2(root).sequence(f"val/{LOG}")  # whole: fine
    lidar = root / "val" / LOG / "sensors" / "lidar"
    (lidar / f"{ts[5]}.feather").unlink()
    with pytest.raises(DataError, match=rf"Argoverse 2 log {lidar} .*: 0.2 s between sweep 4 \({ts[4]} ns\) and sweep 5 "
                                        rf"\({ts[6]} ns\), more than 1.5 periods at 10 Hz: a sweep is missing"):
        Argoverse2(root).sequence(f"val/{LOG}")
    code, out = _check(root, "av2")
    assert code == 1 and "a sweep is missing" in out


# -- MCAP ------------------------------------------------------------------------------------

T0 = 1_700_000_000_000_000_000


def _seq(n=10, drop=()):
    pts, poses, times = toy_world_sweeps(n, beams=8, azimuths=90)
    keep = [k for k in range(n) if k not in drop]
    ts = T0 + np.round(times * 1e9).astype(np.int64)
    return SequenceData.from_arrays("rec", "all", [pts[k] for k in keep], poses[keep], ts[keep]), pts


def _write_raw(path, clouds, tf_items=None):
    """PointCloud2 ``(log_time, message)`` pairs, and /tf messages ``(log_time, [transforms])``."""
    from mcap_ros2.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        cs = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        tfs = w.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE_MSGDEF)
        for t, items in tf_items or []:
            w.write_message("/tf", tfs, {"transforms": items}, log_time=t)
        for t, msg in clouds:
            w.write_message("/points", cs, msg, log_time=t)
        w.finish()
    return path


def test_mcap_with_a_sweep_missing_is_refused(tmp_path):
    seq, _ = _seq(drop=(4,))
    path = write_ros2_recording(tmp_path / "gap.mcap", seq)
    with pytest.raises(DataError, match=r"gap.mcap topic /lidar/points \(header stamps\): 0.2 s between sweep 3 .* and "
                                        r"sweep 4 .*: a sweep is missing"):
        McapRecording(path).sequence("gap")
    code, out = _check(path, "mcap")
    assert code == 1 and "a sweep is missing" in out


def test_mcap_two_clouds_with_one_log_time_are_refused(tmp_path):
    _, pts = _seq()
    moving = [(T0 + k * 100_000_000, [_tf("map", "lidar", np.eye(4), T0 + k * 100_000_000)]) for k in range(4)]
    clouds = [(T0 + k * 100_000_000, pointcloud2_message(pts[k], T0 + k * 100_000_000, "lidar")) for k in range(4)]
    clouds[2] = (clouds[1][0], clouds[2][1])  # logged at cloud 1's time, stamped at its own
    path = _write_raw(tmp_path / "dup.mcap", clouds, moving)
    with pytest.raises(DataError, match=rf"dup.mcap topic /points: clouds 1 and 2 have the same log time {T0 + 100_000_000} ns"):
        McapRecording(path).sequence("dup")
    code, out = _check(path, "mcap")
    assert code == 1 and "have the same log time" in out


def test_mcap_without_transforms_or_with_the_cloud_frame_as_tf_root_is_refused(tmp_path):
    _, pts = _seq()
    clouds = [(T0 + k * 100_000_000, pointcloud2_message(pts[k], T0 + k * 100_000_000, "lidar")) for k in range(4)]
    none = _write_raw(tmp_path / "notf.mcap", clouds)
    with pytest.raises(DataError, match=r"notf.mcap topic /points cloud at \d+ ns: the cloud frame 'lidar' is its own world "
                                        r"frame \(no transform mentions it; frames known: none\): every pose would be the identity"):
        McapRecording(none).sequence("notf")
    # /tf only below the cloud frame: lidar -> base_link, so 'lidar' is the root of the tree
    below = [(T0 + k * 100_000_000, [_tf("lidar", "base_link", np.eye(4), T0 + k * 100_000_000)]) for k in range(4)]
    root = _write_raw(tmp_path / "root.mcap", clouds, below)
    with pytest.raises(DataError, match=r"the cloud frame 'lidar' is its own world frame \(it is the root of the TF tree; "
                                        r"frames known: base_link, lidar\)"):
        McapRecording(root).sequence("root")
    with pytest.raises(DataError, match="its own world frame"):
        McapRecording(root, world_frame="lidar").sequence("root")
    for path in (none, root):
        code, out = _check(path, "mcap")
        assert code == 1 and "every pose would be the identity" in out


def test_mcap_good_recording_still_loads(tmp_path):
    seq, _ = _seq()
    path = write_ros2_recording(tmp_path / "ok.mcap", seq)
    s = McapRecording(path).sequence("ok")
    assert len(s) == 10 and not np.allclose(s.T_world_sensor[0], s.T_world_sensor[-1])
