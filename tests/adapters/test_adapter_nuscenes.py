"""nuScenes adapter: tables written in the real layout, read back; every bad input named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pcfbench.errors import DataError
from pcfbench.geometry import transform_points
from pcfbench.testing import check_adapter, toy_world_sweeps
from pcfbench.datasets.layout import STANDARD_AXES, SequenceData, change_axes
from pcfbench.datasets.nuscenes import NuScenes, official_splits, write_nuscenes


def _scene(name: str, n: int, seed: int = 0, rate_hz: float = 2.0, **kw) -> SequenceData:
    pts, poses, times = toy_world_sweeps(n, beams=8, azimuths=90, rate_hz=rate_hz, seed=seed, **kw)
    ts = 1_531_000_000_000_000_000 + np.round(times * 1e9).astype(np.int64)
    seq = SequenceData.from_arrays(name, "val", pts, poses, ts)
    return change_axes(seq, STANDARD_AXES, NuScenes.axes)


def write_tiny_nuscenes(root: Path, version: str = "v1.0-trainval", names=("scene-0003", "scene-0012"), n: int = 16, keyframe_every: int = 1) -> Path:
    write_nuscenes(root, [_scene(s, n, seed=i) for i, s in enumerate(names)], version=version, keyframe_every=keyframe_every)
    return root


def test_official_split_lists():
    s = official_splits()
    assert {k: len(v) for k, v in s.items()} == {"train": 700, "val": 150, "test": 150, "mini_train": 8, "mini_val": 2}
    assert not set(s["train"]) & set(s["val"])
    assert set(s["mini_val"]) == {"scene-0103", "scene-0916"}
    assert s["val"][:3] == ["scene-0003", "scene-0012", "scene-0013"]


def test_layout_files_and_structure(tmp_path):
    root = write_tiny_nuscenes(tmp_path, n=6)
    for t in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "log"):
        assert (root / "v1.0-trainval" / f"{t}.json").is_file()
    sd = json.loads((root / "v1.0-trainval" / "sample_data.json").read_text())
    assert sd[0]["filename"].startswith("samples/LIDAR_TOP/") and sd[0]["filename"].endswith(".pcd.bin")
    assert len(json.loads((root / "v1.0-trainval" / "sample.json").read_text())) == 12
    raw = np.fromfile(root / sd[0]["filename"], np.float32)
    assert raw.size % 5 == 0


def test_round_trip_poses_points_timestamps(tmp_path):
    src = _scene("scene-0003", 10)
    write_nuscenes(tmp_path, [src])
    ds = NuScenes(tmp_path)
    assert NuScenes.detect(tmp_path)
    assert ds.sequence_names("val") == ["scene-0003"] and ds.sequence_names("train") == []
    seq = ds.sequence("scene-0003")
    assert len(seq) == 10
    np.testing.assert_allclose(seq.T_world_sensor, src.T_world_sensor, atol=1e-9)
    # microsecond timestamps: ns values rounded down to whole microseconds
    np.testing.assert_array_equal(seq.timestamps_ns, src.timestamps_ns // 1000 * 1000)
    np.testing.assert_array_equal(seq.load_points(3), src.load(3))
    check_adapter(ds, "val")


def test_world_points_agree_after_axes_change(tmp_path):
    """The same world points come out whatever the sensor axes: pose and points change together."""
    pts, poses, times = toy_world_sweeps(4, beams=8, azimuths=90, rate_hz=2.0)
    write_nuscenes(tmp_path, [_scene("scene-0003", 4)])
    seq = NuScenes(tmp_path).sequence("scene-0003")
    for i in range(4):
        np.testing.assert_allclose(transform_points(seq.T_world_sensor[i], seq.load_points(i)), transform_points(poses[i], pts[i]), atol=1e-3)


def test_keyframes_only_and_mini_aliases(tmp_path):
    write_nuscenes(tmp_path, [_scene("scene-0103", 12, rate_hz=20.0)], version="v1.0-mini", keyframe_every=3)
    ds = NuScenes(tmp_path)
    assert ds.release == "v1.0-mini" and ds.splits() == ("mini_train", "mini_val")
    assert ds.sequence_names("val") == ["scene-0103"] == ds.sequence_names("mini_val")
    seq = ds.sequence("scene-0103")
    assert len(seq) == 4  # sweeps 0, 3, 6, 9
    assert len(list((tmp_path / "sweeps" / "LIDAR_TOP").glob("*.pcd.bin"))) == 8


def _mutate(root: Path, table: str, fn) -> Path:
    path = root / "v1.0-trainval" / f"{table}.json"
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))
    return path


def test_bad_inputs_each_named(tmp_path):
    root = write_tiny_nuscenes(tmp_path / "a", n=5)
    (root / "v1.0-trainval" / "ego_pose.json").unlink()
    with pytest.raises(DataError, match=r"ego_pose.json is missing"):
        NuScenes(root).sequence("scene-0003")

    root = write_tiny_nuscenes(tmp_path / "b", n=5)
    sd = json.loads((root / "v1.0-trainval" / "sample_data.json").read_text())
    f = root / sd[1]["filename"]
    f.write_bytes(f.read_bytes()[:-7])
    with pytest.raises(DataError, match=r"pcd.bin has .* not a multiple of 20"):
        NuScenes(root).sequence("scene-0003").load_points(1)

    root = write_tiny_nuscenes(tmp_path / "c", n=5)
    _mutate(root, "ego_pose", lambda d: d[2].update(rotation=[0, 0, 0, 0]))
    with pytest.raises(DataError, match=r"ego_pose.json token \w+: rotation quaternion .* zero norm"):
        NuScenes(root).sequence("scene-0003")

    root = write_tiny_nuscenes(tmp_path / "d", n=5)
    _mutate(root, "sample", lambda d: d[2].update(next="deadbeef"))
    with pytest.raises(DataError, match=r"sample token deadbeef .* chain is broken"):
        NuScenes(root).sequence("scene-0003")

    root = write_tiny_nuscenes(tmp_path / "e", n=5)

    def swap(d):
        d[1]["timestamp"], d[2]["timestamp"] = d[2]["timestamp"], d[1]["timestamp"]

    _mutate(root, "sample_data", swap)
    with pytest.raises(DataError, match=r"scene scene-0003 keyframe \w+ has timestamp \d+ us, not after"):
        NuScenes(root).sequence("scene-0003")


def test_check_collects_every_problem(tmp_path):
    root = write_tiny_nuscenes(tmp_path, n=5)
    sd = json.loads((root / "v1.0-trainval" / "sample_data.json").read_text())
    (root / sd[0]["filename"]).unlink()  # scene-0003 sweep 0
    _mutate(root, "sample", lambda d: d[6].update(prev="0" * 32))  # scene-0012 chain
    rep = NuScenes(root).check()
    assert len(rep.problems) == 2, rep.problems
    assert "is missing" in rep.problems[0] and "chain is broken" in rep.problems[1]
    assert rep.found["sequence scene-0003"] == "5 sweeps, 2.00 Hz"


@pytest.mark.parametrize("setting", ["nuscenes-1s", "nuscenes-3s"])
def test_end_to_end_copy_last(tmp_path, setting):
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    root = write_tiny_nuscenes(tmp_path / "nusc", names=("scene-0003",), n=16)
    args = ["run", "--dataset", f"nuscenes={root}", "--setting", setting, "--method", "copy-last",
            "--reports", str(tmp_path / "reports"), "-q"]
    res = CliRunner().invoke(build_cli(), args)
    assert res.exit_code == 0, res.output
    past, fut = (2, 2) if setting == "nuscenes-1s" else (6, 6)
    assert f"{16 - (past - 1) - fut} samples ({16 - (past - 1) - fut} now, 0 failed)" in res.output
    assert f"nuscenes / val / {setting}" in (tmp_path / "reports" / "leaderboard.md").read_text()


def test_datasets_check_cli_names_layout_splits_and_problems(tmp_path):
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    root = write_tiny_nuscenes(tmp_path, names=("scene-0003", "scene-0001"), n=5)
    res = CliRunner().invoke(build_cli(), ["datasets", "check", str(root)])
    assert res.exit_code == 0, res.output
    assert "layout: nuscenes v1.0-trainval" in res.output
    assert "split train: 1 sequence(s)" in res.output and "split val: 1 sequence(s)" in res.output
    assert "sequence scene-0001: 5 sweeps, 2.00 Hz" in res.output
    for t in ("sensor", "log"):
        (root / "v1.0-trainval" / f"{t}.json").unlink()
    res = CliRunner().invoke(build_cli(), ["datasets", "check", f"{root}?version=v1.0-trainval", "--layout", "nuscenes"])
    assert res.exit_code == 1
    assert "sensor.json" in res.output and "log.json" in res.output


def test_installed_command_checks_and_runs_the_fixture_from_outside_the_checkout(tmp_path):
    """The installed `pcfbench` command, started in a folder outside the checkout, as a user
    runs it: `datasets check` and `run` read the split list from the installed package (a
    resource path that resolves only from the repository fails here)."""
    import os
    import subprocess
    import sys

    root = write_tiny_nuscenes(tmp_path / "nusc", names=("scene-0003",), n=16)
    work = tmp_path / "elsewhere"
    work.mkdir()
    exe = [sys.executable, "-m", "pcfbench"]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    check = subprocess.run([*exe, "datasets", "check", str(root)], cwd=work, env=env, capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    assert "split val: 1 sequence(s)" in check.stdout
    run = subprocess.run([*exe, "run", "-d", f"nuscenes={root}", "-s", "nuscenes-1s", "-m", "copy-last",
                          "--reports", str(tmp_path / "reports"), "-q"], cwd=work, env=env, capture_output=True,
                         text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "nuscenes / val / nuscenes-1s" in (tmp_path / "reports" / "leaderboard.md").read_text()
