"""The one training loop (pcfbench.training.loop.fit_loop) on a tiny linear regression: an
interrupted and resumed run is the uninterrupted one (curve and weights), the random state's
one format survives a weights_only round trip, the old formats still resume, the time budget
stops with a checkpoint, and the generic pieces (schedule, parameter groups, curve writer)."""

from __future__ import annotations

import copy
import io
import json
import math
import types
from dataclasses import dataclass

import numpy as np
import pytest
import torch

import pcfbench
from pcfbench.method import resolve_method
from pcfbench.training import (Panel, Randoms, StateError, fit_loop, param_groups, train, warmup_cosine,
                               write_curve)
from pcfbench.training.loop import random_state, restore_random_state

TIMING = ("step_s", "elapsed_s", "cpu_s")
TRUE_W = torch.tensor([[1.5, -2.0, 0.5]])


class MemoryRun:
    """The TrainingRun surface the loop uses, saving in memory through torch.save and a
    ``weights_only`` load, as a real checkpoint goes; ``stop_after`` steps, then it says stop."""

    def __init__(self, saved=None, stop_after=None):
        self.saved, self.stop_after, self.done, self.saves = saved, stop_after, 0, []
        self.shown = []

    def resume(self):
        return self.saved

    def start(self, total, initial=0):
        self.started = (total, initial)

    def update(self, steps=1, **values):
        self.done += steps
        self.shown.append(values)

    def should_stop(self):
        return self.stop_after is not None and self.done >= self.stop_after

    def save(self, step, weights, state, *, config=None, complete=False):
        buf = io.BytesIO()
        torch.save({"weights": weights, "state": state}, buf)
        d = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
        self.saved = {"step": step, "weights": d["weights"], "state": copy.deepcopy(d["state"])}
        self.saves.append((step, complete, dict(config or {})))


def regression(run, *, steps=10, log_every=3, checkpoint_every=4, **kw):
    """y = x W^T + noise: x from the numpy stream, the noise from the loop's torch generator,
    a dropout mask from torch's global stream, so every stream shapes the curve."""

    def sample_batch(rand, step):
        x = torch.from_numpy(rand.numpy.normal(size=(8, 3)).astype(np.float32))
        return x, x @ TRUE_W.T + 0.1 * torch.randn(8, 1, generator=rand.torch)

    def step_fn(model, batch):
        x, y = batch
        keep = (torch.rand(x.shape) > 0.1).float()
        loss = ((model(x * keep) - y) ** 2).mean()
        return loss, {"loss": loss.item(), "kept": float(keep.mean())}

    return fit_loop(lambda: torch.nn.Linear(3, 1), lambda m: torch.optim.AdamW(param_groups(m, 0.01), lr=0.05),
                    sample_batch, step_fn, run, steps=steps, seed=3,
                    schedule=lambda s: warmup_cosine(s, 0.05, 2, steps, 0.1), grad_clip=1.0, log_every=log_every,
                    checkpoint_every=checkpoint_every, torch_generator=True,
                    manifest_config=lambda m: {"parameters": sum(p.numel() for p in m.parameters())},
                    log=lambda *_: None, **kw)


def untimed(history):
    return [{k: v for k, v in r.items() if k not in TIMING} for r in history]


def same_weights(a, b):
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_curve_rows_windows_and_saves():
    run = MemoryRun()
    out = regression(run)
    assert out.step == 10 and [r["step"] for r in out.history] == [3, 6, 9, 10]
    assert list(out.history[0]) == ["step", "lr", "loss", "kept", "grad_norm", "step_s", "elapsed_s", "cpu_s"]
    assert [(s, c) for s, c, _ in run.saves] == [(4, False), (8, False), (10, True)]
    assert run.saves[-1][2] == {"parameters": 4}
    assert out.history[-1]["loss"] < out.history[0]["loss"]
    assert out.history[0]["lr"] == pytest.approx(np.mean([warmup_cosine(s, 0.05, 2, 10, 0.1) for s in range(3)]))
    assert out.elapsed_s == out.history[-1]["elapsed_s"] > 0
    assert run.shown[-1].keys() == {"loss"}
    state = run.saved["state"]
    assert state["loop_format"] == 1 and state["window"] == []
    assert isinstance(state["numpy_rng"], str) and {"torch_rng", "torch_gen"} <= state.keys()


