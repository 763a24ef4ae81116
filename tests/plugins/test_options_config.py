from dataclasses import dataclass
from typing import Literal

import pytest

from pcfbench import config
from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.method import options_hash, parse_method_spec, parse_options


@dataclass(frozen=True)
class Opts:
    voxel: float = 0.2
    iters: int = 3
    dilate: bool = False
    mode: Literal["a", "b"] = "a"
    name: str | None = None


def test_options_convert_by_type_and_reject_unknown_keys():
    o = parse_options(Opts, {"voxel": "0.1", "iters": "5", "dilate": "true", "mode": "b", "name": "none"}, "method x")
    assert o == Opts(0.1, 5, True, "b", None)
    with pytest.raises(UnknownNameError, match=r"unknown method x option 'voxle'; did you mean 'voxel'\? \(known: dilate, iters, mode, name, voxel\)"):
        parse_options(Opts, {"voxle": "1"}, "method x")
    with pytest.raises(PcfbenchError, match="unknown option\\(s\\) a, voxle.*known: dilate, iters, mode, name, voxel"):
        parse_options(Opts, {"voxle": "1", "a": "2"}, "method x")
    with pytest.raises(PcfbenchError, match="cannot read 'abc' as int"):
        parse_options(Opts, {"iters": "abc"}, "method x")
    with pytest.raises(PcfbenchError, match="'c' is not one of a, b"):
        parse_options(Opts, {"mode": "c"}, "method x")


def test_options_hash_is_stable_and_value_sensitive():
    assert options_hash(Opts()) == options_hash(Opts())
    assert options_hash(Opts()) != options_hash(Opts(voxel=0.1))


def test_method_spec_syntax():
    assert parse_method_spec("raycast-voxel:voxel=0.1,dilate=true") == ("raycast-voxel", {"voxel": "0.1", "dilate": "true"})
    assert parse_method_spec("copy-last") == ("copy-last", {})
    with pytest.raises(PcfbenchError, match="key=value"):
        parse_method_spec("m:oops")
    with pytest.raises(PcfbenchError, match="'voxel' is given twice"):
        parse_method_spec("raycast-voxel:voxel=0.1,voxel=0.2")
    with pytest.raises(PcfbenchError, match="no method name"):
        parse_method_spec(":voxel=0.1")


def test_dataset_roots_cli_env_config_never_cwd(tmp_path, monkeypatch):
    cfg = tmp_path / "config.toml"
    cfg.write_text('[datasets]\nkitti = "/from/config"\nnuscenes = "/ns"\n')
    monkeypatch.setenv("PCFBENCH_CONFIG", str(cfg))
    monkeypatch.setenv("PCFBENCH_DATASET_KITTI", "/from/env")
    monkeypatch.chdir(tmp_path)
    names, roots = config.parse_dataset_args(("kitti=/from/cli", "nuscenes"))
    assert names == ["kitti", "nuscenes"]
    assert config.dataset_root("kitti", roots) == "/from/cli"
    assert config.dataset_root("kitti", {}) == "/from/env"
    assert config.dataset_root("nuscenes", {}) == "/ns"
    assert config.dataset_root("av2", {}) is None
    monkeypatch.setenv("PCFBENCH_CONFIG", str(tmp_path / "missing.toml"))
    with pytest.raises(PcfbenchError, match="does not exist"):
        config.dataset_root("av2", {})
