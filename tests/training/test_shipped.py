"""Shipped checkpoints: the mechanism on a toy trained method (float16 copy with a manifest,
fallback from the cache, matching local data by content, refusals), and every checkpoint
shipped inside pcfbench (manifest, sha256, size, the float16 round trip loads)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from pcfbench.method import resolve_method
from pcfbench.training import (
    Checkpoint, CheckpointError, TrainingRun, checkpoint_dir, checkpoint_for, find_checkpoint, open_training_data, ship,
    shipped_dir,
)
from pcfbench.training.checkpoints import SHIPPED_LIMIT_BYTES, may_have_checkpoint, shipped_mismatch

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"pcfbench": ROOT / "bench", "pcfbench.methods": ROOT / "methods", "pcfbench.datasets": ROOT / "datasets"}


def shipped_manifests() -> list[Path]:
    return sorted(p for base in PACKAGES.values() for p in base.rglob("checkpoints/**/manifest.json"))


@pytest.fixture
def toy(tmp_path, monkeypatch):
    import types

    from conftest import write_tiny_kitti
    from test_training import ToyTrained, toy_plugins

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=12)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    monkeypatch.setattr(ToyTrained, "shipped_checkpoints", tmp_path / "shipped")
    plugins = toy_plugins()
    data = f"kitti={root}"
    spec = resolve_method("toy-trained", plugins)
    source = open_training_data(data, "train", plugins, False)
    return types.SimpleNamespace(root=root, plugins=plugins, data=data, spec=spec, source=source, tmp=tmp_path)


def _save(toy, complete=True):
    """A cache checkpoint with float32, float64 and integer tensors."""
    import torch

    run = TrainingRun(toy.spec, toy.source.train_on, checkpoint_dir(toy.spec, toy.source.train_on), progress=False)
    weights = {"a": torch.linspace(-3, 3, 101, dtype=torch.float32), "w": torch.tensor([2.5], dtype=torch.float64),
               "n": torch.arange(4)}
    run.save(7, weights, {"history": []}, config={"size": 101}, complete=complete)
    return Checkpoint.open(run.out_dir), weights


def test_ship_writes_float16_weights_and_a_manifest_and_is_found_when_the_cache_has_none(toy):
    import torch

    ck, weights = _save(toy)
    shipped = ship(toy.spec, ck, toy.source.train_on, "pcfbench train toy-trained --dataset kitti=ROOT --fresh --ship",
                   log=lambda *a: None)
    assert shipped.dir == shipped_dir(toy.spec, "kitti", "train") == (
        toy.tmp / "shipped" / "toy-trained" / "v1" / toy.spec.options_hash / "kitti.train")
    m = json.loads((shipped.dir / "manifest.json").read_text())
    assert sorted(p.name for p in shipped.dir.iterdir()) == ["manifest.json", "weights-00000007.fp16.pt"]
    assert m["weights_dtype"] == "float16" and m["state"] is None and m["steps"] == 7 and m["complete"]
    assert m["config"] == {"size": 101} and m["train_on"] == ck.manifest["train_on"] and m["git_commit"] == ck.manifest["git_commit"]
    assert m["shipped"]["from_weights_sha256"] == ck.sha256
    assert m["shipped"]["data_sha256"] == toy.source.train_on.content_sha256()
    assert m["shipped"]["retrain"].startswith("pcfbench train toy-trained")
    assert hashlib.sha256((shipped.dir / m["weights"]).read_bytes()).hexdigest() == m["weights_sha256"]
    raw = torch.load(shipped.weights_path, weights_only=True)
    assert raw["a"].dtype == torch.float16 and raw["w"].dtype == torch.float64 and raw["n"].dtype == torch.int64
    back = shipped.load_weights()  # float16 comes back float32; the rest as saved
    assert back["a"].dtype == torch.float32 and torch.equal(back["a"], weights["a"].half().float())
    assert float((back["a"] - weights["a"]).abs().max()) <= 3 * 2 ** -11  # float16's relative precision
    assert torch.equal(back["w"], weights["w"]) and torch.equal(back["n"], weights["n"])
    # the cache one wins while it exists ...
    assert find_checkpoint(toy.spec, toy.source.train_on).dir == ck.dir
    # ... and without it the shipped one is found, verified, by readiness and by the run's lookup
    for f in ck.dir.iterdir():
        f.unlink()
    assert may_have_checkpoint(toy.spec, "kitti")
    assert find_checkpoint(toy.spec, toy.source.train_on).sha256 == shipped.sha256
    found = checkpoint_for(toy.spec, train_on=toy.data, plugins=toy.plugins, progress=False)
    assert found.dir == shipped.dir and found.shipped and found.sha256 == m["weights_sha256"]


def test_shipped_checkpoint_matches_local_data_by_content_not_file_times(toy):
    ck, _ = _save(toy)
    ship(toy.spec, ck, toy.source.train_on, "retrain", log=lambda *a: None)
    for f in ck.dir.iterdir():
        f.unlink()
    first = sorted(toy.root.rglob("*.bin"))[0]
    os.utime(first, ns=(1, 1))  # the same bytes, another time: the same data (fingerprints are of content)
    again = open_training_data(toy.data, "train", toy.plugins, False).train_on
    assert again.fingerprint == toy.source.train_on.fingerprint
    assert find_checkpoint(toy.spec, again) is not None and shipped_mismatch(toy.spec, again) is None
    before = toy.source.train_on.content_sha256()  # what the shipped manifest records
    data = bytearray(first.read_bytes())
    data[0] ^= 1  # other data: the shipped checkpoint is not for it
    first.write_bytes(bytes(data))
    other = open_training_data(toy.data, "train", toy.plugins, False).train_on
    assert find_checkpoint(toy.spec, other) is None
    why = shipped_mismatch(toy.spec, other)  # the default run says which data the shipped one is for
    assert why == (f"it was trained on other bytes of kitti:train (content sha256 "
                   f"{before[:12]}, here {other.content_sha256()[:12]}; "
                   f"a generated dataset's bytes can differ from one CPU to another)")
    assert not may_have_checkpoint(resolve_method("toy-trained:lr=0.2", toy.plugins), "kitti")
    with pytest.raises(CheckpointError, match="no checkpoint of toy-trained trained on kitti:train"):
        checkpoint_for(toy.spec, train_on=toy.data, plugins=toy.plugins, progress=False)


def test_shipping_refuses_incomplete_tampered_and_oversized(toy):
    import pcfbench.training.checkpoints as training

    ck, _ = _save(toy, complete=False)
    with pytest.raises(CheckpointError, match=r"manifest.json is not complete \(7 steps\)"):
        ship(toy.spec, ck, toy.source.train_on, "retrain", log=lambda *a: None)
    ck, _ = _save(toy)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(training, "SHIPPED_LIMIT_BYTES", 100)
        with pytest.raises(CheckpointError, match="would exceed 100 bytes of shipped checkpoints"):
            ship(toy.spec, ck, toy.source.train_on, "retrain", log=lambda *a: None)
    assert not (toy.tmp / "shipped").exists()
    shipped = ship(toy.spec, ck, toy.source.train_on, "retrain", log=lambda *a: None)
    for f in ck.dir.iterdir():
        f.unlink()
    good = shipped.weights_path.read_bytes()
    shipped.weights_path.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(CheckpointError, match=rf"{shipped.weights_path}.*does not match the sha256"):
        find_checkpoint(toy.spec, toy.source.train_on)


@pytest.mark.parametrize("manifest_path", shipped_manifests(), ids=lambda p: str(p.parent.relative_to(ROOT)))
def test_every_shipped_checkpoint_verifies_and_loads(manifest_path):
    """Each shipped checkpoint: its manifest's record, its sha256, the method and options it
    names (a registered method with those options), float16 weights that load through the
    method's own ``load`` (weights_only) as float32."""
    import torch

    from pcfbench.plugins import get_plugins

    m = json.loads(manifest_path.read_text())
    for key in ("config", "train_on", "steps", "wall_s", "cpu_s", "git_commit", "weights_sha256", "device", "torch"):
        assert m.get(key) is not None, f"{manifest_path} lacks {key}"
    assert m["complete"] and m["weights_dtype"] == "float16" and m["state"] is None
    assert {"dataset", "split", "fingerprint"} <= set(m["train_on"])
    assert {"from_weights_sha256", "data_sha256", "retrain"} <= set(m["shipped"])
    assert m["shipped"]["retrain"].startswith(f"pcfbench train {m['method']}") and "--ship" in m["shipped"]["retrain"]
    if m["device"] == "cpu" and m.get("threads"):  # the command that rebuilds the bits names the thread count
        assert f"--threads {m['threads']} " in m["shipped"]["retrain"]
    ck = Checkpoint.open(manifest_path.parent)  # sha256 of the weights
    # the options as the command line gives them (a tuple option's items joined by "/")
    raw_options = {k: "/".join(map(str, v)) if isinstance(v, list) else str(v) for k, v in m["options"].items()}
    spec = resolve_method((m["method"], raw_options), get_plugins())
    ck.check_method(spec)
    # where the installed package finds it: this very folder (editable), or its copy in the
    # installed package, byte for byte (a wheel)
    installed = shipped_dir(spec, m["train_on"]["dataset"], m["train_on"]["split"])
    folder = manifest_path.parent
    if installed != folder:
        rel = folder.relative_to(ROOT).parts
        assert installed.parts[-len(rel) + 1:] == rel[1:], (installed, folder)
        for f in folder.iterdir():
            assert (installed / f.name).read_bytes() == f.read_bytes(), f"installed copy of {f} differs"
    raw = torch.load(ck.weights_path, weights_only=True)
    assert any(v.dtype == torch.float16 for v in raw.values()) and not any(v.dtype == torch.float32 for v in raw.values())
    assert all(v.dtype != torch.float16 for v in ck.load_weights().values())
    method = spec.create()
    method.load(ck)
    # trained on a dataset that makes its own data: found by its recipe, which is today's, so a
    # run takes it without making the training data (and whatever bytes this CPU would make)
    from pcfbench.training import data_recipe_sha256

    recipe = data_recipe_sha256(m["train_on"]["dataset"], m["train_on"]["split"])
    if recipe is not None:
        assert m["shipped"].get("data_recipe_sha256") == recipe, (
            f"{manifest_path} was trained on another recipe of {m['train_on']['dataset']}: retrain it "
            f"({m['shipped']['retrain']})")


