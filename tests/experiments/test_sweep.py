"""pcfbench sweep: experiment files, the resumable grid and the ablation table."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

import pcfbench
from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.method import Method, resolve_method
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import get_plugins, load_plugins
from pcfbench.store.cells import Cell
from pcfbench.experiments.sweep import EXPERIMENT_KEYS, METHOD_KEYS, TABLE_KEYS, load_experiment, plan, run_sweep
from tests_helpers import write_kitti_tree

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "docs" / "experiments"
RAYCAST = EXAMPLES / "raycast-voxel-size.toml"
PCFBENCH = str(Path(sys.executable).parent / "pcfbench")


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> Path:
    """A small synthetic-town (one 56-sweep test sequence: 38 kitti-1s and 2 kitti-3s samples)."""
    from pcfbench.datasets.synthetic.domains import get_domain
    from pcfbench.datasets.synthetic.generate import generate_domain

    d = get_domain("synthetic-town")
    sensor = dataclasses.replace(d.sensor, azimuth_steps=240, max_range_m=60.0)
    dom = dataclasses.replace(d, sensor=sensor, splits={"train": (("00", 4),), "test": (("05", 56),)})
    root = tmp_path_factory.mktemp("town")
    generate_domain(dom, root, progress=False, splits=("test",))
    return root


def _cli(args, env=None):
    from pcfbench.cli import build_cli

    return CliRunner().invoke(build_cli(), args, env=env)


def _write(tmp_path: Path, text: str, name: str = "exp.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


# -- the example ray-casting experiment --------------------------------------------------------
def test_example_experiment_writes_the_ablation_table_and_a_rerun_does_no_work(town, tmp_path, monkeypatch):
    store, reports = tmp_path / "store", tmp_path / "reports"
    monkeypatch.setenv("PCFBENCH_DATASET_SYNTHETIC_TOWN", str(town))
    env = {"PCFBENCH_DATASET_SYNTHETIC_TOWN": str(town)}
    res = _cli(["sweep", str(RAYCAST), "--limit", "2", "--store", str(store), "--reports", str(reports), "-q"], env)
    assert res.exit_code == 0, res.output
    for i in range(1, 7):
        assert f"cell {i}/6: " in res.output
    assert "cell 3/6: raycast-voxel (voxel=0.4) | synthetic-town:test | kitti-1s limit=2" in res.output
    # a --limit sweep is partial: its tables and figures go to reports/partial/, in the same layout
    assert sorted(p.name for p in reports.iterdir()) == ["partial"]
    out = reports / "partial" / "sweeps"
    assert sorted(p.name for p in out.iterdir()) == [f"raycast-voxel-size.{e}" for e in ("csv", "html", "md", "tex")]

    # one row per variant in the experiment's order, per setting; the reference row first
    csv = pd.read_csv(out / "raycast-voxel-size.csv")
    assert list(csv["setting"]) == ["kitti-1s"] * 3 + ["kitti-3s"] * 3
    assert list(csv["variant"]) == ["copy-last", "raycast-voxel (voxel=0.2)", "raycast-voxel (voxel=0.4)"] * 2
    assert list(csv["is_reference"]) == [True, False, False] * 2 and (csv["limit"] == 2).all()
    md = (out / "raycast-voxel-size.md").read_text()
    rows = [line for line in md.splitlines() if line.startswith("| copy-last") or line.startswith("| raycast")]
    assert [r.split(" | ")[0] for r in rows] == ["| copy-last (ref)", "| raycast-voxel (voxel=0.2)",
                                                  "| raycast-voxel (voxel=0.4)"] * 2
    assert md.startswith("# pcfbench ablation: Ray casting: voxel size") and "rows in the experiment's order" in md
    assert "No complete" not in md
    tex = (out / "raycast-voxel-size.tex").read_text()
    assert r"\label{tab:pcfbench-raycast-voxel-size}" in tex and tex.isascii()
    assert "<h1>pcfbench ablation: Ray casting: voxel size" in (out / "raycast-voxel-size.html").read_text()
    # the ablation figure: each column against the voxel size (m), a line per setting
    assert sorted(p.name for p in (reports / "partial" / "figures").iterdir()) == [
        f"ablation-raycast-voxel-size_raycast-voxel_voxel.{e}" for e in ("png", "svg")]

    # the numbers: flat means of each cell's rows, and the change against copy-last's row
    cells = plan(load_experiment(RAYCAST), limit=2)
    assert len(cells) == 6
    means = {}
    for spec in cells:
        df = Cell(store, spec).read_rows()
        ok = df[df.status == "ok"]
        assert len(ok) == 2 * 5  # 2 samples x 5 future sweeps
        means[(spec.setting, spec.options_hash)] = ok["l1_median"].mean()
    ref_hash = resolve_method("copy-last").options_hash
    for _, r in csv.iterrows():
        m = means[(r["setting"], r["options_hash"])]
        assert r["l1_median"] == pytest.approx(m, rel=1e-12)
        if not r["is_reference"]:
            assert r["l1_median_rel"] == pytest.approx(m / means[(r["setting"], ref_hash)] - 1, rel=1e-9)
    change = f"({100 * csv.loc[1, 'l1_median_rel']:+.0f} %"
    assert change in rows[1]

    # a rerun calls no method and changes no cell
    before = [(Cell(store, s).dir / "cell.json").read_text() for s in cells]
    chunks = sorted(p.name for s in cells for p in Cell(store, s).chunk_paths())
    written = {p.name: p.read_bytes() for p in out.iterdir()}
    calls = []
    import pcfbench.running.runner as runner

    real = runner.process_sample
    monkeypatch.setattr(runner, "process_sample", lambda *a: calls.append(a) or real(*a))
    again = run_sweep(load_experiment(RAYCAST), store, reports, limit=2, progress=False, echo=lambda s: None)
    assert calls == []
    assert [r.processed for r in again.results] == [0] * 6
    assert all(r.done_before == r.samples == 2 for r in again.results)
    assert [(Cell(store, s).dir / "cell.json").read_text() for s in cells] == before
    assert sorted(p.name for s in cells for p in Cell(store, s).chunk_paths()) == chunks
    assert {p.name: p.read_bytes() for p in out.iterdir()} == written  # the same tables, byte for byte

    # and pcfbench report sees the sweep's cells like any run's
    rep = _cli(["report", "--store", str(store), "--reports", str(tmp_path / "rep")])
    assert rep.exit_code == 0, rep.output
    assert len(pd.read_csv(tmp_path / "rep" / "leaderboard_partial.csv")) == 6


@pytest.mark.slow
def test_example_experiment_on_the_whole_small_test_split(town, tmp_path, monkeypatch):
    monkeypatch.setenv("PCFBENCH_DATASET_SYNTHETIC_TOWN", str(town))
    result = run_sweep(load_experiment(RAYCAST), tmp_path / "s", tmp_path / "r", progress=False, echo=lambda s: None)
    csv = pd.read_csv(result.paths["raycast-voxel-size.csv"])
    assert list(csv["samples"]) == [38] * 3 + [2] * 3 and csv["limit"].isna().all()
    assert "PARTIAL" not in result.paths["raycast-voxel-size.md"].read_text()
    assert result.paths["raycast-voxel-size.md"] == tmp_path / "r" / "sweeps" / "raycast-voxel-size.md"


# -- a partial sweep beside a complete one -----------------------------------------------------
class FailsOnOne(Method):
    """Copy-last that raises on sample 08/000010 (its cell is complete but not scored on every sample)."""

    name = "fails-on-one"

    def forecast(self, sample):
        if sample.sample_id.endswith("000010"):
            raise RuntimeError("no forecast for this one")
        return CopyLast().forecast(sample)


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` but the partial/ sub-folder: relative path -> bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.relative_to(folder).parts[0] != "partial"}


def test_a_partial_sweep_leaves_the_complete_table_untouched(tmp_path, tiny_kitti):
    """A complete grid writes reports/sweeps/ and its figure; the same grid with --limit, and a
    grid whose cell failed on a sample, write under reports/partial/ and change no byte of it."""
    exp = _write(tmp_path, f"""