@pytest.mark.parametrize("stop_after", [1, 4, 5, 9])
def test_resume_after_an_interruption_is_the_uninterrupted_run(stop_after):
    """Stopped anywhere (mid-window, on a checkpoint, one step before the end) and resumed
    from what it saved: the same curve step for step and bit-identical weights."""
    straight = regression(MemoryRun())
    first = MemoryRun(stop_after=stop_after)
    part = regression(first)
    assert part.step == stop_after and first.saved["step"] == stop_after and not first.saves[-1][1]
    resumed_run = MemoryRun(saved=first.saved)
    resumed = regression(resumed_run)
    assert resumed_run.started == (10, stop_after)
    assert resumed.step == 10 and untimed(resumed.history) == untimed(straight.history)
    assert same_weights(resumed.model, straight.model)
    assert resumed.elapsed_s >= part.elapsed_s


def test_random_state_round_trip_through_weights_only():
    rand = Randoms(np.random.default_rng(7), torch.Generator().manual_seed(8))
    torch.manual_seed(9)
    rand.numpy.normal(size=5), torch.rand(3, generator=rand.torch), torch.rand(2)  # move every stream
    buf = io.BytesIO()
    torch.save(random_state(rand, torch.device("cpu")), buf)
    saved = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
    want = rand.numpy.normal(size=4), torch.rand(3, generator=rand.torch), torch.rand(2)
    other = Randoms(np.random.default_rng(0), torch.Generator().manual_seed(0))
    torch.manual_seed(0)
    restore_random_state(other, saved, torch.device("cpu"))
    got = other.numpy.normal(size=4), torch.rand(3, generator=other.torch), torch.rand(2)
    assert np.array_equal(want[0], got[0]) and torch.equal(want[1], got[1]) and torch.equal(want[2], got[2])
    assert json.loads(saved["numpy_rng"])["bit_generator"] == "PCG64"


def test_states_saved_before_the_loop_was_one_still_resume():
    """The tokenizer's old state held the numpy state as a dict: it resumes exactly. A state
    the loop cannot use (no optimiser; no generator state where one is needed) is one error."""
    straight = regression(MemoryRun())
    first = MemoryRun(stop_after=5)
    regression(first)
    old = copy.deepcopy(first.saved)
    old["state"]["numpy_rng"] = json.loads(old["state"]["numpy_rng"])
    del old["state"]["loop_format"]
    resumed = regression(MemoryRun(saved=old))
    assert untimed(resumed.history) == untimed(straight.history) and same_weights(resumed.model, straight.model)
    broken = copy.deepcopy(first.saved)
    del broken["state"]["optimizer"]
    with pytest.raises(StateError, match=r"lacks optimizer.*--fresh"):
        regression(MemoryRun(saved=broken))
    broken = copy.deepcopy(first.saved)
    del broken["state"]["torch_gen"]
    with pytest.raises(StateError, match=r"no torch generator state \(torch_gen\).*--fresh"):
        regression(MemoryRun(saved=broken))


def test_a_built_model_and_prefixed_weights():
    """A model built by the caller is trained as given; weights are saved under the prefix
    with the extra ones after, and a resume loads the prefixed ones only."""
    torch.manual_seed(3)
    built = torch.nn.Linear(3, 1)
    run = MemoryRun(stop_after=2)
    out = fit_loop(built, lambda m: torch.optim.SGD(m.parameters(), lr=0.1),
                   lambda rand, step: torch.from_numpy(rand.numpy.normal(size=(4, 3)).astype(np.float32)), _sq, run,
                   steps=4,
                   weights_prefix="net.", extra_weights={"other.w": torch.ones(2)}, log=lambda *_: None)
    assert out.model is built and out.step == 2
    assert list(run.saved["weights"]) == ["net.weight", "net.bias", "other.w"]
    again = fit_loop(torch.nn.Linear(3, 1), lambda m: torch.optim.SGD(m.parameters(), lr=0.1),
                     lambda rand, step: torch.from_numpy(rand.numpy.normal(size=(4, 3)).astype(np.float32)),
                     _sq, MemoryRun(saved=run.saved), steps=4, weights_prefix="net.", log=lambda *_: None)
    assert again.step == 4


def _sq(m, x):
    loss = ((m(x) - 1) ** 2).mean()
    return loss, {"loss": loss.item()}


def test_schedule_and_parameter_groups():
    assert warmup_cosine(0, 1e-3, 10, 110, 0.1) == pytest.approx(1e-4)
    assert warmup_cosine(9, 1e-3, 10, 110, 0.1) == pytest.approx(1e-3)
    assert warmup_cosine(60, 1e-3, 10, 110, 0.1) == pytest.approx(0.55e-3)
    assert warmup_cosine(110, 1e-3, 10, 110, 0.1) == warmup_cosine(10**6, 1e-3, 10, 110, 0.1) == pytest.approx(1e-4)
    net = torch.nn.Sequential(torch.nn.Embedding(4, 3), torch.nn.Linear(3, 3), torch.nn.LayerNorm(3))
    decay, no_decay = param_groups(net, 0.1)
    assert decay["params"] == [net[1].weight] and decay["weight_decay"] == 0.1
    assert len(no_decay["params"]) == 4 and no_decay["weight_decay"] == 0.0
    assert math.isclose(sum(p.numel() for g in (decay, no_decay) for p in g["params"]),
                        sum(p.numel() for p in net.parameters()))


