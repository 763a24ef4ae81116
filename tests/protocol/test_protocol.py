"""The protocol as data: the shipped file, its views, bad files, sample policies, plugin settings."""

from __future__ import annotations

import dataclasses
import re
import tomllib
from fractions import Fraction
from importlib import resources

import numpy as np
import pytest
from click.testing import CliRunner

import pcfbench
from pcfbench import protocol
from pcfbench import boxes
from pcfbench.dataset import DatasetAdapter, Sequence
from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.hookspecs import hookimpl
from pcfbench.plugins import all_settings, get_setting, load_plugins
from pcfbench.protocol import (
    SETTINGS, SampleBuilder, SamplePolicy, Setting, active_protocol, anchors, evenly_spaced,
    load_protocol,
)
from pcfbench.boxes import EgoBox

#: The values the settings had as Python literals before the protocol became a file.
LEGACY_SETTINGS = [
    ("kitti-1s", 10.0, 5, 5, 2, "KITTI 10 Hz: 5 past (-0.8..0 s), 5 future (+0.2..+1.0 s)"),
    ("kitti-3s", 10.0, 5, 5, 6, "KITTI 10 Hz: 5 past (-2.4..0 s), 5 future (+0.6..+3.0 s)"),
    ("nuscenes-1s", 2.0, 2, 2, 1, "nuScenes 2 Hz keyframes: 2 past, 2 future (+0.5, +1.0 s)"),
    ("nuscenes-3s", 2.0, 6, 6, 1, "nuScenes 2 Hz keyframes: 6 past, 6 future (+0.5..+3.0 s)"),
    ("av2-1s", 10.0, 5, 5, 2, "Argoverse 2 10 Hz: as kitti-1s"),
    ("av2-3s", 10.0, 5, 5, 6, "Argoverse 2 10 Hz: as kitti-3s"),
]


# -- the shipped file ---------------------------------------------------------------------------

def test_shipped_protocol_has_the_legacy_values_exactly():
    p = active_protocol()
    assert p.version == "1"
    assert [dataclasses.astuple(s) for s in p.settings.values()] == LEGACY_SETTINGS  # order kept too
    assert p.roi.lo == (-70.0, -70.0, -4.5) and p.roi.hi == (70.0, 70.0, 4.5)
    assert p.min_range_m == 0.01 and protocol.MIN_RANGE_M == 0.01
    assert tuple(p.policies) == ("full-context", "every-frame", "subsample-4000", "subsample-500", "every-third") == protocol.SAMPLE_POLICIES
    assert p.default_policy == "full-context"


def test_module_names_are_views_of_the_active_protocol():
    p = active_protocol()
    assert protocol.SETTINGS is p.settings and protocol.ROI is p.roi and not hasattr(boxes, "ROI")
    assert get_setting("kitti-3s") is p.settings["kitti-3s"]
    with pytest.raises(TypeError):
        SETTINGS["mine"] = SETTINGS["kitti-1s"]  # read-only
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.version = "2"
    # the public API hands out the same objects
    assert pcfbench.active_protocol() is p and pcfbench.Protocol is protocol.Protocol


def test_the_box_functions_take_the_protocol_roi_from_the_caller():
    o = np.zeros(3)
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t0, t1 = boxes.ray_box_interval(o, d, protocol.ROI)
    assert t0.tolist() == [0.0, 0.0] and t1.tolist() == [70.0, 4.5]
    _, end, kept = boxes.clamp_ranges_to_box(o, d, np.array([100.0, 2.0]), protocol.ROI)
    assert end.tolist() == [70.0, 2.0] and kept.all()
    with pytest.raises(TypeError):  # no box of its own: the protocol is handed down
        boxes.ray_box_interval(o, d)


def test_the_file_is_package_data():
    resource = resources.files("pcfbench.protocol").joinpath(protocol.PROTOCOL_FILE)
    assert resource.is_file()
    assert load_protocol(str(resource)) == active_protocol()


# -- bad protocol files: one error naming the file and the key ---------------------------------

def _shipped() -> dict:
    return tomllib.loads(resources.files("pcfbench.protocol").joinpath(protocol.PROTOCOL_FILE).read_text())


def _write(tmp_path, data: dict) -> str:
    lines = []

    def emit(prefix, table):
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        if prefix:
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml(v)}")
        for k, v in table.items():
            if isinstance(v, dict):
                emit(f"{prefix}.{k}" if prefix else k, v)

    emit("", data)
    path = tmp_path / "protocol.toml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(v)


