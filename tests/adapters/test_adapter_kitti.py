import numpy as np
import pytest
from click.testing import CliRunner

from pcfbench.cli import build_cli
from pcfbench.errors import DataError
from pcfbench.geometry import invert, transform_points, yaw_transform
from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.testing import check_adapter
from pcfbench.datasets.kitti import DEFAULT_TR, KittiOdometry, read_calib, write_kitti_sequence


def _write(root, name="08", n=6, semantic=False):
    rng = np.random.default_rng(3)
    pts = [rng.uniform(-30, 30, size=(100 + i, 3)).astype(np.float32) for i in range(n)]
    poses = np.stack([yaw_transform(0.1 * i, (2.0 * i, 0.5 * i, 0.1)) for i in range(n)])
    write_kitti_sequence(root, name, pts, poses, np.arange(n) * 0.1036, semantic_kitti_poses=semantic)
    return pts, poses


@pytest.mark.parametrize("semantic", [False, True])
def test_layout_round_trip(tmp_path, semantic):
    pts, poses = _write(tmp_path, semantic=semantic)
    assert (tmp_path / "sequences/08/velodyne/000005.bin").stat().st_size == 105 * 16
    assert (tmp_path / ("sequences/08/poses.txt" if semantic else "poses/08.txt")).is_file()
    ds = KittiOdometry(tmp_path)
    assert ds.sequence_names("test") == ["08"] and ds.sequence_names("train") == []
    seq = ds.sequence("08")
    assert len(seq) == 6
    np.testing.assert_allclose(seq.T_world_sensor, poses, atol=1e-9)
    np.testing.assert_array_equal(seq.load_points(5), pts[5])
    assert seq.timestamps_ns[1] == 103_600_000
    check_adapter(ds, "test")


def test_lidar_pose_is_inv_tr_p_tr(tmp_path):
    """A hand-written camera pose file: P moves the camera 1 m along its z (forward) axis."""
    _write(tmp_path, n=2)
    P = np.eye(4)
    P[2, 3] = 1.0  # camera z is forward
    lines = "1 0 0 0 0 1 0 0 0 0 1 0\n" + " ".join(f"{v:.6f}" for v in P[:3].reshape(-1)) + "\n"
    (tmp_path / "poses/08.txt").write_text(lines)
    seq = KittiOdometry(tmp_path).sequence("08")
    # camera forward (z) is velodyne x: the LiDAR moved 1 m along its own x axis
    np.testing.assert_allclose(seq.T_world_sensor[1], np.linalg.inv(DEFAULT_TR) @ P @ DEFAULT_TR, atol=1e-9)
    np.testing.assert_allclose(seq.T_world_sensor[1][:3, 3], [1.0, 0.0, 0.0], atol=1e-9)


def test_calib_real_format(tmp_path):
    _write(tmp_path, n=2)
    calib = read_calib(tmp_path / "sequences/08/calib.txt")
    assert set(calib) == {"P0", "P1", "P2", "P3", "Tr"}
    np.testing.assert_allclose(calib["Tr"], DEFAULT_TR[:3], atol=1e-12)
    assert calib["P0"][0, 0] == pytest.approx(718.856)


