import json
import os
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import pytest

from pcfbench.errors import PluginError, UnknownNameError
from pcfbench.hookspecs import hookimpl
from pcfbench.plugins import Plugins, load_plugins

VENV_BIN = Path(sys.executable).parent


def _plugin_module(name, **hooks):
    mod = types.ModuleType(name)
    for hook, fn in hooks.items():
        setattr(mod, hook, hookimpl(fn))
    return mod


def test_builtins_load_through_entry_points():
    plugins = load_plugins()
    assert {"builtin-datasets", "builtin-methods", "builtin-metrics"} <= set(plugins.info)
    assert "copy-last" in plugins.methods and "kitti" in plugins.datasets and "chamfer" in plugins.metrics
    assert plugins.methods.entries["copy-last"].plugin == "builtin-methods"


def test_duplicate_names_rejected_and_attributed():
    plugins = load_plugins()
    dup = _plugin_module("dup", register_methods=lambda register: register("copy-last", "pcfbench.methods.copy_last:CopyLast"))
    plugins.add_plugin(dup, "dup")
    assert "registered twice" in plugins.info["dup"].error and "builtin-methods" in plugins.info["dup"].error


def test_type_checks_on_eager_and_lazy_targets():
    plugins = Plugins()
    with pytest.raises(PluginError, match="subclass of pcfbench.method.Method"):
        plugins.methods.add("bad", object, "p")
    plugins.methods.add("lazy-bad", "pcfbench.geometry:invert", "p")
    with pytest.raises(PluginError, match="lazy-bad.*subclass"):
        plugins.methods.get("lazy-bad")
    with pytest.raises(PluginError, match="must look like 'module:attribute'"):
        plugins.methods.add("x", "no_colon", "p")


def test_unknown_name_did_you_mean_and_failed_plugins_named():
    plugins = load_plugins()
    plugins.add_plugin(_plugin_module("m"), "m")
    plugins._fail("broken-plugin", "broken:mod", "ImportError: nope")
    with pytest.raises(UnknownNameError) as err:
        plugins.methods.get("copy-lst")
    assert "did you mean 'copy-last'" in str(err.value) and "broken-plugin" in str(err.value)


def test_import_failure_breaks_only_what_needs_it():
    plugins = load_plugins()
    mod = _plugin_module("half", register_methods=lambda register: register("ghost", "no_such_module_xyz:Ghost"))
    plugins.add_plugin(mod, "half")
    assert plugins.methods.get("copy-last")  # unaffected
    with pytest.raises(PluginError, match="ghost.*plugin 'half'.*No module named 'no_such_module_xyz'"):
        plugins.methods.get("ghost")


def test_misspelled_hook_fails_loudly():
    plugins = load_plugins()
    mod = _plugin_module("typo", register_method=lambda register: None)
    plugins.add_plugin(mod, "typo")
    assert "register_method" in plugins.info["typo"].error


EXTERNAL = {
    "pyproject.toml": """
        [build-system]
        requires = ["setuptools"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "pcfbench-example-plugin"
        version = "0.0.1"
        [project.entry-points.pcfbench]
        example = "pcfbench_example"
        broken = "pcfbench_broken"
        [tool.setuptools]
        py-modules = ["pcfbench_example", "pcfbench_broken"]
    """,
    "pcfbench_example.py": """
        from pcfbench.data import Forecast
        from pcfbench.hookspecs import hookimpl
        from pcfbench.method import Method

        class Shifted(Method):
            name = "shifted-copy"
            def forecast(self, sample):
                pts = sample.past_points_ref[-1] + 0.5
                return Forecast(points_ref=tuple(pts for _ in sample.queries))

        @hookimpl
        def register_methods(register):
            register("shifted-copy", Shifted, "copy-last moved by 0.5 m")
    """,
    "pcfbench_broken.py": "raise ImportError('this plugin is broken on purpose')\n",
}


@pytest.fixture(scope="module")
def external_plugin(tmp_path_factory):
    """Build and install a tiny distribution with a pcfbench entry point into a target folder."""
    src = tmp_path_factory.mktemp("src")
    for name, text in EXTERNAL.items():
        (src / name).write_text(textwrap.dedent(text))
    target = tmp_path_factory.mktemp("site")
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
         "--target", str(target), str(src)],
        check=True, capture_output=True,
    )
    return target


def _cli(args, site, **env):
    full_env = {**os.environ, "PYTHONPATH": str(site), **env}
    return subprocess.run([str(VENV_BIN / "pcfbench"), *args], capture_output=True, text=True, env=full_env, timeout=300)


