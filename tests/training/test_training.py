"""The trained-method contract on a toy trained method: fit, checkpoint, resume after SIGKILL,
the manifest and hash refusals, weights_only loading, cells keyed by checkpoint, the train-split
refusal, the missing-checkpoint message, the CLI (train, run --checkpoint / --train-on)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import pcfbench
from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.training import Checkpoint, CheckpointError, checkpoint_for, open_training_data, train

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent  # conftest.py, tests_helpers.py


@dataclass(frozen=True)
class ToyOptions:
    lr: float = pcfbench.option(0.1, help="step size")
    steps: int = pcfbench.option(12, help="training steps")
    save_every: int = pcfbench.option(3, help="checkpoint every this many steps")


class ToyTrained(pcfbench.TrainedMethod):
    """Learns one number, the median range of the training sweeps, by SGD on random sweeps
    with a little torch noise (so both RNGs matter for the curve); forecasts it as every depth."""

    name = "toy-trained"
    Options = ToyOptions
    default_train_on = "kitti"
    training_time = "about 1 s (toy)"

    def training_steps(self) -> int:
        return self.options.steps

    def fit(self, train_source, out_dir, progress):
        import torch

        adapter = train_source.adapter
        ranges = [float(np.median(np.linalg.norm(adapter.sequence(n).load_points(i), axis=1)))
                  for n in adapter.sequence_names(train_source.split) for i in range(len(adapter.sequence(n)))]
        w, step, history = torch.zeros(1, dtype=torch.float64), 0, []
        rng = np.random.default_rng(0)
        torch.manual_seed(0)
        resumed = progress.resume()
        if resumed is not None:
            w, step, history = resumed["weights"]["w"], resumed["step"], list(resumed["state"]["history"])
            rng.bit_generator.state = resumed["state"]["numpy_rng"]
            torch.set_rng_state(resumed["state"]["torch_rng"])
        total = self.options.steps
        progress.start(total, step)
        sleep = float(os.environ.get("TOY_STEP_SLEEP", "0"))
        while step < total and not progress.should_stop():
            target = ranges[int(rng.integers(len(ranges)))] + 0.01 * float(torch.randn(1))
            history.append({"step": step + 1, "loss": float((w - target) ** 2), "w": float(w)})
            w = w - self.options.lr * 2 * (w - target)
            step += 1
            progress.update(1, loss=history[-1]["loss"])
            if step % self.options.save_every == 0 or step == total or progress.should_stop():
                progress.save(step, {"w": w}, {"history": history, "numpy_rng": rng.bit_generator.state,
                                               "torch_rng": torch.get_rng_state(),
                                               "torch_threads": torch.get_num_threads()}, complete=step == total)
            time.sleep(sleep)

    def load(self, checkpoint):
        self.w = float(checkpoint.load_weights()["w"])

    def forecast(self, sample):
        return pcfbench.Forecast.from_depths(sample, [np.full(len(q), self.w) for q in sample.queries])


def toy_plugins():
    from pcfbench.hookspecs import hookimpl
    from pcfbench.plugins import load_plugins

    module = types.ModuleType("pcfb_toy_trained")

    @hookimpl
    def register_methods(register):
        register("toy-trained", ToyTrained, "a toy trained method")

    module.register_methods = register_methods
    plugins = load_plugins()
    plugins.add_plugin(module, "toy-trained")
    return plugins


@pytest.fixture
def env(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "01", "08"), num_sweeps=24)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    plugins = toy_plugins()
    return types.SimpleNamespace(root=root, plugins=plugins, tmp=tmp_path, data=f"kitti={root}")


def _train(env, spec="toy-trained", **kw):
    kw.setdefault("progress", False)
    return train(resolve_method(spec, env.plugins), env.data, plugins=env.plugins, log=lambda *a: None, **kw)


def test_fit_writes_a_checkpoint_with_identity(env):
    import torch

    ck = _train(env)
    spec = resolve_method("toy-trained", env.plugins)
    train_on = open_training_data(env.data, "train", env.plugins, False).train_on
    assert ck.dir == Path(os.environ["PCFBENCH_CACHE"]) / "checkpoints" / "toy-trained" / "v1" / spec.options_hash / train_on.key
    m = json.loads((ck.dir / "manifest.json").read_text())
    assert m["method"] == "toy-trained" and m["options"] == {"lr": 0.1, "steps": 12, "save_every": 3}
    assert m["steps"] == 12 and m["complete"] is True and m["device"] in ("cpu", "cuda")
    assert m["train_on"]["dataset"] == "kitti" and m["train_on"]["split"] == "train"
    assert m["train_on"]["fingerprint"] == train_on.fingerprint
    assert m["wall_s"] >= 0 and m["cpu_s"] >= 0 and m["git_commit"] and m["torch"] == torch.__version__
    import hashlib

    assert hashlib.sha256((ck.dir / m["weights"]).read_bytes()).hexdigest() == m["weights_sha256"] == ck.sha256
    assert sorted(p.name for p in ck.dir.glob("*.pt")) == ["state-00000012.pt", "weights-00000012.pt"]  # old ones gone
    # the learned number is the SGD iterate of the recorded curve
    h = ck.load_state()["history"]
    assert [r["step"] for r in h] == list(range(1, 13))
    w = h[-1]["w"]
    assert float(ck.load_weights()["w"]) != pytest.approx(0.0) and np.isfinite(w)
    # a second call resumes a complete checkpoint and does nothing more
    again = _train(env)
    assert again.sha256 == ck.sha256 and again.steps == 12


def test_sigkill_mid_training_then_resume_continues_the_same_curve(env, tmp_path, monkeypatch):
    spec = "toy-trained:steps=30"
    straight = _train(env, spec)  # uninterrupted reference, in its own cache
    reference = straight.load_state()["history"]
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache-killed"))
    script = (f"import sys; sys.path[:0] = {[str(HERE), str(TESTS)]!r}; from test_training import toy_plugins; "
              "from pcfbench.method import resolve_method; from pcfbench.training import train; "
              f"p = toy_plugins(); train(resolve_method({spec!r}, p), {env.data!r}, plugins=p, progress=False)")
    proc = subprocess.Popen([sys.executable, "-c", script], env={**os.environ, "TOY_STEP_SLEEP": "0.2"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    manifest = None
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            found = list((tmp_path / "cache-killed").rglob("manifest.json"))
            if found and json.loads(found[0].read_text())["steps"] >= 9:
                manifest = found[0]
                break
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert manifest is not None, "the training subprocess saved no checkpoint in time"
    killed_at = json.loads(manifest.read_text())["steps"]
    assert 9 <= killed_at < 30  # killed mid-run
    resumed = _train(env, spec)
    assert resumed.steps == 30 and resumed.manifest["complete"]
    curve = resumed.load_state()["history"]
    assert [r["step"] for r in curve] == list(range(1, 31))
    assert [r["loss"] for r in curve] == [r["loss"] for r in reference]  # exactly: same data order and noise
    assert float(resumed.load_weights()["w"]) == float(straight.load_weights()["w"])


def test_max_minutes_stops_with_a_checkpoint_and_fresh_starts_over(env):
    ck = _train(env, max_minutes=0)
    assert ck.steps == 1 and not ck.manifest["complete"]  # the budget is checked before each further step
    assert _train(env).steps == 12
    assert _train(env, max_minutes=0, fresh=True).steps == 1


def test_resuming_on_another_device_is_refused(env):
    """A run stopped on one device does not silently continue on another: the numerics and
    the RNG streams differ, so it could not continue the same curve."""
    ck = _train(env, max_minutes=0)
    m = json.loads(ck.manifest_path.read_text())
    here = m["device"]
    m["device"] = "cuda" if here == "cpu" else "cpu"
    ck.manifest_path.write_text(json.dumps(m))
    with pytest.raises(CheckpointError, match=rf"trained on {m['device']} and this run would resume it on {here}"):
        _train(env)
    assert _train(env, fresh=True).steps == 12  # --fresh starts over


def test_training_runs_under_its_thread_budget_and_resumes_only_with_the_same(env):
    """``--threads``: fit runs with torch pinned to the budget (then it is put back), the manifest
    records it, and a resume with another count is refused (the rounding of the weights, and so
    the curve it continues, depend on it)."""
    import torch

    before = torch.get_num_threads()
    ck = _train(env, max_minutes=0, threads=1)
    assert ck.manifest["threads"] == 1 and ck.load_state()["torch_threads"] == 1
    assert torch.get_num_threads() == before
    with pytest.raises(CheckpointError, match=r"trained with 1 CPU threads and this run has 2; resume it with "
                                              r"--threads 1, or rerun with --fresh"):
        _train(env, threads=2)
    done = _train(env, threads=1)
    assert done.steps == 12 and done.manifest["complete"] and done.manifest["threads"] == 1
    again = _train(env, fresh=True, threads=2)
    assert again.manifest["threads"] == 2 and again.load_state()["torch_threads"] == 2


def test_the_retrain_command_names_options_split_and_cpu_threads(env):
    from pcfbench.training import retrain_command

    spec = resolve_method("toy-trained:steps=5,lr=0.2", env.plugins)
    assert retrain_command(spec, "kitti=/d", "train", {"device": "cpu", "threads": 3}) == (
        "pcfbench train toy-trained:lr=0.2,steps=5 --dataset kitti=/d --threads 3 --fresh --ship")
    plain = resolve_method("toy-trained", env.plugins)
    assert retrain_command(plain, "kitti", "val", {"device": "cuda", "threads": 3}) == (
        "pcfbench train toy-trained --dataset kitti --split val --fresh --ship")  # a GPU's bits: not the CPU's threads
    assert retrain_command(plain, "kitti", "train", {"device": "cpu"}) == (
        "pcfbench train toy-trained --dataset kitti --fresh --ship")  # not recorded (before 2026-11-26)


def test_truncated_tampered_and_foreign_checkpoints_are_refused(env):
    ck = _train(env)
    weights = ck.weights_path
    good = weights.read_bytes()
    weights.write_bytes(good[: len(good) // 2])
    with pytest.raises(CheckpointError, match=rf"{weights}.*does not match the sha256.*truncated or altered"):
        Checkpoint.open(ck.dir)
    weights.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(CheckpointError, match=rf"{weights}.*does not match the sha256"):
        Checkpoint.open(weights)
    weights.write_bytes(good)
    assert Checkpoint.open(ck.dir / "manifest.json").sha256 == ck.sha256
    other = resolve_method("toy-trained:lr=0.2", env.plugins)
    with pytest.raises(CheckpointError, match=r"manifest.json was made by another method or configuration: "
                                              r"options_hash .*toy-trained:lr=0.1"):
        Checkpoint.open(ck.dir).check_method(other)
    with pytest.raises(CheckpointError, match="made by another method"):
        checkpoint_for(resolve_method("copy-last", env.plugins), checkpoint=ck.dir)
    manifest = ck.dir / "manifest.json"
    text = manifest.read_text()
    manifest.write_text(text[:40])
    with pytest.raises(CheckpointError, match=rf"{manifest} is not valid JSON"):
        Checkpoint.open(ck.dir)
    manifest.write_text(text)
    with pytest.raises(CheckpointError, match=r"no checkpoint at .*manifest.json does not exist"):
        Checkpoint.open(env.tmp)


def test_weights_load_with_weights_only(env):
    """A weights file holding an arbitrary object (whose sha256 the manifest matches) is
    refused by torch.load(weights_only=True) instead of being unpickled."""
    import hashlib
    import io

    import torch

    ck = _train(env)
    buf = io.BytesIO()
    torch.save({"w": torch.zeros(1), "evil": ToyOptions()}, buf)
    ck.weights_path.write_bytes(buf.getvalue())
    m = json.loads(ck.manifest_path.read_text())
    m["weights_sha256"] = hashlib.sha256(buf.getvalue()).hexdigest()
    ck.manifest_path.write_text(json.dumps(m))
    with pytest.raises(CheckpointError, match=rf"{ck.weights_path} does not load with weights_only=True"):
        Checkpoint.open(ck.dir).load_weights()


def test_missing_checkpoint_says_how_to_train_it(env):
    with pytest.raises(CheckpointError) as err:
        checkpoint_for(resolve_method("toy-trained:lr=0.5", env.plugins), train_on=env.data, plugins=env.plugins,
                       progress=False)
    msg = str(err.value)
    assert "no checkpoint of toy-trained:lr=0.5 trained on kitti:train" in msg
    assert f"`pcfbench train toy-trained:lr=0.5 --dataset kitti={env.root}`" in msg
    assert msg.endswith("which takes about 1 s (toy)")
    # the figure a method states is for its default step count: another count says so
    with pytest.raises(CheckpointError) as err:
        checkpoint_for(resolve_method("toy-trained:steps=30", env.plugins), train_on=env.data, plugins=env.plugins,
                       progress=False)
    assert str(err.value).endswith("which takes about 1 s (toy); that figure is for 12 steps, these options train 30")
    # once a training of the same method and options ran here, its measured rate is quoted
    _train(env, "toy-trained:lr=0.5", max_minutes=0)
    other = open_training_data(env.data, "test", env.plugins, False).train_on
    from pcfbench.training import missing_checkpoint_message

    msg = missing_checkpoint_message(resolve_method("toy-trained:lr=0.5", env.plugins), other)
    assert "on this machine (12 steps at" in msg and "--split test" in msg


def _cell(env, ck, split="test", **kw):
    from pcfbench.running.runner import RunOptions, run_cell
    from pcfbench.store.cells import CellSpec

    spec = resolve_method("toy-trained", env.plugins)
    cell = CellSpec("toy-trained", {}, spec.options_hash, "kitti", str(env.root), split, "kitti-1s", limit=2,
                    metrics=("chamfer", "l1_mean"), checkpoint=str(ck.dir), checkpoint_sha256=ck.sha256,
                    train_on=ck.train_on_label)
    return run_cell(cell, env.tmp / "store", RunOptions(progress=False, **kw), plugins=env.plugins)


def test_cells_know_their_checkpoint_and_a_changed_one_is_a_new_cell(env):
    first = _train(env, max_minutes=0)
    a = _cell(env, first)
    meta_a = json.loads((a.path / "cell.json").read_text())
    assert meta_a["checkpoint_sha256"] == first.sha256 and meta_a["train_on"]["dataset"] == "kitti"
    assert meta_a["train_on"]["split"] == "train" and meta_a["evaluated_on_training_data"] is False
    assert meta_a["spec"]["train_on"] == "kitti:train"
    second = _train(env)  # resumed to the end: other weights
    assert second.sha256 != first.sha256
    b = _cell(env, second)
    assert b.path != a.path and b.processed == 2 and first.sha256[:12] in a.path.name
    assert json.loads((a.path / "cell.json").read_text())["checkpoint_sha256"] == first.sha256  # kept side by side
    # a cell whose checkpoint file changed under it is refused, never scored with other weights
    from pcfbench.store.cells import CellSpec

    with pytest.raises(PcfbenchError, match="changed since cell"):
        from pcfbench.running.runner import resolve

        resolve(CellSpec("toy-trained", {}, resolve_method("toy-trained", env.plugins).options_hash, "kitti",
                         str(env.root), "test", "kitti-1s", checkpoint=str(second.dir), checkpoint_sha256=first.sha256,
                         train_on="kitti:train"), env.plugins)
    from pcfbench.reporting.report import collect

    board = collect(env.tmp / "store")
    labels = sorted(board.partial["variant"])
    assert labels == sorted([f"toy-trained [trained on kitti:train (UNFINISHED 1 of 12 steps), ck {first.sha256[:8]}]",
                             f"toy-trained [trained on kitti:train, ck {second.sha256[:8]}]"])
    assert set(board.partial["train_on"]) == {"kitti:train"}


def test_evaluating_on_the_training_split_is_refused_unless_allowed(env):
    ck = _train(env)
    with pytest.raises(PcfbenchError, match=r"was trained on this very data \(kitti:train.*--allow-train-split"):
        _cell(env, ck, split="train")
    r = _cell(env, ck, split="train", allow_train_split=True)
    assert json.loads((r.path / "cell.json").read_text())["evaluated_on_training_data"] is True
    from pcfbench.reporting.report import collect

    assert list(collect(env.tmp / "store").partial["variant"]) == [
        f"toy-trained [trained on kitti:train, ck {ck.sha256[:8]}, ON ITS TRAINING DATA]"]


def test_cli_train_and_run_with_checkpoint_and_train_on(env, monkeypatch):
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    monkeypatch.setattr("pcfbench.cli.get_plugins", lambda: env.plugins)
    cli = build_cli()
    runner = CliRunner()
    store, reports = str(env.tmp / "store"), str(env.tmp / "reports")
    base = ["run", "-m", "toy-trained", "-d", env.data, "-s", "kitti-1s", "--limit", "1", "-q", "--store", store,
            "--reports", reports, "--metric", "chamfer"]
    r = runner.invoke(cli, base + ["--train-on", env.data])
    assert r.exit_code == 2 and "pcfbench train toy-trained --dataset kitti=" in r.output
    r = runner.invoke(cli, ["train", "toy-trained", "--dataset", env.data, "-q"])
    assert r.exit_code == 0, r.output
    assert "toy-trained: 12 steps on kitti:train" in r.output and "(complete)" in r.output
    r = runner.invoke(cli, base + ["--train-on", env.data])
    assert r.exit_code == 0, r.output
    assert "toy-trained [trained on kitti:train] | kitti:test | kitti-1s limit=1: 1 samples" in r.output
    ck = next((env.tmp / "cache").rglob("manifest.json"))
    r = runner.invoke(cli, base + ["--checkpoint", str(ck)])
    assert r.exit_code == 0 and "complete, nothing to do" in r.output, r.output  # the same checkpoint: the same cell
    r = runner.invoke(cli, base + ["--checkpoint", str(ck), "-m", "copy-last", "--split", "train"])
    assert r.exit_code == 2 and "was trained on this very data" in r.output
    r = runner.invoke(cli, ["train", "copy-last", "--dataset", env.data])
    assert r.exit_code == 2 and "does not train" in r.output


def test_run_gives_each_variant_of_a_trained_method_its_own_checkpoint(env, monkeypatch):
    """Two variants of one trained method in one run (a token-resolution sweep by hand): each
    cell is evaluated with its own variant's checkpoint. Before, the run kept one checkpoint per
    method name, the last variant's, and the other variant's cell refused it as another
    configuration's."""
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    monkeypatch.setattr("pcfbench.cli.get_plugins", lambda: env.plugins)
    runner = CliRunner()
    cks = {n: _train(env, f"toy-trained:steps={n}") for n in (6, 9)}
    store = env.tmp / "store"
    r = runner.invoke(build_cli(), ["run", "-m", "toy-trained:steps=6", "-m", "toy-trained:steps=9", "-d", env.data,
                                    "-s", "kitti-1s", "--limit", "1", "-q", "--store", str(store), "--reports",
                                    str(env.tmp / "reports"), "--metric", "chamfer", "--train-on", env.data])
    assert r.exit_code == 0, r.output
    cells = [json.loads(p.read_text()) for p in store.rglob("cell.json")]
    assert sorted((c["spec"]["options"]["steps"], c["checkpoint_sha256"]) for c in cells) == sorted(
        (str(n), ck.sha256) for n, ck in cks.items())
    assert cks[6].sha256 != cks[9].sha256


