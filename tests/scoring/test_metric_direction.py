"""Issue 41: a metric says which way is better, and the tables take it from the metric.

A higher-is-better metric a plugin registers ranks, bolds and points its arrow the right way
in a preset that does not say ``better``; a preset that contradicts a metric is one error
naming both; the kinds that were bare strings are enums that still read and write the same
strings."""

import json
import types

import numpy as np
import pandas as pd
import pytest

from pcfbench.reporting import tables
from pcfbench.errors import PcfbenchError, PluginError
from pcfbench.hookspecs import hookimpl
from pcfbench.kinds import Better, Needs, PolicyKind
from pcfbench.metrics.base import Metric
from pcfbench.method import options_hash, parse_options
from pcfbench.plugins import Plugins, load_plugins
from pcfbench.protocol import SamplePolicy
from pcfbench.reporting.report import ReportOptions, collect, metric_directions, write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec, iter_cells

from conftest import write_tiny_kitti
from tests_helpers import Shifted


def _near_share(ctx) -> float:
    """Share of the ground-truth points with a predicted point within 0.5 m: a score."""
    if ctx.pred_points.shape[0] == 0:
        return float("nan")
    return float(np.mean(ctx.nn_gt_to_pred[0] < 0.25))


NEAR_SHARE = Metric(name="near_share", version="1", fn=_near_share, unit="fraction", higher_is_better=True,
                    description="share of ground-truth points with a prediction within 0.5 m")

PRESET = '[presets.share]\ntitle = "Near share"\ncolumns = [{ metric = "near_share", label = "Near" }, ' \
         '{ metric = "chamfer", label = "CD" }]\n'


def _plugins():
    """The built-ins, a test plugin registering the higher-is-better metric, and a method."""
    plugins = load_plugins()
    module = types.ModuleType("pcfb_direction_test")
    module.register_metrics = hookimpl(lambda register: register("near_share", NEAR_SHARE, "a score"))
    plugins.add_plugin(module, "direction-test")
    assert plugins.info["direction-test"].error is None
    plugins.methods.add("shifted", Shifted, "test")
    return plugins


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """copy-last and copy-last moved by 2 m, scored with near_share (higher is better) and chamfer."""
    tmp = tmp_path_factory.mktemp("direction")
    root = write_tiny_kitti(tmp / "kitti")
    store = tmp / "store"
    plugins = _plugins()
    for method, raw in [("copy-last", {}), ("shifted", {"dx": "2"})]:
        opts = parse_options(plugins.methods.get(method).Options, raw, method)
        spec = CellSpec(method, raw, options_hash(opts), "kitti", str(root), "test", "kitti-1s", "full-context",
                        None, ("near_share", "chamfer"))
        run_cell(spec, store, RunOptions(progress=False), plugins=plugins)
    return store


def test_cells_record_each_metrics_direction(store):
    metas = [meta for _, meta in iter_cells(store)]
    assert metas and all(m["metric_higher_is_better"] == {"near_share": True, "chamfer": False} for m in metas)


def test_a_higher_is_better_plugin_metric_ranks_right_in_a_preset_that_does_not_say_so(store, tmp_path):
    mine = tmp_path / "mine.toml"
    mine.write_text(PRESET)
    # the report's own registry does not hold near_share (the tests load no third-party
    # plugin): its direction comes from the cells
    paths = write_reports(store, tmp_path / "rep", ReportOptions(preset="share", tables_file=str(mine)))
    md = paths["md"].read_text()
    assert "| Near ↑ (%) | CD ↓ (m²) |" in md
    rows = [line for line in md.splitlines() if line.startswith("| copy-last") or line.startswith("| shifted")]
    share = pd.read_csv(paths["csv"]).set_index("method")["near_share"]
    assert len(rows) == 2 and share.nunique() == 2
    top, bottom = share.idxmax(), share.idxmin()  # the toy world drives along x: the shift helps
    assert rows[0].startswith(f"| {top}") and rows[1].startswith(f"| {bottom}"), md  # the higher share first
    near = [r.split("|")[3] for r in rows]
    assert f"**{100 * share[top]:.2f}**" in near[0] and "**" not in near[1]  # bold on the highest
    assert r"Near $\uparrow$" in paths["tex"].read_text()
    assert "rows ranked by Near" in md


