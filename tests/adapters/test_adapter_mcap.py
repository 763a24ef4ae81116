"""MCAP adapter: recordings written with mcap-ros2-support / mcap-protobuf-support, read back."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from pcfbench.errors import DataError
from pcfbench.testing import check_adapter, toy_world_sweeps
from pcfbench.datasets.layout import SequenceData
from pcfbench.datasets.mcap import McapRecording
from pcfbench.datasets.mcap_writer import pointcloud2_message, write_foxglove_recording, write_ros2_recording

T0 = 1_700_000_000_000_000_000


def _seq(n: int = 10, rate_hz: float = 10.0, seed: int = 0) -> tuple[SequenceData, list, np.ndarray]:
    pts, poses, times = toy_world_sweeps(n, beams=8, azimuths=90, rate_hz=rate_hz, seed=seed)
    return SequenceData.from_arrays("rec", "all", pts, poses, T0 + np.round(times * 1e9).astype(np.int64)), pts, poses


def test_module_name_does_not_shadow_the_library():
    mod = importlib.import_module("pcfbench.datasets.mcap")
    assert mod.mcap.__name__ == "mcap" and hasattr(mod.mcap, "reader")


@pytest.mark.parametrize("flavour", ["ros2", "ros2-bigendian-padded", "protobuf", "json"])
def test_round_trip(tmp_path, flavour):
    seq, pts, poses = _seq()
    path = tmp_path / "rec.mcap"
    if flavour.startswith("ros2"):
        kw = dict(big_endian=True, row_padding=8, height=2) if "bigendian" in flavour else {}
        write_ros2_recording(path, seq, **kw)
    else:
        write_foxglove_recording(path, seq, encoding=flavour)
    ds = McapRecording(path)
    assert McapRecording.detect(path) and ds.sequence_names("all") == ["rec"]
    assert ds.rate_hz == 10.0
    s = ds.sequence("rec")
    np.testing.assert_array_equal(s.timestamps_ns, seq.timestamps_ns)
    np.testing.assert_allclose(s.T_world_sensor, poses, atol=1e-9)
    for i in (0, 7):
        np.testing.assert_array_equal(s.load_points(i), pts[i])
    check_adapter(ds, "all")


def test_folder_options_and_rate_stride(tmp_path):
    seq, pts, poses = _seq(n=12, rate_hz=20.0)
    write_ros2_recording(tmp_path / "a" / "one.mcap", seq, topic="/velodyne_points", world_frame="odom")
    write_ros2_recording(tmp_path / "a" / "sub" / "two.mcap", seq, topic="/velodyne_points", world_frame="odom")
    ds = McapRecording(tmp_path / "a")
    assert ds.sequence_names("all") == ["one", "sub/two"]
    assert ds.rate_hz == 20.0  # matches no setting: pick one by keeping every 2nd sweep
    ds10 = McapRecording(tmp_path / "a", rate_hz="10", world_frame="base_link")
    assert ds10.rate_hz == 10.0 and ds10.stride == 2
    s = ds10.sequence("one")
    assert len(s) == 6
    np.testing.assert_array_equal(s.load_points(1), pts[2])
    # world frame base_link: the sensor pose is the static mounting
    np.testing.assert_allclose(s.T_world_sensor[3][:3, 3], [0.5, 0.0, 1.8], atol=1e-12)
    with pytest.raises(DataError, match=r"recorded at 20.00 Hz: keeping every k-th sweep cannot give 3 Hz"):
        McapRecording(tmp_path / "a", rate_hz=3)
    with pytest.raises(DataError, match=r"no point-cloud topic '/points' \(found: /velodyne_points\)"):
        McapRecording(tmp_path / "a", topic="/points").sequence("one")


def test_root_option_syntax_reaches_the_adapter(tmp_path):
    from pcfbench.config import split_root_options

    seq, _, _ = _seq(n=12, rate_hz=20.0)
    write_ros2_recording(tmp_path / "r.mcap", seq)
    path, opts = split_root_options(f"{tmp_path / 'r.mcap'}?rate_hz=10&topic=/lidar/points")
    assert opts == {"rate_hz": "10", "topic": "/lidar/points"}
    assert McapRecording(path, **opts).stride == 2


def _write_raw_ros2(path, clouds, tf=True):
    """A ROS 2 recording from PointCloud2 dicts (to plant bad clouds)."""
    from mcap_ros2.writer import Writer

    from pcfbench.datasets.mcap_writer import POINTCLOUD2_MSGDEF, TFMESSAGE_MSGDEF, _tf

    with open(path, "wb") as f:
        w = Writer(f)
        cs = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        ts_schema = w.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE_MSGDEF)
        for k, msg in enumerate(clouds):
            t = T0 + k * 100_000_000
            if tf:
                w.write_message("/tf", ts_schema, {"transforms": [_tf("map", "lidar", np.eye(4), t)]}, log_time=t)
            w.write_message("/points", cs, msg, log_time=t)
        w.finish()


def test_bad_inputs_each_named(tmp_path):
    seq, pts, _ = _seq(n=4)
    good = tmp_path / "good.mcap"
    write_ros2_recording(good, seq)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(DataError, match=r"cut.mcap .*cut short"):
        McapRecording(cut).sequence("cut")

    clouds = [pointcloud2_message(pts[k], T0 + k * 100_000_000, "lidar") for k in range(3)]
    clouds[1]["point_step"] = 12  # intensity at offset 12 no longer fits
    _write_raw_ros2(tmp_path / "step.mcap", clouds)
    with pytest.raises(DataError, match=r"step.mcap topic /points cloud at \d+ ns: point_step 12 is smaller than field 'intensity'"):
        McapRecording(tmp_path / "step.mcap").sequence("step").load_points(1)

    clouds = [pointcloud2_message(pts[k], T0 + k * 100_000_000, "lidar") for k in range(3)]
    _write_raw_ros2(tmp_path / "notf.mcap", clouds, tf=False)
    with pytest.raises(DataError, match=r"notf.mcap topic /points cloud at \d+ ns: no transform from 'map' to 'lidar' \(frame 'lidar' has no parent"):
        McapRecording(tmp_path / "notf.mcap", world_frame="map").sequence("notf")

    clouds = [pointcloud2_message(pts[k], T0 + (2 - k) * 100_000_000, "lidar") for k in range(3)]
    _write_raw_ros2(tmp_path / "order.mcap", clouds)
    with pytest.raises(DataError, match=r"order.mcap topic /points: cloud \d has timestamp \d+ ns, not after"):
        McapRecording(tmp_path / "order.mcap").sequence("order")


def test_zero_quaternion_and_missing_dynamic_transform(tmp_path):
    from mcap_ros2.writer import Writer

    from pcfbench.datasets.mcap_writer import POINTCLOUD2_MSGDEF, TFMESSAGE_MSGDEF, _tf

    _, pts, _ = _seq(n=3)
    path = tmp_path / "zq.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        cs = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        tfs = w.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE_MSGDEF)
        tf = _tf("map", "lidar", np.eye(4), T0)
        tf["transform"]["rotation"] = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}
        w.write_message("/tf", tfs, {"transforms": [tf]}, log_time=T0)
        w.write_message("/points", cs, pointcloud2_message(pts[0], T0, "lidar"), log_time=T0)
        w.finish()
    with pytest.raises(DataError, match=r"zq.mcap topic /tf transform map -> lidar at \d+ ns: rotation quaternion .* zero norm"):
        McapRecording(path).sequence("zq")

    path = tmp_path / "late.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        cs = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        tfs = w.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE_MSGDEF)
        for k in range(2):
            w.write_message("/tf", tfs, {"transforms": [_tf("map", "lidar", np.eye(4), T0 + k * 10_000_000)]}, log_time=T0 + k)
        for k in range(3):
            w.write_message("/points", cs, pointcloud2_message(pts[k], T0 + k * 500_000_000, "lidar"), log_time=T0 + k * 500_000_000)
        w.finish()
    with pytest.raises(DataError, match=r"late.mcap topic /points cloud at \d+ ns: no transform map -> lidar available at that time"):
        McapRecording(path).sequence("late")


def test_check_reports_topics_frames_and_every_problem(tmp_path):
    seq, pts, _ = _seq(n=4)
    write_ros2_recording(tmp_path / "ok.mcap", seq)
    (tmp_path / "cut.mcap").write_bytes((tmp_path / "ok.mcap").read_bytes()[:300])
    clouds = [pointcloud2_message(pts[k], T0 + k * 100_000_000, "lidar") for k in range(3)]
    clouds[2]["point_step"] = 8
    _write_raw_ros2(tmp_path / "step.mcap", clouds)
    rep = McapRecording(tmp_path).check()
    assert rep.found["ok: point-cloud topics"] == "/lidar/points (sensor_msgs/msg/PointCloud2)"
    assert "tree roots map" in rep.found["ok: frames"]
    assert len(rep.problems) == 2, rep.problems
    assert any("cut.mcap" in p for p in rep.problems) and any("point_step 8" in p for p in rep.problems)


def test_end_to_end_copy_last(tmp_path):
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    seq, _, _ = _seq(n=44, rate_hz=20.0)
    write_ros2_recording(tmp_path / "drive.mcap", seq)
    args = ["run", "--dataset", f"mcap={tmp_path / 'drive.mcap'}?rate_hz=10", "--setting", "kitti-1s", "--method", "copy-last",
            "--reports", str(tmp_path / "reports"), "-q"]
    res = CliRunner().invoke(build_cli(), args)
    assert res.exit_code == 0, res.output
    # 44 sweeps at 20 Hz -> 22 at 10 Hz; kitti-1s anchors 8..11
    assert "4 samples (4 now, 0 failed)" in res.output


def test_recordings_of_different_rates_in_one_folder_are_refused(tmp_path):
    write_ros2_recording(tmp_path / "a.mcap", _seq(n=6)[0])
    write_ros2_recording(tmp_path / "b.mcap", _seq(n=6, rate_hz=2.0)[0])
    ds = McapRecording(tmp_path)
    assert ds.rate_hz == 10.0 and len(ds.sequence("a")) == 6
    with pytest.raises(DataError, match=r"b.mcap topic /lidar/points is recorded at 2.00 Hz, but this dataset runs at 10 Hz"):
        ds.sequence("b")


try:
    from hypothesis import given, settings
    from hypothesis import strategies as st
except ImportError:  # pragma: no cover - hypothesis is a test dependency
    given = None

if given is not None:

    @settings(max_examples=40, deadline=None)
    @given(
        order=st.permutations(["x", "y", "z", "i"]),
        coord=st.sampled_from(["f4", "f8"]),
        big=st.booleans(),
        pad=st.integers(0, 7),
        row_pad=st.integers(0, 9),
        height=st.sampled_from([1, 2, 5]),
        seed=st.integers(0, 2**16),
    )
    def test_pointcloud2_layouts_decode_exactly(order, coord, big, pad, row_pad, height, seed):
        """Any field order, float32/64 coordinates, endianness, point and row padding."""
        from pcfbench.datasets.mcap import cloud_points

        rng = np.random.default_rng(seed)
        pts = rng.uniform(-80, 80, size=(10 * height, 3)).astype(np.float32)
        sizes = {"x": int(coord[1]), "y": int(coord[1]), "z": int(coord[1]), "i": 4}
        offsets, off = {}, 0
        for name in order:
            offsets[name] = off
            off += sizes[name]
        step = off + pad
        bo = ">" if big else "<"
        rec = np.zeros(len(pts), np.dtype({"names": list(order), "formats": [bo + (coord if n != "i" else "f4") for n in order],
                                          "offsets": [offsets[n] for n in order], "itemsize": step}))
        for j, c in enumerate("xyz"):
            rec[c] = pts[:, j]
        width = len(pts) // height
        raw = rec.tobytes()
        data = b"".join(raw[r * width * step:(r + 1) * width * step] + b"\xff" * row_pad for r in range(height))
        types = {"f4": 7, "f8": 8}
        msg = {"height": height, "width": width, "point_step": step, "row_step": width * step + row_pad, "is_bigendian": big, "data": data,
               "fields": [{"name": n if n != "i" else "intensity", "offset": offsets[n],
                           "datatype": types[coord] if n != "i" else 7, "count": 1} for n in order]}
        np.testing.assert_array_equal(cloud_points(msg, "sensor_msgs/msg/PointCloud2", "test"), pts)