def test_transfer_table_layout(env):
    """A trained cell on other data than its training data gets a Table-5 block: the trained row
    and the untrained baselines of the same block, the paper's columns, the leaderboard's values."""
    from pcfbench.reporting.report import collect, write_reports
    from pcfbench.running.runner import RunOptions, run_cell
    from pcfbench.store.cells import CellSpec

    ck = _train(env)
    _cell(env, ck)
    copy = resolve_method("copy-last", env.plugins)
    run_cell(CellSpec("copy-last", {}, copy.options_hash, "kitti", str(env.root), "test", "kitti-1s", limit=2,
                      metrics=("chamfer", "l1_mean")), env.tmp / "store", RunOptions(progress=False), plugins=env.plugins)
    paths = write_reports(env.tmp / "store", env.tmp / "reports")
    md = paths["transfer_md"].read_text().splitlines()
    i = md.index("## [kitti → kitti] 1s Prediction (test split, kitti-1s, PARTIAL: first 2 samples)")
    assert md[i + 2] == "| Method | Trained on | L1 Mean ↓ (m) | Chamfer (full) ↓ (m²) | n |"
    board = collect(env.tmp / "store").partial.set_index("method")
    assert md[i + 4] == (f"| copy-last | - | {board.loc['copy-last', 'l1_mean']:.3f} | "
                         f"{board.loc['copy-last', 'chamfer']:.3f} | 2 |")
    assert md[i + 5] == (f"| toy-trained | kitti:train (ck {ck.sha256[:8]}) | {board.loc['toy-trained', 'l1_mean']:.3f} | "
                         f"{board.loc['toy-trained', 'chamfer']:.3f} | 2 |")
    import pandas as pd

    csv = pd.read_csv(paths["transfer_csv"])
    assert list(csv["method_label"]) == ["copy-last", "toy-trained"] and csv["train_on"].fillna("").tolist() == ["", "kitti:train"]
    # without trained cells there is no transfer table
    import shutil

    shutil.rmtree(env.tmp / "store" / "kitti" / "kitti-1s" / "test" / next(
        p.name for p in (env.tmp / "store" / "kitti" / "kitti-1s" / "test").iterdir() if p.name.startswith("toy-trained")))
    assert "transfer_md" not in write_reports(env.tmp / "store", env.tmp / "reports")
    assert not (env.tmp / "reports" / "transfer.md").exists()


