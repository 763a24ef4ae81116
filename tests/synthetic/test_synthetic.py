"""The synthetic world: generation, determinism, the cache, the adapters and the CLI."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.testing import check_adapter
from pcfbench.datasets.synthetic.domains import GENERATOR_VERSION, get_domain
from pcfbench.datasets.synthetic.generate import (
    COMPLETE, MANIFEST, ensure_domain, generate_domain, get_writer, simulate_sequence, split_complete,
)


def tiny(name: str = "synthetic-town", sweeps: int = 8, azimuths: int = 240):
    """A small copy of a domain: one train and one test sequence, a coarse azimuth grid."""
    d = get_domain(name)
    sensor = dataclasses.replace(d.sensor, azimuth_steps=azimuths, max_range_m=60.0)  # a smaller world to build
    return dataclasses.replace(d, sensor=sensor, splits={"train": (("00", 4),), "test": (("05", sweeps),)})


def tree_digest(root: Path) -> dict[str, str]:
    """sha256 of every data file (completion markers hold timings, so they are left out)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.name.startswith(COMPLETE)}


def test_generation_is_deterministic_byte_for_byte(tmp_path):
    dom = tiny(sweeps=3)
    generate_domain(dom, tmp_path / "a", progress=False, splits=("test",))
    generate_domain(dom, tmp_path / "b", progress=False, splits=("test",))
    a, b = tree_digest(tmp_path / "a"), tree_digest(tmp_path / "b")
    assert len(a) == 3 * 2 + 4  # .bin + .label per sweep, calib, times, poses, manifest
    assert a == b
    other = dataclasses.replace(dom, seed=dom.seed + 1)
    generate_domain(other, tmp_path / "c", progress=False, splits=("test",))
    c = tree_digest(tmp_path / "c")
    assert c["sequences/05/velodyne/000000.bin"] != a["sequences/05/velodyne/000000.bin"]


def test_generating_a_split_into_a_folder_keeps_its_other_splits_of_the_same_world(tmp_path):
    import json

    from pcfbench.datasets.synthetic.adapter import SyntheticTown

    dom = tiny(sweeps=3)
    generate_domain(dom, tmp_path, progress=False, splits=("test",))
    generate_domain(dom, tmp_path, progress=False, splits=("train",))  # before: the manifest forgot test
    adapter = SyntheticTown(tmp_path)
    assert adapter.sequence_names("test") == ["05"] and adapter.sequence_names("train") == ["00"]
    assert set(json.loads((tmp_path / "synthetic.json").read_text())["sequences"]) == {"00", "05"}
    before = tree_digest(tmp_path)
    other = dataclasses.replace(dom, seed=dom.seed + 1)  # another world: refused before anything is written
    with pytest.raises(PcfbenchError, match=r"holds split\(s\) train of another world \(seed .* generating test into"):
        generate_domain(other, tmp_path, progress=False, splits=("test",))
    assert tree_digest(tmp_path) == before
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "synthetic.json").write_text("{not json")
    with pytest.raises(PcfbenchError, match=r"synthetic.json: not a readable synthetic manifest"):
        generate_domain(dom, tmp_path / "bad", progress=False, splits=("test",))
    generate_domain(other, tmp_path / "all", progress=False)  # every split at once: a folder of its own
    generate_domain(other, tmp_path / "all", progress=False)  # and again over itself, all splits: fine


