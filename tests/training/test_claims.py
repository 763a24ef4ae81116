"""Issue 45: a checkpoint's claims are checked, not believed. An unfinished checkpoint is
marked with its steps of those planned; a manifest's training data is verified by content
where the data is at hand (marked otherwise); training on a copy of the test sweeps under
other names is caught by content."""

from __future__ import annotations

import json
import shutil

import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.reporting.report import collect
from pcfbench.training import Checkpoint
from test_training import _cell, _train, toy_plugins


@pytest.fixture
def env(tmp_path, monkeypatch):
    """The toy trained method and a tiny KITTI tree with train (00, 01) and test (08) sequences."""
    import types

    from conftest import write_tiny_kitti

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "01", "08"), num_sweeps=24)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    return types.SimpleNamespace(root=root, plugins=toy_plugins(), tmp=tmp_path, data=f"kitti={root}")


def _meta(result):
    return json.loads((result.path / "cell.json").read_text())


def _variants(env):
    board = collect(env.tmp / "store")
    return sorted(board.partial["variant"])


def test_an_unfinished_checkpoint_is_marked_with_its_steps(env):
    ck = _train(env, max_minutes=0)  # stops after its first step
    assert ck.manifest["steps"] == 1 and ck.manifest["steps_planned"] == 12 and not ck.manifest["complete"]
    meta = _meta(_cell(env, ck))
    assert meta["checkpoint_steps"] == {"trained": 1, "planned": 12, "complete": False}
    assert _variants(env) == [f"toy-trained [trained on kitti:train (UNFINISHED 1 of 12 steps), ck {ck.sha256[:8]}]"]


def test_a_finished_checkpoint_on_data_at_hand_is_verified_and_unmarked(env):
    ck = _train(env)
    meta = _meta(_cell(env, ck))
    assert meta["checkpoint_steps"] == {"trained": 12, "planned": 12, "complete": True}
    assert meta["training_data_check"]["status"] == "verified"
    assert _variants(env) == [f"toy-trained [trained on kitti:train, ck {ck.sha256[:8]}]"]


def _claim(ck, **train_on):
    """Edit what the manifest claims of its training data (the weights' sha256 is unchanged)."""
    m = json.loads(ck.manifest_path.read_text())
    m["train_on"].update(train_on)
    ck.manifest_path.write_text(json.dumps(m))
    return Checkpoint.open(ck.dir)


def test_a_manifest_claiming_other_training_data_is_marked(env):
    from conftest import write_tiny_kitti

    ck = _train(env)
    other = write_tiny_kitti(env.tmp / "other", sequences=("00",), num_sweeps=30)
    claimed = _claim(ck, root=str(other))  # "trained on that kitti": its content says otherwise
    meta = _meta(_cell(env, claimed))
    assert meta["training_data_check"]["status"] == "differs"
    assert str(other) in meta["training_data_check"]["why"]
    assert _variants(env) == [f"toy-trained [trained on kitti:train (training data NOT as claimed), "
                              f"ck {ck.sha256[:8]}]"]


def test_a_claim_whose_data_is_not_at_hand_is_marked_unverified(env):
    ck = _claim(_train(env), root=str(env.tmp / "gone"))
    meta = _meta(_cell(env, ck))
    assert meta["training_data_check"] == {"status": "unverified",
                                           "why": f"its training data kitti:train ({env.tmp / 'gone'}) is not at hand"}
    assert _variants(env) == [f"toy-trained [trained on kitti:train (training data unverified), ck {ck.sha256[:8]}]"]


def test_training_on_a_renamed_copy_of_the_test_sweeps_is_caught_by_content(env):
    # the test sequence 08 copied as sequence 00 of another root: KITTI's train split there
    copy = env.tmp / "copy"
    shutil.copytree(env.root / "sequences" / "08", copy / "sequences" / "00")
    (copy / "poses").mkdir()
    shutil.copy(env.root / "poses" / "08.txt", copy / "poses" / "00.txt")
    env.data = f"kitti={copy}"
    ck = _train(env)
    assert ck.train_on_label == "kitti:train"  # by its names, other data than kitti:test
    with pytest.raises(PcfbenchError, match=r"was trained on this very data \(kitti:test, 27 of its 27 files, "
                                            r"100 % of its bytes, are in the training data kitti:train\).*--allow-train-split"):
        _cell(env, ck)
    meta = _meta(_cell(env, ck, allow_train_split=True))
    assert meta["evaluated_on_training_data"] is True
    assert meta["training_data_overlap"] == {"files": 27, "of": 27, "bytes_fraction": 1.0}


def test_another_split_shares_no_content(env):
    ck = _train(env)  # on kitti:train, sequences 00 and 01
    meta = _meta(_cell(env, ck))
    assert meta["evaluated_on_training_data"] is False
    overlap = meta["training_data_overlap"]
    assert overlap["of"] == 27 and overlap["bytes_fraction"] < 0.01