def test_shipped_checkpoints_stay_small():
    files = [f for base in PACKAGES.values() for d in base.rglob("checkpoints") for f in d.rglob("*") if f.is_file()]
    assert sum(f.stat().st_size for f in files) <= SHIPPED_LIMIT_BYTES


def test_shipping_counts_every_method_package_of_the_distribution():
    """``ship`` weighs what the whole of pcfbench carries, not one method's folder: the same
    files as this checkout's, installed editable or as a wheel (the copies there, by name)."""
    from pcfbench.methods.bevworld.forecaster import BevWorld
    from pcfbench.methods.copy_last import CopyLast
    from pcfbench.training.checkpoints import shipped_files

    here = sorted((f.parent.name, f.name, f.stat().st_size) for base in PACKAGES.values()
                  for d in base.rglob("checkpoints") for f in d.rglob("*") if f.is_file())
    assert here  # the project ships checkpoints
    for cls in (BevWorld, CopyLast):  # any class of the package: CopyLast's own folder holds none
        assert sorted((f.parent.name, f.name, f.stat().st_size) for f in shipped_files(cls)) == here


@pytest.fixture
def made(toy, monkeypatch):
    """``toy-made``: a dataset that makes its own data (the tiny KITTI root stands for it) by a
    recipe, with the toy method trained on it and shipped; ``made.roots`` counts the times its
    data was made or opened at its default root."""
    import types

    from pcfbench.datasets.kitti import KittiOdometry
    from pcfbench.hookspecs import hookimpl

    roots = []

    class Made(KittiOdometry):
        name = "toy-made"
        seed = 1

        @classmethod
        def default_root(cls, progress=True):
            roots.append(1)
            return toy.root

        @classmethod
        def recipe(cls, split):
            return {"seed": cls.seed, "split": split} if split in ("train", "test") else None

    module = types.ModuleType("pcfb_toy_made")
    module.register_datasets = hookimpl(lambda register: register("toy-made", Made, "a made toy dataset"))
    toy.plugins.add_plugin(module, "toy-made")
    source = open_training_data("toy-made", "train", toy.plugins, False)
    run = TrainingRun(toy.spec, source.train_on, checkpoint_dir(toy.spec, source.train_on), progress=False)
    run.save(3, {"a": __import__("torch").zeros(4)}, {"history": []}, config={}, complete=True)
    shipped = ship(toy.spec, Checkpoint.open(run.out_dir), source.train_on, "retrain", log=lambda *a: None)
    for f in run.out_dir.iterdir():
        f.unlink()
    run.out_dir.rmdir()
    roots.clear()
    return types.SimpleNamespace(cls=Made, roots=roots, shipped=shipped, source=source)


