"""The docs are part of the product: the README's plugin runs, docs/metrics.md is in sync, links resolve."""

from __future__ import annotations

import ast
import importlib
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import pcfbench
from pcfbench import docs
from pcfbench.errors import PcfbenchError
from pcfbench.metrics.base import Metric
from pcfbench.options import describe_options
from pcfbench.plugins import load_plugins

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
DOCS = REPO / "docs"
VENV_BIN = Path(sys.executable).parent


def _blocks(path: Path, lang: str) -> list[str]:
    """The fenced code blocks of ``path`` in language ``lang``, in order."""
    return re.findall(rf"^```{lang}\n(.*?)^```", path.read_text(encoding="utf-8"), re.S | re.M)


def _readme_plugin() -> str:
    (code,) = _blocks(README, "python")  # the README has exactly one Python example
    return code


def _import_source(tmp_path: Path, module: str, source: str):
    (tmp_path / f"{module}.py").write_text(source, encoding="utf-8")
    sys.path.insert(0, str(tmp_path))
    try:
        return importlib.import_module(module)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop(module, None)


# -- the README ------------------------------------------------------------------------------

def test_readme_keeps_the_two_commands_and_is_short():
    first_sh = _blocks(README, "sh")[0].splitlines()
    assert first_sh == [  # .ci/run executes the second line; a new user runs the first
        "bash .ci/setup && .venv/bin/pcfbench run",
        'bash .ci/setup test && bash .ci/test -m "slow or not slow"',
    ]
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 160


def test_readme_plugin_imports_only_pcfbench():
    tree = ast.parse(_readme_plugin())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add(node.module)
    assert "pcfbench" in imported
    assert {name.split(".")[0] for name in imported} <= {"pcfbench", "dataclasses"}, imported
    assert not any(name.startswith("pcfbench.") for name in imported), imported  # the public API only


def test_readme_plugin_registers_and_passes_check_method(tmp_path):
    module = _import_source(tmp_path, "readme_plugin", _readme_plugin())
    plugins = load_plugins()
    plugins.add_plugin(module, "readme-plugin")
    info = plugins.info["readme-plugin"]
    assert info.error is None and info.registered == {"methods": ["lifted-copy"]}
    method_cls = plugins.methods.get("lifted-copy")
    assert pcfbench.testing.check_method(method_cls()) is not None
    (dz,) = describe_options(method_cls.Options, "lifted-copy")  # what `ls methods --options` prints
    assert (dz.name, dz.default, dz.help) == ("dz", 0.0, "height added to every point (m)")

    # by hand: every future sweep is the t=0 sweep with dz added to z, nothing else moved
    lifted = method_cls(method_cls.Options(dz=0.5))
    forecast = pcfbench.testing.check_method(lifted)
    sample, _ = pcfbench.testing.toy_sample("kitti-1s")
    last = sample.past_points_ref[-1]
    assert len(forecast.points_ref) == sample.num_future == 5
    for pts in forecast.points_ref:
        assert pts.dtype == np.float32 and pts.shape == last.shape
        np.testing.assert_array_equal(pts[:, :2], last[:, :2])
        np.testing.assert_array_equal(pts[:, 2], last[:, 2] + np.float32(0.5))


@pytest.fixture(scope="module")
def readme_distribution(tmp_path_factory):
    """The README's plugin installed as the README says: its module and entry point, nothing else."""
    code = _readme_plugin()
    header = code.splitlines()[0]
    m = re.fullmatch(r'# (\w+)\.py\s+--\s+pyproject\.toml: \[project\.entry-points\.pcfbench\] ([\w-]+) = "(\w+)"', header)
    assert m, f"the README's plugin example should start with its file name and entry point, got {header!r}"
    filename, ep_name, ep_module = m.groups()
    assert filename == ep_module
    src = tmp_path_factory.mktemp("readme-src")
    (src / f"{filename}.py").write_text(code, encoding="utf-8")
    (src / "pyproject.toml").write_text(textwrap.dedent(f"""
        [build-system]
        requires = ["setuptools"]
        build-backend = "setuptools.build_meta"
        [project]
        name = "readme-plugin"
        version = "0.0.1"
        [project.entry-points.pcfbench]
        {ep_name} = "{ep_module}"
        [tool.setuptools]
        py-modules = ["{filename}"]
    """))
    site = tmp_path_factory.mktemp("readme-site")
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                    "--target", str(site), str(src)], check=True, capture_output=True)
    return site