def test_adapter_reads_generated_kitti_layout_and_builds_samples(tmp_path):
    from pcfbench.datasets.synthetic.adapter import SyntheticTown

    dom = tiny(sweeps=20)
    generate_domain(dom, tmp_path, progress=False, splits=("test",))
    adapter = SyntheticTown(tmp_path)
    assert SyntheticTown.detect(tmp_path)
    assert adapter.sequence_names("test") == ["05"]
    assert adapter.sequence_names("train") == []  # not generated here
    check_adapter(adapter, "test", max_sweeps=3)
    seq = adapter.sequence("05")
    assert len(seq) == 20
    assert np.allclose(np.diff(seq.timestamps_ns), 100_000_000)
    speed = np.linalg.norm(np.diff(seq.T_world_sensor[:, :3, 3], axis=0), axis=1) * 10.0
    assert 0.0 <= speed.max() < 20.0  # an urban driving speed, m/s
    builder = SampleBuilder(adapter, SETTINGS["kitti-1s"])
    keys = builder.sample_keys("test")
    assert len(keys) == 20 - 18
    sample, truth = builder.build(*keys[0])
    assert len(sample.past_points_ref) == 5 and len(truth.future_points_ref) == 5
    assert all(len(p) > 100 for p in truth.future_points_ref)
    # the ego body is hit by the simulator and removed by the declared ego box
    raw = seq.load_points(0)
    assert adapter.ego_box.inside(raw).sum() > 0
    assert adapter.ego_box.inside(sample.past_points_ref[-1]).sum() == 0


def test_suburb_adapter_rate_and_settings(tmp_path):
    from pcfbench.datasets.synthetic.adapter import SyntheticSuburb

    dom = tiny("synthetic-suburb", sweeps=6)
    generate_domain(dom, tmp_path, progress=False, splits=("test",))
    adapter = SyntheticSuburb(tmp_path)
    seq = adapter.sequence("05")
    assert np.allclose(np.diff(seq.timestamps_ns), 500_000_000)
    assert SampleBuilder(adapter, SETTINGS["nuscenes-1s"]).sample_keys("test") == [("05", 1), ("05", 2), ("05", 3)]
    with pytest.raises(PcfbenchError, match="not 'synthetic-town'"):
        from pcfbench.datasets.synthetic.adapter import SyntheticTown

        SyntheticTown(tmp_path)


def test_a_folder_of_another_physics_or_generator_version_is_refused_by_name(tmp_path):
    """A folder generated by an earlier pcfbench (physics 9's realistic town, say) is not read
    as today's data: its results would carry today's recipe."""
    from pcfbench.datasets.synthetic import adapter as A

    physics = get_domain("synthetic-town-realistic").physics
    manifest = tmp_path / MANIFEST
    for made in ({"physics": physics - 1}, {"physics": physics, "generator_version": "1"}, {}):
        manifest.write_text(json.dumps({"domain": "synthetic-town-realistic", "generator_version": GENERATOR_VERSION,
                                        **made}))
        with pytest.raises(PcfbenchError, match=rf"{MANIFEST}: synthetic-town-realistic made by generator version "
                                                rf"{made.get('generator_version', GENERATOR_VERSION)}, world physics "
                                                rf"{made.get('physics', 1)}; this pcfbench makes version "
                                                rf"{GENERATOR_VERSION}, physics {physics}"):
            A.SyntheticTownRealistic(tmp_path)
    manifest.write_text(json.dumps({"domain": "synthetic-town-realistic", "generator_version": GENERATOR_VERSION,
                                    "physics": physics}))
    assert A.SyntheticTownRealistic(tmp_path).splits() == ("train", "val", "test")
    manifest.write_text(json.dumps({"domain": "synthetic-town", "generator_version": GENERATOR_VERSION}))
    A.SyntheticTown(tmp_path)  # physics 1 manifests name no physics
    manifest.write_text(json.dumps({"domain": "synthetic-town", "generator_version": GENERATOR_VERSION, "physics": 9}))
    with pytest.raises(PcfbenchError, match="world physics 9; this pcfbench makes version .*, physics 1"):
        A.SyntheticTown(tmp_path)