def test_sample_past_in_reference_frame(tmp_path):
    pts, poses = _write(tmp_path, n=30)
    ds = KittiOdometry(tmp_path)
    builder = SampleBuilder(ds, SETTINGS["kitti-1s"])
    keys = builder.sample_keys("test")
    assert keys[0] == ("08", 8) and keys[-1] == ("08", 29 - 10)
    sample, truth = builder.build("08", 10)
    assert sample.sample_id == "08/000010"
    assert len(sample.past_points_ref) == 5 and len(sample.queries) == 5
    # past sweep index 10 - 4*2 = 2, expressed in the frame of sweep 10
    T_ref_2 = invert(poses[10]) @ poses[2]
    expect = transform_points(T_ref_2, ds.ego_box.remove(pts[2]))
    np.testing.assert_allclose(sample.past_points_ref[0], expect, atol=1e-4)
    np.testing.assert_allclose(sample.future_T_ref_sensor[0], invert(poses[10]) @ poses[12], atol=1e-9)
    # query rays point at the held-back ground truth
    q = sample.queries[0]
    g = truth.future_points_ref[0].astype(np.float64)
    dirs = (g - q.origin_ref) / np.linalg.norm(g - q.origin_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(q.directions_ref, dirs, atol=1e-5)
    assert not hasattr(sample, "future_points_ref")


def test_every_frame_policy_pads_missing_sweeps(tmp_path):
    _write(tmp_path, n=12)
    builder = SampleBuilder(KittiOdometry(tmp_path), SETTINGS["kitti-1s"], policy="every-frame")
    keys = builder.sample_keys("test")
    assert len(keys) == 12
    sample, truth = builder.build("08", 0)
    assert [len(p) for p in sample.past_points_ref[:4]] == [0, 0, 0, 0]
    sample, truth = builder.build("08", 11)
    assert all(len(t) == 0 for t in truth.future_points_ref)


def _run(root, tmp_path, *extra):
    cli = build_cli()
    return CliRunner().invoke(
        cli, ["run", "--dataset", f"kitti={root}", "--setting", "kitti-1s", "--method", "copy-last",
              "--reports", str(tmp_path / "rep"), "-q", *extra],
    )


def _assert_no_complete_cell(tmp_path):
    import json

    for meta in (tmp_path / "rep").rglob("cell.json"):
        assert json.loads(meta.read_text())["status"] != "complete"


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda r: (r / "sequences/08/velodyne/000012.bin").write_bytes(b"\0" * 17), "000012.bin has 17 bytes, not a multiple of 16"),
        (lambda r: (r / "sequences/08/velodyne/000012.bin").unlink(), "missing sweep(s) 000012.bin"),
        (lambda r: (r / "poses/08.txt").write_text("\n".join((r / "poses/08.txt").read_text().splitlines()[:20])), "has 20 poses for 30 sweeps"),
        (lambda r: (r / "sequences/08/calib.txt").write_text("P0: 1 2 3\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n"), "calib.txt line 1: expected 'KEY: 12 numbers'"),
        (lambda r: np.full((10, 4), np.nan, np.float32).tofile(r / "sequences/08/velodyne/000012.bin"), "10 point(s) with NaN or inf"),
    ],
    ids=["truncated-bin", "missing-bin", "short-poses", "bad-calib", "nan-points"],
)
def test_bad_input_gives_one_clear_error(tmp_path, corrupt, message):
    root = tmp_path / "kitti"
    _write(root, n=30)
    corrupt(root)
    result = _run(root, tmp_path)
    assert result.exit_code != 0
    assert message in result.output, result.output
    assert "Traceback" not in result.output
    _assert_no_complete_cell(tmp_path)


def test_unknown_names_are_clear(tmp_path):
    root = tmp_path / "kitti"
    _write(root, n=30)
    r = _run(root, tmp_path, "--setting", "kitti-1x")
    assert r.exit_code != 0 and "unknown setting 'kitti-1x'" in r.output and "did you mean" in r.output
    r = CliRunner().invoke(build_cli(), ["run", "--dataset", f"kitti={root}", "--method", "copy-lats", "-q",
                                         "--reports", str(tmp_path / "rep")])
    assert r.exit_code != 0 and "unknown method 'copy-lats'; did you mean 'copy-last'" in r.output


def test_missing_root_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    r = CliRunner().invoke(build_cli(), ["run", "--dataset", f"kitti={tmp_path / 'nope'}", "-q"])
    assert r.exit_code != 0 and "does not exist" in r.output
    # before the default methods' readiness generated their training data (the embedded town's)
    assert not (tmp_path / "cache").exists()


def test_reader_errors_name_file(tmp_path):
    _write(tmp_path, n=3)
    (tmp_path / "sequences/08/times.txt").write_text("0.0\nabc\n0.2\n")
    with pytest.raises(DataError, match=r"times.txt line 2"):
        KittiOdometry(tmp_path).sequence("08")


def test_datasets_check_reports_problems(tmp_path):
    _write(tmp_path, n=4)
    (tmp_path / "sequences/08/velodyne/000002.bin").write_bytes(b"\0" * 20)
    r = CliRunner().invoke(build_cli(), ["datasets", "check", str(tmp_path)])
    assert r.exit_code == 1
    assert "layout: kitti" in r.output and "sequence 08: 4 sweeps" in r.output
    assert "000002.bin has 20 bytes" in r.output