def test_round_trip_of_the_test_writer(tmp_path):
    assert load_protocol(_write(tmp_path, _shipped())) == active_protocol()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.pop("version"), r"is missing 'version'"),
        (lambda d: d.update(version=2), r"version must be a non-empty string, got 2"),
        (lambda d: d.update(min_range_m=-1.0), r"min_range_m must be a number of metres >= 0"),
        (lambda d: d.update(extra=1), r"unknown key\(s\) extra"),
        (lambda d: d["roi"].update(lo=[-70.0, -70.0]), r"roi.lo must be 3 finite numbers"),
        (lambda d: d["roi"].update(lo=[70.0, -70.0, -4.5]), r"roi.lo .* must be below roi.hi"),
        (lambda d: d["settings"]["kitti-1s"].update(past=0), r"\[settings.kitti-1s\].*past must be an integer >= 1, got 0"),
        (lambda d: d["settings"]["kitti-1s"].update(stride=2.0), r"\[settings.kitti-1s\].*stride must be an integer"),
        (lambda d: d["settings"]["kitti-1s"].update(rate_hz=0.0), r"\[settings.kitti-1s\].*rate_hz must be a positive"),
        (lambda d: d["settings"]["kitti-1s"].pop("future"), r"\[settings.kitti-1s\] is missing 'future'"),
        (lambda d: d["settings"]["kitti-1s"].update(horizon=1), r"\[settings.kitti-1s\] has unknown key\(s\) horizon"),
        (lambda d: d["policies"]["subsample-4000"].pop("n"), r"\[policies.subsample-4000\]: a subsample policy needs one of n"),
        (lambda d: d["policies"]["subsample-4000"].update(n=0), r"n must be an integer >= 1, got 0"),
        (lambda d: d["policies"]["subsample-4000"].update(every=2), r"needs one of n .* got n=4000, every=2"),
        (lambda d: d["policies"]["every-third"].update(every=0), r"\[policies.every-third\]: .*every must be an integer >= 1, got 0"),
        (lambda d: d["policies"]["every-third"].update(every=1.5), r"every must be an integer >= 1, got 1.5"),
        (lambda d: d["policies"]["subsample-4000"].update(of="subsample-4000"), r"of must name a full-context or every-frame"),
        (lambda d: d["policies"]["every-frame"].update(kind="sometimes"), r"kind must be one of .*got 'sometimes'"),
        (lambda d: d["policies"]["every-frame"].update(n=3), r"only a subsample policy takes n, every and of"),
        (lambda d: d["policies"]["every-frame"].update(every=3), r"only a subsample policy takes n, every and of"),
        (lambda d: [d["policies"].pop(k) for k in ("full-context", "subsample-4000", "subsample-500", "every-third")], r"has no \[policies.full-context\]"),
    ],
)
def test_bad_protocol_file_is_one_clear_error(tmp_path, edit, message):
    data = _shipped()
    edit(data)
    path = _write(tmp_path, data)
    with pytest.raises(PcfbenchError, match=message) as info:
        load_protocol(path)
    assert path in str(info.value)


