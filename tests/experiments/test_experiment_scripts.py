"""The scripts of docs/experiments/ run: each imports the package's internals, so a rename that
breaks one fails here, not on the next person who reproduces a measurement with it.

Each script is imported as a module (its top-level imports resolved) and its command line asked
for ``--help``; then one path of it runs on the smallest input there is. Paths that compile the
casters' kernels from cold or simulate a town are marked slow.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[2] / "docs" / "experiments"
SCRIPTS = sorted(p.name for p in EXPERIMENTS.glob("*.py"))


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"experiment_{Path(name).stem}", EXPERIMENTS / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _main(module, argv: list[str], monkeypatch) -> str:
    """Run ``module.main()`` with ``argv``; its stdout."""
    monkeypatch.setattr(sys, "argv", [module.__file__, *argv])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        module.main()
    return out.getvalue()


def test_the_folder_holds_the_scripts_tested_here():
    assert SCRIPTS == ["copilot4d_gpu.py", "copilot4d_gpu_stage.py", "copilot4d_replay.py", "copilot4d_token_table.py",
                       "realism_far_views.py", "realism_yard_trees_inside.py"], (
        "a script added to docs/experiments/ needs a smoke test here (or a journal entry and no script)")
    assert sorted(p.name for p in EXPERIMENTS.glob("*.sh")) == ["copilot4d_gpu.sh"], (
        "a script added to docs/experiments/ needs a smoke test here (or a journal entry and no script)")


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_imports_and_prints_its_usage(name, monkeypatch):
    module = _load(name)
    with pytest.raises(SystemExit) as exit_:
        _main(module, ["--help"], monkeypatch)
    assert exit_.value.code == 0


def test_copilot4d_gpu_sh_parses_and_runs_the_script_here():
    sh = EXPERIMENTS / "copilot4d_gpu.sh"
    subprocess.run(["bash", "-n", str(sh)], check=True)
    text = sh.read_text(encoding="utf-8")
    assert "docs/experiments/copilot4d_gpu.py" in text
    for folder in ("bench", "methods", "datasets"):  # the package it assembles, as pyproject.toml maps it
        assert f"cp -r {folder} " in text and (EXPERIMENTS.parent.parent / folder).is_dir()


def test_copilot4d_replay_renders_replayed_tokens_at_the_future_poses():
    import pcfbench
    from pcfbench.errors import PcfbenchError

    module = _load("copilot4d_replay.py")
    sample, _ = pcfbench.testing.toy_sample("kitti-1s")
    codes = np.zeros((sample.num_future, 4, 4), np.int16)
    tokens, T_s0_future, T_s0_ref = module.Replay(None, {sample.sample_id: codes}).forecast_tokens(sample)
    assert len(tokens) == sample.num_future and tokens[0].dtype == __import__("torch").int64
    assert T_s0_future.shape == (sample.num_future, 4, 4) and T_s0_ref.shape == (4, 4)
    with pytest.raises(PcfbenchError, match="replayed future frames"):
        module.Replay(None, {sample.sample_id: codes[:2]}).forecast_tokens(sample)


def test_copilot4d_token_table_learns_a_code_that_always_follows():
    """Two windows whose every future token is its t=0 code plus one: the table learns that change
    with share 1 and forecasts it above any bar, right on every token; a key seen fewer than
    MIN_COUNT times keeps the t=0 code."""
    module = _load("copilot4d_token_table.py")
    grid = module.Grid(10.0, 4)  # 4 x 4 tokens of 5 m; every token within 20 m of the sensor
    c0 = np.arange(16, dtype=np.int16).reshape(4, 4)
    tokens = np.stack([c0] * 5 + [c0 + 1] * 5)[None].repeat(2, 0)  # (2 windows, 10 frames, 4, 4)
    w = {"tokens": tokens, "poses": np.broadcast_to(np.eye(4, dtype=np.float32), (2, 10, 4, 4)).copy(),
         "stride": np.array([2, 2])}
    table = module.fit(grid, w)
    assert len(table) == 16 and all(v[1] == 1.0 and v[2] == 10 for v in table.values())
    assert np.array_equal(module.forecast(grid, table, c0, np.eye(4), 0.9), c0 + 1)
    assert np.array_equal(module.forecast(grid, table, c0 + 100, np.eye(4), 0.0), c0 + 100)  # unseen keys
    rare = module.fit(grid, {**w, "tokens": tokens[:, :6], "poses": w["poses"][:, :6]})  # 2 sightings a key
    assert np.array_equal(module.forecast(grid, rare, c0, np.eye(4), 0.0), c0)
    lines = module.token_stats(grid, table, w, bars=(0.5,))
    assert lines[0].startswith("bar 0.5, stride 2, all: moved 100.0 %, precision 100.0 %, changes right 100.0 %, "
                               "accuracy 100.0 % (copying 0.0 %)")
    assert lines[1].startswith("bar 0.5, stride 2, 0-20 m: moved 100.0 %")


def test_realism_far_views_why_on_tiny_kitti(tiny_kitti, monkeypatch):
    out = _main(_load("realism_far_views.py"), ["why", "--dataset", f"kitti={tiny_kitti}", "--split", "test"],
                monkeypatch)
    assert "== kitti test: far points" in out and "why: {" in out


@pytest.mark.slow
def test_realism_far_views_split_on_tiny_kitti(tiny_kitti, monkeypatch):
    out = _main(_load("realism_far_views.py"), ["split", "--dataset", f"kitti={tiny_kitti}", "--split", "test"],
                monkeypatch)
    assert "== kitti test all: 6 samples, 30 sweeps" in out
    rows = [line.split() for line in out.splitlines() if line.startswith(("copy-last", "raycast-"))]
    assert [r[0] for r in rows] == ["copy-last", "raycast-4docc", "raycast-freespace"]
    for r in rows:  # chamfer_nf = far + rest + true -> forecast
        assert float(r[1]) == pytest.approx(float(r[3]) + float(r[5]) + float(r[7]), abs=2e-3)


def test_realism_far_views_probe_generates_a_folder(tmp_path, monkeypatch):
    module = _load("realism_far_views.py")
    seen = {}
    monkeypatch.setattr("pcfbench.datasets.synthetic.generate.generate_domain",
                        lambda d, out, **kw: seen.update(domain=d, out=out, **kw) or {"seconds": 0.0})
    out = _main(module, ["probe", str(tmp_path / "probe"), "--yard-trees", "0", "--style", '{"fence_prob": 1.0}'],
                monkeypatch)
    assert "read it as synthetic-town-realistic=" in out
    assert seen["domain"].realism.yard_trees_per_100m == 0 and seen["domain"].style.fence_prob == 1.0
    assert seen["splits"] == ("test",)


@pytest.mark.slow
def test_realism_yard_trees_inside_counts_one_town():
    module = _load("realism_yard_trees_inside.py")
    total, inside, above = module.count(["06"])
    assert total > 0 and 0 <= above <= inside <= total


@pytest.mark.slow
def test_copilot4d_gpu_smoke_on_the_cpu(tmp_path, monkeypatch):
    import json

    _main(_load("copilot4d_gpu.py"), ["--smoke", "--parts", "train_step", "--inputs", str(tmp_path / "none"),
                                      "--out", str(tmp_path / "out")], monkeypatch)
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert results["env"]["smoke"] is True and "paper_train_step_b1" in results
    assert results["paper_train_step_b1"]["median_step_s"] > 0