datasets = ["kitti={tiny_kitti}"]
settings = ["kitti-1s"]
metrics = ["chamfer", "l1_median"]
jobs = 1

[[methods]]
name = "copy-last"

[[methods]]
name = "raycast-zbuffer"
grid = {{ fill_ring = [4, 8] }}
""")
    store, reports = tmp_path / "store", tmp_path / "reports"
    args = ["sweep", str(exp), "--store", str(store), "--reports", str(reports), "-q"]
    for extra, where in (([], reports), (["--limit", "2"], reports / "partial")):  # --dry-run says where they go
        dry = _cli(args + ["--dry-run", *extra])
        assert dry.exit_code == 0 and f"tables: {where / 'sweeps' / 'exp'}.{{md,csv,tex,html}}\n" in dry.output, dry.output
    full = _cli(args)
    assert full.exit_code == 0, full.output
    complete = _files(reports)
    assert sorted(complete) == [*(f"figures/ablation-exp_raycast-zbuffer_fill_ring.{e}" for e in ("png", "svg")),
                                *(f"sweeps/exp.{e}" for e in ("csv", "html", "md", "tex"))]
    assert "PARTIAL" not in complete["sweeps/exp.md"].decode() and "PARTIAL sweep" not in full.output
    assert list(pd.read_csv(reports / "sweeps" / "exp.csv")["samples"]) == [6, 6, 6]

    part = _cli(args + ["--limit", "2"])
    assert part.exit_code == 0, part.output
    assert _files(reports) == complete  # the complete table and figure, byte for byte
    out = reports / "partial" / "sweeps"
    assert sorted(p.name for p in out.iterdir()) == [f"exp.{e}" for e in ("csv", "html", "md", "tex")]
    assert "PARTIAL" in (out / "exp.md").read_text()
    assert (pd.read_csv(out / "exp.csv")["limit"] == 2).all()
    assert (reports / "partial" / "figures" / "ablation-exp_raycast-zbuffer_fill_ring.png").is_file()
    assert f"PARTIAL sweep (a --limit, or a cell not scored on every sample): its tables and figures are under " \
           f"{reports / 'partial'}, never over the complete ones under {reports}" in part.output
    assert f"{out / 'exp.md'}\n" in part.output

    # no --limit, but a sample failed: the grid is not complete either
    plugins = load_plugins()
    plugins.methods.add("fails-on-one", FailsOnOne, "test")
    failing = load_experiment(_write(tmp_path, exp.read_text().replace('"raycast-zbuffer"', '"fails-on-one"')
                                     .replace("grid = { fill_ring = [4, 8] }", ""), "exp.toml"), plugins)
    res = run_sweep(failing, store, reports, progress=False, plugins=plugins, echo=lambda s: None)
    assert [r.failed for r in res.results] == [0, 1]
    assert _files(reports) == complete
    assert res.paths["exp.md"] == out / "exp.md" and "INCOMPLETE" in (out / "exp.md").read_text()


# -- killed mid-grid ---------------------------------------------------------------------------
def test_a_sweep_killed_mid_grid_and_rerun_loses_and_duplicates_nothing(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("08",), num_sweeps=70)
    exp = _write(tmp_path, f"""