def test_cache_generates_once_detects_interrupted_split_and_regenerates(tmp_path, capsys):
    dom = tiny(sweeps=3)
    root = tmp_path / "cache" / "town"
    out = ensure_domain(dom, splits=("test",), progress=False, root=root)
    assert out == root and split_complete(root, "test") and not split_complete(root, "train")
    before = tree_digest(root)
    ensure_domain(dom, splits=("test",), progress=False, root=root)  # reused: nothing rewritten
    assert tree_digest(root) == before
    # An interrupted generation: marker missing, a sweep truncated.
    (root / f"{COMPLETE}-test").unlink()
    sweep = root / "sequences" / "05" / "velodyne" / "000001.bin"
    sweep.write_bytes(sweep.read_bytes()[:100])
    ensure_domain(dom, splits=("test",), progress=False, root=root)
    assert "incomplete" in capsys.readouterr().err
    assert tree_digest(root) == before
    ensure_domain(dom, splits=("train",), progress=False, root=root)
    assert split_complete(root, "train") and (root / "sequences" / "00" / "velodyne" / "000003.bin").is_file()


def test_managed_cache_generates_a_split_when_the_adapter_asks(tmp_path, monkeypatch):
    import pcfbench.datasets.synthetic.adapter as adapter_mod

    dom = tiny(sweeps=3)
    monkeypatch.setattr(adapter_mod, "get_domain", lambda name: dom)
    import pcfbench.datasets.synthetic.generate as gen

    monkeypatch.setattr(gen, "get_domain", lambda name: dom)
    root = ensure_domain(dom, splits=("test",), progress=False, root=tmp_path / "c")
    adapter = adapter_mod.SyntheticTown(root)
    assert not split_complete(root, "train")
    assert adapter.sequence_names("train") == ["00"]
    assert split_complete(root, "train")


def test_unwritable_cache_and_foreign_folder_are_clear_errors(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("PCFBENCH_CACHE", str(blocker))
    with pytest.raises(PcfbenchError, match="cannot write the synthetic data cache .*PCFBENCH_CACHE"):
        ensure_domain(tiny(), splits=("test",), progress=False)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "mine.txt").write_text("x")
    with pytest.raises(PcfbenchError, match="not a pcfbench synthetic cache"):
        ensure_domain(tiny(), splits=("test",), progress=False, root=foreign)
    assert (foreign / "mine.txt").read_text() == "x"


def test_unknown_names_are_clear_errors():
    with pytest.raises(UnknownNameError, match="did you mean 'synthetic-town'"):
        get_domain("synthetic-twn")
    with pytest.raises(UnknownNameError, match="unknown layout 'kity'"):
        get_writer("kity")
    with pytest.raises(UnknownNameError, match="no split"):
        ensure_domain(tiny(), splits=("dev",), progress=False)


def test_generate_command_and_plugin_registration(tmp_path):
    from pcfbench.cli import build_cli
    from pcfbench.plugins import get_plugins

    plugins = get_plugins()
    town = plugins.datasets.get("synthetic-town")
    suburb = plugins.datasets.get("synthetic-suburb")
    realistic = plugins.datasets.get("synthetic-town-realistic")
    # the default run's one dataset is the realistic town, scored on every third sample
    assert [n for n in plugins.datasets.names() if plugins.datasets.get(n).embedded] == ["synthetic-town-realistic"]
    assert not town.embedded and not suburb.embedded
    assert realistic.default_policy == "every-third" and town.default_policy == "full-context"
    assert town.default_settings == ("kitti-1s", "kitti-3s") and suburb.default_settings == ("nuscenes-1s", "nuscenes-3s")
    cli = build_cli()
    res = CliRunner().invoke(cli, ["generate", "synthetic-nowhere", "--out", str(tmp_path / "x"), "-q"])
    assert res.exit_code == 2 and "unknown synthetic domain" in res.output
    res = CliRunner().invoke(cli, ["generate", "synthetic-town", "--layout", "bogus", "--out", str(tmp_path / "x"), "-q"])
    assert res.exit_code == 2 and "unknown layout" in res.output