def _cli(args, site):
    env = {**os.environ, "PYTHONPATH": str(site)}
    return subprocess.run([str(VENV_BIN / "pcfbench"), *args], capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.third_party_plugins
def test_readme_plugin_installed_appears_on_the_leaderboard(readme_distribution, tiny_kitti, tmp_path):
    listing = _cli(["ls", "methods"], readme_distribution)
    assert listing.returncode == 0, listing.stderr
    assert "lifted-copy" in listing.stdout
    rep = tmp_path / "rep"
    run = _cli(["run", "--dataset", f"kitti={tiny_kitti}", "--setting", "kitti-1s", "-m", "copy-last",
                "-m", "lifted-copy", "-m", "lifted-copy:dz=0.5", "--reports", str(rep), "-q"], readme_distribution)
    assert run.returncode == 0, run.stderr
    assert "lifted-copy" in (rep / "leaderboard.md").read_text()
    board = pd.read_csv(rep / "leaderboard.csv")
    label = "variant" if "variant" in board.columns else "method"  # a row per method and option set
    board = board.set_index(label)
    (lifted_dz,) = [name for name in board.index if name.startswith("lifted-copy") and "dz=0.5" in name]
    assert set(board.index) == {"copy-last", "lifted-copy", lifted_dz}
    assert (board.samples == 6).all() and (board.failed == 0).all()
    # dz=0 is copy-last (z = -0.0 turns +0.0, which can move an angle-space tie by an ulp) ...
    metrics = [c for c in board.columns if c in load_plugins().metrics]
    assert metrics and board.loc["copy-last", "chamfer"] == board.loc["lifted-copy", "chamfer"]
    np.testing.assert_allclose(board.loc["lifted-copy", metrics].astype(float),
                               board.loc["copy-last", metrics].astype(float), rtol=1e-9)
    # ... and dz=0.5 is a different forecast
    assert board.loc[lifted_dz, "chamfer"] > board.loc["copy-last", "chamfer"]


# -- docs/plugins.md -------------------------------------------------------------------------

def test_plugins_tutorial_method_is_the_readme_example():
    tutorial = _blocks(DOCS / "plugins.md", "python")[0]
    readme = _readme_plugin().split("\n", 1)[1]  # without the file-name comment
    assert tutorial == readme


def test_plugins_tutorial_dataset_passes_check_adapter(tmp_path):
    blocks = _blocks(DOCS / "plugins.md", "python")
    module_src = next(b for b in blocks if "class NpyFolder" in b)
    writer_src = next(b for b in blocks if "check_adapter" in b)
    module = _import_source(tmp_path, "npy_dataset", module_src)
    root = tmp_path / "npy"
    writer_src = writer_src.replace('"/tmp/npy', f'"{root}').replace("from npy_dataset import NpyFolder\n", "")
    exec(compile(writer_src, "docs/plugins.md", "exec"), {"NpyFolder": module.NpyFolder})  # writes and checks
    plugins = load_plugins()
    plugins.add_plugin(module, "npy-dataset")
    assert plugins.info["npy-dataset"].registered == {"datasets": ["npy-folder"]}
    adapter = plugins.datasets.get("npy-folder")(root)
    assert adapter.sequence_names("test") == ["seq-a"] and len(adapter.sequence("seq-a")) == 60
    assert module.NpyFolder.detect(root) and not module.NpyFolder.detect(tmp_path)
    np.save(root / "test" / "seq-a" / "poses.npy", np.zeros((3, 4, 4)))
    with pytest.raises(PcfbenchError, match=r"poses\.npy has shape \(3, 4, 4\), expected \(60, 4, 4\)"):
        adapter.sequence("seq-a")


# -- docs/metrics.md -------------------------------------------------------------------------

def test_metrics_doc_is_in_sync_with_the_registry():
    assert (DOCS / "metrics.md").read_text(encoding="utf-8") == docs.metrics_markdown(), (
        "docs/metrics.md is out of date: run .venv/bin/python -m pcfbench.docs metrics --out docs/metrics.md"
    )
    assert docs.main(["metrics", "--out", str(DOCS / "metrics.md"), "--check"]) == 0


def test_performance_doc_is_the_cost_benchmarks_measurements():
    from pcfbench import costtable

    data = costtable.load(DOCS / "performance-costs.json")
    assert (DOCS / "performance.md").read_text(encoding="utf-8") == costtable.markdown(data), (
        "docs/performance.md is out of date: run .venv/bin/python -m pcfbench.docs performance --out docs/performance.md"
    )
    assert docs.main(["performance", "--data", str(DOCS / "performance-costs.json"),
                      "--out", str(DOCS / "performance.md"), "--check"]) == 0


def test_the_cost_table_projects_a_split_onto_cores(tmp_path):
    from pcfbench import costtable

    data = {"measured": {"date": "2026-11-29", "commit": "abc", "machine": "2 cores", "load": "1.0"},
            "split": {"name": "a split", "samples": {"kitti-1s": 6000, "kitti-3s": 1000}},
            "sizes": [{"name": "small", "description": "a small street"}],
            "costs": [{"method": "a", "size": "small", "samples": 4, "gt_points": 10, "load_s": 0.5, "forecast_s": 1.0,
                       "metrics_s": 1.5, "alone_s": 3.0},
                      {"method": "b", "size": "small", "samples": 4, "gt_points": 10, "load_s": 0.5, "forecast_s": 0.25,
                       "metrics_s": 0.25, "alone_s": 1.25}],
            "ratios": [{"what": "suite", "baseline": "floor", "ratio": 1.234, "bar": "<= 1.5", "rounds": 21, "where": "x"}]}
    text = costtable.markdown(data)
    # a: 3 s a sample x 7,000 samples = 5.8 h on one core, 21.9 min on 16, 164 s on 128
    assert "| `a` | 0.500 | 1.00 | 1.50 | 3.00 | 5.8 h | 22 min | 2.7 min |" in text
    # both in one pass: the sample loaded once, 0.5 + (1 + 0.25) + (1.5 + 0.25) = 3.5 s
    assert "| all 2 in one pass | 0.500 | 1.25 | 1.75 | 3.50 | 6.8 h | 26 min | 3.2 min |" in text
    # b's share of the pass (1.0 s) is less than b alone (1.25 s, which its row projects): it shares
    assert "| `b` | 0.500 | 0.250 | 0.250 | 1.25 | 2.4 h | 9.1 min | 1.1 min |" in text
    # one run each: 3 + 1.25 = 4.25 s a sample
    assert "| all 2, one run each | | | | 4.25 | 8.3 h | 31 min | 3.9 min |" in text
    assert "| suite | floor | 1.23 | <= 1.5 | 21 | x |" in text
    (tmp_path / "bad.json").write_text('{"measured": {}}')
    with pytest.raises(PcfbenchError, match="bad.json: no split, sizes, costs: not the cost benchmark's output"):
        costtable.load(tmp_path / "bad.json")
    old = {**data, "costs": [{k: v for k, v in c.items() if k != "alone_s"} for c in data["costs"]]}
    (tmp_path / "old.json").write_text(json.dumps(old))
    with pytest.raises(PcfbenchError, match=r"old.json: costs\[0\] has no alone_s: written by an older cost benchmark"):
        costtable.load(tmp_path / "old.json")


def test_metrics_doc_lists_every_metric_with_its_changelog():
    text = docs.metrics_markdown()
    registry = load_plugins().metrics
    for name in registry.names():
        metric = registry.get(name)
        assert f"\n## {name}\n\n- version: {metric.version}\n- unit: {metric.unit}\n" in text
    assert "- 2026-11-21, version 1: first version. CD of docs/protocol.md section 4" in text


def test_a_new_metric_or_version_changes_the_page_and_needs_a_changelog_line(tmp_path):
    new = Metric(name="toy", version="2", fn=lambda ctx: 0.0, description="a toy metric", unit="m",
                 empty_policy="never skipped", reference="nowhere", higher_is_better=True)
    log = tmp_path / "CHANGELOG.md"
    log.write_text("# log\n\n## 2026-01-01\n\n- `toy` 1: first version.\n")
    with pytest.raises(PcfbenchError, match="no line for metric version.*toy 2"):
        docs.metrics_markdown([new], docs.read_changelog(log))
    log.write_text("# log\n\n## 2026-01-01\n\n- `toy` 1: first version.\n\n## 2026-02-01\n\n- `toy` 2: now zero.\n")
    text = docs.metrics_markdown([new], docs.read_changelog(log))
    assert "| [`toy`](#toy) | 2 | m | higher | either | a toy metric |" in text
    assert "- better: higher (higher_is_better = True)" in text
    assert "- 2026-01-01, version 1: first version.\n- 2026-02-01, version 2: now zero." in text
    log.write_text("## 2026-01-01\n\n- toy 1 first version\n")
    with pytest.raises(PcfbenchError, match=r"CHANGELOG\.md:3: expected"):
        docs.read_changelog(log)


# -- links and citations -----------------------------------------------------------------------

_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _anchors(path: Path) -> set[str]:
    """GitHub's anchors of the Markdown headings of ``path`` (code blocks left out)."""
    text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.S | re.M)
    return {docs._anchor(m.group(1).strip()) for m in re.finditer(r"^#{1,6} (.+)$", text, re.M)}