datasets = ["kitti={root}"]
settings = ["kitti-1s"]
metrics = ["chamfer", "l1_median"]
jobs = 1

[[methods]]
name = "raycast-zbuffer"
grid = {{ fill_ring = [4, 8] }}
""")
    store, reports = tmp_path / "store", tmp_path / "reports"
    env = {**os.environ, "PCFBENCH_CHUNK_SAMPLES": "2", "PCFBENCH_NO_PROGRESS": "1"}
    args = [PCFBENCH, "sweep", str(exp), "--store", str(store), "--reports", str(reports)]
    first, second = plan(load_experiment(exp))
    c1, c2 = Cell(store, first), Cell(store, second)
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    killed_at = None
    while time.monotonic() < deadline and proc.poll() is None:
        meta1 = json.loads((c1.dir / "cell.json").read_text()) if (c1.dir / "cell.json").is_file() else {}
        if meta1.get("status") == "complete" and len(c2.chunk_paths()) >= 2:
            proc.send_signal(signal.SIGKILL)
            killed_at = len(c2.chunk_paths())
            break
        time.sleep(0.02)
    proc.wait()
    assert killed_at is not None, f"the sweep ended before it could be killed mid-grid: {proc.stderr.read()!r}"
    meta2 = json.loads((c2.dir / "cell.json").read_text())
    assert meta2["status"] == "running" and not (reports / "sweeps").exists()

    final = subprocess.run(args, env=env, capture_output=True, text=True)
    assert final.returncode == 0, final.stderr
    assert "cell 1/2: complete, nothing to do" in final.stdout
    samples = 70 - 18
    for spec, cell in ((first, c1), (second, c2)):
        raw = pd.concat([pd.read_parquet(p) for p in cell.chunk_paths()])
        assert not raw.duplicated(["sample_id", "step"]).any()
        assert len(raw) == samples * 5 and raw["sample_id"].nunique() == samples
        assert json.loads((cell.dir / "cell.json").read_text())["status"] == "complete"
    # the resumed cell's rows equal those of an uninterrupted run
    from pcfbench.running.runner import RunOptions, run_cell

    run_cell(second, tmp_path / "clean", RunOptions(jobs=1, progress=False))
    key = ["sample_id", "step"]
    a = pd.concat([pd.read_parquet(p) for p in c2.chunk_paths()]).sort_values(key).reset_index(drop=True)
    b = Cell(tmp_path / "clean", second).read_rows().sort_values(key).reset_index(drop=True)
    pd.testing.assert_frame_equal(a[key + ["chamfer", "l1_median"]], b[key + ["chamfer", "l1_median"]])
    csv = pd.read_csv(reports / "sweeps" / "exp.csv")
    assert list(csv["variant"]) == ["raycast-zbuffer (fill_ring=4)", "raycast-zbuffer (fill_ring=8)"]
    assert list(csv["samples"]) == [samples, samples]


# -- the file format ---------------------------------------------------------------------------
class Seeded(Method):
    """Copy-last shifted by a seeded draw (a method with a seed option)."""

    name = "seeded"

    @dataclasses.dataclass(frozen=True)
    class Options:
        seed: int = pcfbench.option(0, help="draw")
        scale: float = pcfbench.option(1.0, help="shift scale, metres")

    def forecast(self, sample):
        dz = self.options.scale * np.random.default_rng(self.options.seed).uniform(0, 0.1)
        last = sample.past_points_ref[-1] + np.array([0, 0, dz], dtype=np.float32)
        return pcfbench.Forecast(points_ref=tuple(last for _ in range(sample.num_future)))


@pytest.fixture
def plugins():
    p = load_plugins()
    p.methods.add("seeded", Seeded, "test")
    return p


def test_grid_variants_options_and_seeds(tmp_path, tiny_kitti, plugins):
    exp = load_experiment(_write(tmp_path, f"""
name = "format"
datasets = ["kitti={tiny_kitti}"]
settings = ["kitti-1s"]

