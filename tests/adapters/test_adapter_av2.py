"""Argoverse 2 adapter: Sensor and LiDAR layouts written with the real columns, read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from pcfbench.errors import DataError
from pcfbench.testing import check_adapter, toy_world_sweeps
from pcfbench.datasets.av2 import Argoverse2, write_av2
from pcfbench.datasets.layout import SequenceData

LOG = "0c6e62d7-bdfa-3061-8d3d-03b13aa21f68"


def _log(name: str = LOG, split: str = "val", n: int = 12, seed: int = 0) -> SequenceData:
    pts, poses, times = toy_world_sweeps(n, beams=8, azimuths=90, seed=seed)
    ts = 315_967_376_859_506_000 + np.round(times * 1e9).astype(np.int64)
    return SequenceData.from_arrays(name, split, pts, poses, ts)


def write_tiny_av2(root: Path, layout: str = "lidar", n: int = 12) -> Path:
    write_av2(root, [_log(n=n), _log("1f2e3d4c-0000-4000-8000-000000000001", "val", n, seed=1),
                     _log("aaaa0000-0000-4000-8000-000000000002", "train", n, seed=2)], layout=layout)
    return root


@pytest.mark.parametrize("layout", ["lidar", "sensor"])
def test_round_trip_both_layouts(tmp_path, layout):
    src = _log()
    root = write_tiny_av2(tmp_path, layout)
    ds = Argoverse2(root)
    assert Argoverse2.detect(root) and ds.layout == layout
    assert ds.sequence_names("val") == [f"val/{LOG}", "val/1f2e3d4c-0000-4000-8000-000000000001"]
    assert len(ds.sequence_names("train")) == 1
    seq = ds.sequence(f"val/{LOG}")
    np.testing.assert_array_equal(seq.timestamps_ns, src.timestamps_ns)
    np.testing.assert_allclose(seq.T_world_sensor, src.T_world_sensor, atol=1e-9)
    pts = seq.load_points(4)
    assert pts.dtype == np.float32
    # float16 storage: relative error below 2^-11
    ref = src.load(4)
    assert np.all(np.abs(pts - ref) <= np.abs(ref) * 2.0**-11 + 1e-6)
    check_adapter(ds, "val")
    assert ds.check().ok and ds.check().layout == f"av2 {layout} dataset"


def test_real_dtypes_on_disk(tmp_path):
    root = write_tiny_av2(tmp_path, n=3)
    f = next((root / "val" / LOG / "sensors" / "lidar").glob("*.feather"))
    schema = feather.read_table(f).schema
    assert [(n, str(schema.field(n).type)) for n in schema.names] == [
        ("x", "halffloat"), ("y", "halffloat"), ("z", "halffloat"), ("intensity", "uint8"), ("laser_number", "uint8"), ("offset_ns", "int32")]
    pose = feather.read_table(root / "val" / LOG / "city_SE3_egovehicle.feather")
    assert pose.schema.names == ["timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"]
    assert pose.schema.field("timestamp_ns").type == pa.int64()


def _rewrite(path: Path, fn) -> None:
    feather.write_feather(fn(feather.read_table(path)), path)


def test_bad_inputs_each_named(tmp_path):
    log = tmp_path / "a" / "val" / LOG
    write_tiny_av2(tmp_path / "a", n=4)
    sweep = sorted((log / "sensors" / "lidar").glob("*.feather"))[1]
    sweep.write_bytes(sweep.read_bytes()[:100])
    with pytest.raises(DataError, match=rf"LiDAR sweep .*{sweep.name} is not a readable feather file"):
        Argoverse2(tmp_path / "a").sequence(f"val/{LOG}").load_points(1)

    write_tiny_av2(tmp_path / "b", n=4)
    log = tmp_path / "b" / "val" / LOG
    sweep = sorted((log / "sensors" / "lidar").glob("*.feather"))[0]
    _rewrite(sweep, lambda t: t.drop_columns(["z"]))
    with pytest.raises(DataError, match=r"has no column 'z'"):
        Argoverse2(tmp_path / "b").sequence(f"val/{LOG}").load_points(0)
    _rewrite(sweep, lambda t: t.append_column("z", pa.array(np.zeros(t.num_rows, np.int32)).cast(pa.string())))
    with pytest.raises(DataError, match=r"column 'z' has type string, expected float"):
        Argoverse2(tmp_path / "b").sequence(f"val/{LOG}").load_points(0)

    write_tiny_av2(tmp_path / "c", n=4)
    pose = tmp_path / "c" / "val" / LOG / "city_SE3_egovehicle.feather"
    _rewrite(pose, lambda t: (
        t.set_column(1, "qw", pa.array(np.zeros(t.num_rows)))
        .set_column(2, "qx", pa.array(np.zeros(t.num_rows)))
        .set_column(3, "qy", pa.array(np.zeros(t.num_rows)))
        .set_column(4, "qz", pa.array(np.zeros(t.num_rows)))
    ))
    with pytest.raises(DataError, match=r"city_SE3_egovehicle.feather row 0 \(timestamp_ns \d+\): quaternion .* zero norm"):
        Argoverse2(tmp_path / "c").sequence(f"val/{LOG}")

    write_tiny_av2(tmp_path / "d", n=4)
    pose = tmp_path / "d" / "val" / LOG / "city_SE3_egovehicle.feather"
    _rewrite(pose, lambda t: t.take([0, 2, 1, 3]))
    with pytest.raises(DataError, match=r"timestamp_ns \d+ at row 2 is not after"):
        Argoverse2(tmp_path / "d").sequence(f"val/{LOG}")
    _rewrite(pose, lambda t: t.take([0, 2, 3]))
    with pytest.raises(DataError, match=r"has no pose at timestamp_ns \d+"):
        Argoverse2(tmp_path / "d").sequence(f"val/{LOG}")

    write_tiny_av2(tmp_path / "e", n=4)
    (tmp_path / "e" / "val" / LOG / "calibration" / "egovehicle_SE3_sensor.feather").unlink()
    with pytest.raises(DataError, match=r"calibration file .*egovehicle_SE3_sensor.feather is missing"):
        Argoverse2(tmp_path / "e").sequence(f"val/{LOG}")


def test_check_collects_every_problem(tmp_path):
    root = write_tiny_av2(tmp_path, n=4)
    lidar = root / "val" / LOG / "sensors" / "lidar"
    files = sorted(lidar.glob("*.feather"))
    files[0].write_bytes(b"garbage")
    files[2].write_bytes(files[2].read_bytes()[:50])
    (root / "train" / "aaaa0000-0000-4000-8000-000000000002" / "city_SE3_egovehicle.feather").unlink()
    rep = Argoverse2(root).check()
    assert len(rep.problems) == 3, rep.problems
    assert rep.found[f"sequence val/{LOG}"] == "4 sweeps, 10.00 Hz"


@pytest.mark.parametrize("setting", ["av2-1s", "av2-3s"])
def test_end_to_end_copy_last(tmp_path, setting):
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    stride = 2 if setting == "av2-1s" else 6
    num = 9 * stride + 3
    root = write_av2(tmp_path / "av2", [_log(n=num)], layout="sensor")
    args = ["run", "--dataset", f"av2={root}", "--setting", setting, "--method", "copy-last",
            "--reports", str(tmp_path / "reports"), "-q"]
    res = CliRunner().invoke(build_cli(), args)
    assert res.exit_code == 0, res.output
    n = num - 4 * stride - 5 * stride
    assert f"{n} samples ({n} now, 0 failed)" in res.output
    assert f"av2 / val / {setting}" in (tmp_path / "reports" / "leaderboard.md").read_text()
