"""Typed options with help texts (methods and adapters), ``ls --options`` and the one
method-spec resolver."""

import dataclasses
import hashlib
import json
from typing import Literal

import pytest
from click.testing import CliRunner

import pcfbench
from pcfbench import config
from pcfbench.cli import cli
from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.method import MethodSpec, options_hash, parse_method_spec, resolve_method
from pcfbench.options import HELP, NoOptions, describe_options, option, options_dict, type_name
from pcfbench.plugins import load_plugins

#: options_hash of each built-in method's default options, computed from the code before the
#: options got help texts (commit 4ace452); a change here moves every stored cell.
GOLDEN_DEFAULT_HASHES = {
    "copy-last": "44136fa355b3",
    "raycast-4docc": "7fb25c0a5548",
    "raycast-zbuffer": "ec2657268669",
    "raycast-voxel": "763a55d0fdf6",
    "raycast-freespace": "151fcdf81cab",
    # new with the trained-method contract (issue 13); moved on purpose when the rendering
    # options noise and readout came in and the threshold default went 0.5 -> 0.02 (issue 14)
    "copilot4d-token-copy": "399b687887eb",
    # issue 42 added the options frame and top_k (a950d364665d), then made the shipped world models'
    # training the defaults (config tiny-window, anchor_every 1; `config=tiny,anchor_every=2` is a950d364665d)
    "copilot4d": "3f90563d887e",
    "copilot4d-maskgit": "3f90563d887e",
    # issue 47: forecasts read from a file; a cell's options always name the file and its sha256
    "submission": "230160ea66bc",
    # issue 43: OccWorld, its tokenizer and world model (no checkpoint ships); moved on purpose
    # when the option surface came in (the planes' offsets), readout went to surface and frame to t0
    "occworld-occ-copy": "8b6a8742f8ef",
    "occworld": "b8a054b791db",
    # issue 44: BEVWorld, its tokenizer and world model
    "bevworld-latent-copy": "d4668c0e6c5d",
    "bevworld": "b477dfee934d",  # the render stage's options (render_weight, render_steps) came in
}
#: and of a few non-default specs, from the same code
GOLDEN_SPEC_HASHES = {
    "raycast-voxel:voxel=0.1,constant_velocity=true": "b3812348bc21",
    "raycast-freespace:renderer=zbuffer,splat=0": "ef2379462a8a",
    "raycast-zbuffer:fill_ring=4": "def39d791caf",
    "copilot4d:config=tiny,anchor_every=2": "a950d364665d",  # copilot4d's defaults until issue 42 shipped it
}


@pytest.fixture(scope="module")
def plugins():
    return load_plugins()


def test_builtin_option_hashes_unchanged(plugins):
    assert set(GOLDEN_DEFAULT_HASHES) == set(plugins.methods.names())
    for name, expected in GOLDEN_DEFAULT_HASHES.items():
        assert options_hash(plugins.methods.get(name).Options()) == expected, name
        assert resolve_method(name, plugins).options_hash == expected, name
    for spec, expected in GOLDEN_SPEC_HASHES.items():
        assert resolve_method(spec, plugins).options_hash == expected, spec


def test_options_hash_is_the_hash_of_the_values_alone():
    @dataclasses.dataclass(frozen=True)
    class Opts:
        b: int = option(2, help="b's help")
        a: float = option(0.5, help="a's help")

    @dataclasses.dataclass(frozen=True)
    class Bare:
        b: int = 2
        a: float = 0.5

    # by hand: canonical JSON with sorted keys, sha256, 12 hex digits
    by_hand = hashlib.sha256(b'{"a": 0.5, "b": 2}').hexdigest()[:12]
    assert options_hash(Opts()) == options_hash(Bare()) == by_hand
    assert dataclasses.asdict(Opts()) == {"b": 2, "a": 0.5}
    assert [f.metadata[HELP] for f in dataclasses.fields(Opts)] == ["b's help", "a's help"]
    with pytest.raises(TypeError, match="help"):
        option(1, help="  ")


def test_an_option_added_with_a_quiet_default_keeps_the_hash_at_its_default():
    """An option added later (``quiet_default``) leaves the hash of the options as they were
    while it holds its default, and enters it like any other option once it does not."""
    @dataclasses.dataclass(frozen=True)
    class Before:
        a: float = option(0.5, help="a")

    @dataclasses.dataclass(frozen=True)
    class After:
        a: float = option(0.5, help="a")
        n: int = option(0, help="added later", quiet_default=True)
        t: tuple[int, ...] = option(default_factory=lambda: (1, 2), help="added later too", quiet_default=True)

    assert options_hash(After()) == options_hash(Before())
    assert options_dict(After()) == {"a": 0.5}
    assert options_dict(After(n=3)) == {"a": 0.5, "n": 3}
    assert options_dict(After(t=(2,))) == {"a": 0.5, "t": (2,)}
    by_hand = hashlib.sha256(b'{"a": 0.5, "n": 3}').hexdigest()[:12]
    assert options_hash(After(n=3)) == by_hand != options_hash(Before())


