"""``pcfbench export`` writes an MCAP that reads back with the right schemas, topics, times, counts;
``pcfbench convert`` moves sweeps and poses between layouts."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from pcfbench.cli import build_cli
from pcfbench.geometry import transform_points


def _read_back(path):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((schema.name, message.log_time, decoded))
    return out


def test_export_reads_back(tiny_kitti, tmp_path):
    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.protocol import SETTINGS, SampleBuilder

    out = tmp_path / "sample.mcap"
    res = CliRunner().invoke(build_cli(), ["export", "-d", f"kitti={tiny_kitti}", "-s", "kitti-1s", "--sample", "08/000010",
                                           "-m", "copy-last", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "15 point clouds" in res.output
    sample, truth = SampleBuilder(KittiOdometry(tiny_kitti), SETTINGS["kitti-1s"]).build("08", 10)
    topics = _read_back(out)
    assert set(topics) == {"/tf", "/ego/pose", "/ego/trajectory", "/past/points", "/ground_truth/points", "/forecast/copy-last/points"}
    schemas = {t: {m[0] for m in msgs} for t, msgs in topics.items()}
    assert schemas["/past/points"] == {"foxglove.PointCloud"} and schemas["/tf"] == {"foxglove.FrameTransform"}
    assert schemas["/ego/trajectory"] == {"foxglove.PosesInFrame"} and schemas["/ego/pose"] == {"foxglove.PoseInFrame"}
    past = topics["/past/points"]
    assert [m[1] for m in past] == list(sample.past_timestamps_ns)
    assert [len(m[2].data) // m[2].point_stride for m in past] == [len(p) for p in sample.past_points_ref]
    gt = topics["/ground_truth/points"]
    assert [m[1] for m in gt] == list(sample.future_timestamps_ns)
    assert [len(m[2].data) // 12 for m in gt] == [len(p) for p in truth.future_points_ref]
    fc = topics["/forecast/copy-last/points"]
    assert [len(m[2].data) // 12 for m in fc] == [len(sample.past_points_ref[-1])] * 5
    assert len(topics["/tf"]) == 10 and len(topics["/ego/trajectory"][0][2].poses) == 10
    # a ground-truth cloud, placed by its transform at its own time, lands on the truth in world coordinates
    tf = {m[1]: m[2] for m in topics["/tf"]}
    from pcfbench.geometry import quat_wxyz_to_rotation

    t, msg = gt[2][1], gt[2][2]
    T = np.eye(4)
    r = tf[t].rotation
    T[:3, :3] = quat_wxyz_to_rotation(np.array([r.w, r.x, r.y, r.z]))
    T[:3, 3] = [tf[t].translation.x, tf[t].translation.y, tf[t].translation.z]
    pts = np.frombuffer(msg.data, "<f4").reshape(-1, 3)
    np.testing.assert_allclose(transform_points(T, pts), transform_points(sample.T_world_ref, truth.future_points_ref[2]), atol=2e-3)


@pytest.mark.parametrize("layout", ["nuscenes", "av2-sensor", "mcap", "mcap-foxglove"])
def test_convert_kitti_to_layout_keeps_world_points(tiny_kitti, tmp_path, layout):
    from pcfbench.plugins import get_plugins
    from pcfbench.datasets.kitti import KittiOdometry

    out = tmp_path / layout
    res = CliRunner().invoke(build_cli(), ["convert", "--from", f"kitti={tiny_kitti}", "--to", f"{layout}={out}"])
    assert res.exit_code == 0, res.output
    name = {"nuscenes": "nuscenes", "av2-sensor": "av2", "mcap": "mcap", "mcap-foxglove": "mcap"}[layout]
    dst = get_plugins().datasets.get(name)(out)
    split = "test" if name == "av2" else dst.default_split  # KITTI 08 is a test sequence
    (seq_name,) = dst.sequence_names(split)
    src = KittiOdometry(tiny_kitti).sequence("08")
    seq = dst.sequence(seq_name)
    assert len(seq) == len(src)
    tol = 0.07 if name == "av2" else 2e-3  # av2 stores float16 coordinates
    for i in (0, 11):
        np.testing.assert_allclose(transform_points(seq.T_world_sensor[i], seq.load_points(i)),
                                   transform_points(src.T_world_sensor[i], src.load_points(i)), atol=tol)


def test_convert_nuscenes_to_kitti_places_val_scene_in_kitti_val(tmp_path):
    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.datasets.nuscenes import NuScenes
    from test_adapter_nuscenes import write_tiny_nuscenes

    src_root = write_tiny_nuscenes(tmp_path / "nusc", names=("scene-0003",), n=6)
    res = CliRunner().invoke(build_cli(), ["convert", "--from", f"nuscenes={src_root}", "--to", f"kitti={tmp_path / 'kitti'}"])
    assert res.exit_code == 0, res.output
    assert "scene-0003 -> 06" in res.output
    from pcfbench.errors import DataError

    with pytest.raises(DataError, match=r"sweeps are 0.5 s apart \(2 Hz\), but the dataset is read at 10 Hz"):
        KittiOdometry(tmp_path / "kitti").sequence("06")  # nuScenes' 2 Hz keyframes are not 10 Hz KITTI

    class Kitti2Hz(KittiOdometry):
        rate_hz = 2.0

    dst = Kitti2Hz(tmp_path / "kitti")
    assert dst.sequence_names("val") == ["06"]
    src, seq = NuScenes(src_root).sequence("scene-0003"), dst.sequence("06")
    np.testing.assert_allclose(np.diff(seq.timestamps_ns), np.diff(src.timestamps_ns), atol=1e3)  # KITTI keeps ~us
    for i in (0, 5):
        np.testing.assert_allclose(transform_points(seq.T_world_sensor[i], seq.load_points(i)),
                                   transform_points(src.T_world_sensor[i], src.load_points(i)), atol=2e-3)