def test_moving_agents_move_between_sweeps():
    dom = tiny(sweeps=6, azimuths=360)
    seq = simulate_sequence(dom, "05")
    moving = [((lab & 0xFFFF) >= 5) & ((lab & 0xFFFF) <= 7) for lab in seq.labels]
    assert sum(m.sum() for m in moving) > 0, "no agent was seen"
    assert seq.stats["agents"] > 5


@pytest.mark.slow
def test_copy_last_error_is_larger_on_moving_agents(tmp_path):
    """Moving agents make copy-last's error larger than on static points (robust statistics)
    and larger than on parked vehicles of the same shapes."""
    from pcfbench.datasets.synthetic.adapter import SyntheticTown
    from pcfbench.datasets.synthetic.analysis import copy_last_error_by_class

    dom = tiny(sweeps=26, azimuths=512)
    generate_domain(dom, tmp_path, progress=False, splits=("test",))
    res = copy_last_error_by_class(SyntheticTown(tmp_path), "kitti-1s")
    assert res["samples"] == 8 and res["moving_points"] > 500
    assert res["moving_robust"]["median_m"] > 1.5 * res["static_robust"]["median_m"]
    assert res["moving_robust"]["frac_over_0.5m"] > res["static_robust"]["frac_over_0.5m"]
    assert res["vehicle_vs_parked_ratio"] > 1.5


@pytest.mark.slow
def test_pcfbench_run_without_arguments_generates_the_default_domain_once(tmp_path, monkeypatch):
    import pcfbench.datasets.synthetic.adapter as adapter_mod
    import pcfbench.datasets.synthetic.generate as gen
    from pcfbench.cli import build_cli
    from pcfbench.plugins import get_plugins
    from pcfbench.running.runner import default_metrics

    dom = tiny("synthetic-town-realistic", sweeps=56, azimuths=240)
    monkeypatch.setattr(adapter_mod, "get_domain", lambda name: dom)
    monkeypatch.setattr(gen, "get_domain", lambda name: dom)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    from pcfbench.running.warmup import KernelWarmup

    warmups = []  # the run's kernel warm-up starts with the generation, once (tests/running/test_warmup.py runs it)
    monkeypatch.setattr(KernelWarmup, "start", lambda self: warmups.append((self.methods, self.metrics)))
    cli = build_cli()
    args = ["run", "--method", "copy-last", "--limit", "2", "--reports", str(tmp_path / "reports"), "-q"]
    first = CliRunner().invoke(cli, args)
    assert first.exit_code == 0, first.output
    assert warmups and set(warmups) == {(("copy-last",), tuple(default_metrics(get_plugins())))}
    assert "generating synthetic-town-realistic" in first.output
    # its default policy: every third of the 38 kitti-1s anchors (13), of the 2 kitti-3s ones the first
    assert "synthetic-town-realistic:test | kitti-1s (every-third) limit=2: 2 samples (2 now, 0 failed)" in first.output
    assert "synthetic-town-realistic:test | kitti-3s (every-third) limit=2: 1 samples (1 now, 0 failed)" in first.output
    root = tmp_path / "cache" / "synthetic" / f"synthetic-town-realistic-v{GENERATOR_VERSION}-physics{dom.physics}"
    assert split_complete(root, "test") and not split_complete(root, "train")
    warmups.clear()
    second = CliRunner().invoke(cli, args)
    assert second.exit_code == 0 and "generating" not in second.output and "nothing to do" in second.output
    assert warmups == []  # nothing generated: no warm-up