[[methods]]
name = "raycast-voxel"
options = {{ surface = "mean" }}
grid = {{ voxel = [0.2, 1], cone_factor = [0, 1.0] }}

[[methods]]
name = "raycast-zbuffer"
variants = [{{ splat = 0.5 }}, {{ splat = 2, fill_ring = 4 }}]

[[methods]]
name = "seeded"
grid = {{ scale = [1, 2] }}
seeds = [3, 4]

[[methods]]
name = "copy-last"
"""), plugins)
    specs = [(v.method.name, v.method.options_hash) for v in exp.variants]
    expected = [f"raycast-voxel:surface=mean,voxel={v},cone_factor={c}" for v in ("0.2", "1.0") for c in ("0", "1")]
    expected += ["raycast-zbuffer:splat=0.5", "raycast-zbuffer:splat=2,fill_ring=4"]
    expected += [f"seeded:scale={s},seed={seed}" for s in (1, 2) for seed in (3, 4)] + ["copy-last"]
    assert specs == [(r.name, r.options_hash) for r in (resolve_method(e, plugins) for e in expected)]
    assert exp.variants[1].label == "raycast-voxel (cone_factor=1.0, surface=mean, voxel=0.2)"
    assert exp.variants[1].method.options.voxel == 0.2 and exp.variants[2].method.options.voxel == 1.0
    assert exp.variants[-2].label == "seeded (scale=2, seed=4)"
    # the reference defaults to copy-last; the stem to the file's name
    assert exp.tables[0].reference.label == "copy-last" and exp.tables[0].stem == "exp"
    assert [c.method for c in plan(exp, plugins=plugins)] == [n for n, _ in specs]


def test_seeds_run_as_cells_and_rows_are_per_seed(tmp_path, tiny_kitti, plugins):
    exp = load_experiment(_write(tmp_path, f"""
datasets = ["kitti={tiny_kitti}"]
settings = ["kitti-1s"]
metrics = ["chamfer"]

[[methods]]
name = "seeded"
seeds = [0, 1]

[[tables]]
preset = "full"
reference = "seeded:seed=0"
"""), plugins)
    res = run_sweep(exp, tmp_path / "s", tmp_path / "r", progress=False, plugins=plugins, echo=lambda s: None)
    csv = pd.read_csv(res.paths["exp.csv"])
    assert list(csv["variant"]) == ["seeded (seed=0)", "seeded (seed=1)"] and list(csv["is_reference"]) == [True, False]
    assert list(csv["option.seed"]) == [0, 1] and csv.loc[0, "chamfer"] != csv.loc[1, "chamfer"]


def test_relative_dataset_roots_are_relative_to_the_file(tmp_path, tiny_kitti):
    (tmp_path / "sub").mkdir()
    exp = load_experiment(_write(tmp_path / "sub", """