def test_unreadable_or_invalid_toml_names_the_file(tmp_path):
    with pytest.raises(PcfbenchError, match="cannot read protocol file .*nope.toml"):
        load_protocol(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("version = \n")
    with pytest.raises(PcfbenchError, match="bad.toml is not valid TOML"):
        load_protocol(bad)


def test_unknown_setting_and_policy_use_the_one_did_you_mean():
    with pytest.raises(UnknownNameError, match=r"unknown setting 'kitti-2s'; did you mean 'kitti-3s' or 'kitti-1s'\?"):
        get_setting("kitti-2s")
    with pytest.raises(UnknownNameError, match=r"unknown sample policy 'every_frame'; did you mean 'every-frame'"):
        active_protocol().policy("every_frame")


# -- evenly subsampled policies -----------------------------------------------------------------

def test_evenly_spaced_hand_computed():
    assert evenly_spaced(10, 4) == [0, 2, 5, 7]  # 0*10//4, 10//4, 20//4, 30//4
    assert evenly_spaced(12, 4) == [0, 3, 6, 9]
    assert evenly_spaced(3, 4) == [0, 1, 2]  # fewer candidates than n: every candidate once
    assert evenly_spaced(4, 4) == [0, 1, 2, 3]
    assert evenly_spaced(0, 4000) == []
    with pytest.raises(PcfbenchError):
        evenly_spaced(10, 0)


@pytest.mark.parametrize("count, n", [(4001, 4000), (23_500, 4000), (7, 3), (100, 1), (997, 13)])
def test_evenly_spaced_against_exact_fractions(count, n):
    got = evenly_spaced(count, n)
    assert got == [int(Fraction(i * count, n)) for i in range(n)]  # floor of the exact position
    assert len(set(got)) == n and got == sorted(got) and got[0] == 0 and got[-1] < count
    assert set(np.diff(got).tolist()) <= {count // n, count // n + 1}


class Lengths(DatasetAdapter):
    """Sequences of given lengths and no points: enough to list sample keys."""

    name = "lengths"
    rate_hz = 10.0
    ego_box = EgoBox(-1.0, 1.0, -1.0, 1.0)

    def __init__(self, lengths: dict[str, int]) -> None:
        super().__init__(None)
        self.lengths = lengths

    def splits(self):
        return ("test",)

    def sequence_names(self, split):
        return list(self.lengths)

    def sequence(self, name):
        n = self.lengths[name]
        return Sequence(name, np.tile(np.eye(4), (n, 1, 1)), np.arange(n, dtype=np.int64) * 100_000_000,
                        lambda s, i: np.zeros((0, 3), np.float32))


def test_subsample_spans_the_split_in_its_stable_order():
    kitti_1s = SETTINGS["kitti-1s"]  # full-context anchors: 8 .. n - 11
    adapter = Lengths({"08": 23, "09": 23})  # 5 anchors each: 10 candidates
    full = SampleBuilder(adapter, kitti_1s).sample_keys("test")
    assert full == [("08", i) for i in range(8, 13)] + [("09", i) for i in range(8, 13)]
    four = SamplePolicy("subsample-4", "subsample", n=4, of="full-context", rule="full-context")
    # candidates 0, 2, 5, 7 of the 10 (hand-computed above)
    assert SampleBuilder(adapter, kitti_1s, four).sample_keys("test") == [("08", 8), ("08", 10), ("09", 8), ("09", 10)]
    # the shipped 4,000-frame policy keeps every candidate of a split with fewer
    assert SampleBuilder(adapter, kitti_1s, "subsample-4000").sample_keys("test") == full
    assert anchors(23, kitti_1s, "subsample-4000") == anchors(23, kitti_1s, "full-context") == list(range(8, 13))


def test_every_third_keeps_every_third_anchor_of_the_split_from_the_first():
    kitti_1s = SETTINGS["kitti-1s"]
    adapter = Lengths({"08": 23, "09": 24})  # 5 + 6 anchors: candidates 0..10
    full = SampleBuilder(adapter, kitti_1s).sample_keys("test")
    assert len(full) == 11
    keys = SampleBuilder(adapter, kitti_1s, "every-third").sample_keys("test")
    # candidates 0, 3, 6, 9: 08/8, 08/11, then 09's anchors 8..13 are candidates 5..10
    assert keys == [("08", 8), ("08", 11), ("09", 9), ("09", 12)] == [full[i] for i in range(0, 11, 3)]
    # a split with fewer than three anchors keeps its first; an every-1 policy keeps all
    assert SampleBuilder(Lengths({"08": 20}), kitti_1s, "every-third").sample_keys("test") == [("08", 8)]
    one = SamplePolicy("every-1", "subsample", of="full-context", rule="full-context", every=1)
    assert SampleBuilder(adapter, kitti_1s, one).sample_keys("test") == full
    # the identity names every, not n; an n policy's identity is as it was
    assert active_protocol().policy("every-third").params() == {"name": "every-third", "kind": "subsample", "every": 3,
                                                                "of": "full-context"}
    assert active_protocol().policy("subsample-4000").params() == {"name": "subsample-4000", "kind": "subsample",
                                                                   "n": 4000, "of": "full-context"}


def test_subsample_4000_on_a_split_larger_than_4000():
    adapter = Lengths({f"{k:03d}": 168 for k in range(40)})  # 40 logs x 150 anchors (8 .. 157) = 6000
    keys = SampleBuilder(adapter, SETTINGS["av2-1s"], "subsample-4000").sample_keys("test")
    full = SampleBuilder(adapter, SETTINGS["av2-1s"]).sample_keys("test")
    assert len(full) == 6000 and len(keys) == 4000 and len(set(keys)) == 4000
    assert keys == [full[i * 6000 // 4000] for i in range(4000)]
    # candidates floor(1.5 i): 0, 1, 3, 4, 6 -> anchors 8, 9, 11, 12, 14; the last pick is 5998 (log 039, anchor 156)
    assert keys[:5] == [("000", 8), ("000", 9), ("000", 11), ("000", 12), ("000", 14)]
    assert keys[-1] == ("039", 156)


def test_subsample_500_spreads_a_whole_kitti_sequence():
    # KITTI sequence 08's 4071 sweeps: kitti-1s anchors 8 .. 4060 (4053); 500 of them, 8 or 9 apart
    keys = SampleBuilder(Lengths({"08": 4071}), SETTINGS["kitti-1s"], "subsample-500").sample_keys("test")
    assert len(keys) == 500 and keys[0] == ("08", 8)
    assert keys == [("08", 8 + i * 4053 // 500) for i in range(500)]
    assert {b[1] - a[1] for a, b in zip(keys, keys[1:])} == {8, 9}
    assert keys[-1] == ("08", 8 + 499 * 4053 // 500) == ("08", 4052)
    short = SampleBuilder(Lengths({"08": 60}), SETTINGS["kitti-1s"], "subsample-500").sample_keys("test")
    assert short == SampleBuilder(Lengths({"08": 60}), SETTINGS["kitti-1s"]).sample_keys("test")  # 42: all of them


def test_subsample_policy_is_offered_on_the_command_line():
    from pcfbench.cli import cli

    out = CliRunner().invoke(cli, ["run", "--help"]).output
    assert "subsample-4000" in out
    bad = CliRunner().invoke(cli, ["run", "--policy", "subsample-40", "--no-report"])
    assert bad.exit_code != 0 and "subsample-4000" in bad.output


# -- settings from plugins ------------------------------------------------------------------------

TINY = Setting("tiny-1s", 10.0, 3, 2, 1, "a plugin's setting")


class AddsTiny:
    @hookimpl
    def register_settings(register):
        register(TINY)


class AddsTinyToo:
    @hookimpl
    def register_settings(register):
        register(Setting("tiny-1s", 10.0, 4, 2, 1))


class ShadowsBuiltin:
    @hookimpl
    def register_settings(register):
        register(Setting("kitti-1s", 10.0, 5, 5, 1))


class RegistersJunk:
    @hookimpl
    def register_settings(register):
        register("tiny-2s")


def test_a_plugin_adds_a_setting():
    plugins = load_plugins()
    plugins.add_plugin(AddsTiny, "tiny-plugin")
    assert plugins.info["tiny-plugin"].error is None
    assert plugins.info["tiny-plugin"].registered == {"settings": ["tiny-1s"]}
    assert get_setting("tiny-1s", plugins) is TINY
    assert list(all_settings(plugins))[-1] == "tiny-1s"
    assert "tiny-1s" not in active_protocol().settings  # the protocol itself stays frozen
    with pytest.raises(UnknownNameError, match=r"unknown setting 'tiny-2s'; did you mean 'tiny-1s'"):
        get_setting("tiny-2s", plugins)


@pytest.mark.parametrize(
    "plugin, message",
    [
        (AddsTinyToo, r"setting 'tiny-1s' is registered twice: by plugin 'tiny-plugin' and by plugin 'other'"),
        (ShadowsBuiltin, r"plugin 'other': setting 'kitti-1s' is already a setting of the protocol file .*protocol.toml"),
        (RegistersJunk, r"plugin 'other': register_settings takes a pcfbench.Setting, got 'tiny-2s'"),
    ],
)
def test_setting_collisions_are_clear_plugin_errors(plugin, message):
    plugins = load_plugins()
    plugins.add_plugin(AddsTiny, "tiny-plugin")
    plugins.add_plugin(plugin, "other")
    assert plugins.info["other"].error is not None
    assert plugins.info["other"].error.startswith("register_settings: PluginError:")
    assert re.search(message, plugins.info["other"].error), plugins.info["other"].error
    assert get_setting("tiny-1s", plugins) is TINY and get_setting("kitti-1s", plugins) is SETTINGS["kitti-1s"]


def test_setting_validates_its_values():
    with pytest.raises(PcfbenchError, match=r"setting 'x': stride must be an integer >= 1, got 0"):
        Setting("x", 10.0, 5, 5, 0)
    with pytest.raises(PcfbenchError, match=r"setting 'x': rate_hz must be a positive number of Hz, got nan"):
        Setting("x", float("nan"), 5, 5, 1)
    with pytest.raises(PcfbenchError, match="without spaces"):
        Setting("a b", 10.0, 5, 5, 1)
