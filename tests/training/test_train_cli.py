"""``pcfbench train`` as a person meets it: Ctrl-C says which checkpoint was kept and the command
that resumes it; off a terminal the progress is labelled log lines at a sane rate, not a bar;
``ls methods`` lists each trained method's checkpoints and their data (issue 46)."""

from __future__ import annotations

import json
import os
import re
import shlex
import types
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from click.testing import CliRunner

import pcfbench
import pcfbench.training.trained
from pcfbench.training import fit_loop


@dataclass(frozen=True)
class StopToyOptions:
    steps: int = pcfbench.option(9, help="training steps")


class StopToy(pcfbench.TrainedMethod):
    """A linear map fitted through fit_loop (a save every 4 steps); ``STOP_TOY_AT=N`` makes its
    step function raise KeyboardInterrupt at the N-th step (1-based), as Ctrl-C would."""

    name = "stop-toy"
    Options = StopToyOptions
    default_train_on = "kitti"
    training_time = "about 1 s (toy)"

    def fit(self, train_source, out_dir, progress):
        stop_at = int(os.environ.get("STOP_TOY_AT", "0"))
        calls = []

        def sample_batch(rand, step):
            calls.append(step)
            x = torch.from_numpy(rand.numpy.normal(size=(4, 1)).astype(np.float32))
            return x, 2 * x

        def step_fn(model, batch):
            if len(calls) and calls[-1] + 1 == stop_at:
                raise KeyboardInterrupt
            x, y = batch
            loss = ((model(x) - y) ** 2).mean()
            return loss, {"loss": loss.item(), "w": float(model.weight.item())}

        fit_loop(lambda: torch.nn.Linear(1, 1), lambda m: torch.optim.SGD(m.parameters(), lr=0.05), sample_batch,
                 step_fn, progress, steps=self.options.steps, log_every=2, checkpoint_every=4,
                 progress_values={"squared error": "loss", "slope": "w"}, log=progress.log)

    def load(self, checkpoint):  # pragma: no cover - not run here
        self.weights = checkpoint.load_weights()

    def forecast(self, sample):  # pragma: no cover - not run here
        raise AssertionError("the Ctrl-C tests train this method; none of them evaluates it")


@pytest.fixture
def env(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    from pcfbench.cli import build_cli
    from pcfbench.hookspecs import hookimpl
    from pcfbench.plugins import load_plugins

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00",), num_sweeps=4, beams=8, azimuths=90)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("PCFBENCH_NO_PROGRESS", raising=False)
    monkeypatch.delenv("STOP_TOY_AT", raising=False)
    module = types.ModuleType("pcfb_stop_toy")

    @hookimpl
    def register_methods(register):
        register("stop-toy", StopToy, "a toy method trained by fit_loop")

    module.register_methods = register_methods
    plugins = load_plugins()
    plugins.add_plugin(module, "stop-toy")
    monkeypatch.setattr("pcfbench.cli.get_plugins", lambda: plugins)
    cli = build_cli()

    def invoke(*args):
        return CliRunner().invoke(cli, list(args), catch_exceptions=False)

    return types.SimpleNamespace(root=root, data=f"kitti={root}", invoke=invoke, cache=tmp_path / "cache")


def _interrupt_note(res) -> tuple[str, str]:
    """The interrupt's two lines (what is kept; the command) from a train that exited 130."""
    assert res.exit_code == 130, res.output
    assert "Aborted!" not in res.output and "Traceback" not in res.output
    lines = res.output.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("pcfbench: training interrupted"))
    assert lines[at + 1].startswith("  pcfbench train "), lines
    return lines[at], lines[at + 1].strip()


def test_ctrl_c_names_the_checkpoint_kept_and_the_command_that_resumes_it(env, monkeypatch):
    monkeypatch.setenv("STOP_TOY_AT", "7")  # after the save of step 4
    res = env.invoke("train", "stop-toy", "--dataset", env.data, "--threads", "1", "--fresh", "-q")
    note, command = _interrupt_note(res)
    manifest = next(env.cache.rglob("manifest.json"))
    assert note == (f"pcfbench: training interrupted at step 6 of 9: the checkpoint of step 4 is kept, {manifest}; "
                    "resume it (steps 5..6 are trained again) with:")
    # the same options but --fresh, which would throw the kept checkpoint away
    assert command == f"pcfbench train stop-toy --dataset {shlex.quote(env.data)} --threads 1 --quiet"
    assert json.loads(manifest.read_text())["steps"] == 4
    monkeypatch.delenv("STOP_TOY_AT")
    again = env.invoke(*shlex.split(command)[1:])
    assert again.exit_code == 0, again.output
    assert f"resuming {manifest.parent} at step 4" in again.output
    assert "stop-toy: 9 steps on kitti:train" in again.output and "(complete)" in again.output