@pytest.mark.third_party_plugins
def test_external_plugin_via_entry_point(external_plugin, tiny_kitti, tmp_path):
    out = _cli(["ls", "methods"], external_plugin)
    assert out.returncode == 0, out.stderr
    assert "shifted-copy" in out.stdout and "example" in out.stdout
    listing = json.loads(_cli(["plugins", "--json"], external_plugin).stdout)
    by_name = {p["name"]: p for p in listing}
    assert by_name["example"]["registered"] == {"methods": ["shifted-copy"]}
    assert "broken on purpose" in by_name["broken"]["error"]
    run = _cli(["run", "--dataset", f"kitti={tiny_kitti}", "--setting", "kitti-1s", "-m", "copy-last",
                "-m", "shifted-copy", "--reports", str(tmp_path / "rep"), "-q"], external_plugin)
    assert run.returncode == 0, run.stderr
    assert "plugin 'broken'" in run.stderr  # warned, not fatal
    md = (tmp_path / "rep" / "leaderboard.md").read_text()
    assert "shifted-copy" in md and "copy-last" in md


@pytest.mark.third_party_plugins
def test_allow_and_block_lists(external_plugin):
    only_builtins = _cli(["plugins", "--json"], external_plugin, PCFBENCH_PLUGINS="")
    names = {p["name"] for p in json.loads(only_builtins.stdout)}
    assert "example" not in names and "builtin-methods" in names
    allowed = {p["name"] for p in json.loads(_cli(["plugins", "--json"], external_plugin, PCFBENCH_PLUGINS="example").stdout)}
    assert "example" in allowed and "broken" not in allowed
    blocked = _cli(["ls", "methods"], external_plugin, PCFBENCH_BLOCK_PLUGINS="example,builtin-methods")
    assert "shifted-copy" not in blocked.stdout and "copy-last" not in blocked.stdout


def _hookimpl_module(name, hook, fn, **marks):
    mod = types.ModuleType(name)
    setattr(mod, hook, hookimpl(**marks)(fn) if marks else hookimpl(fn))
    return mod


def _registering(*names, fail=None):
    def register_methods(register):
        for n in names:
            register(n, "pcfbench.methods.copy_last:CopyLast", "test")
        if fail:
            raise RuntimeError(fail)

    return register_methods


@pytest.fixture
def fake_entry_points(monkeypatch):
    """Add modules as entry points of the pcfbench group, beside the installed ones, and let
    third-party plugins load (the tests' default allow-list holds none)."""
    import importlib.metadata

    monkeypatch.delenv("PCFBENCH_PLUGINS", raising=False)

    real = importlib.metadata.entry_points(group="pcfbench")
    added = []

    def install(name, module):
        monkeypatch.setitem(sys.modules, module.__name__, module)
        added.append(importlib.metadata.EntryPoint(name, module.__name__, "pcfbench"))

    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: [*real, *added] if group == "pcfbench" else [])
    return install


def test_hooks_run_in_pluggys_order_tryfirst_and_trylast_honoured(fake_entry_points):
    fake_entry_points("zz-first", _hookimpl_module("pcfb_t_first", "register_methods", _registering("m-first"), tryfirst=True))
    fake_entry_points("aa-last", _hookimpl_module("pcfb_t_last", "register_methods", _registering("m-last"), trylast=True))
    fake_entry_points("mm-plain", _hookimpl_module("pcfb_t_plain", "register_methods", _registering("m-plain")))
    plugins = load_plugins()
    builtins = ["bevworld-latent-copy", "bevworld", "copilot4d-token-copy", "copilot4d", "copilot4d-maskgit",
                "copy-last", "raycast-4docc", "raycast-zbuffer", "raycast-voxel", "raycast-freespace", "submission",
                "occworld-occ-copy", "occworld"]
    # tryfirst first, then the built-ins, the others by entry-point name, trylast last
    assert list(plugins.methods.entries) == ["m-first", *builtins, "m-plain", "m-last"]
    # ... which is exactly the order of one pm.hook call (pluggy itself as the reference)
    called = []
    plugins.pm.hook.register_methods(register=lambda name, target, description="": called.append(name))
    assert called == list(plugins.methods.entries)
    # attributed to the plugin that registered it
    assert plugins.methods.entries["m-first"].plugin == "zz-first"
    assert plugins.info["aa-last"].registered == {"methods": ["m-last"]} and plugins.info["aa-last"].error is None