@pytest.mark.parametrize("layout,domain,adapter_name", [
    ("nuscenes", "synthetic-suburb", "nuscenes"), ("av2", "synthetic-town", "av2"),
    ("mcap", "synthetic-town", "mcap"), ("mcap-foxglove", "synthetic-town", "mcap"),
])
def test_generate_other_layouts_read_back_by_their_adapters(tmp_path, layout, domain, adapter_name):
    """Every layout writer gets the same world: the matching adapter reads back the same
    world-frame points (whatever frame and axes the layout stores them in)."""
    from scipy.spatial import cKDTree

    from pcfbench.geometry import transform_points
    from pcfbench.plugins import get_plugins

    dom = tiny(domain, sweeps=3, azimuths=120)
    dom = dataclasses.replace(dom, splits={"test": dom.splits["test"]})
    generate_domain(dom, tmp_path / "kitti", progress=False)
    manifest = generate_domain(dom, tmp_path / layout, layout, progress=False)
    written = manifest["written_as"]["05"]
    adapter = get_plugins().datasets.get(adapter_name)(str(tmp_path / layout))
    names = [n for split in adapter.splits() for n in adapter.sequence_names(split)]
    match = [n for n in names if n == written or n.endswith("/" + written)]
    assert len(match) == 1, (names, written)
    seq = adapter.sequence(match[0])
    # the domain's own KITTI-layout adapter: plain KittiOdometry refuses a 2 Hz times.txt
    kitti = get_plugins().datasets.get(domain)(tmp_path / "kitti").sequence("05")
    assert len(seq) == len(kitti) == 3
    assert np.allclose(np.diff(seq.timestamps_ns), np.diff(kitti.timestamps_ns))
    for i in range(3):
        a = transform_points(seq.T_world_sensor[i], seq.load_points(i))
        b = transform_points(kitti.T_world_sensor[i], kitti.load_points(i))
        assert len(a) == len(b) > 1000
        d, _ = cKDTree(b).query(a)
        # AV2 stores float16 coordinates (half a millimetre per metre of range); others float32
        tol = 0.04 if layout == "av2" else 1e-3
        assert d.max() < tol and np.median(d) < tol / 4


def test_domains_differ_like_real_datasets():
    """Town vs suburb: sensor, rate, building heights and set-backs, traffic density."""
    from pcfbench.datasets.synthetic.world import (
        STRUCTURE, SUBURB, TOWN, Ground, build_static, make_agents, make_road_graph,
    )

    town, suburb = get_domain("synthetic-town"), get_domain("synthetic-suburb")
    assert (town.sensor.beams, suburb.sensor.beams) == (64, 32)
    assert town.sensor.mount_height_m < suburb.sensor.mount_height_m
    assert (town.rate_hz, suburb.rate_hz) == (10.0, 2.0)
    stats = {}
    for style in (TOWN, SUBURB):
        rng = np.random.default_rng(5)
        graph = make_road_graph(style, rng)
        ground = Ground(style, graph, rng)
        lo, hi = np.array([-80.0, -80.0]), np.array([80.0, 80.0])
        soup = build_static(style, graph, ground, rng, lo, hi)
        V, T = soup.merged(STRUCTURE)
        tops = V.reshape(-1, 8, 3)[:, :, 2].max(1) - V.reshape(-1, 8, 3)[:, :, 2].min(1)  # boxes: 8 vertices
        agents = make_agents(style, graph, rng, lo, hi, 10.0)
        stats[style.name] = (np.percentile(tops, 90), len(agents))
    assert stats["town"][0] > 2 * stats["suburb"][0]  # tall town blocks vs low houses
    assert stats["town"][1] > 2 * stats["suburb"][1]  # busier traffic


def test_reading_generated_data_does_not_import_open3d():
    """Every worker of a run imports the synthetic adapter to read its data: open3d (seconds
    to import, it brings scikit-learn) is only for casting rays, so it is imported then."""
    import subprocess
    import sys

    code = ("import sys, pcfbench.datasets.synthetic.adapter, pcfbench.datasets.synthetic.generate, pcfbench.running.runner; "
            "print(sorted(m for m in ('open3d', 'sklearn') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    from pcfbench.datasets.synthetic.lidar import open3d

    assert open3d().t.geometry.RaycastingScene is not None
