"""Issue 45: a sweep's grid has a cap on its cells, refused before its variants are made, and
--dry-run plans (and prints) its cells one at a time."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from pcfbench.errors import PcfbenchError
from pcfbench.experiments import sweep
from pcfbench.experiments.sweep import MAX_CELLS, count_cells, iter_plan, load_experiment, plan
from pcfbench.plugins import load_plugins


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "exp.toml"
    p.write_text(text)
    return p


def _grid(tmp_path: Path, root: Path, a: int, b: int, extra: str = "", settings: str = '["kitti-1s"]') -> Path:
    voxels = ", ".join(f"{0.1 + 0.01 * i:.2f}" for i in range(a))
    cones = ", ".join(f"{0.5 + 0.01 * i:.2f}" for i in range(b))
    return _write(tmp_path, f"""
name = "big"
datasets = ["kitti={root}"]
settings = {settings}
{extra}

[[methods]]
name = "raycast-voxel"
grid = {{ voxel = [{voxels}], cone_factor = [{cones}] }}

[[methods]]
name = "copy-last"
""")


def test_a_grid_over_the_cap_is_refused_before_any_variant_is_made(tmp_path, tiny_kitti, monkeypatch):
    made = []
    real = sweep.resolve_method
    monkeypatch.setattr(sweep, "resolve_method", lambda *a, **k: made.append(a) or real(*a, **k))
    path = _grid(tmp_path, tiny_kitti, 100, 100)
    with pytest.raises(PcfbenchError) as err:
        load_experiment(path, load_plugins())
    msg = str(err.value)
    assert msg.startswith(f"experiment {path}: max_cells: the grid has 10,001 cells")
    assert f"over the cap of {MAX_CELLS:,}" in msg and "max_cells = 10001" in msg and "--max-cells 10001" in msg
    assert made == []  # counted, not expanded


def test_the_cap_counts_datasets_settings_and_can_be_raised(tmp_path, tiny_kitti):
    plugins = load_plugins()
    # 26 variants x 2 settings = 52 cells: within the default cap, over a cap of 40
    two = '["kitti-1s", "kitti-3s"]'
    path = _grid(tmp_path, tiny_kitti, 5, 5, extra='policy = "every-frame"', settings=two)
    exp = load_experiment(path, plugins)
    assert count_cells(exp, plugins) == 52 == len(plan(exp, plugins=plugins))
    with pytest.raises(PcfbenchError, match=r"max_cells: the grid has 52 cells \(26 method variants x datasets"):
        load_experiment(path, plugins, max_cells=40)
    capped = _grid(tmp_path, tiny_kitti, 5, 5, extra='policy = "every-frame"\nmax_cells = 40', settings=two)
    with pytest.raises(PcfbenchError, match="over the cap of 40"):
        load_experiment(capped, plugins)
    assert count_cells(load_experiment(capped, plugins, max_cells=60), plugins) == 52  # the option wins
    raised = _grid(tmp_path, tiny_kitti, 40, 30, extra="max_cells = 2000")
    assert count_cells(load_experiment(raised, plugins), plugins) == 1201
    for bad in ("0", "true", '"many"'):
        with pytest.raises(PcfbenchError, match="max_cells: expected a positive integer"):
            load_experiment(_grid(tmp_path, tiny_kitti, 2, 2, extra=f"max_cells = {bad}"), plugins)


def test_the_plan_is_made_one_cell_at_a_time(tmp_path, tiny_kitti, monkeypatch):
    plugins = load_plugins()
    exp = load_experiment(_grid(tmp_path, tiny_kitti, 5, 5), plugins)
    asked = []
    real = sweep._checkpoints
    monkeypatch.setattr(sweep, "_checkpoints", lambda exp, v, *a: asked.append(v) or real(exp, v, *a))
    cells = iter_plan(exp, plugins=plugins, progress=False)
    first = next(cells)
    assert first.method == "raycast-voxel" and len(asked) == 1  # the other 25 variants not yet planned
    assert len([first, *cells]) == count_cells(exp, plugins) == 26


def test_dry_run_prints_the_count_and_refuses_an_oversized_grid(tmp_path, tiny_kitti):
    from pcfbench.cli import build_cli

    path = _grid(tmp_path, tiny_kitti, 3, 2)
    out = CliRunner().invoke(build_cli(), ["sweep", str(path), "--dry-run", "-q", "--reports", str(tmp_path / "r")])
    assert out.exit_code == 0, out.output
    assert out.output.startswith("cell 1/7: raycast-voxel") and "cell 7/7: copy-last" in out.output
    refused = CliRunner().invoke(build_cli(), ["sweep", str(path), "--dry-run", "--max-cells", "5"])
    assert refused.exit_code != 0 and "the grid has 7 cells" in refused.output and "over the cap of 5" in refused.output