def test_a_failing_hook_marks_only_its_plugin(fake_entry_points):
    fake_entry_points("bb", _hookimpl_module("pcfb_t_boom", "register_methods", _registering("m-boom", fail="boom"),
                                             tryfirst=True))
    fake_entry_points("cc", _hookimpl_module("pcfb_t_after", "register_methods", _registering("m-after")))
    plugins = load_plugins()
    assert plugins.info["bb"].error == "register_methods: RuntimeError: boom"
    assert plugins.info["bb"].registered == {} and "m-boom" not in plugins.methods  # a failed plugin keeps nothing
    assert plugins.methods.failed_plugins == {"bb": "register_methods: RuntimeError: boom"}
    assert plugins.info["cc"].error is None and plugins.methods.entries["m-after"].plugin == "cc"
    assert plugins.info["builtin-methods"].error is None and plugins.methods.get("raycast-voxel")


def test_trylast_loses_a_name_conflict_whatever_the_names(fake_entry_points):
    fake_entry_points("aa", _hookimpl_module("pcfb_t_aa", "register_methods", _registering("dup"), trylast=True))
    fake_entry_points("zz", _hookimpl_module("pcfb_t_zz", "register_methods", _registering("dup")))
    plugins = load_plugins()
    assert plugins.methods.entries["dup"].plugin == "zz" and plugins.info["zz"].error is None
    assert "'dup' is registered twice: by plugin 'zz' and by plugin 'aa'" in plugins.info["aa"].error
    fake_entry_points("ab", _hookimpl_module("pcfb_t_ab", "register_methods", _registering("dup2")))
    fake_entry_points("ac", _hookimpl_module("pcfb_t_ac", "register_methods", _registering("dup2")))
    plugins = load_plugins()  # no marks: by entry-point name
    assert plugins.methods.entries["dup2"].plugin == "ab" and "by plugin 'ac'" in plugins.info["ac"].error


def test_impls_are_called_through_pluggy_and_wrappers_rejected():
    plugins = Plugins()
    plugins.add_plugin(_hookimpl_module("noargs", "register_methods", lambda: None), "noargs")  # fewer args: allowed
    assert plugins.info["noargs"].error is None

    def wrapper(register):
        yield

    plugins.add_plugin(_hookimpl_module("wrap", "register_methods", wrapper, wrapper=True), "wrap")
    assert "register_methods cannot be a hook wrapper" in plugins.info["wrap"].error


def test_register_commands_ordering_lets_a_plugin_extend_anothers_group():
    import click

    def make_group(cli):
        @cli.group("grp")
        def grp():
            """A group."""

    def extend(cli):
        @cli.commands["grp"].command("sub")
        def sub():
            """A subcommand."""

    def broken(cli):
        raise RuntimeError("no commands today")

    plugins = Plugins()
    plugins.add_plugin(_hookimpl_module("ext", "register_commands", extend, trylast=True), "aa-ext")
    plugins.add_plugin(_hookimpl_module("grp", "register_commands", make_group), "zz-grp")
    plugins.add_plugin(_hookimpl_module("brk", "register_commands", broken), "mm-broken")
    group = click.Group("pcfbench")
    plugins.add_commands(group)
    assert set(group.commands["grp"].commands) == {"sub"}
    assert plugins.info["aa-ext"].error is None
    assert plugins.info["mm-broken"].error == "register_commands: RuntimeError: no commands today"


def _uninvited(monkeypatch):
    """An installed third-party entry point ``uninvited`` that registers the method ``uninvited``."""
    import importlib.metadata

    real = list(importlib.metadata.entry_points(group="pcfbench"))
    mod = _plugin_module("pcfb_uninvited", register_methods=_registering("uninvited"))
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    ep = importlib.metadata.EntryPoint("uninvited", mod.__name__, "pcfbench")
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: [*real, ep] if group == "pcfbench" else [])


def test_tests_load_no_third_party_plugin_unless_they_ask(monkeypatch):
    _uninvited(monkeypatch)
    assert os.environ["PCFBENCH_PLUGINS"] == ""  # conftest: the built-ins only
    plugins = load_plugins()
    assert "uninvited" not in plugins.methods and "uninvited" not in plugins.info
    assert "copy-last" in plugins.methods


@pytest.mark.third_party_plugins("uninvited")
def test_a_test_marked_third_party_plugins_loads_the_ones_it_names(monkeypatch):
    _uninvited(monkeypatch)
    assert load_plugins().methods.entries["uninvited"].plugin == "uninvited"


@pytest.mark.third_party_plugins
def test_a_test_marked_third_party_plugins_without_names_loads_every_one(monkeypatch):
    _uninvited(monkeypatch)
    assert "PCFBENCH_PLUGINS" not in os.environ
    assert "uninvited" in load_plugins().methods