datasets = ["kitti=../kitti"]
settings = ["kitti-1s"]
[[methods]]
name = "copy-last"
"""))
    assert exp.datasets == (("kitti", str(tiny_kitti.resolve())),)


# -- bad input: one clear error naming the file and key, nothing written -----------------------
BAD = [
    ("setings = ['kitti-1s']\n[[methods]]\nname = 'copy-last'", "setings", "unknown key 'setings'; did you mean 'settings'"),
    ("[[methods]]\nname = 'raycast-voxl'", "methods[0].name", "unknown method 'raycast-voxl'; did you mean 'raycast-voxel'"),
    ("[[methods]]\nname = 'raycast-voxel'\ngird = { voxel = [0.2] }", "methods[0].gird", "did you mean 'grid'"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxl = [0.2, 0.4] }", "methods[0].grid",
     "unknown method raycast-voxel option 'voxl'; did you mean 'voxel'"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxel = ['big'] }", "methods[0].grid", "cannot read 'big' as float"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxel = [[0.2]] }", "methods[0].grid.voxel",
     "must be a string, number or boolean"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxel = [] }", "methods[0].grid.voxel", "an empty list"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxel = [0.2, 0.20] }", "methods[0].grid", "listed twice"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxel = [0.2] }\nvariants = [{ voxel = 0.4 }]", "methods[0]",
     "not both"),
    ("[[methods]]\nname = 'raycast-voxel'\noptions = { voxel = 0.2 }\ngrid = { voxel = [0.4] }",
     "methods[0].grid.voxel", "also fixed"),
    ("seeds = [0, 1]\n[[methods]]\nname = 'copy-last'", "seeds", "method copy-last has no 'seed' option"),
    ("[[methods]]\nname = 'raycast-voxel'\nseeds = [0]", "methods[0].seeds", "method raycast-voxel has no 'seed' option"),
    ("settings = ['kitti-2s']\n[[methods]]\nname = 'copy-last'", "settings",
     "unknown setting 'kitti-2s'; did you mean"),
    ("settings = ['nuscenes-1s']\n[[methods]]\nname = 'copy-last'", "settings", "expects 2 Hz sweeps"),
    ("datasets = ['synthetic-twn']\n[[methods]]\nname = 'copy-last'", "datasets",
     "unknown dataset 'synthetic-twn'; did you mean 'synthetic-town'"),
    ("datasets = ['kitti=/nonexistent/kitti']\n[[methods]]\nname = 'copy-last'", "datasets", "does not exist"),
    ("datasets = ['synthetic-town']\nsplits = ['tset']\n[[methods]]\nname = 'copy-last'", "splits",
     "unknown split of dataset synthetic-town 'tset'"),
    ("metrics = ['chamfre']\n[[methods]]\nname = 'copy-last'", "metrics", "unknown metric 'chamfre'; did you mean"),
    ("policy = 'subsample'\n[[methods]]\nname = 'copy-last'", "policy", "did you mean 'subsample-500' or 'subsample-4000'"),
    ("limit = 0\n[[methods]]\nname = 'copy-last'", "limit", "positive integer"),
    ("jobs = -1\n[[methods]]\nname = 'copy-last'", "jobs", "integer >= 0"),
    ("train_on = ['synthetic-suburb']\n[[methods]]\nname = 'copy-last'", "train_on", "trained method"),
    ("train_on = ['synthetic-suburbs']\n[[methods]]\nname = 'copy-last'", "train_on",
     "unknown dataset 'synthetic-suburbs'; did you mean 'synthetic-suburb'"),
    ("[[methods]]\nname = 'copy-last'\n[[tables]]\npreset = 'papr'", "tables[0].preset",
     "unknown table preset 'papr'; did you mean 'paper'"),
    ("[[methods]]\nname = 'raycast-voxel'\ngrid = { voxel = [0.2, 0.4] }\n[[tables]]\nreference = 'raycast-voxel:voxel=0.3'",
     "tables[0].reference", "unknown reference row 'raycast-voxel:voxel=0.3'"),
    ("[[methods]]\nname = 'copy-last'\n[[tables]]\nstem = '../x'", "tables[0].stem", "expected a file name"),
    ("[[methods]]\nname = 'copy-last'\n[[tables]]\nrefrence = 'copy-last'", "tables[0].refrence",
     "did you mean 'reference'"),
    ("[[methods]]\nname = 'copy-last'\n[[tables]]\nci = 'bars'", "tables[0].ci", "unknown interval style 'bars'"),
    ("name = 'x'", "methods", "at least one [[methods]]"),
]


@pytest.mark.parametrize("text,key,message", BAD, ids=[b[1] + ":" + b[2][:24] for b in BAD])
def test_bad_experiment_is_one_clear_error_and_writes_nothing(tmp_path, town, text, key, message):
    path = _write(tmp_path, text)
    store, reports = tmp_path / "store", tmp_path / "reports"
    res = _cli(["sweep", str(path), "--store", str(store), "--reports", str(reports), "-q"],
               {"PCFBENCH_DATASET_SYNTHETIC_TOWN": str(town)})
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.startswith("pcfbench: error:")]
    assert len(lines) == 1 and "cell " not in res.output, res.output
    assert lines[0].startswith(f"pcfbench: error: experiment {path}: {key}: "), lines[0]
    assert message in lines[0], lines[0]
    assert not store.exists() and not reports.exists()


def test_unreadable_or_missing_file(tmp_path):
    bad = _write(tmp_path, "[[methods]\nname =")
    with pytest.raises(PcfbenchError, match=f"experiment {re.escape(str(bad))} is not valid TOML"):
        load_experiment(bad)
    with pytest.raises(PcfbenchError, match=f"experiment file {re.escape(str(tmp_path / 'none.toml'))} does not exist"):
        load_experiment(tmp_path / "none.toml")


def test_a_sample_less_setting_fails_before_any_cell_runs(tmp_path):
    root = write_kitti_tree(tmp_path / "k", num_sweeps=24)  # kitti-3s needs 55 sweeps
    path = _write(tmp_path, f"datasets = ['kitti={root}']\nsettings = ['kitti-1s', 'kitti-3s']\n"
                            "[[methods]]\nname = 'copy-last'")
    res = _cli(["sweep", str(path), "--store", str(tmp_path / "store"), "--reports", str(tmp_path / "r"), "-q"])
    assert res.exit_code == 2 and "no samples for setting kitti-3s" in res.output
    assert not (tmp_path / "store").exists()


# -- the shipped example files ---------------------------------------------------------------
WORLD_MODEL = {"copilot4d-cfg-weight.toml": "copilot4d", "copilot4d-sampling-steps.toml": "copilot4d",
               "copilot4d-vs-maskgit.toml": "copilot4d-maskgit"}
# Tables 3-4 on the world model's tokenizer of issue 42 (`tiny-window`, frame t0)
TINY_WINDOW = ("copilot4d-tiny-window-cfg-weight.toml", "copilot4d-tiny-window-vs-maskgit.toml",
               "copilot4d-tiny-window-sampling-steps.toml")
SOFT_MIX = EXAMPLES / "copilot4d-soft-mix.toml"
KITTI_3S_SAMPLING = EXAMPLES / "copilot4d-kitti-3s-sampling.toml"
EVERY_SAMPLE = EXAMPLES / "copilot4d-every-sample.toml"
TRAINING_LENGTH = EXAMPLES / "copilot4d-training-length.toml"
PER_HORIZON = EXAMPLES / "copilot4d-per-horizon.toml"


#: the options by which the default run's copilot4d forecasts kitti-3s with a network of its own (stop 81)
ONE_NETWORK_PER_HORIZON = ("stride_models", "stride_steps")
#: the option by which the default run decodes every future frame in one causal pass (stop 84): the
#: experiments below were run before it, so their rows are the default run as it sampled then
ONE_PASS = ("one_pass",)

OCCWORLD_TOKENS = EXAMPLES / "occworld-tokens.toml"
OCCWORLD_WORLD_TOKENS = EXAMPLES / "occworld-world-tokens.toml"
BEVWORLD_DDIM = EXAMPLES / "bevworld-ddim-steps.toml"


def test_every_example_experiment_is_checked():
    assert sorted(p.name for p in EXAMPLES.glob("*.toml")) == sorted([RAYCAST.name, OCCWORLD_TOKENS.name,
                                                                      OCCWORLD_WORLD_TOKENS.name, BEVWORLD_DDIM.name,
                                                                      SOFT_MIX.name, KITTI_3S_SAMPLING.name,
                                                                      EVERY_SAMPLE.name, TRAINING_LENGTH.name,
                                                                      PER_HORIZON.name,
                                                                      *WORLD_MODEL, *TINY_WINDOW])
    exp = load_experiment(RAYCAST)
    assert [v.label for v in exp.variants] == ["copy-last", "raycast-voxel (voxel=0.2)", "raycast-voxel (voxel=0.4)"]
    assert exp.settings == ("kitti-1s", "kitti-3s") and exp.datasets == (("synthetic-town", None),)
    exp = load_experiment(OCCWORLD_TOKENS)  # OccWorld's Table 3 axis: a tokenizer per token resolution
    assert [v.label for v in exp.variants] == [*(f"occworld-occ-copy (steps=300, tokens={t})" for t in (25, 50, 100)),
                                               "occworld-occ-copy", "copy-last"]
    assert exp.train_on == ("synthetic-town-realistic",) and exp.settings == ("kitti-1s", "kitti-3s")
    exp = load_experiment(OCCWORLD_WORLD_TOKENS)  # its forecasting side: a world model on each of those tokenizers
    world = [f"occworld (anchor_every=4, steps=300, tokenizer_steps=300, tokens={t})" for t in (25, 50, 100)]
    assert [v.label for v in exp.variants] == [*world, *(f"occworld-occ-copy (steps=300, tokens={t})" for t in
                                                         (25, 50, 100)), "copy-last"]
    assert [(t.stem, t.reference.label) for t in exp.tables] == [  # each resolution against its own copy
        (f"occworld-world-tokens-{t}", f"occworld-occ-copy (steps=300, tokens={t})") for t in (25, 50, 100)]
    assert exp.train_on == ("synthetic-town-realistic",)
    for v in exp.variants[:3]:  # each world model on the very tokenizer its occupancy copy row scores
        assert v.method.create().tokenizer_spec().options.tokens == v.method.options.tokens
        assert v.method.create().tokenizer_spec().options.steps == 300
    exp = load_experiment(BEVWORLD_DDIM)  # every kitti-3s sample, the one checkpoint at each step count
    assert [v.label for v in exp.variants] == [*(f"bevworld (ddim_steps={n})" for n in (5, 10, 20, 50)), "bevworld",
                                               "bevworld-latent-copy", "copy-last"]
    assert exp.settings == ("kitti-3s",) and exp.policy == "full-context"
    exp = load_experiment(SOFT_MIX)  # the shipped world models: soft_mix=0 is the plain arg max's very cell
    one = "sampling_steps=1, soft_mix={}, top_k=1"
    assert [v.label for v in exp.variants] == [
        *(f"copilot4d ({one.format(a)})" for a in ("0.0", "0.3", "0.5", "0.7", "1.0")),
        *(f"copilot4d-maskgit ({one.format(a)})" for a in ("0.0", "0.3")), "copilot4d-token-copy (config=tiny-window)",
        "copy-last"]
    assert exp.variants[0].method.options_hash == resolve_method("copilot4d:sampling_steps=1,top_k=1").options_hash
    assert exp.splits == ("val", "test") and exp.tables[0].reference.label == "copilot4d-token-copy (config=tiny-window)"
    from pcfbench.methods.copilot4d.forecaster import Copilot4D

    default_run = {k: v for k, v in Copilot4D.default_run_options[0].items()
                   if k not in ONE_NETWORK_PER_HORIZON + ONE_PASS}
    assert resolve_method("copilot4d:" + ",".join(f"{k}={v}" for k, v in default_run.items())).options_hash \
        == exp.variants[1].method.options_hash  # the default run's sampling and rendering is one of the rows
    from pcfbench.training.checkpoints import checkpoint_options_hash

    exp = load_experiment(KITTI_3S_SAMPLING)  # guidance x soft_mix at kitti-3s only, the one shipped checkpoint
    assert exp.settings == ("kitti-3s",) and exp.splits == ("val", "test") and exp.policy is None
    world = [v for v in exp.variants if v.method.name == "copilot4d"]
    assert sorted((v.method.options.cfg_weight, v.method.options.soft_mix) for v in world) == sorted(
        (w, a) for w in (0.0, 0.5, 1.0, 2.0) for a in (0.3, 0.5, 0.7, 1.0))
    assert {checkpoint_options_hash(v.method) for v in world} == {checkpoint_options_hash(resolve_method("copilot4d"))}
    assert resolve_method("copilot4d:sampling_steps=1,top_k=1,soft_mix=0.3").options_hash in {
        v.method.options_hash for v in world}  # the default run's pair is a row: the grid's w = 2, a = 0.3
    assert exp.tables[0].reference.label == "copilot4d-token-copy (config=tiny-window)"
    exp = load_experiment(EVERY_SAMPLE)  # the default run's rows on every anchor of both splits
    assert exp.policy == "full-context" and exp.settings == ("kitti-1s", "kitti-3s") and exp.splits == ("val", "test")
    assert [v.label for v in exp.variants] == [f"copilot4d ({one.format(0.3)})", f"copilot4d-maskgit ({one.format(0.3)})",
                                               "copilot4d-token-copy (config=tiny-window)", "copilot4d-token-copy",
                                               "copy-last"]
    for v in exp.variants[:2]:  # as the default run scored them then (copilot4d: one network since stop 81)
        spec = f"{v.method.name}:" + ",".join(f"{k}={x}" for k, x in v.method.create().default_run_options[0].items()
                                              if k not in ONE_NETWORK_PER_HORIZON + ONE_PASS)
        assert resolve_method(spec).options_hash == v.method.options_hash
    assert exp.tables[0].reference.label == "copilot4d-token-copy (config=tiny-window)"
    exp = load_experiment(TRAINING_LENGTH)  # three trainings of copilot4d, each rendered as the default run renders
    assert exp.policy == "full-context" and exp.settings == ("kitti-1s", "kitti-3s") and exp.splits == ("val", "test")
    world = exp.variants[:3]
    assert [v.method.name for v in exp.variants] == ["copilot4d"] * 3 + ["copilot4d-token-copy"]
    assert world[0].method.options_hash == resolve_method("copilot4d:sampling_steps=1,top_k=1,soft_mix=0.3").options_hash
    assert [(v.method.options.steps, v.method.options.init_steps) for v in world] == [(0, 0), (800, 0), (600, 800)]
    assert len({checkpoint_options_hash(v.method) for v in world}) == 3  # three trainings, one sampling
    assert {(v.method.options.sampling_steps, v.method.options.top_k, v.method.options.soft_mix) for v in world} == {
        (1, 1, 0.3)}
    # the warm restart goes on from the very checkpoint of the 800-step row
    assert checkpoint_options_hash(world[2].method.create().start_spec()) \
        == checkpoint_options_hash(world[1].method)
    assert exp.tables[0].reference.label == "copilot4d-token-copy (config=tiny-window)"
    exp = load_experiment(PER_HORIZON)  # one network per horizon: kitti-3s alone, the default run's copilot4d a row
    assert exp.policy == "full-context" and exp.settings == ("kitti-3s",) and exp.splits == ("val", "test")
    one, own, both = exp.variants[:3]
    assert [v.method.name for v in exp.variants] == ["copilot4d"] * 3 + ["copilot4d-token-copy"]
    assert one.method.options_hash == resolve_method("copilot4d:sampling_steps=1,top_k=1,soft_mix=0.3").options_hash
    assert (own.method.options.strides, own.method.options.stride_models) == ((6,), ())
    default_run = ",".join(f"{k}={v}" for k, v in Copilot4D.default_run_options[0].items() if k not in ONE_PASS)
    assert both.method.options_hash == resolve_method(f"copilot4d:{default_run}").options_hash
    assert [checkpoint_options_hash(s) for s in both.method.create().part_specs().values()] == [
        checkpoint_options_hash(one.method), checkpoint_options_hash(resolve_method("copilot4d:strides=6,steps=500"))]
    assert exp.tables[0].reference.label == "copilot4d-token-copy (config=tiny-window)"


def test_the_tiny_window_tables_evaluate_the_chain_of_trainings_they_name():
    """Every world-model row of Tables 3-4 on `tiny-window` is one checkpoint's inference options
    (the 2,400-step chain, or the 1,400-step one of both variants), and each table's reference is
    a row of its grid: the sweep would refuse a reference that is not, so this pins which rows."""
    chain = "anchor_every=1, config=tiny-window, init_steps=800/600, steps=1000, top_k=1"
    cfg, maskgit, steps = (load_experiment(EXAMPLES / name) for name in TINY_WINDOW)
    for exp in (cfg, maskgit, steps):
        assert exp.datasets == (("synthetic-town-realistic", None),) and exp.train_on == ("synthetic-town-realistic",)
        assert exp.settings == ("kitti-1s", "kitti-3s") and exp.policy is None  # every third: the dataset's own
    world = [f"copilot4d ({chain.replace('anchor_every=1, ', f'anchor_every=1, cfg_weight={w}, ')})"
             for w in ("0.0", "1.0", "2.0", "4.0")]
    assert [v.label for v in cfg.variants] == [*world, "copilot4d-token-copy (config=tiny-window)", "copy-last"]
    assert [(t.stem, t.reference.label) for t in cfg.tables] == [
        ("copilot4d-tiny-window-cfg-weight", world[0]),
        ("copilot4d-tiny-window-cfg-weight-vs-token-copy", "copilot4d-token-copy (config=tiny-window)")]
    warm = "anchor_every=1, config=tiny-window, init_steps=800, steps=600, top_k=1"
    assert [v.label for v in maskgit.variants] == [f"copilot4d-maskgit ({warm})", f"copilot4d ({warm})",
                                                   f"copilot4d ({chain})",
                                                   "copilot4d-token-copy (config=tiny-window)", "copy-last"]
    assert maskgit.tables[0].reference.label == f"copilot4d-maskgit ({warm})"
    # inference options only: every row of a table but the copies is one training's checkpoint
    trained = {v.method.options.init_steps for v in (*cfg.variants[:4], *steps.variants[:4])}
    assert trained == {(800, 600)} and [v.method.options.sampling_steps for v in steps.variants[:4]] == [1, 3, 5, 10]
    assert steps.tables[0].reference.label == steps.variants[3].label


@pytest.mark.parametrize("name", sorted(WORLD_MODEL))
def test_world_model_experiments_name_their_missing_method(name):
    """Until issue 14 registers the world model, each file says so at the top and gives the
    clear unknown-method error; once the method exists, the whole file must validate."""
    path = EXAMPLES / name
    method = WORLD_MODEL[name]
    if method in get_plugins().methods:
        load_experiment(path)
        return
    assert path.read_text().startswith(f"# NOT RUNNABLE YET: the method{'s' if 'maskgit' in name else ''} copilot4d")
    with pytest.raises(UnknownNameError) as err:
        load_experiment(path)
    assert str(err.value).startswith(f"experiment {path}: methods[0].name: unknown method {method!r}")


def test_the_docs_describe_every_key():
    doc = (REPO / "docs" / "experiments.md").read_text()
    for key in EXPERIMENT_KEYS + METHOD_KEYS + TABLE_KEYS:
        assert f"`{key}`" in doc, key
    assert "pcfbench sweep" in (REPO / "README.md").read_text()


# -- trained methods: train_on -----------------------------------------------------------------
def test_train_on_evaluates_each_checkpoint_and_says_how_to_train_a_missing_one(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "training"))  # the toy trained method
    from test_training import toy_plugins

    from pcfbench.training import train

    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "01", "08"), num_sweeps=24)
    plugins = toy_plugins()
    path = _write(tmp_path, f"""