def test_every_builtin_option_has_type_default_and_help(plugins):
    for registry in (plugins.methods, plugins.datasets):
        for name in registry.names():
            cls = registry.get(name)
            assert dataclasses.is_dataclass(cls.Options) and cls.Options.__dataclass_params__.frozen, name
            for info in describe_options(cls.Options):
                assert info.help and info.type and info.default is not dataclasses.MISSING, (name, info)
    # adapters with root options declare them; the others take none
    assert [f.name for f in describe_options(plugins.datasets.get("mcap").Options)] == [
        "topic", "world_frame", "sensor_frame", "rate_hz", "ego_box", "tf_tolerance_ms"]
    assert [f.name for f in describe_options(plugins.datasets.get("nuscenes").Options)] == ["version", "channel"]
    assert plugins.datasets.get("kitti").Options is NoOptions


def test_type_names():
    assert type_name(float) == "float"
    assert type_name(int | None) == "int | None"
    assert type_name(Literal["plane", "mean"]) == "'plane' | 'mean'"
    assert type_name(tuple[float, ...] | None) == "tuple[float, ...] | None"


def test_ls_options_prints_name_type_default_help():
    runner = CliRunner()
    res = runner.invoke(cli, ["ls", "methods", "--options"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    voxel = next(i for i, line in enumerate(lines) if line.startswith("raycast-voxel "))
    row = lines[voxel + 1].split()
    assert row[:3] == ["voxel", "float", "0.2"] and "voxel edge of the occupancy grid, metres" in lines[voxel + 1]
    assert lines[lines.index(next(line for line in lines if line.startswith("copy-last "))) + 1].strip() == "(no options)"
    res = runner.invoke(cli, ["ls", "datasets", "--options", "--json"])
    assert res.exit_code == 0, res.output
    rows = {r["name"]: r for r in json.loads(res.output)}
    rate = next(o for o in rows["mcap"]["options"] if o["name"] == "rate_hz")
    assert rate["type"] == "float | None" and rate["default"] is None and "k-th sweep" in rate["help"]
    assert rows["kitti"]["options"] == [] and rows["kitti"]["error"] is None
    res = runner.invoke(cli, ["ls", "metrics", "--options"])
    assert res.exit_code == 2 and "--options lists the options of methods and datasets" in res.output


def test_ls_options_names_a_method_that_fails_to_load(plugins, monkeypatch):
    plugins.methods.add("broken-method", "pcfbench.no_such_module:Broken", "tests")
    monkeypatch.setattr("pcfbench.cli.get_plugins", lambda: plugins)
    res = CliRunner().invoke(cli, ["ls", "methods", "--options"])
    assert res.exit_code == 0 and "(options unavailable: method 'broken-method'" in res.output
    del plugins.methods.entries["broken-method"]


def test_resolve_method_text_and_stored_form_agree(plugins):
    m = resolve_method("raycast-voxel:voxel=0.1,surface=mean", plugins)
    assert isinstance(m, MethodSpec) and m.name == "raycast-voxel" and m.raw == {"voxel": "0.1", "surface": "mean"}
    assert m.options.voxel == 0.1 and m.options.surface == "mean" and m.options.max_level == 3
    assert m.options_hash == options_hash(m.options)
    stored = resolve_method(("raycast-voxel", {"voxel": "0.1", "surface": "mean"}), plugins)
    assert stored.options == m.options and stored.options_hash == m.options_hash and stored.cls is m.cls
    method = m.create()
    assert isinstance(method, pcfbench.Method) and method.options is m.options
    assert resolve_method("copy-last", plugins).options == NoOptions()


def test_resolve_method_errors_name_the_method_and_option(plugins):
    with pytest.raises(UnknownNameError, match=r"unknown method 'raycast-voxl'; did you mean 'raycast-voxel'"):
        resolve_method("raycast-voxl", plugins)
    with pytest.raises(UnknownNameError, match=r"unknown method raycast-voxel option 'voxle'; did you mean 'voxel'\?"):
        resolve_method("raycast-voxel:voxle=0.1", plugins)
    with pytest.raises(PcfbenchError, match=r"method raycast-voxel option max_level: cannot read '2.5' as int"):
        resolve_method("raycast-voxel:max_level=2.5", plugins)
    with pytest.raises(PcfbenchError, match=r"method raycast-voxel option surface: 'flat' is not one of plane, mean"):
        resolve_method("raycast-voxel:surface=flat", plugins)
    assert parse_method_spec("raycast-voxel: voxel = 0.1 ,") == ("raycast-voxel", {"voxel": "0.1"})


def test_run_rejects_a_bad_method_option_before_any_work(tmp_path):
    res = CliRunner().invoke(cli, ["run", "-d", f"kitti={tmp_path}", "-m", "raycast-zbuffer:splat=big", "--limit", "1",
                                   "--store", str(tmp_path / "store"), "--no-report", "-q"])
    assert res.exit_code == 2 and "method raycast-zbuffer option splat: cannot read 'big' as float" in res.output
    assert not (tmp_path / "store").exists()


def test_root_options_are_typed_with_one_clear_error(plugins, tmp_path):
    mcap = plugins.datasets.get("mcap")
    rec = tmp_path / "r.mcap"
    rec.write_bytes(b"")
    opts = config.root_options("mcap", mcap, f"{rec}?rate_hz=5&ego_box=-2,3.5,-1.5,1.5&topic=/points")
    assert opts == mcap.Options(topic="/points", rate_hz=5.0, ego_box=(-2.0, 3.5, -1.5, 1.5))
    with pytest.raises(PcfbenchError, match=rf"dataset mcap root {rec} option rate_hz: cannot read 'abc' as float \| None"):
        config.root_options("mcap", mcap, f"{rec}?rate_hz=abc")
    with pytest.raises(UnknownNameError, match=rf"unknown dataset mcap root {rec} option 'bogus' \(known: ego_box, rate_hz"):
        config.root_options("mcap", mcap, f"{rec}?bogus=1")
    with pytest.raises(UnknownNameError, match=r"option 'rate_h'; did you mean 'rate_hz'\?"):
        config.root_options("mcap", mcap, f"{rec}?rate_h=10")
    with pytest.raises(PcfbenchError, match=r"ego_box=\(1.0, 2.0\): expected xmin,xmax,ymin,ymax"):
        config.root_options("mcap", mcap, f"{rec}?ego_box=1,2")
    with pytest.raises(PcfbenchError, match=r"rate_hz=0.0: expected a positive rate"):
        config.root_options("mcap", mcap, f"{rec}?rate_hz=0")
    with pytest.raises(PcfbenchError, match=r"option 'topic' is given twice"):
        config.split_root_options(f"{rec}?topic=/a&topic=/b")
    with pytest.raises(UnknownNameError, match=r"unknown dataset kitti root .* option 'rate_hz' \(known: none\)"):
        config.root_options("kitti", plugins.datasets.get("kitti"), f"{tmp_path}?rate_hz=10")
    # the adapters read the same options from keywords (values or strings) or an Options instance
    with pytest.raises(UnknownNameError, match=r"unknown dataset kitti option 'rate_hz'"):
        plugins.datasets.get("kitti")(tmp_path, rate_hz="10")
    with pytest.raises(PcfbenchError, match="not both"):
        mcap(rec, mcap.Options(), topic="/a")
    with pytest.raises(PcfbenchError, match="options must be a McapOptions"):
        mcap(rec, plugins.datasets.get("nuscenes").Options())


def test_cli_rejects_a_bad_root_option_before_any_work(tmp_path):
    (tmp_path / "ns").mkdir()
    res = CliRunner().invoke(cli, ["run", "-d", f"nuscenes={tmp_path / 'ns'}?chanel=LIDAR_TOP", "-m", "copy-last",
                                   "--limit", "1", "--store", str(tmp_path / "store"), "--no-report", "-q"])
    assert res.exit_code == 2, res.output
    assert "unknown dataset nuscenes root" in res.output and "option 'chanel'; did you mean 'channel'?" in res.output
    assert not (tmp_path / "store").exists()


def test_a_method_takes_only_its_own_options_class(plugins):
    voxel, freespace = plugins.methods.get("raycast-voxel"), plugins.methods.get("raycast-freespace")
    assert voxel().options == voxel.Options() and voxel(voxel.Options(voxel=0.1)).options.voxel == 0.1
    with pytest.raises(PcfbenchError, match=r"method raycast-freespace: options must be a FreespaceOptions, got VoxelOptions"):
        freespace(voxel.Options())
    with pytest.raises(PcfbenchError, match=r"method raycast-voxel: options must be a VoxelOptions, got \{'voxel': 0.1\}"):
        voxel({"voxel": 0.1})


def test_a_spec_writes_itself_as_a_command_line_does(plugins):
    """MethodSpec.text: the options as given, keys sorted; less the named ones (the command that
    trains a method names its training options only)."""
    spec = resolve_method("copilot4d:top_k=1,steps=800,config=tiny", plugins)
    assert spec.text() == "copilot4d:config=tiny,steps=800,top_k=1"
    assert spec.text(drop=spec.cls.inference_options) == "copilot4d:config=tiny,steps=800"
    assert resolve_method("copilot4d:top_k=1", plugins).text(drop=("top_k",)) == "copilot4d"
    assert resolve_method("copy-last", plugins).text() == "copy-last"