def test_every_relative_link_resolves():
    pages = [README, *sorted(DOCS.glob("*.md")), *sorted((DOCS / "journal").glob("*.md")),
             REPO / "datasets" / "synthetic" / "CHANGELOG.md"]
    assert len(pages) >= 8
    checked = 0
    for page in pages:
        for target in _LINK.findall(page.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target):
                continue  # http(s), mailto: not checked offline
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            assert dest.exists(), f"{page.relative_to(REPO)}: link {target!r} points at a missing file"
            if anchor and dest.suffix == ".md":
                assert anchor in _anchors(dest), f"{page.relative_to(REPO)}: no heading #{anchor} in {dest.name}"
            checked += 1
    assert checked >= 20


def test_code_cites_the_protocol_in_the_repository():
    stale = [f"{p.relative_to(REPO)}" for folder in ("bench", "methods", "datasets") for p in (REPO / folder).rglob("*")
             if p.suffix in (".py", ".md", ".toml") and "PROTOCOL.md" in p.read_text(encoding="utf-8")]
    assert not stale, f"cite docs/protocol.md, not PROTOCOL.md: {stale}"


def test_every_world_physics_version_has_a_changelog_entry():
    from pcfbench.datasets.synthetic.realism import REALISM

    text = (REPO / "datasets" / "synthetic" / "CHANGELOG.md").read_text(encoding="utf-8")
    missing = [v for v in range(1, REALISM.version + 1) if f"\n- physics {v}: " not in text]
    assert not missing, f"datasets/synthetic/CHANGELOG.md has no entry for physics {missing}"
