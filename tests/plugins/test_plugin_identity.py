"""Issue 15: built-ins are known by their distribution, not their name; a failed plugin keeps nothing."""

import importlib.metadata
import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from pcfbench.errors import PcfbenchError, PluginError, UnknownNameError
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


# -- issue 45: a cell knows its method's code ------------------------------------------------------

PLUGIN_SOURCE = '''
from pcfbench.data import Forecast
from pcfbench.method import Method


class Edited(Method):
    name = "edited"
    version = "1"

    def forecast(self, sample):
        last = sample.past_points_ref[-1] * {scale}
        return Forecast(points_ref=tuple(last for _ in range(sample.num_future)))
'''


def _edited_plugin(tmp_path, monkeypatch, scale):
    """Write (or rewrite) the plugin module ``pcfb_edited`` and import it afresh."""
    (tmp_path / "pcfb_edited.py").write_text(PLUGIN_SOURCE.format(scale=scale))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "pcfb_edited", raising=False)
    import importlib

    module = importlib.import_module("pcfb_edited")
    plugins = load_plugins()
    plugins.methods.add("edited", module.Edited, "test")
    return plugins


def _cell(root):
    from pcfbench.method import options_hash
    from pcfbench.store.cells import CellSpec

    return CellSpec("edited", {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None,
                    ("chamfer",))


def test_plugin_code_edited_with_the_same_version_is_not_reused(tiny_kitti, tmp_path, monkeypatch):
    from pcfbench.running.runner import RunOptions, run_cell

    store = tmp_path / "store"
    code = tmp_path / "code"
    code.mkdir()
    first = run_cell(_cell(tiny_kitti), store, RunOptions(progress=False), plugins=_edited_plugin(code, monkeypatch, 1.0))
    assert first.processed == 6
    again = _edited_plugin(code, monkeypatch, 1.0)  # imported again, the same source: the same cell
    assert run_cell(_cell(tiny_kitti), store, RunOptions(progress=False), plugins=again).processed == 0
    edited = _edited_plugin(code, monkeypatch, 1.5)  # the author forgot to bump version = "1"
    with pytest.raises(PcfbenchError, match=r"(?s)different method_code \(the method's code changed "
                                            r"\(edited: pcfb_edited.py, its version '1' unchanged.*--force"):
        run_cell(_cell(tiny_kitti), store, RunOptions(progress=False), plugins=edited)
    assert run_cell(_cell(tiny_kitti), store, RunOptions(progress=False, force=True), plugins=edited).processed == 6


def test_cell_json_records_the_methods_distribution_and_code(tiny_kitti, tmp_path):
    import json

    import pcfbench.methods
    from pcfbench.method import options_hash
    from pcfbench.provenance import source_files_sha256
    from pcfbench.running.runner import RunOptions, run_cell
    from pcfbench.store.cells import Cell, CellSpec

    spec = CellSpec("copy-last", {}, options_hash(None), "kitti", str(tiny_kitti), "test", "kitti-1s", "full-context",
                    None, ("chamfer",))
    run_cell(spec, tmp_path / "store", RunOptions(progress=False))
    meta = json.loads((Cell(tmp_path / "store", spec).dir / "cell.json").read_text())
    assert meta["method_distribution"] == {"name": "pcfbench", "version": importlib.metadata.version("pcfbench")}
    sha, files = source_files_sha256(Path(pcfbench.methods.__file__).parent)
    assert meta["method_code"] == sha and meta["method_code_unit"] == "pcfbench.methods"
    assert meta["method_code_files"] == files and "copy_last.py" in files and "raycast/__init__.py" in files
    # the host and the libraries the numbers depend on (the generated data's bytes on the CPU)
    env = meta["environment"]
    assert env["cpu"] and env["numpy"] == np.__version__ and env["cpus"] == os.cpu_count()
    if os.path.exists("/proc/cpuinfo"):
        flags = next(ln for ln in open("/proc/cpuinfo") if ln.startswith("flags")).split(":", 1)[1].split()
        assert env["cpu_simd"] == [f for f in ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "avx512_fp16",
                                               "amx_tile") if f in flags]
    for name in ("numba", "open3d"):  # imported by the metrics and the ray casters
        if name in sys.modules:
            assert env[name] == sys.modules[name].__version__, name
    if "torch" in sys.modules:
        assert env["torch_cpu_capability"] == sys.modules["torch"].backends.cpu.get_cpu_capability()


def test_the_code_hash_is_of_relative_paths_and_contents_only(tmp_path):
    """A wheel's copy and an editable checkout of the same sources agree: no absolute path,
    modification time, byte-code cache or non-package folder counts."""
    import hashlib
    import os
    import shutil

    import pcfbench.methods
    from pcfbench.provenance import source_files_sha256

    here = Path(pcfbench.methods.__file__).parent
    copy = tmp_path / "site-packages" / "pcfbench" / "methods"
    shutil.copytree(here, copy, ignore=shutil.ignore_patterns("__pycache__"))
    for f in copy.rglob("*.py"):
        os.utime(f, ns=(1, 1))
    (copy / "__pycache__").mkdir(exist_ok=True)
    (copy / "__pycache__" / "x.py").write_text("# not a package folder")
    assert source_files_sha256(copy) == source_files_sha256(here)
    # against a hand-built hash of two files
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_bytes(b"")
    (tmp_path / "pkg" / "a.py").write_bytes(b"x = 1\n")
    sha = {n: hashlib.sha256(b).hexdigest()[:16] for n, b in (("__init__.py", b""), ("a.py", b"x = 1\n"))}
    blob = "".join(f"{n}\0{sha[n]}\n" for n in sorted(sha)).encode()
    assert source_files_sha256(tmp_path / "pkg") == (hashlib.sha256(blob).hexdigest()[:16], sha)
