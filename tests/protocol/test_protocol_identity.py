"""A cell's identity notices what changed: the dataset's files, its root options, the setting."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import pytest

from pcfbench.data import Forecast
from pcfbench.datasets.kitti import KittiOdometry, read_bin
from pcfbench.dataset import DatasetAdapter, fingerprint_files, options_identity
from pcfbench.errors import PcfbenchError
from pcfbench.hookspecs import hookimpl
from pcfbench.method import Method, options_hash
from pcfbench.options import option
from pcfbench.plugins import load_plugins
from pcfbench.protocol import Setting
from pcfbench.reporting.report import collect
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import PROTOCOL_IDENTITY, Cell, CellSpec
from tests_helpers import write_kitti_tree

METRICS = ("chamfer", "chamfer_nf")


def _spec(root, dataset="kitti", setting="kitti-1s", policy="full-context", limit=None):
    return CellSpec("copy-last", {}, options_hash(None), dataset, str(root), "test", setting, policy, limit, METRICS)


def _meta(store, spec) -> dict:
    return json.loads((Cell(store, spec).dir / "cell.json").read_text())


# -- the fingerprint ------------------------------------------------------------------------------

def test_fingerprint_against_a_hand_built_hash(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.bin").write_bytes(b"12345")
    (tmp_path / "b.txt").write_bytes(b"xy")
    os.utime(tmp_path / "a" / "x.bin", ns=(1, 1_000_000_007))
    os.utime(tmp_path / "b.txt", ns=(1, 2_000_000_009))
    fp = fingerprint_files(tmp_path, [tmp_path / "b.txt", tmp_path / "a" / "x.bin"])
    sha_x, sha_b = hashlib.sha256(b"12345").hexdigest(), hashlib.sha256(b"xy").hexdigest()
    assert fp.files == (("a/x.bin", 5, 1_000_000_007, sha_x), ("b.txt", 2, 2_000_000_009, sha_b))
    # path, size and content; the modification time only says what changed
    expected = hashlib.sha256(f"a/x.bin\x005\x00{sha_x}\nb.txt\x002\x00{sha_b}\n".encode()).hexdigest()[:16]
    assert fp.digest == expected
    summary = fp.summary()
    assert summary["files"] == 2 and summary["bytes"] == 7 and set(summary["groups"]) == {".", "a"}
    assert summary["groups"]["a"] == {"files": 1, "bytes": 5, "mtime_ns_max": 1_000_000_007,
                                      "digest": hashlib.sha256(f"a/x.bin\x005\x00{sha_x}\n".encode()).hexdigest()[:16]}


def test_fingerprint_says_which_files_changed(tmp_path):
    for i in range(3):
        (tmp_path / f"{i}.bin").write_bytes(b"0" * 8)
        os.utime(tmp_path / f"{i}.bin", ns=(1, 10**9))
    before = fingerprint_files(tmp_path, sorted(tmp_path.iterdir()))
    (tmp_path / "1.bin").write_bytes(b"1" * 8)  # rewritten later, same size
    os.utime(tmp_path / "1.bin", ns=(1, 2 * 10**9))
    after = fingerprint_files(tmp_path, sorted(tmp_path.iterdir()))
    assert after.digest != before.digest
    assert after.changes_since(before.summary()) == ".: modified since: 1.bin"
    (tmp_path / "3.bin").write_bytes(b"0" * 4)
    os.utime(tmp_path / "3.bin", ns=(1, 10**9))
    grown = fingerprint_files(tmp_path, sorted(tmp_path.iterdir()))
    assert grown.changes_since(after.summary()) == ".: 3 -> 4 files; 24 -> 28 bytes"
    assert fingerprint_files(tmp_path, sorted(tmp_path.iterdir())).digest == grown.digest  # stable


class Whole(DatasetAdapter):
    """The default data_files: every file under the root."""

    name = "whole"
    rate_hz = 10.0

    def splits(self):
        return ("test",)

    def sequence_names(self, split):
        return []

    def sequence(self, name):
        raise NotImplementedError


def test_default_data_files_cover_every_file_under_the_root(tmp_path):
    root = tmp_path / "root"
    (root / "x" / "y").mkdir(parents=True)
    (root / "x" / "y" / "deep.bin").write_bytes(b"1")
    (root / ".hidden").write_bytes(b"2")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "linked.bin").write_bytes(b"3")
    (root / "link").symlink_to(elsewhere)  # a folder linked into the root counts
    (root / "loop").symlink_to(root)  # and a cycle does not loop
    rels = sorted(f[0] for f in Whole(root).fingerprint("test").files)
    assert rels == [".hidden", "link/linked.bin", "x/y/deep.bin"]
    single = tmp_path / "rec.mcap"
    single.write_bytes(b"1234")
    assert Whole(single).fingerprint("test").files[0][:2] == ("rec.mcap", 4)
    with pytest.raises(PcfbenchError, match="root .*missing does not exist"):
        Whole(tmp_path / "missing").fingerprint("test")


def test_kitti_fingerprint_is_what_the_split_reads(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00", "08"), num_sweeps=20)
    ds = KittiOdometry(root)
    rels = [f[0] for f in ds.fingerprint("test").files]
    assert rels == ["poses/08.txt", "sequences/08/calib.txt", "sequences/08/times.txt"] + [
        f"sequences/08/velodyne/{i:06d}.bin" for i in range(20)
    ]
    before = ds.fingerprint("test").digest
    (root / "sequences" / "08" / "labels").mkdir()  # SemanticKITTI labels: not read by the split
    (root / "sequences" / "08" / "labels" / "000000.label").write_bytes(b"\0" * 8)
    (root / "sequences" / "00" / "velodyne" / "000003.bin").write_bytes(b"\0" * 16)  # the train split
    assert ds.fingerprint("test").digest == before


# -- reruns -----------------------------------------------------------------------------------------

def test_cell_json_records_the_protocol_identity(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    run_cell(spec, store, RunOptions(progress=False))
    meta = _meta(store, spec)
    assert meta["protocol_version"] == "1"
    assert meta["roi"] == {"lo": [-70.0, -70.0, -4.5], "hi": [70.0, 70.0, 4.5]} and meta["min_range_m"] == 0.01
    assert meta["setting_params"] == {"rate_hz": 10.0, "past": 5, "future": 5, "stride": 2}
    assert meta["sample_policy"] == {"name": "full-context", "kind": "full-context"}
    assert meta["ego_box"] == {"x_min": -2.0, "x_max": 3.5, "y_min": -1.55, "y_max": 1.55}
    assert meta["dataset_options"] == {}
    assert meta["data_fingerprint"] == KittiOdometry(tiny_kitti).fingerprint("test").digest
    assert meta["data_files"]["files"] == 24 + 3
    assert set(meta["data_files"]["groups"]) == {"poses", "sequences/08", "sequences/08/velodyne"}
    assert set(PROTOCOL_IDENTITY) <= set(meta)
    # the store path is what it was before the identity grew
    assert Cell(store, spec).dir == store / "kitti" / "kitti-1s" / "test" / f"copy-last.{options_hash(None)}"
    again = run_cell(spec, store, RunOptions(progress=False))
    assert again.processed == 0 and again.done_before == 6


def _shift_sweep(path: Path, dx: float) -> None:
    pts = read_bin(path)
    pts[:, 0] += dx
    pts.tofile(path)


def test_editing_one_sweep_is_never_reused_silently(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    run_cell(spec, store, RunOptions(progress=False))
    old = Cell(store, spec).read_rows().set_index(["sample_id", "step"]).chamfer
    sweep = tiny_kitti / "sequences" / "08" / "velodyne" / "000012.bin"
    stat = sweep.stat()
    _shift_sweep(sweep, 0.5)  # same size: only its modification time tells
    os.utime(sweep, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # written later (whatever the clock's grain)
    with pytest.raises(PcfbenchError, match=r"(?s)different data_fingerprint \(dataset files changed: "
                                            r"sequences/08/velodyne: modified since: sequences/08/velodyne/000012.bin\).*--force"):
        run_cell(spec, store, RunOptions(progress=False))
    assert Cell(store, spec).read_rows().set_index(["sample_id", "step"]).chamfer.equals(old)  # untouched
    redone = run_cell(spec, store, RunOptions(progress=False, force=True))
    assert redone.processed == 6
    new = Cell(store, spec).read_rows().set_index(["sample_id", "step"]).chamfer
    assert len(new) == len(old) == 30
    # stride 2: sweep 12 is a future sweep (ground truth) of anchors 8 and 10 and the last past
    # sweep (what copy-last repeats) of anchor 12; no other sample of 8 .. 13 reads it
    moved = sorted({sid for (sid, _), a, b in zip(new.index, old, new) if a != b})
    assert moved == ["08/000008", "08/000010", "08/000012"]
    assert _meta(store, spec)["data_fingerprint"] == KittiOdometry(tiny_kitti).fingerprint("test").digest


def test_a_sweep_that_changes_size_or_disappears_is_noticed(tmp_path):
    root = write_kitti_tree(tmp_path / "k", num_sweeps=24)
    spec = _spec(root)
    run_cell(spec, tmp_path / "s", RunOptions(progress=False))
    sweep = root / "sequences" / "08" / "velodyne" / "000005.bin"
    sweep.write_bytes(read_bin(sweep)[:-10].tobytes())
    with pytest.raises(PcfbenchError, match=r"data_fingerprint.*sequences/08/velodyne: .*bytes.*--force"):
        run_cell(spec, tmp_path / "s", RunOptions(progress=False))


@dataclasses.dataclass(frozen=True)
class FlavourOptions:
    flavour: str = option("plain", help="a root option that a test changes")


class KittiWithOption(KittiOdometry):
    name = "kitti-opt"
    Options = FlavourOptions


class KittiKeywords(KittiOdometry):
    """An adapter that reads a keyword itself instead of declaring Options."""

    name = "kitti-kw"

    def __init__(self, root, flavour: str = "plain"):
        super().__init__(root)
        self.flavour = flavour


def test_a_changed_root_option_is_noticed(tiny_kitti, store):
    plugins = load_plugins()
    plugins.datasets.add("kitti-opt", KittiWithOption, "test")
    spec = _spec(f"{tiny_kitti}?flavour=plain", dataset="kitti-opt")
    run_cell(spec, store, RunOptions(progress=False), plugins=plugins)
    assert _meta(store, spec)["dataset_options"] == {"flavour": "plain"}
    # the typed value is the identity: the default spelled out or left out is the same cell
    assert run_cell(_spec(tiny_kitti, dataset="kitti-opt"), store, RunOptions(progress=False), plugins=plugins).processed == 0
    other = _spec(f"{tiny_kitti}?flavour=salted", dataset="kitti-opt")
    assert Cell(store, other).dir == Cell(store, spec).dir  # the same cell folder ...
    with pytest.raises(PcfbenchError, match=r"different dataset_options \(dataset_options: flavour 'plain' -> 'salted'\).*--force"):
        run_cell(other, store, RunOptions(progress=False), plugins=plugins)  # ... so it must not be reused


def test_a_changed_keyword_of_an_adapter_without_options_is_noticed(tiny_kitti, store):
    plugins = load_plugins()
    plugins.datasets.add("kitti-kw", KittiKeywords, "test")
    spec = _spec(f"{tiny_kitti}?flavour=plain", dataset="kitti-kw")
    run_cell(spec, store, RunOptions(progress=False), plugins=plugins)
    assert _meta(store, spec)["dataset_options"] == {"flavour": "plain"}
    with pytest.raises(PcfbenchError, match=r"dataset_options: flavour 'plain' -> 'salted'"):
        run_cell(_spec(f"{tiny_kitti}?flavour=salted", dataset="kitti-kw"), store, RunOptions(progress=False), plugins=plugins)


@dataclasses.dataclass(frozen=True)
class BoxOptions:
    box: tuple[float, ...] | None = option(None, help="a tuple option")
    where: Path = option(Path("/data"), help="a path option")


def test_options_identity_is_plain_json():
    class Adapter:
        options = BoxOptions(box=(-1.0, 1.0))

    # typed values as cell.json reads them back; a raw keyword that is no field is kept as given
    assert options_identity(Adapter(), {"box": "-1,1", "extra": "x"}) == {"box": [-1.0, 1.0], "extra": "x", "where": "/data"}
    assert options_identity(object(), {"b": "2", "a": "1"}) == {"a": "1", "b": "2"}


def _setting_plugin(setting: Setting):
    class Plugin:
        @hookimpl
        def register_settings(register):
            register(setting)

    plugins = load_plugins()
    plugins.add_plugin(Plugin, "tiny-settings")
    assert plugins.info["tiny-settings"].error is None
    return plugins


def test_a_plugin_setting_runs_and_a_changed_parameter_is_noticed(tiny_kitti, store):
    # every-frame: the sample ids do not depend on the setting, so only its parameters differ
    spec = _spec(tiny_kitti, setting="tiny-2s", policy="every-frame", limit=3)
    first = _setting_plugin(Setting("tiny-2s", 10.0, 3, 2, 2, "a dataset plugin's setting"))
    result = run_cell(spec, store, RunOptions(progress=False), plugins=first)
    assert result.samples == 3 and _meta(store, spec)["setting_params"]["stride"] == 2
    changed = _setting_plugin(Setting("tiny-2s", 10.0, 3, 2, 3, "the same name, another stride"))
    with pytest.raises(PcfbenchError, match=r"different setting_params \(setting_params: stride 2 -> 3\).*--force"):
        run_cell(spec, store, RunOptions(progress=False), plugins=changed)
    assert run_cell(spec, store, RunOptions(progress=False), plugins=first).processed == 0  # the original still reuses


def test_subsample_policy_cell(tiny_kitti, store):
    spec = _spec(tiny_kitti, policy="subsample-4000")
    result = run_cell(spec, store, RunOptions(progress=False))
    assert result.samples == 6  # fewer candidates than 4,000: every one
    assert Cell(store, spec).dir.relative_to(store).as_posix() == f"kitti/kitti-1s.subsample-4000/test/copy-last.{options_hash(None)}"
    assert _meta(store, spec)["sample_policy"] == {"name": "subsample-4000", "kind": "subsample", "n": 4000, "of": "full-context"}
    table = collect(store).table
    assert table.policy.tolist() == ["subsample-4000"] and table.samples.tolist() == [6]


def test_cells_from_before_the_protocol_identity(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    run_cell(spec, store, RunOptions(progress=False))
    path = Cell(store, spec).dir / "cell.json"
    legacy = {k: v for k, v in json.loads(path.read_text()).items() if k not in PROTOCOL_IDENTITY and k != "data_files"}
    path.write_text(json.dumps(legacy))
    # complete: reused as before (no rows are added, so none can mix), and left as it was
    assert run_cell(spec, store, RunOptions(progress=False)).processed == 0
    assert json.loads(path.read_text()) == legacy
    assert len(collect(store).table) == 1
    # incomplete: nothing tells whether new rows would match the old ones
    path.write_text(json.dumps({**legacy, "status": "running"}))
    with pytest.raises(PcfbenchError, match=r"incomplete and its cell.json predates the protocol identity.*--force"):
        run_cell(spec, store, RunOptions(progress=False))
    # a legacy field that differs is still named
    path.write_text(json.dumps({**legacy, "dataset_version": "0"}))
    with pytest.raises(PcfbenchError, match=r"different dataset_version \(dataset_version: '0' -> '1'\)"):
        run_cell(spec, store, RunOptions(progress=False))


class TouchesASweep(Method):
    """Copies the last sweep, and on one sample rewrites a sweep file of the dataset (a file
    edited by someone else while the cell runs)."""

    name = "touches-a-sweep"
    sweep: Path | None = None

    def forecast(self, sample):
        if sample.ref_index == 10 and self.sweep is not None:
            st = self.sweep.stat()
            _shift_sweep(self.sweep, 0.25)
            os.utime(self.sweep, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        return Forecast(points_ref=tuple(sample.past_points_ref[-1] for _ in range(sample.num_future)))


def test_data_changed_during_the_run_leaves_the_cell_incomplete(tiny_kitti, store):
    TouchesASweep.sweep = tiny_kitti / "sequences" / "08" / "velodyne" / "000020.bin"
    plugins = load_plugins()
    plugins.methods.add("touches-a-sweep", TouchesASweep, "test")
    spec = CellSpec("touches-a-sweep", {}, options_hash(None), "kitti", str(tiny_kitti), "test", "kitti-1s",
                    "full-context", None, METRICS)
    with pytest.raises(PcfbenchError, match=r"files of kitti:test changed while cell .* was computed "
                                            r"\(sequences/08/velodyne: modified since: sequences/08/velodyne/000020.bin\).*--force"):
        run_cell(spec, store, RunOptions(progress=False), plugins=plugins)
    assert _meta(store, spec)["status"] == "running"  # never complete ...
    assert len(collect(store).table) == 0  # ... so no leaderboard reads its mixed rows
    TouchesASweep.sweep = None
    with pytest.raises(PcfbenchError, match="different data_fingerprint"):  # and a plain rerun does not resume it
        run_cell(spec, store, RunOptions(progress=False), plugins=plugins)
    assert run_cell(spec, store, RunOptions(progress=False, force=True), plugins=plugins).processed == 6