datasets = ["kitti={root}"]
settings = ["kitti-1s"]
metrics = ["l1_median"]
train_on = ["kitti={root}"]

[[methods]]
name = "copy-last"

[[methods]]
name = "toy-trained"
grid = {{ lr = [0.1, 0.2] }}
""")
    exp = load_experiment(path, plugins)
    with pytest.raises(PcfbenchError) as err:  # no checkpoint yet: before any cell runs
        plan(exp, plugins=plugins, progress=False)
    assert str(err.value).startswith(f"experiment {path}: train_on: no checkpoint of toy-trained:lr=0.1 trained on kitti:train")
    assert "pcfbench train toy-trained:lr=0.1 --dataset kitti=" in str(err.value)
    assert not (tmp_path / "store").exists()
    cks = {lr: train(resolve_method(f"toy-trained:lr={lr}", plugins), f"kitti={root}", plugins=plugins,
                     progress=False, log=lambda *a: None) for lr in ("0.1", "0.2")}
    res = run_sweep(load_experiment(path, plugins), tmp_path / "store", tmp_path / "r", progress=False,
                    plugins=plugins, echo=lambda s: None)
    trained = [c for c in res.cells if c.method == "toy-trained"]
    assert [c.checkpoint_sha256 for c in trained] == [cks["0.1"].sha256, cks["0.2"].sha256]
    for spec in trained:
        meta = json.loads((Cell(tmp_path / "store", spec).dir / "cell.json").read_text())
        assert meta["checkpoint_sha256"] == spec.checkpoint_sha256 and meta["train_on"]["split"] == "train"
    csv = pd.read_csv(res.paths["exp.csv"])
    assert list(csv["variant"]) == ["copy-last"] + [
        f"toy-trained (lr={lr}) [trained on kitti:train, ck {cks[lr].sha256[:8]}]" for lr in ("0.1", "0.2")]
    assert list(csv["is_reference"]) == [True, False, False] and csv["l1_median_rel"].iloc[1:].notna().all()


def test_train_on_needs_a_trained_method(tmp_path):
    path = _write(tmp_path, "train_on = ['synthetic-suburb']\n[[methods]]\nname = 'raycast-voxel'")
    with pytest.raises(PcfbenchError, match="train_on: applies to trained methods, and none of raycast-voxel trains"):
        load_experiment(path)