def test_write_curve_draws_whatever_columns_there_are(tmp_path):
    history = [{"step": s, "lr": 0.1, "loss": 1 / s, "accuracy": s / 10, "step_s": 0.1, "elapsed_s": s / 10,
                "cpu_s": s / 10} for s in range(1, 6)]
    csv_path, png = write_curve(history, tmp_path / "out")
    assert csv_path.read_text().splitlines()[0] == "step,lr,loss,accuracy,step_s,elapsed_s,cpu_s"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # panels as data: columns the history lacks are left out, a divisor scales a line
    _, png = write_curve(history, tmp_path / "out", "other", [Panel((("loss", "loss"), ("nope", "absent")), log=True),
                                                              Panel((("accuracy", "acc", 2.0),), ylim=(0, 1))])
    assert png.is_file()


# -- through the harness: real checkpoints, the time budget, weights_only loading -----------------
@dataclass(frozen=True)
class LoopToyOptions:
    steps: int = pcfbench.option(9, help="training steps")


class LoopToy(pcfbench.TrainedMethod):
    """Fits a linear map to the median ranges of the training sweeps through fit_loop."""

    name = "loop-toy"
    Options = LoopToyOptions
    default_train_on = "kitti"
    training_time = "about 1 s (toy)"

    def fit(self, train_source, out_dir, progress):
        adapter = train_source.adapter
        ranges = np.array([float(np.median(np.linalg.norm(adapter.sequence(n).load_points(i), axis=1)))
                           for n in adapter.sequence_names(train_source.split)
                           for i in range(len(adapter.sequence(n)))], np.float32)
        out = regression_on(ranges, progress, self.options.steps)
        write_curve(out.history, out_dir)

    def load(self, checkpoint):
        self.weights = checkpoint.load_weights()

    def forecast(self, sample):  # pragma: no cover - not run here
        raise NotImplementedError


def regression_on(ranges, run, steps):
    def sample_batch(rand, step):
        k = rand.numpy.integers(0, len(ranges), 4)
        x = torch.from_numpy(ranges[k])[:, None] / 10
        return x, 2 * x + torch.randn(4, 1, generator=rand.torch)

    def step_fn(model, batch):
        x, y = batch
        loss = ((model(x) - y) ** 2).mean()
        return loss, {"loss": loss.item()}

    return fit_loop(lambda: torch.nn.Linear(1, 1), lambda m: torch.optim.SGD(m.parameters(), lr=0.05),
                    sample_batch, step_fn, run, steps=steps, log_every=2, checkpoint_every=4, torch_generator=True,
                    log=run.log)


@pytest.fixture
def harness(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    from pcfbench.hookspecs import hookimpl
    from pcfbench.plugins import load_plugins

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=6, beams=8, azimuths=90)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    module = types.ModuleType("pcfb_loop_toy")

    @hookimpl
    def register_methods(register):
        register("loop-toy", LoopToy, "a toy method trained by fit_loop")

    module.register_methods = register_methods
    plugins = load_plugins()
    plugins.add_plugin(module, "loop-toy")

    def run(**kw):
        return train(resolve_method("loop-toy", plugins), f"kitti={root}", plugins=plugins, progress=False,
                     log=lambda *_: None, threads=1, **kw)

    return run


def test_time_budget_stop_then_resume_through_the_harness(harness):
    """--max-minutes 0 stops after one step with a checkpoint whose files load with
    weights_only=True; the rerun completes the uninterrupted run's curve and weights."""
    first = harness(max_minutes=0)
    assert first.steps == 1 and not first.manifest["complete"]
    state = torch.load(first.dir / first.manifest["state"], weights_only=True)
    assert state["loop_format"] == 1 and state["window"][0]["step"] == 1 and state["history"] == []
    done = harness()
    assert done.steps == 9 and done.manifest["complete"]
    curve = (done.dir / "curve.csv").read_text()
    resumed_state, resumed_w = done.load_state(), done.load_weights()
    straight = harness(fresh=True)
    assert untimed(straight.load_state()["history"]) == untimed(resumed_state["history"])
    assert straight.sha256 == done.sha256 and all(torch.equal(v, straight.load_weights()[k]) for k, v in resumed_w.items())
    assert curve.splitlines()[0] == "step,lr,loss,grad_norm,step_s,elapsed_s,cpu_s"
    assert done.manifest["wall_s"] >= first.manifest["wall_s"]
