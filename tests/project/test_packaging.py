"""The distribution installs one import package, ``pcfbench``, and nothing else at the top level.

The repository keeps its folders (bench/, methods/, datasets/); pyproject.toml maps them to
``pcfbench``, ``pcfbench.methods`` and ``pcfbench.datasets``. A generic top-level name such as
``datasets`` would shadow (or be shadowed by) Hugging Face ``datasets``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = {"pcfbench": "bench", "pcfbench.methods": "methods", "pcfbench.datasets": "datasets"}


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _package_folders() -> dict[str, Path]:
    """Every import package the repository holds: dotted name -> folder."""
    out = {}
    for top, folder in FOLDERS.items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            if "__pycache__" in init.parts:
                continue
            rel = init.parent.relative_to(base)
            out[".".join((top, *rel.parts))] = init.parent
    return out


def test_pyproject_lists_every_package_and_maps_the_folders():
    tool = _pyproject()["tool"]["setuptools"]
    assert tool["package-dir"] == FOLDERS
    assert sorted(tool["packages"]) == sorted(_package_folders()), (
        "pyproject.toml [tool.setuptools] packages must list every folder with an __init__.py "
        "(a package left out is missing from the wheel)"
    )
    assert all(p == "pcfbench" or p.startswith("pcfbench.") for p in tool["packages"])


def test_entry_points_and_script_use_the_one_package():
    project = _pyproject()["project"]
    assert project["scripts"]["pcfbench"].startswith("pcfbench.")
    for name, target in project["entry-points"]["pcfbench"].items():
        assert target.startswith("pcfbench."), (name, target)


def test_no_module_imports_the_old_top_level_names():
    bad = []
    for folder in FOLDERS.values():
        for path in (ROOT / folder).rglob("*.py"):
            for lineno, line in enumerate(path.read_text().splitlines(), 1):
                stripped = line.strip()
                for old in ("bench", "methods", "datasets"):
                    if stripped.startswith((f"from {old}.", f"from {old} ", f"import {old}.")) or stripped == f"import {old}":
                        bad.append(f"{path.relative_to(ROOT)}:{lineno}: {stripped}")
    assert not bad, "\n".join(bad)


def test_installed_package_resolves_outside_the_checkout(tmp_path):
    """From another directory, the editable install gives pcfbench and no generic top-level names."""
    code = textwrap.dedent(
        """
        import importlib.util, json, pcfbench, pcfbench.methods, pcfbench.datasets
        print(json.dumps({
            "pcfbench": pcfbench.__file__,
            "methods": pcfbench.methods.__file__,
            "datasets": pcfbench.datasets.__file__,
            "top": {n: importlib.util.find_spec(n) is not None for n in ("bench", "methods", "datasets")},
        }))
        """
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    import json

    info = json.loads(out.stdout)
    package = Path(info["pcfbench"]).parent
    if package == ROOT / "bench":  # editable: the folders are mapped
        assert Path(info["methods"]).parent == ROOT / "methods"
        assert Path(info["datasets"]).parent == ROOT / "datasets"
    else:  # a wheel (CI): one tree in an environment's site-packages, not the source folders
        assert package.parent.name == "site-packages" and package.name == "pcfbench", package
        assert Path(info["methods"]).parent == package / "methods"
        assert Path(info["datasets"]).parent == package / "datasets"
    assert info["top"] == {"bench": False, "methods": False, "datasets": False}
    version = subprocess.run(
        [sys.executable, "-m", "pcfbench", "--version"], cwd=tmp_path, capture_output=True, text=True, check=True
    )
    assert "pcfbench" in version.stdout


def test_the_tests_cannot_import_the_source_folders():
    """However pytest was started (`python -m pytest` from the checkout puts its root on
    sys.path), the suite sees the installed package only: conftest.py drops the root."""
    import importlib.util

    assert importlib.util.find_spec("bench") is None
    assert importlib.util.find_spec("methods") is None
    spec = importlib.util.find_spec("datasets")  # may be Hugging Face's, never ours
    assert spec is None or ROOT not in Path(spec.origin or "").parents
    assert all(Path(p or os.getcwd()).resolve() != ROOT for p in sys.path), sys.path


def _source_files() -> list[tuple[str, Path]]:
    """(package, file) for every tracked file of the package folders (every file there when
    this is not a git checkout)."""
    out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", *FOLDERS.values()], capture_output=True)
    if out.returncode == 0 and out.stdout:
        paths = [ROOT / p for p in out.stdout.decode().split("\0") if p]
    else:
        paths = [p for f in FOLDERS.values() for p in (ROOT / f).rglob("*")
                 if p.is_file() and "__pycache__" not in p.parts]
    folder_to_package = {f: p for p, f in FOLDERS.items()}
    return [(folder_to_package[p.relative_to(ROOT).parts[0]], p) for p in paths]


def _build_wheel(out: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(ROOT)]
    subprocess.run(cmd, check=True, capture_output=True, text=True, env={**os.environ, "PIP_NO_INPUT": "1"})
    (wheel,) = out.glob("pcfbench-*.whl")
    return wheel


def _fake_datasets_distribution(tmp: Path) -> Path:
    """A distribution with a top-level ``datasets`` package, as Hugging Face's has."""
    src = tmp / "fake-datasets"
    (src / "datasets").mkdir(parents=True)
    (src / "datasets" / "__init__.py").write_text("WHO = 'the other datasets'\n")
    (src / "pyproject.toml").write_text(
        textwrap.dedent(
            """
            [build-system]
            requires = ["setuptools>=61"]
            build-backend = "setuptools.build_meta"

            [project]
            name = "fake-hf-datasets"
            version = "1.0"

            [tool.setuptools]
            packages = ["datasets"]
            """
        )
    )
    return src


