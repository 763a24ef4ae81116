"""``pcfbench export`` of many samples and of a run's stored forecasts: each sample on its own
span of one timeline (or one file each), the dataset's intensity on past and ground-truth
clouds, forecast topics Foxglove users can type, and a forecast written only when it scores
exactly as the store says it was scored."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from conftest import write_tiny_kitti
from tests_helpers import Shifted, shifted_plugins
from pcfbench.cli import build_cli
from pcfbench.errors import PcfbenchError
from pcfbench.geometry import transform_points
from pcfbench.method import options_hash, parse_options
from pcfbench.reporting.select import Selection
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec
from pcfbench.datasets.export_mcap import TOPIC_CHARS, forecast_topic, unique_topics

METRICS = ("chamfer", "l1_mean", "absrel_mean")


def _read(path):
    """topic -> [(log_time, decoded)], and metadata name -> record."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    topics = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages():
            topics.setdefault(channel.topic, []).append((message.log_time, decoded))
    with open(path, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    return topics, meta


def _cloud(msg):
    """(N, k) float32 of a foxglove.PointCloud and its field names."""
    names = [f.name for f in msg.fields]
    assert [f.offset for f in msg.fields] == [4 * k for k in range(len(names))] and msg.point_stride == 4 * len(names)
    return np.frombuffer(msg.data, "<f4").reshape(-1, len(names)), names


# -- topic names ------------------------------------------------------------------------------

@pytest.mark.parametrize("method, options, ck, topic", [
    ("copy-last", {}, None, "/forecast/copy_last/points"),
    ("raycast-voxel", {"voxel": "0.4"}, None, "/forecast/raycast_voxel/voxel_0p4/points"),
    ("shifted", {"dx": "-1.5", "a": "x y"}, None, "/forecast/shifted/a_x_y/dx_m1p5/points"),
    ("copilot4d-token-copy", {}, "84120cdf0123abcd", "/forecast/copilot4d_token_copy/ck_84120cdf/points"),
])
def test_forecast_topic_is_typeable_and_keeps_every_option(method, options, ck, topic):
    got = forecast_topic(method, options, ck)
    assert got == topic and TOPIC_CHARS.match(got)
    assert not any(c in got for c in ":=,.- ")


def test_colliding_topics_get_a_hash_each_and_distinct_ones_stay():
    a, b, c = "m:a=x-y", "m:a=x_y", "m:a=z"
    got = unique_topics({a: forecast_topic("m", {"a": "x-y"}), b: forecast_topic("m", {"a": "x_y"}),
                         c: forecast_topic("m", {"a": "z"})})
    assert forecast_topic("m", {"a": "x-y"}) == forecast_topic("m", {"a": "x_y"}) == "/forecast/m/a_x_y/points"
    assert got[c] == "/forecast/m/a_z/points"
    assert got[a].startswith("/forecast/m/a_x_y_h") and got[b].startswith("/forecast/m/a_x_y_h") and got[a] != got[b]
    assert all(TOPIC_CHARS.match(t) for t in got.values())
    assert unique_topics({a: "/forecast/m/points"}) == {a: "/forecast/m/points"}


# -- many samples, reflectance ----------------------------------------------------------------

def _intensity_of(points_sensor):
    """The reflectance written for a point: a smooth function of where it is (sensor frame)."""
    return (0.01 * np.linalg.norm(points_sensor.astype(np.float64), axis=1)).astype(np.float32)


@pytest.fixture(scope="module")
def kitti_with_intensity(tmp_path_factory):
    """A tiny KITTI whose every point's reflectance is 0.01 x its range."""
    from pcfbench.datasets.kitti import read_bin

    root = write_tiny_kitti(tmp_path_factory.mktemp("refl") / "kitti")
    for path in sorted((root / "sequences" / "08" / "velodyne").glob("*.bin")):
        data = read_bin(path).copy()
        data[:, 3] = _intensity_of(data[:, :3])
        data.tofile(path)
    return root


def test_many_samples_share_one_timeline_without_overlap_and_carry_intensity(kitti_with_intensity, tmp_path):
    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.protocol import SETTINGS, SampleBuilder

    out = tmp_path / "three.mcap"
    res = CliRunner().invoke(build_cli(), ["export", "-d", f"kitti={kitti_with_intensity}", "-s", "kitti-1s", "--samples", "3",
                                           "-m", "copy-last", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "1 file(s), 45 point clouds" in res.output
    topics, meta = _read(out)
    builder = SampleBuilder(KittiOdometry(kitti_with_intensity), SETTINGS["kitti-1s"])
    keys = builder.sample_keys("test")[:3]
    assert [k for k in keys] == [("08", 8), ("08", 9), ("08", 10)]  # neighbours: their sweeps overlap in time
    samples = {sid: json.loads(v) for sid, v in meta["pcfbench.samples"].items()}
    assert list(samples) == ["08/000008", "08/000009", "08/000010"]
    spans = [(samples[s]["start_ns"], samples[s]["end_ns"]) for s in samples]
    assert spans[0][0] == 0 and all(b[0] - a[1] == 1_000_000_000 for a, b in zip(spans, spans[1:]))  # a 1 s gap
    assert [m.message.split(";")[0] for _, m in topics["/pcfbench/sample"]] == [
        f"sample {s} (kitti sequence 08, reference sweep {int(s[3:])})" for s in samples]
    past, gt = topics["/past/points"], topics["/ground_truth/points"]
    assert len(past) == len(gt) == 15
    for j, (seq, index) in enumerate(keys):
        sample, truth = builder.build(seq, index)
        off = samples[sample.sample_id]["offset_ns"]
        mine_past, mine_gt = past[5 * j:5 * j + 5], gt[5 * j:5 * j + 5]
        # recorded time = log time - offset, for the message time and the header's stamp alike
        assert [t - off for t, _ in mine_past] == list(sample.past_timestamps_ns)
        assert [m.timestamp.ToNanoseconds() - off for _, m in mine_gt] == list(sample.future_timestamps_ns)
        T_world_sensor = [sample.T_world_ref @ T for T in sample.future_T_ref_sensor]
        for k, (_, msg) in enumerate(mine_gt):
            data, names = _cloud(msg)
            assert names == ["x", "y", "z", "intensity"] and len(data) == len(truth.future_points_ref[k])
            np.testing.assert_allclose(data[:, 3], _intensity_of(data[:, :3]), atol=2e-6)  # each value on its point
            world = transform_points(T_world_sensor[k], data[:, :3])
            np.testing.assert_allclose(world, transform_points(sample.T_world_ref, truth.future_points_ref[k]), atol=2e-3)
        for k, (_, msg) in enumerate(mine_past):
            data, names = _cloud(msg)
            assert names == ["x", "y", "z", "intensity"] and len(data) == len(sample.past_points_ref[k])
            np.testing.assert_allclose(data[:, 3], _intensity_of(data[:, :3]), atol=2e-6)
        assert np.all(data[:, 3] > 0)
    fc = topics["/forecast/copy_last/points"]
    assert [f.name for f in fc[0][1].fields] == ["x", "y", "z", "error"]  # a forecast has no intensity
    # the timeline is ordered: every message of a sample lies inside its span
    for topic, msgs in topics.items():
        times = [t for t, _ in msgs]
        assert times == sorted(times), topic
        assert all(any(a <= t <= b for a, b in spans) for t in times), topic


def test_per_sample_writes_one_file_each_at_recorded_times(kitti_with_intensity, tmp_path):
    out = tmp_path / "each"
    res = CliRunner().invoke(build_cli(), ["export", "-d", f"kitti={kitti_with_intensity}", "-s", "kitti-1s",
                                           "--sample", "08/000012", "--sample", "08/000009", "--per-sample", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == ["08_000009.mcap", "08_000012.mcap"]
    assert "2 file(s), 20 point clouds" in res.output
    for name, sid in (("08_000009.mcap", "08/000009"), ("08_000012.mcap", "08/000012")):
        topics, meta = _read(out / name)
        assert list(meta["pcfbench.samples"]) == [sid] and json.loads(meta["pcfbench.samples"][sid])["offset_ns"] == 0
        assert not any(t.startswith("/forecast/") for t in topics)
    res = CliRunner().invoke(build_cli(), ["export", "-d", f"kitti={kitti_with_intensity}", "-s", "kitti-1s",
                                           "--sample", "08/000012", "--samples", "2", "-o", str(tmp_path / "x.mcap")])
    assert res.exit_code == 2 and "give one of them" in res.output


def test_nuscenes_sequences_give_their_intensity_column(tmp_path):
    from test_adapter_nuscenes import write_tiny_nuscenes
    from pcfbench.datasets.nuscenes import NuScenes, read_pcd_bin

    root = write_tiny_nuscenes(tmp_path / "nusc", names=("scene-0003",), n=4)
    for path in root.rglob("*.pcd.bin"):
        data = read_pcd_bin(path).copy()
        data[:, 3] = np.arange(len(data), dtype=np.float32) * 0.5
        data.tofile(path)
    seq = NuScenes(root).sequence("scene-0003")
    for i in range(len(seq)):
        n = len(seq.load_points(i))
        np.testing.assert_array_equal(seq.load_intensity(i), np.arange(n, dtype=np.float32) * 0.5)


def test_av2_sequences_give_their_intensity_column(tmp_path):
    import pyarrow.feather as feather
    from test_adapter_av2 import write_tiny_av2
    from pcfbench.datasets.av2 import Argoverse2

    root = write_tiny_av2(tmp_path / "av2", n=4)
    for path in (root / "train").rglob("sensors/lidar/*.feather"):
        t = feather.read_table(path)
        values = pa.array((np.arange(t.num_rows) % 256).astype(np.uint8))
        feather.write_feather(t.set_column(t.schema.get_field_index("intensity"), "intensity", values), path)
    adapter = Argoverse2(root)
    seq = adapter.sequence(adapter.sequence_names("train")[0])
    for i in range(len(seq)):
        n = len(seq.load_points(i))
        np.testing.assert_array_equal(seq.load_intensity(i), (np.arange(n) % 256).astype(np.float32))


# -- a run's stored forecasts ----------------------------------------------------------------

def _spec(root, method="copy-last", raw=None, setting="kitti-1s"):
    opts = parse_options(shifted_plugins().methods.get(method).Options, raw or {}, method)
    return CellSpec(method, dict(raw or {}), options_hash(opts), "kitti", str(root), "test", setting, "full-context", None, METRICS)


@pytest.fixture(scope="module")
def run_store(tmp_path_factory, kitti_with_intensity):
    """A store of copy-last and shifted dx=0.5 on kitti-1s (6 samples each)."""
    store = tmp_path_factory.mktemp("run") / "store"
    for method, raw in (("copy-last", None), ("shifted", {"dx": "0.5"})):
        run_cell(_spec(kitti_with_intensity, method, raw), store, RunOptions(progress=False), plugins=shifted_plugins())
    return store


def _stored_rows(store, method):
    from pcfbench.store.cells import Cell, iter_cells

    (d,) = [d for d, m in iter_cells(store) if m["spec"]["method"] == method]
    return d, Cell.at(store, d.relative_to(store)).read_rows()


def test_store_export_writes_the_scored_forecasts_with_their_stored_rows(run_store, kitti_with_intensity, tmp_path):
    from pcfbench.datasets.commands import export_stored
    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.protocol import SETTINGS, SampleBuilder

    out = tmp_path / "run.mcap"
    written, n = export_stored(run_store, out, count=2, plugins=shifted_plugins())
    assert written == [out] and n == 2 * (5 + 5 * 3)
    topics, meta = _read(out)
    shifted_topic = "/forecast/shifted/dx_0p5/points"
    assert {"/forecast/copy_last/points", shifted_topic} <= set(topics)
    described = {t: json.loads(v) for t, v in meta["pcfbench.topics"].items()}
    cell_dir, rows = _stored_rows(run_store, "shifted")
    assert described[shifted_topic]["spec"] == "shifted:dx=0.5"
    assert described[shifted_topic]["cell"] == str(cell_dir.relative_to(run_store))
    assert meta["pcfbench.export"]["source"] == f"results store {run_store}"
    assert list(meta["pcfbench.samples"]) == ["08/000008", "08/000009"]
    builder = SampleBuilder(KittiOdometry(kitti_with_intensity), SETTINGS["kitti-1s"])
    method = Shifted(Shifted.Options(dx=0.5))
    msgs = topics[shifted_topic]
    assert len(msgs) == 10
    for j, sid in enumerate(["08/000008", "08/000009"]):
        sample, _ = builder.build("08", int(sid[3:]))
        off = json.loads(meta["pcfbench.samples"][sid])["offset_ns"]
        want = method.forecast(sample.for_method())
        T_world_sensor = [sample.T_world_ref @ T for T in sample.future_T_ref_sensor]
        for k in range(5):
            t, msg = msgs[5 * j + k]
            assert t - off == sample.future_timestamps_ns[k]
            data, _ = _cloud(msg)
            np.testing.assert_allclose(transform_points(T_world_sensor[k], data[:, :3]),
                                       transform_points(sample.T_world_ref, want.points_ref[k]), atol=2e-3)
        got = json.loads(meta["pcfbench.scores"][sid])[shifted_topic]
        stored = rows[rows["sample_id"] == sid].sort_values("step")
        for m in METRICS:  # the rows of the run, bit for bit
            assert [r[m] for r in got] == stored[m].tolist()
    gt, _ = _cloud(topics["/ground_truth/points"][0][1])
    assert gt.shape[1] == 4 and np.all(gt[:, 3] > 0)  # the dataset's intensity


def test_store_export_from_the_command_line_picks_cells_by_pattern(run_store, tmp_path):
    out = tmp_path / "cl"
    res = CliRunner().invoke(build_cli(), ["export", "--store", str(run_store), "-m", "copy-*", "--sample", "08/000011",
                                           "--per-sample", "-o", str(out)])
    assert res.exit_code == 0, res.output
    topics, meta = _read(out / "08_000011.mcap")
    assert [t for t in topics if t.startswith("/forecast/")] == ["/forecast/copy_last/points"]
    res = CliRunner().invoke(build_cli(), ["export", "--store", str(run_store), "-m", "copy-last", "--sample", "08/000020",
                                           "-o", str(tmp_path / "x.mcap")])
    assert res.exit_code == 2, res.output
    assert "--sample '08/000020': it is not a sample of the cells (the samples every selected cell holds: " \
           "08/000008 .. 08/000013, 6 in all)" in res.output
    res = CliRunner().invoke(build_cli(), ["export", "--store", str(run_store), "-m", "raycast-*", "-o", str(tmp_path / "y.mcap")])
    assert res.exit_code == 2 and "--method 'raycast-*' matches no method" in res.output


def _copy_store(store, tmp_path):
    dst = tmp_path / "store"
    shutil.copytree(store, dst)
    return dst


def test_store_export_refuses_a_forecast_that_does_not_score_as_stored(run_store, tmp_path):
    from pcfbench.datasets.commands import export_stored

    store = _copy_store(run_store, tmp_path)
    cell_dir, _ = _stored_rows(store, "shifted")
    (chunk,) = sorted((cell_dir / "rows").glob("*.parquet"))
    df = pq.read_table(chunk).to_pandas()
    hit = (df["sample_id"] == "08/000009") & (df["step"] == 2)
    stored = float(df.loc[hit, "l1_mean"].iloc[0])
    df.loc[hit, "l1_mean"] = stored + 1e-12  # the smallest lie is still a lie
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), chunk)
    out = tmp_path / "x.mcap"
    with pytest.raises(PcfbenchError, match=r"^sample 08/000009 sweep 2 of shifted:dx=0\.5: l1_mean is .* recomputed but "
                                             r".* stored; the forecast made now is not the one that was scored"):
        export_stored(store, out, count=3, plugins=shifted_plugins())
    assert not out.exists() and list(tmp_path.glob(".x.mcap*")) == []  # the first sample was written, then dropped
    export_stored(store, out, count=1, plugins=shifted_plugins())  # the samples before it are fine
    assert out.exists()


def test_store_export_refuses_a_cell_made_by_another_method_version(run_store, tmp_path):
    from pcfbench.datasets.commands import export_stored

    class ShiftedV2(Shifted):
        version = "2"

    plugins = shifted_plugins()  # a fresh registry each call
    assert plugins.methods.remove_plugin("test") == ["shifted"]
    plugins.methods.add("shifted", ShiftedV2, "test")
    with pytest.raises(PcfbenchError, match=r"cannot export the forecasts of shifted:dx=0\.5: cell .* was computed with "
                                            r"a different (method_code, )?method_version"):
        export_stored(run_store, tmp_path / "x.mcap", plugins=plugins)


def test_store_export_needs_one_set_of_samples_and_records_failed_samples(run_store, tmp_path):
    from pcfbench.datasets.export_forecasts import select_cells
    from pcfbench.datasets.commands import export_stored

    store = _copy_store(run_store, tmp_path)
    cell_dir, _ = _stored_rows(store, "copy-last")
    other = cell_dir.parent.parent.parent / "kitti-3s" / "test" / cell_dir.name
    shutil.copytree(cell_dir, other)
    meta = json.loads((other / "cell.json").read_text())
    meta["spec"]["setting"] = "kitti-3s"
    (other / "cell.json").write_text(json.dumps(meta))
    with pytest.raises(PcfbenchError, match=r"the selected cells hold 2 different sets of samples .* narrow with "
                                            r"--dataset, --setting or --cell"):
        select_cells(store, Selection())
    assert [c.spec.setting for c in select_cells(store, Selection(settings=("kitti-3s",)))] == ["kitti-3s"]
    with pytest.raises(PcfbenchError, match=r"--cell 'nothing\*' matches no selected cell"):
        select_cells(store, Selection(settings=("kitti-1s",)), ("nothing*",))
    shutil.rmtree(other)
    # a sample the method failed on in the run: not re-run, its error in the scores record
    shifted_dir, _ = _stored_rows(store, "shifted")
    (chunk,) = sorted((shifted_dir / "rows").glob("*.parquet"))
    df = pq.read_table(chunk).to_pandas()
    keep = df[df["sample_id"] != "08/000008"]
    failed = pd.DataFrame([{**df.iloc[0].to_dict(), "step": -1, "status": "failed", "error": "ValueError: boom"}])
    pq.write_table(pa.Table.from_pandas(pd.concat([failed, keep]), preserve_index=False), chunk)
    out = tmp_path / "f.mcap"
    export_stored(store, out, count=1, plugins=shifted_plugins())
    topics, meta = _read(out)
    scores = json.loads(meta["pcfbench.scores"]["08/000008"])
    assert scores["/forecast/shifted/dx_0p5/points"] == {"failed": "ValueError: boom"}
    assert "/forecast/shifted/dx_0p5/points" not in topics and len(topics["/forecast/copy_last/points"]) == 5


@pytest.mark.parametrize("args, message", [
    (["-d", "kitti", "-d", "nuscenes", "-s", "kitti-1s"], "without --store, give one --dataset NAME[=ROOT] and one --setting"),
    (["-d", "kitti", "-s", "kitti-1s", "--cell", "kitti/*"], "--cell picks cells of a results store: pass --store DIR"),
    (["--store", "STORE", "--split", "val"], "--split and --policy pick samples to make; with --store the cells say them"),
    (["--store", "STORE", "--per-sample", "-o", "FILE"], "with --per-sample it is the folder to write one .mcap per sample into"),
    (["--store", "STORE", "-o", "DIR"], "is a folder: name the .mcap file to write, or pass --per-sample"),
])
def test_export_arguments_that_cannot_go_together_are_one_error(run_store, tmp_path, args, message):
    (tmp_path / "FILE").write_text("")
    (tmp_path / "DIR").mkdir()
    args = [str(run_store) if a == "STORE" else str(tmp_path / a) if a in ("FILE", "DIR") else a for a in args]
    if "-o" not in args:
        args += ["-o", str(tmp_path / "x.mcap")]
    res = CliRunner().invoke(build_cli(), ["export", "-m", "copy-last", "--samples", "1", *args])
    assert res.exit_code == 2 and message in res.output, res.output
