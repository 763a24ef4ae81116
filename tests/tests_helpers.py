"""Helpers importable by test modules (conftest fixtures cover the common cases)."""

import dataclasses
import os

import numpy as np

import pcfbench
from conftest import write_tiny_kitti
from pcfbench.data import Forecast
from pcfbench.method import Method
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins


def write_kitti_tree(root, sequences=("08",), num_sweeps=24):
    return write_tiny_kitti(root, sequences=sequences, num_sweeps=num_sweeps)


class Shifted(Method):
    """The last past sweep moved by ``dx`` metres along x."""

    name = "shifted"

    @dataclasses.dataclass(frozen=True)
    class Options:
        dx: float = pcfbench.option(0.0, help="shift along x (m)")

    def forecast(self, sample):
        last = sample.past_points_ref[-1] + np.array([self.options.dx, 0, 0], dtype=np.float32)
        return Forecast(points_ref=tuple(last for _ in range(sample.num_future)))


def shifted_plugins():
    """The built-in plugins and the test method ``shifted``."""
    plugins = load_plugins()
    if "shifted" not in plugins.methods:
        plugins.methods.add("shifted", Shifted, "test")
    return plugins


#: the sample at which the failing test methods below fail: the tiny KITTI tree's reference
#: index 8 (its first kitti-1s sample)
BAD_INDEX = 8


class Exits(CopyLast):
    """Kills its own process (exit 3) on the sample at ``BAD_INDEX``, copies the last sweep elsewhere."""

    name = "exits"

    def forecast(self, sample):
        if sample.ref_index == BAD_INDEX:
            os._exit(3)
        return super().forecast(sample)


class Raises(CopyLast):
    """Raises on the sample at ``BAD_INDEX``, copies the last sweep elsewhere."""

    name = "raises"

    def forecast(self, sample):
        if sample.ref_index == BAD_INDEX:
            raise RuntimeError("boom")
        return super().forecast(sample)


def chromium() -> str:
    """Debian's chromium for the browser tests: skipped where it is missing, a failure in CI
    (``bash .ci/setup test`` installs it)."""
    import os
    import shutil

    import pytest

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing: bash .ci/setup test installs it (apt-get install chromium)")
        pytest.skip("chromium is not installed (bash .ci/setup test installs it)")
    return exe


def headless(exe: str, *args: str) -> str:
    """Run headless chromium with ``args``; its standard output (a dumped DOM)."""
    import subprocess

    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
           "--hide-scrollbars", "--virtual-time-budget=5000", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


def check_ships_without_its_tokenizer(tok_spec: str, world_spec: str, kitti) -> None:
    """A world model on a tokenizer (``pcfbench.training.tokenized.OnTokenizer``), both trained
    on ``kitti`` here, the methods' shipped folders redirected by the caller: shipped alone, the
    world model keeps its copy of the tokenizer; shipped after the tokenizer, it leaves the copy
    out, says where it is, and loads the same tensors; with the tokenizer's gone, loading is one
    error that says so."""
    import pytest
    import torch

    from pcfbench.method import resolve_method
    from pcfbench.training import CheckpointError, open_training_data, train
    from pcfbench.training.checkpoints import ship

    quiet = lambda *_: None  # noqa: E731
    tok = train(resolve_method(tok_spec), f"kitti={kitti}", progress=False, log=quiet)
    world = train(resolve_method(world_spec), f"kitti={kitti}", progress=False, log=quiet)
    train_on = open_training_data(f"kitti={kitti}", progress=False).train_on
    spec = resolve_method(world_spec)

    whole = ship(spec, world, train_on, "retrain", log=quiet)  # its tokenizer not shipped: the copy stays
    assert {k.split(".")[0] for k in whole.load_weights()} == {"world", "tokenizer"}
    assert "left_out" not in whole.manifest["shipped"]
    with_copy, whole_bytes = spec.create(), whole.weights_path.stat().st_size
    with_copy.load(whole)

    tok_shipped = ship(resolve_method(tok_spec), tok, train_on, "retrain", log=quiet)
    alone = ship(spec, world, train_on, "retrain", log=quiet)
    assert {k.split(".")[0] for k in alone.load_weights()} == {"world"}
    assert alone.manifest["shipped"]["left_out"] == {"prefix": "tokenizer.", "method": tok_spec.split(":")[0],
                                                     "weights_sha256": tok_shipped.sha256}
    assert alone.weights_path.stat().st_size < whole_bytes  # shipped again into the same folder
    m = spec.create()
    m.load(alone)
    for k, v in with_copy.tokenizer.state_dict().items():
        assert torch.equal(v, m.tokenizer.state_dict()[k]), k
    for k, v in with_copy.world.state_dict().items():
        assert torch.equal(v, m.world.state_dict()[k]), k

    for f in tok_shipped.dir.iterdir():
        f.unlink()
    with pytest.raises(CheckpointError, match="ships without its tokenizer.*missing"):
        spec.create().load(alone)
