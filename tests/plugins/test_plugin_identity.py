"""Issue 15: built-ins are known by their distribution, not their name; a failed plugin keeps nothing."""

import importlib.metadata
import sys
import types

import pytest

from pcfbench.errors import PluginError, UnknownNameError
from pcfbench.hookspecs import hookimpl
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import Plugins, is_builtin_entry_point, load_plugins


def _dist(tmp_path, name):
    info = tmp_path / f"{name}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    return importlib.metadata.PathDistribution(info)


class Marker(CopyLast):
    """A method only the third-party plugins register (to see whether they ran)."""


@pytest.fixture
def third_party(monkeypatch, tmp_path):
    """Add ``name -> module`` entry points of a third-party distribution ``evil`` beside the
    installed ones, and let third-party plugins load (the tests' default allow-list holds none)."""
    monkeypatch.delenv("PCFBENCH_PLUGINS", raising=False)
    real = list(importlib.metadata.entry_points(group="pcfbench"))
    dist = _dist(tmp_path, "evil")
    added = []

    def install(name, **hooks):
        mod = types.ModuleType(f"pcfb_trust_{len(added)}")
        for hook, fn in hooks.items():
            setattr(mod, hook, hookimpl(fn))
        monkeypatch.setitem(sys.modules, mod.__name__, mod)
        added.append(importlib.metadata.EntryPoint(name, mod.__name__, "pcfbench")._for(dist))

    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: [*real, *added] if group == "pcfbench" else [])
    return install


def test_builtins_are_the_pcfbench_distributions_entry_points():
    eps = list(importlib.metadata.entry_points(group="pcfbench"))
    assert eps and all(is_builtin_entry_point(ep) for ep in eps)
    # a name alone (no distribution) makes nothing a built-in
    assert not is_builtin_entry_point(importlib.metadata.EntryPoint("builtin-methods", "x", "pcfbench"))


def test_a_third_party_builtin_prefix_obeys_the_allow_list(third_party, monkeypatch):
    third_party("builtin-sneaky", register_methods=lambda register: register("sneaky", Marker))
    monkeypatch.setenv("PCFBENCH_PLUGINS", "")  # allow no third-party plugin
    plugins = load_plugins()
    assert "sneaky" not in plugins.methods and "builtin-sneaky" not in plugins.info
    assert "copy-last" in plugins.methods  # the real built-ins still load
    monkeypatch.setenv("PCFBENCH_PLUGINS", "builtin-sneaky")
    plugins = load_plugins()
    assert plugins.methods.entries["sneaky"].plugin == "builtin-sneaky"
    assert plugins.info["builtin-sneaky"].builtin is False and plugins.info["builtin-methods"].builtin is True


def test_a_third_party_named_like_a_builtin_cannot_replace_it(third_party, monkeypatch):
    def hijack(register):
        register("copy-last", Marker)

    third_party("builtin-methods", register_methods=hijack)
    for allow in (None, "builtin-methods"):
        if allow is None:
            monkeypatch.delenv("PCFBENCH_PLUGINS", raising=False)
        else:
            monkeypatch.setenv("PCFBENCH_PLUGINS", allow)
        plugins = load_plugins()
        entry = plugins.methods.entries["copy-last"]
        assert plugins.methods.get("copy-last") is CopyLast and entry.plugin == "builtin-methods"
        assert plugins.info["builtin-methods"].builtin and plugins.info["builtin-methods"].error is None
        assert "raycast-voxel" in plugins.methods  # the real built-ins all registered
        refused = plugins.info["builtin-methods (evil)"]
        assert "takes the name of a pcfbench built-in" in refused.error


def _register_then_fail(register):
    register("half-a", Marker)
    register("copy-last", Marker)  # a duplicate of a built-in: raises


def test_a_plugin_that_fails_half_way_registers_nothing(third_party):
    def datasets(register):
        from pcfbench.datasets.kitti import KittiOdometry

        register("half-dataset", KittiOdometry)

    third_party("half", register_datasets=datasets, register_methods=_register_then_fail,
                register_metrics=lambda register: register("half-metric", "x:y"))
    plugins = load_plugins()
    info = plugins.info["half"]
    assert "registered twice" in info.error and info.registered == {}
    # nothing it registered, before or after the failure, in any registry
    assert "half-a" not in plugins.methods and "half-dataset" not in plugins.datasets
    assert "half-metric" not in plugins.metrics
    assert plugins.methods.get("copy-last") is CopyLast
    with pytest.raises(UnknownNameError, match="failed to load and may provide it: half"):
        plugins.methods.get("half-a")


def test_register_kept_past_its_hook_is_refused():
    kept = []
    mod = types.ModuleType("pcfb_trust_keep")
    mod.register_methods = hookimpl(lambda register: kept.append(register))
    plugins = Plugins()
    plugins.add_plugin(mod, "keep")
    with pytest.raises(PluginError, match="after its registration hook returned"):
        kept[0]("late", Marker)
    assert "late" not in plugins.methods


def test_docs_metrics_page_takes_builtins_by_distribution_not_name(third_party):
    """A third-party metric from an entry point named ``builtin-...`` stays off docs/metrics.md."""
    from pcfbench import docs
    from pcfbench.metrics.base import Metric

    rogue = Metric("rogue", "1", lambda ctx: 0.0, "a third-party metric", higher_is_better=False)
    third_party("builtin-rogue", register_metrics=lambda register: register("rogue", rogue))
    assert "rogue" in load_plugins().metrics  # it is loaded (no allow-list)...
    names = [m.name for m in docs.builtin_metrics()]
    assert "rogue" not in names and "chamfer" in names  # ... but it is not a built-in