def test_a_preset_that_contradicts_its_metric_is_one_error_naming_both(store, tmp_path):
    lb = collect(store)
    assert lb.higher_is_better == {"near_share": True, "chamfer": False}
    mine = tmp_path / "mine.toml"
    mine.write_text(PRESET.replace('label = "Near" }', 'label = "Near", better = "lower" }'))
    preset = tables.get_preset("share", tables.load_presets(mine))
    with pytest.raises(PcfbenchError, match=r"mine.toml: preset 'share': column 'near_share' says better = \"lower\", "
                                            r"but metric 'near_share' is higher-is-better"):
        tables.build(lb, preset)
    # a preset that agrees with its metric is fine
    mine.write_text(PRESET.replace('label = "Near" }', 'label = "Near", better = "higher" }'))
    table = tables.build(lb, tables.get_preset("share", tables.load_presets(mine)))
    assert [c.better for c in table.columns] == [Better.HIGHER, Better.LOWER]


def test_a_metric_whose_direction_nobody_knows_is_shown_lower_is_better_with_a_note():
    notes = []
    assert metric_directions(["chamfer", "unheard_of"], {}, notes) == {"chamfer": False}
    assert len(notes) == 1 and "'unheard_of'" in notes[0] and "lower-is-better" in notes[0]
    assert metric_directions(["unheard_of"], {"unheard_of": True}) == {"unheard_of": True}


def test_a_metric_must_say_which_way_is_better(tmp_path, monkeypatch):
    with pytest.raises(PcfbenchError, match="metric 'score' must say which way is better: higher_is_better="):
        Metric(name="score", version="1", fn=lambda ctx: 0.0, description="no direction")
    with pytest.raises(PcfbenchError, match="got 'yes'"):
        Metric(name="score", version="1", fn=lambda ctx: 0.0, description="d", higher_is_better="yes")
    # a plugin's metric that forgets it fails to load, and says why
    (tmp_path / "pcfb_forgetful_metric.py").write_text(
        "from pcfbench.metrics.base import Metric\n"
        "METRIC = Metric(name='forgetful', version='1', fn=lambda c: 0.0, description='d')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    plugins = Plugins()
    plugins.metrics.add("forgetful", "pcfb_forgetful_metric:METRIC", "p")
    with pytest.raises(PluginError, match="forgetful.*must say which way is better"):
        plugins.metrics.get("forgetful")


def test_every_builtin_metric_says_its_direction():
    registry = load_plugins().metrics
    for name in registry.names():
        metric = registry.get(name)
        assert metric.higher_is_better is False, name  # the built-ins are all errors
        assert metric.better == Better.LOWER


# -- the kinds -----------------------------------------------------------------------------

def test_kinds_are_their_strings():
    assert Needs("depths") is Needs.DEPTHS and Needs.DEPTHS == "depths" and f"{Needs.DEPTHS}" == "depths"
    assert json.dumps({"kind": PolicyKind.SUBSAMPLE}) == '{"kind": "subsample"}'
    metric = Metric(name="m", version="1", fn=lambda ctx: 0.0, description="d", needs="depths", higher_is_better=False)
    assert metric.needs is Needs.DEPTHS
    policy = SamplePolicy("every-2", "subsample", of="full-context", rule="full-context", every=2)
    assert policy.kind is PolicyKind.SUBSAMPLE and policy.rule is PolicyKind.FULL_CONTEXT
    params = policy.params()
    assert params == {"name": "every-2", "kind": "subsample", "every": 2, "of": "full-context"}
    assert type(params["kind"]) is str  # cell.json holds the plain string, as before


def test_an_invalid_kind_lists_the_valid_values():
    with pytest.raises(PcfbenchError, match=r"metric 'm': needs must be one of \"points\", \"depths\", \"either\", "
                                            r"got 'rays'"):
        Metric(name="m", version="1", fn=lambda ctx: 0.0, description="d", needs="rays", higher_is_better=False)
    with pytest.raises(PcfbenchError, match=r"sample policy 'x': kind must be one of \"full-context\", "
                                            r"\"every-frame\", \"subsample\", got 'sometimes'"):
        SamplePolicy("x", "sometimes")
    with pytest.raises(PcfbenchError, match=r"column 'chamfer': better must be one of \"lower\", \"higher\", got 'up'"):
        tables._read_presets('[presets.x]\ncolumns = [{ metric = "chamfer", better = "up" }]\n', "x.toml")
