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
    assert "1 file(s), 15 point clouds" in res.output
    sample, truth = SampleBuilder(KittiOdometry(tiny_kitti), SETTINGS["kitti-1s"]).build("08", 10)
    topics = _read_back(out)
    assert set(topics) == {"/tf", "/ego/pose", "/ego/trajectory", "/past/points", "/ground_truth/points",
                           "/forecast/copy_last/points", "/pcfbench/sample"}
    assert [m[2].message for m in topics["/pcfbench/sample"]] == [
        "sample 08/000010 (kitti sequence 08, reference sweep 10); times shifted by 0 ns"]
    schemas = {t: {m[0] for m in msgs} for t, msgs in topics.items()}
    assert schemas["/past/points"] == {"foxglove.PointCloud"} and schemas["/tf"] == {"foxglove.FrameTransform"}
    assert schemas["/ego/trajectory"] == {"foxglove.PosesInFrame"} and schemas["/ego/pose"] == {"foxglove.PoseInFrame"}
    past = topics["/past/points"]
    assert [m[1] for m in past] == list(sample.past_timestamps_ns)
    assert [len(m[2].data) // m[2].point_stride for m in past] == [len(p) for p in sample.past_points_ref]
    gt = topics["/ground_truth/points"]
    assert [m[1] for m in gt] == list(sample.future_timestamps_ns)
    assert [len(m[2].data) // 16 for m in gt] == [len(p) for p in truth.future_points_ref]  # x, y, z, intensity
    assert [f.name for f in gt[0][2].fields] == ["x", "y", "z", "intensity"]
    fc = topics["/forecast/copy_last/points"]
    assert [m[2].point_stride for m in fc] == [16] * 5 and [f.name for f in fc[0][2].fields] == ["x", "y", "z", "error"]
    assert [len(m[2].data) // 16 for m in fc] == [len(sample.past_points_ref[-1])] * 5
    assert len(topics["/tf"]) == 10 and len(topics["/ego/trajectory"][0][2].poses) == 10
    # a ground-truth cloud, placed by its transform at its own time, lands on the truth in world coordinates
    tf = {m[1]: m[2] for m in topics["/tf"]}
    from pcfbench.geometry import quat_wxyz_to_rotation

    t, msg = gt[2][1], gt[2][2]
    T = np.eye(4)
    r = tf[t].rotation
    T[:3, :3] = quat_wxyz_to_rotation(np.array([r.w, r.x, r.y, r.z]))
    T[:3, 3] = [tf[t].translation.x, tf[t].translation.y, tf[t].translation.z]
    pts = np.frombuffer(msg.data, "<f4").reshape(-1, 4)[:, :3]
    np.testing.assert_allclose(transform_points(T, pts), transform_points(sample.T_world_ref, truth.future_points_ref[2]), atol=2e-3)


def _metadata(path):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return {m.name: m.metadata for m in make_reader(f).iter_metadata()}


def test_export_keeps_variants_apart_with_per_point_errors_and_scores(tiny_kitti, tmp_path):
    """Two options of one method: two topics. Each forecast point carries its distance to the
    nearest ground-truth point; the metadata records say which sample and hold the scores."""
    import json

    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.metrics.base import score_sample
    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.protocol import SETTINGS, SampleBuilder
    from pcfbench.running.runner import default_metrics

    out = tmp_path / "two.mcap"
    args = ["export", "-d", f"kitti={tiny_kitti}", "-s", "kitti-1s", "--sample", "08/000012", "-o", str(out),
            "-m", "raycast-voxel:voxel=0.4", "-m", "raycast-voxel:voxel=0.8", "-m", "copy-last"]
    res = CliRunner().invoke(build_cli(), args)
    assert res.exit_code == 0, res.output
    assert "25 point clouds" in res.output  # 5 past + 5 truth + 3 x 5 forecasts
    topics = _read_back(out)
    names = {"raycast-voxel:voxel=0.4": "/forecast/raycast_voxel/voxel_0p4/points",
             "raycast-voxel:voxel=0.8": "/forecast/raycast_voxel/voxel_0p8/points", "copy-last": "/forecast/copy_last/points"}
    assert set(names.values()) <= set(topics)
    sample, truth = SampleBuilder(KittiOdometry(tiny_kitti), SETTINGS["kitti-1s"]).build("08", 12)
    plugins = get_plugins()
    metrics = [plugins.metrics.get(m) for m in default_metrics(plugins)]
    meta = _metadata(out)
    assert json.loads(meta["pcfbench.samples"]["08/000012"]) == {"sequence": "08", "ref_index": 12, "offset_ns": 0,
                                                                 "start_ns": int(sample.past_timestamps_ns[0]),
                                                                 "end_ns": int(sample.future_timestamps_ns[-1])}
    assert meta["pcfbench.export"]["setting"] == "kitti-1s" and meta["pcfbench.export"]["split"] == "test"
    assert meta["pcfbench.export"]["dataset"] == "kitti" and meta["pcfbench.export"]["samples"] == "1"
    assert {t: json.loads(v)["spec"] for t, v in meta["pcfbench.topics"].items()} == {t: n for n, t in names.items()}
    scores = json.loads(meta["pcfbench.scores"]["08/000012"])
    for name, topic in names.items():
        msgs = topics[topic]
        fc = resolve_method(name).create().forecast(sample.for_method())
        for k, (_, _, msg) in enumerate(msgs):
            data = np.frombuffer(msg.data, "<f4").reshape(-1, 4)
            pred, gt = np.asarray(fc.points_ref[k], np.float64), truth.future_points_ref[k].astype(np.float64)
            assert len(data) == len(pred)
            brute = np.sqrt(((pred[:, None] - gt[None]) ** 2).sum(-1)).min(1)
            np.testing.assert_allclose(data[:, 3], brute, rtol=1e-5, atol=1e-5)
        want = score_sample(sample, truth, fc, metrics)
        got = scores[topic]
        assert [r["l1_mean"] for r in got] == pytest.approx([r["l1_mean"] for r in want], rel=1e-12)
        assert [r["chamfer"] for r in got] == pytest.approx([r["chamfer"] for r in want], rel=1e-12)
    a, b = (topics[f"/forecast/raycast_voxel/voxel_{v}/points"] for v in ("0p4", "0p8"))
    assert len(a) == len(b) == 5 and a[-1][2].data != b[-1][2].data  # both variants' clouds, not one twice


@pytest.mark.parametrize("sample_id, message", [
    ("08-000012", r"--sample '08-000012': expected SEQUENCE/INDEX"),
    ("07/000012", r"kitti:test has no sequence '07' \(it has 08\)"),
    ("08/000099", r"sequence 08 has 24 sweeps \(indices 0..23\)"),
    ("08/000003", r"not enough past for kitti-1s: it needs 4 past sweeps 2 apart before the reference, so the index "
                  r"must be at least 8 \(valid indices of sequence 08: 8..13\)"),
    ("08/000020", r"not enough future for kitti-1s: it needs 5 future sweeps 2 apart"),
])
def test_export_rejects_a_bad_sample_with_one_error(tiny_kitti, tmp_path, sample_id, message):
    import re

    out = tmp_path / "x.mcap"
    res = CliRunner().invoke(build_cli(), ["export", "-d", f"kitti={tiny_kitti}", "-s", "kitti-1s", "--sample", sample_id,
                                           "-o", str(out)])
    assert res.exit_code == 2 and not out.exists(), res.output
    (line,) = [x for x in res.output.splitlines() if x.strip()]
    assert line.startswith("pcfbench: error: ") and re.search(message, line), line
    assert "`pcfbench ls samples kitti=ROOT --setting kitti-1s --split test` lists the valid ids" in line


def test_export_refuses_the_same_variant_twice(tiny_kitti, tmp_path):
    res = CliRunner().invoke(build_cli(), ["export", "-d", f"kitti={tiny_kitti}", "-s", "kitti-1s", "-o", str(tmp_path / "x.mcap"),
                                           "-m", "raycast-voxel:voxel=0.4", "-m", "raycast-voxel:voxel=0.40"])
    assert res.exit_code == 2 and "is the same variant as 'raycast-voxel:voxel=0.4'" in res.output


def test_ls_samples_lists_the_valid_ids(tiny_kitti):
    import json

    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.protocol import SETTINGS, SampleBuilder

    res = CliRunner().invoke(build_cli(), ["ls", "samples", f"kitti={tiny_kitti}", "--setting", "kitti-1s", "--json"])
    assert res.exit_code == 0, res.output
    keys = SampleBuilder(KittiOdometry(tiny_kitti), SETTINGS["kitti-1s"]).sample_keys("test")
    assert json.loads(res.output.splitlines()[0]) == [f"{q}/{i:06d}" for q, i in keys] == [f"08/{i:06d}" for i in range(8, 14)]
    res = CliRunner().invoke(build_cli(), ["ls", "samples", f"kitti={tiny_kitti}"])
    assert res.exit_code == 2 and "--setting SETTING" in res.output


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
