"""World models on a tokenizer (pcfbench.training.tokenized): occworld on occworld-occ-copy
and bevworld on bevworld-latent-copy keep a copy of their tokenizer in their checkpoint, ship
without it when the tokenizer ships, and refuse what is not theirs, one error each."""

from __future__ import annotations

import json

import pytest
import torch

from pcfbench.method import resolve_method
from tests_helpers import check_ships_without_its_tokenizer

#: (tokenizer spec, world model spec, the classes whose shipped folder the test redirects)
FAMILIES = {
    "occworld": ("occworld-occ-copy:config=micro,steps=2",
                 "occworld:config=micro,strides=2,anchor_every=4,tokenizer_steps=2,steps=2",
                 ("pcfbench.methods.occworld.occ_copy:OccCopy", "pcfbench.methods.occworld.forecaster:OccWorld")),
    "bevworld": ("bevworld-latent-copy:config=micro,steps=2",
                 "bevworld:config=micro,strides=2,anchor_every=4,tokenizer_steps=2,steps=2",
                 ("pcfbench.methods.bevworld.latent_copy:LatentCopy", "pcfbench.methods.bevworld.forecaster:BevWorld")),
}


@pytest.fixture
def micro(monkeypatch, tmp_path):
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: more threads only contend
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def kitti(tmp_path):
    from conftest import write_tiny_kitti

    return write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=20, beams=8, azimuths=180)


def _train(spec: str, root):
    from pcfbench.training import train

    return train(resolve_method(spec), f"kitti={root}", progress=False, log=lambda *_: None)


def _class(path: str):
    import importlib

    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_the_world_model_ships_without_its_tokenizer_when_the_tokenizer_ships(family, micro, kitti, tmp_path,
                                                                            monkeypatch):
    """A world model's checkpoint holds a copy of its tokenizer; shipped, it leaves the copy out
    when the tokenizer's shipped checkpoint for the same data holds the same tokenizer, and loads
    it from there; when that one is gone, loading is one error that says so."""
    tok_spec, world_spec, classes = FAMILIES[family]
    for cls in classes:
        monkeypatch.setattr(_class(cls), "shipped_checkpoints", str(tmp_path / "shipped"))
    check_ships_without_its_tokenizer(tok_spec, world_spec, kitti)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_a_checkpoint_that_is_not_the_world_models_is_one_error(family, micro, kitti, tmp_path):
    """The tokenizer's own checkpoint read as the world model's, a checkpoint whose tokenizer
    tensors were altered, and a resumed training on another tokenizer checkpoint: each one
    error naming the file."""
    from pcfbench.training import Checkpoint, CheckpointError
    from pcfbench.training.checkpoints import MANIFEST, sha256_hex

    tok_spec, world_spec, _ = FAMILIES[family]
    tok = _train(tok_spec, kitti)
    world = _train(world_spec, kitti)
    with pytest.raises(CheckpointError, match=f"{tok.manifest_path}.*records no config.world"):
        resolve_method(world_spec).create().load(tok)

    weights = world.load_weights()
    key = next(k for k in sorted(weights) if k.startswith("tokenizer.") and weights[k].is_floating_point())
    weights[key] = weights[key] + 1.0
    torch.save(weights, world.weights_path)
    manifest = json.loads(world.manifest_path.read_text())
    manifest["weights_sha256"] = sha256_hex(world.weights_path.read_bytes())
    (world.dir / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match="tokenizer weights are not the tokenizer it was trained with"):
        resolve_method(world_spec).create().load(Checkpoint.open(world.dir))

    other = resolve_method(world_spec).create()
    manifest["config"]["tokenizer_sha256"] = "0" * 64
    (world.dir / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match=f"{world.dir / MANIFEST} was trained on the .* of tokenizer 000000000000"):
        other.check_resumed_tokenizer(world.dir, tok)