def test_shipped_checkpoint_of_a_made_dataset_is_found_by_its_recipe_without_making_the_data(toy, made):
    from pcfbench.cli import _selected_methods
    from pcfbench.training import find_shipped_by_recipe, recipe_sha256

    m = json.loads((made.shipped.dir / "manifest.json").read_text())
    assert m["shipped"]["data_recipe_sha256"] == recipe_sha256({"seed": 1, "split": "train"}) == made.source.train_on.recipe
    found = checkpoint_for(toy.spec, train_on="toy-made", plugins=toy.plugins, progress=False)
    assert found.sha256 == made.shipped.sha256 and made.roots == []  # no data made or read
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(toy.spec.cls, "default_train_on", "toy-made")
        assert "toy-trained" in [s.name for s in _selected_methods(toy.plugins, ())] and made.roots == []
    # the bytes are not compared on this path (they can differ by CPU): a flipped bit still finds it
    first = sorted(toy.root.rglob("*.bin"))[0]
    first.write_bytes(bytes([first.read_bytes()[0] ^ 1]) + first.read_bytes()[1:])
    assert find_shipped_by_recipe(toy.spec, "toy-made", "train", toy.plugins).sha256 == made.shipped.sha256
    # a root given, or another recipe: the data is opened and matched by content, which now differs
    assert find_shipped_by_recipe(toy.spec, f"toy-made={toy.root}", "train", toy.plugins) is None
    made.cls.seed = 2
    assert find_shipped_by_recipe(toy.spec, "toy-made", "train", toy.plugins) is None
    with pytest.raises(CheckpointError, match="no checkpoint of toy-trained trained on toy-made:train"):
        checkpoint_for(toy.spec, train_on="toy-made", plugins=toy.plugins, progress=False)
    assert made.roots  # it had to open the data to say so


def test_a_checkpoint_trained_here_wins_over_the_shipped_one_found_by_recipe(toy, made):
    source = open_training_data("toy-made", "train", toy.plugins, False)
    run = TrainingRun(toy.spec, source.train_on, checkpoint_dir(toy.spec, source.train_on), progress=False)
    run.save(5, {"a": __import__("torch").ones(4)}, {"history": []}, config={}, complete=True)
    here = Checkpoint.open(run.out_dir)
    assert checkpoint_for(toy.spec, train_on="toy-made", plugins=toy.plugins, progress=False).sha256 == here.sha256
