"""Issue 15: options that parse but mean nothing are one clear error before any work."""

import dataclasses

import pytest
from click.testing import CliRunner

from pcfbench.cli import cli
from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.options import check_options, describe_options, option, options_hash, parse_options
from pcfbench.plugins import load_plugins


@pytest.fixture(scope="module")
def plugins():
    return load_plugins()


@pytest.mark.parametrize("value, why", [
    ("nan", "must be a finite number, got nan"),
    ("inf", "must be a finite number, got inf"),
    ("-inf", "must be a finite number, got -inf"),
    ("-1", r"must be > 0 \(valid: > 0, <= 10\), got -1.0"),
    ("0", r"must be > 0 \(valid: > 0, <= 10\), got 0.0"),
    ("1e9", r"must be <= 10 \(valid: > 0, <= 10\), got 1000000000.0"),
])
@pytest.mark.parametrize("method", ["raycast-voxel", "raycast-freespace"])
def test_voxel_outside_its_range_is_one_error(plugins, method, value, why):
    with pytest.raises(PcfbenchError, match=rf"^method {method} option voxel {why}$"):
        resolve_method(f"{method}:voxel={value}", plugins)


def test_every_float_option_of_the_raycast_methods_refuses_nan(plugins):
    for method in ("raycast-voxel", "raycast-freespace", "raycast-zbuffer"):
        cls = plugins.methods.get(method)
        for f in dataclasses.fields(cls.Options):
            if f.type in ("float", float):
                with pytest.raises(PcfbenchError, match=rf"method {method} option {f.name} must be a finite number"):
                    resolve_method(f"{method}:{f.name}=nan", plugins)


def test_values_inside_the_range_and_bounds_inclusive_or_not(plugins):
    assert resolve_method("raycast-voxel:voxel=10", plugins).options.voxel == 10.0  # max is inclusive
    assert resolve_method("raycast-voxel:cone_factor=0", plugins).options.cone_factor == 0.0  # min inclusive
    with pytest.raises(PcfbenchError, match="option max_level must be >= 0"):
        resolve_method("raycast-voxel:max_level=-1", plugins)
    with pytest.raises(PcfbenchError, match="option fill_ring must be >= 0"):
        resolve_method("raycast-zbuffer:fill_ring=-3", plugins)


@dataclasses.dataclass(frozen=True)
class Plain:
    voxel: float = option(0.2, help="voxel edge")
    sizes: tuple[float, ...] = option((1.0,), help="sizes")


@dataclasses.dataclass(frozen=True)
class Ranged:
    voxel: float = option(0.2, help="voxel edge", gt=0, max=10)
    sizes: tuple[float, ...] = option((1.0,), help="sizes", min=0.5)
    anything: float = option(0.0, help="may be NaN", finite=False)


def test_ranges_are_metadata_outside_the_option_hash():
    # the same values hash the same whether or not the class declares ranges
    plain = {"voxel": 0.3, "sizes": (1.0,)}
    assert options_hash(Plain(**plain)) == options_hash(_Ranged2(**plain))
    assert [o.range for o in describe_options(Ranged)] == ["> 0, <= 10", ">= 0.5", ""]


@dataclasses.dataclass(frozen=True)
class _Ranged2:
    voxel: float = option(0.2, help="voxel edge", gt=0, max=10)
    sizes: tuple[float, ...] = option((1.0,), help="sizes", min=0.5)


def test_tuple_items_python_values_and_finite_false():
    with pytest.raises(PcfbenchError, match=r"owner option sizes must be >= 0.5 \(valid: >= 0.5\), got 0.25"):
        parse_options(Ranged, {"sizes": "1/0.25"}, "owner")
    with pytest.raises(PcfbenchError, match="owner option voxel must be a finite number"):
        parse_options(Ranged, {"voxel": float("nan")}, "owner")  # a value, not a string
    assert parse_options(Ranged, {"anything": "nan"}, "owner").anything != 0.0
    with pytest.raises(PcfbenchError, match="owner option voxel must be > 0"):
        check_options(Ranged(voxel=-1.0), "owner")
    assert check_options(Ranged(), "owner") == Ranged()
    with pytest.raises(TypeError, match="min= must be a number"):
        option(1.0, help="x", min="0")


def test_run_refuses_voxel_nan_before_any_work(tmp_path):
    store = tmp_path / "store"
    res = CliRunner().invoke(cli, ["run", "-d", f"kitti={tmp_path}", "-m", "raycast-voxel:voxel=nan", "--limit", "1",
                                   "--store", str(store), "--no-report", "-q"])
    assert res.exit_code == 2 and "method raycast-voxel option voxel must be a finite number, got nan" in res.output
    assert "Traceback" not in res.output and not store.exists()


def test_ls_options_prints_the_ranges():
    res = CliRunner().invoke(cli, ["ls", "methods", "--options"])
    assert res.exit_code == 0, res.output
    line = next(x for x in res.output.splitlines() if x.split()[:1] == ["voxel"])
    assert line.rstrip().endswith("voxel edge of the occupancy grid, metres (valid: > 0, <= 10)")


def test_a_method_built_with_direct_options_checks_their_ranges(plugins):
    """``Method(Options(...))`` (the Python API, no spec string) refuses what parsing refuses."""
    cls = plugins.methods.get("raycast-voxel")
    for value, why in ((float("nan"), "must be a finite number, got nan"), (-1.0, r"must be > 0 \(valid: > 0, <= 10\)")):
        with pytest.raises(PcfbenchError, match=rf"^method raycast-voxel option voxel {why}"):
            cls(cls.Options(voxel=value))
    assert cls(cls.Options(voxel=0.5)).options.voxel == 0.5


def test_docs_trust_lists_the_baselines_ranges_as_declared(plugins):
    """Every row of the option-range table in docs/trust.md is what the options declare."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "trust.md").read_text(encoding="utf-8")
    rows = re.findall(r"^  \| (raycast[^|]*) \| (\w+) \| ([^|]+) \|$", text, re.M)
    assert len(rows) >= 12
    for methods, name, valid in rows:
        for method in (m.strip() for m in methods.split(",")):
            declared = {f.name: f.range for f in describe_options(plugins.methods.get(method).Options, method)}
            assert declared[name] == valid.strip(), (method, name)