@pytest.mark.slow
def test_wheel_has_one_top_level_name_and_installs_beside_a_datasets_package(tmp_path):
    wheel = _build_wheel(tmp_path / "dist")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        top_level = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
        assert top_level == {"pcfbench"}, top_level
        for package in _package_folders():
            assert f"{package.replace('.', '/')}/__init__.py" in names, f"{package} missing from the wheel"
        top_txt = [n for n in names if n.endswith(".dist-info/top_level.txt")]
        for t in top_txt:
            assert zf.read(t).decode().split() == ["pcfbench"]
        # every file of the package folders is in the wheel: the modules and every resource
        # the code reads (protocol and presets TOML, nuScenes' split list, the metric
        # changelog, the shipped checkpoints: docs/training.md)
        missing = []
        for package, path in _source_files():
            rel = path.relative_to(ROOT / FOLDERS[package]).as_posix()
            if f"{package.replace('.', '/')}/{rel}" not in names:
                missing.append(path.relative_to(ROOT).as_posix())
        assert not missing, f"in the package folders but not in the wheel (pyproject.toml package-data): {missing}"

    # A fresh environment: the wheel and a distribution with a top-level ``datasets`` package,
    # both installed there; the project's dependencies come from this test's environment as a
    # plain path entry (no .pth processing there, so the editable install stays inactive).
    env_dir = tmp_path / "fresh"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True)
    fresh_py = env_dir / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(fresh_py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    )
    deps = Path(
        subprocess.run(
            [sys.executable, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    )
    fake = _fake_datasets_distribution(tmp_path)
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", str(site),
         str(wheel), str(fake)],
        check=True, capture_output=True, text=True,
    )
    (site / "zz-project-deps.pth").write_text(f"{deps}\n")
    check = textwrap.dedent(
        """
        import datasets, pcfbench, pcfbench.datasets, pcfbench.methods
        from pcfbench.plugins import get_plugins
        assert datasets.WHO == "the other datasets", datasets.__file__
        assert pcfbench.__file__.startswith(SITE), pcfbench.__file__
        assert pcfbench.datasets.__file__.startswith(SITE), pcfbench.datasets.__file__
        plugins = get_plugins()
        assert "synthetic-town" in plugins.datasets and "copy-last" in plugins.methods
        errors = {n: i.error for n, i in plugins.info.items() if i.error}
        assert not errors, errors
        plugins.datasets.get("kitti"); plugins.methods.get("raycast-voxel")
        # every resource the code reads, read from the wheel alone
        from pcfbench.datasets.nuscenes import official_splits
        from pcfbench.docs import read_changelog
        from pcfbench.method import resolve_method
        from pcfbench.protocol import load_protocol
        from pcfbench.reporting.tables import load_presets
        from pcfbench.training import shipped_dir
        assert len(official_splits()["train"]) == 700
        assert load_protocol().settings and load_presets() and read_changelog()
        shipped = shipped_dir(resolve_method("copilot4d-token-copy"), "synthetic-town-realistic", "train")
        assert shipped.is_relative_to(SITE) and (shipped / "manifest.json").is_file(), shipped
        print("ok", datasets.__file__, pcfbench.__file__)
        """
    ).replace("SITE", repr(str(site)))
    out = subprocess.run([str(fresh_py), "-c", check], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok")
    cli = subprocess.run([str(fresh_py), "-m", "pcfbench", "ls", "methods"], cwd=tmp_path, capture_output=True, text=True)
    assert cli.returncode == 0, cli.stderr
    assert "copy-last" in cli.stdout