def test_default_run_includes_a_trained_method_only_with_its_checkpoint(env, monkeypatch, capsys):
    from pcfbench.cli import _selected_methods

    monkeypatch.setenv("PCFBENCH_DATASET_KITTI", str(env.root))  # the toy's default_train_on is kitti
    names = [m.name for m in _selected_methods(env.plugins, ())]
    assert "toy-trained" not in names and "copy-last" in names
    assert "toy-trained is not trained on kitti:train yet (`pcfbench train toy-trained --dataset kitti`)" in capsys.readouterr().err
    _train(env)
    assert "toy-trained" in [m.name for m in _selected_methods(env.plugins, ())]


def test_default_run_says_when_the_shipped_checkpoint_is_for_other_bytes(env, monkeypatch, capsys):
    """A shipped checkpoint whose data differ from this machine's (a generated dataset's bytes
    can differ by CPU) is left out with the reason, not as "not trained yet"."""
    from pcfbench.cli import _selected_methods
    from pcfbench.method import resolve_method
    from pcfbench.training import Checkpoint, checkpoint_dir, open_training_data, ship

    monkeypatch.setenv("PCFBENCH_DATASET_KITTI", str(env.root))
    monkeypatch.setattr(ToyTrained, "shipped_checkpoints", env.tmp / "shipped")
    _train(env)
    spec = resolve_method("toy-trained", env.plugins)
    source = open_training_data(f"kitti={env.root}", "train", env.plugins, False)
    ck = Checkpoint.open(checkpoint_dir(spec, source.train_on))
    ship(spec, ck, source.train_on, "retrain", log=lambda *a: None)
    for f in ck.dir.iterdir():
        f.unlink()
    capsys.readouterr()
    assert "toy-trained" in [m.name for m in _selected_methods(env.plugins, ())]  # the shipped one
    first = sorted(Path(env.root).rglob("*.bin"))[0]
    first.write_bytes(bytes([first.read_bytes()[0] ^ 1]) + first.read_bytes()[1:])
    assert "toy-trained" not in [m.name for m in _selected_methods(env.plugins, ())]
    err = capsys.readouterr().err
    assert "toy-trained's shipped checkpoint is not for this machine's kitti:train: it was trained on other bytes" in err
    assert "not trained on kitti:train yet" not in err