def test_ctrl_c_before_the_first_checkpoint_says_nothing_is_kept(env, monkeypatch):
    monkeypatch.setenv("STOP_TOY_AT", "3")
    res = env.invoke("train", "stop-toy:steps=8", "--dataset", env.data, "--split", "train", "--max-minutes", "5", "-q")
    note, command = _interrupt_note(res)
    folder = next((env.cache / "checkpoints" / "stop-toy").glob("v*/*/kitti.train.*"))
    assert note == (f"pcfbench: training interrupted at step 2 of 8, before its first checkpoint: nothing is kept in "
                    f"{folder}; start again with:")
    assert command == f"pcfbench train stop-toy:steps=8 --dataset {shlex.quote(env.data)} --max-minutes 5 --quiet"


def test_off_a_terminal_progress_is_labelled_log_lines_at_a_sane_rate(env, monkeypatch):
    # CliRunner's stderr is no terminal: no bar; a line at the first step, then every LOG_EVERY_S
    # seconds (far more than this training takes), and at the last step
    res = env.invoke("train", "stop-toy", "--dataset", env.data, "--threads", "1")
    assert res.exit_code == 0, res.output
    assert "\r" not in res.output and "it/s" not in res.output and "step/s" not in res.output
    lines = [line for line in res.output.splitlines() if line.startswith("train stop-toy: ")]
    pattern = (r"train stop-toy: step {}/9 \({}%\), [0-9.e+-]+ s/step, \d+ s left; "
               r"squared error [0-9.e+-]+, slope [0-9.e+-]+")
    assert len(lines) == 2, res.output
    assert re.fullmatch(pattern.format(1, 11), lines[0]), lines[0]
    assert re.fullmatch(pattern.format(9, 100), lines[1]), lines[1]
    # with no interval, every step has its line
    monkeypatch.setattr(pcfbench.training.trained, "LOG_EVERY_S", 0.0)
    res = env.invoke("train", "stop-toy", "--dataset", env.data, "--threads", "1", "--fresh")
    steps = [int(m.group(1)) for m in re.finditer(r"^train stop-toy: step (\d+)/9 ", res.output, re.M)]
    assert steps == list(range(1, 10)), res.output
    # --quiet: neither bar nor lines
    res = env.invoke("train", "stop-toy", "--dataset", env.data, "--threads", "1", "--fresh", "-q")
    assert res.exit_code == 0 and "train stop-toy: step" not in res.output


def test_ls_methods_lists_each_trained_method_s_checkpoints_and_their_data(env, monkeypatch):
    res = env.invoke("ls", "methods")
    assert ("stop-toy" in res.output and "    no checkpoint: `pcfbench train stop-toy --dataset kitti` trains the "
            "checkpoint it uses by default" in res.output)
    assert env.invoke("train", "stop-toy", "--dataset", env.data, "--threads", "1", "-q").exit_code == 0
    monkeypatch.setenv("STOP_TOY_AT", "6")
    assert env.invoke("train", "stop-toy:steps=20", "--dataset", env.data, "--threads", "1", "-q").exit_code == 130
    complete, unfinished = sorted(env.cache.rglob("manifest.json"), key=lambda p: json.loads(p.read_text())["steps"],
                                  reverse=True)
    res = env.invoke("ls", "methods")
    block = res.output.split("stop-toy", 1)[1].splitlines()[1:3]
    assert sorted(block) == sorted([
        f"    checkpoint kitti:train (root {env.root}): 9 steps, complete; {complete}",
        f"    checkpoint kitti:train (root {env.root}, options steps=20): 4 steps, unfinished (rerun its pcfbench train "
        f"to continue); {unfinished}",
    ]), res.output
    rows = {r["name"]: r for r in json.loads(env.invoke("ls", "methods", "--json").output)}
    assert "checkpoints" not in rows["copy-last"]
    mine = sorted(rows["stop-toy"]["checkpoints"], key=lambda c: c["steps"])
    assert [(c["where"], c["train_on"], c["options"], c["steps"], c["complete"]) for c in mine] == [
        ("cache", "kitti:train", {"steps": 20}, 4, False), ("cache", "kitti:train", {}, 9, True)]
    # the shipped ones are listed with their data, from the package
    shipped = [c for c in rows["copilot4d-token-copy"]["checkpoints"] if c["where"] == "shipped"]
    assert {c["train_on"] for c in shipped} >= {"synthetic-town:train", "synthetic-town-realistic:train"}
    assert all(c["complete"] and c["root"] is None for c in shipped)
    # a shipped checkpoint of the default options lists none as differing, a tuple option (strides)
    # included: its manifest holds it as a JSON list
    world = [c for c in rows["copilot4d"]["checkpoints"] if c["where"] == "shipped"]
    assert world and all(c["options"] == {} for c in world), world


def test_ctrl_c_while_opening_the_data_says_nothing_was_trained(env, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pcfbench.training.trained, "open_training_data", interrupted)
    res = env.invoke("train", "stop-toy", "--dataset", env.data)
    assert res.exit_code == 130 and "Aborted!" not in res.output
    assert res.output.strip().splitlines()[-1] == "pcfbench: interrupted before training began: nothing was trained or saved"