@dataclass(frozen=True)
class ToyInferenceOptions(ToyOptions):
    offset: float = pcfbench.option(0.0, help="added to every forecast depth")


class ToyWithInferenceOption(ToyTrained):
    """The toy with an option that only inference reads."""

    name = "toy-trained-offset"
    Options = ToyInferenceOptions
    inference_options = ("offset",)

    def forecast(self, sample):
        return pcfbench.Forecast.from_depths(sample, [np.full(len(q), self.w + self.options.offset)
                                                      for q in sample.queries])


def _spec(cls, **opts):
    from pcfbench.method import MethodSpec, options_hash

    o = cls.Options(**opts)
    return MethodSpec(cls.name, {k: str(v) for k, v in opts.items()}, o, options_hash(o), cls)


def test_inference_options_are_left_out_of_the_checkpoint_identity(env):
    """A checkpoint trained with offset=0 is the checkpoint of offset=2 (the option changes no
    weight), recorded with the training options; a training option changed is another one; an
    inference option the options lack is one error."""
    from pcfbench.training import checkpoint_options_hash, find_checkpoint

    train_on = open_training_data(env.data, "train", env.plugins, False).train_on
    base = train(_spec(ToyWithInferenceOption), env.data, plugins=env.plugins, progress=False, log=lambda *a: None)
    shifted = _spec(ToyWithInferenceOption, offset=2.0)
    assert shifted.options_hash != base.manifest["options_hash"] == checkpoint_options_hash(shifted)
    assert find_checkpoint(shifted, train_on).dir == base.dir
    again = train(shifted, env.data, plugins=env.plugins, progress=False, log=lambda *a: None)
    assert again.dir == base.dir and again.sha256 == base.sha256
    assert again.manifest["options"]["offset"] == 0.0
    assert find_checkpoint(_spec(ToyWithInferenceOption, offset=2.0, lr=0.2), train_on) is None

    class Broken(ToyWithInferenceOption):
        inference_options = ("offest",)

    with pytest.raises(PcfbenchError, match="inference_options names offest"):
        checkpoint_options_hash(_spec(Broken))


def test_a_shipped_checkpoint_is_refused_on_its_own_training_split_made_elsewhere(env, monkeypatch):
    """A shipped checkpoint records the fingerprint (file sizes and times) of the machine it
    was trained on, never this one's: the same dataset and split is still its training data."""
    from pcfbench.training import Checkpoint, ship

    monkeypatch.setattr(ToyTrained, "shipped_checkpoints", env.tmp / "shipped")
    ck = _train(env)
    shipped = ship(resolve_method("toy-trained", env.plugins), ck, open_training_data(env.data, "train", env.plugins, False).train_on,
                   "retrain", log=lambda *a: None)
    m = json.loads((shipped.dir / "manifest.json").read_text())
    m["train_on"]["fingerprint"] = "0" * 16  # as made on another machine
    (shipped.dir / "manifest.json").write_text(json.dumps(m))
    elsewhere = Checkpoint.open(shipped.dir)
    with pytest.raises(PcfbenchError, match=r"was trained on this very data \(kitti:train"):
        _cell(env, elsewhere, split="train")
    assert json.loads((_cell(env, elsewhere).path / "cell.json").read_text())["evaluated_on_training_data"] is False
