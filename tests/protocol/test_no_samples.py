"""A split without samples is one error that says why, with what ``datasets check`` knows, and
the exact option that fixes it: the sequences are in another split, too short for the setting,
absent altogether, or the split name is unknown (pcfbench.protocol.nosamples)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from pcfbench.cli import build_cli
from pcfbench.datasets.kitti import KittiOdometry
from pcfbench.kinds import PolicyKind
from pcfbench.protocol.nosamples import EXPERIMENT_FILE, explain, window
from pcfbench.protocol import SampleBuilder, anchors
from pcfbench.plugins import all_settings, get_setting
from tests_helpers import write_kitti_tree


def _run(args: list[str]):
    return CliRunner().invoke(build_cli(), args, catch_exceptions=False)


def _error(res) -> str:
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.startswith("pcfbench: error: ")]
    assert len(lines) == 1, res.output
    return lines[0]


def _run_args(root: Path, tmp_path: Path, *more: str) -> list[str]:
    return ["run", "-d", f"kitti={root}", "-m", "copy-last", "--no-report", "-q", "--store", str(tmp_path / "store"), *more]


def test_a_root_of_train_sequences_is_told_to_pick_the_train_split(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00",), num_sweeps=24)
    line = _error(_run(_run_args(root, tmp_path)))
    assert line == (f"pcfbench: error: kitti:test has no samples for setting kitti-1s (full-context): the root {root} "
                    "holds no sequence of split test; its sequences are in split train (00): pick it with --split train")
    # the option it names is the fix
    res = _run(_run_args(root, tmp_path, "--split", "train", "--setting", "kitti-1s"))
    assert res.exit_code == 0, res.output
    assert "kitti:train" in res.output and "6 samples (6 now, 0 failed)" in res.output


def test_sequences_of_two_other_splits_are_both_named(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00", "06"), num_sweeps=20)
    msg = explain(SampleBuilder(KittiOdometry(root), get_setting("kitti-1s")), "test").message
    assert msg.endswith("its sequences are in split train (00) and split val (06): pick one with --split train or --split val")


def test_a_setting_longer_than_every_sequence_names_the_settings_that_fit(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("08", "09"), num_sweeps=24)
    line = _error(_run(_run_args(root, tmp_path, "--setting", "kitti-3s")))
    assert line == ("pcfbench: error: kitti:test has no samples for setting kitti-3s (full-context): a sample needs "
                    "55 consecutive sweeps (5 past and 5 future, 6 apart) and the longest of its 2 sequence(s) has 24 "
                    "(08, 09); pick a setting of a shorter horizon: --setting kitti-1s (needs 19), or --policy "
                    "every-frame (every sweep a sample; sweeps outside the sequence are empty)")


def test_sequences_too_short_for_every_setting_get_only_the_policy(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("08",), num_sweeps=12)
    line = _error(_run(_run_args(root, tmp_path)))
    assert "needs 19 consecutive sweeps" in line and "has 12 (08)" in line
    assert line.endswith("; pick --policy every-frame (every sweep a sample; sweeps outside the sequence are empty)")


def test_a_root_with_no_sequence_of_any_split_is_blamed(tmp_path):
    root = tmp_path / "k"
    (root / "sequences" / "11" / "velodyne").mkdir(parents=True)  # KITTI's test sequences 11-21 have no poses
    line = _error(_run(_run_args(root, tmp_path)))
    assert line == (f"pcfbench: error: kitti:test has no samples for setting kitti-1s (full-context): the root {root} "
                    f"holds no sequence of any split of kitti (train, val, test); `pcfbench datasets check {root}` "
                    "shows what it holds")


def test_an_unknown_split_gets_did_you_mean_and_the_option(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00",), num_sweeps=24)
    line = _error(_run(_run_args(root, tmp_path, "--split", "trian")))
    assert line == ("pcfbench: error: unknown split of dataset kitti 'trian'; did you mean 'train'? "
                    "(known: test, train, val); pick one with --split NAME")


def test_training_on_an_empty_split_names_the_split_of_the_sequences(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("08",), num_sweeps=24)
    line = _error(_run(["train", "copilot4d", "-d", f"kitti={root}", "-q"]))
    assert line == (f"pcfbench: error: dataset 'kitti' has no sequences in split 'train': the root {root} holds no "
                    "sequence of split train; its sequences are in split test (08): pick it with --split test")
    line = _error(_run(_run_args(root, tmp_path, "-m", "copilot4d", "--train-on", f"kitti={root}")))
    assert line.endswith("its sequences are in split test (08): pick it with --train-split test"), line


def test_an_experiment_file_is_told_its_key(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00",), num_sweeps=24)
    exp = tmp_path / "e.toml"
    exp.write_text(f"datasets = ['kitti={root}']\n[[methods]]\nname = 'copy-last'\n")
    line = _error(_run(["sweep", str(exp), "--store", str(tmp_path / "s"), "--reports", str(tmp_path / "r"), "-q"]))
    assert line.startswith(f"pcfbench: error: experiment {exp}: splits: kitti:test has no samples"), line
    assert line.endswith('its sequences are in split train (00): pick it with splits = ["train"]'), line
    assert EXPERIMENT_FILE.setting.format("kitti-1s") == 'settings = ["kitti-1s"]'


def test_export_names_the_split_too(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00",), num_sweeps=24)
    line = _error(_run(["export", "-d", f"kitti={root}", "-s", "kitti-1s", "-o", str(tmp_path / "x.mcap")]))
    assert re.search(r"its sequences are in split train \(00\): pick it with --split train$", line), line


@pytest.mark.parametrize("name", sorted(all_settings()))
def test_the_window_is_the_shortest_sequence_with_a_sample(name):
    s = get_setting(name)
    for rule in (PolicyKind.FULL_CONTEXT, PolicyKind.EVERY_FRAME):
        need = window(s, rule)
        assert len(anchors(need, s, rule.value)) == 1 and anchors(need - 1, s, rule.value) == []


@pytest.mark.parametrize("dataset", ["nuscenes", "av2", "mcap"])
def test_a_root_of_another_layout_is_named_with_the_dataset_that_reads_it(tmp_path, dataset):
    root = write_kitti_tree(tmp_path / "k", sequences=("08",), num_sweeps=24)
    line = _error(_run(["run", "-d", f"{dataset}={root}", "-s", "kitti-1s", "-m", "copy-last", "--no-report", "-q",
                        "--store", str(tmp_path / "store")]))
    assert line.endswith(f"; {root} holds the kitti layout: pass --dataset kitti={root}"), line


def test_ls_samples_says_why_the_list_is_empty(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00",), num_sweeps=24)
    res = CliRunner().invoke(build_cli(), ["ls", "samples", f"kitti={root}", "-s", "kitti-1s"])
    assert res.exit_code == 0, res.output
    assert ("pcfbench: note: kitti:test has no samples for setting kitti-1s (full-context): the root "
            f"{root} holds no sequence of split test; its sequences are in split train (00): pick it with --split train"
            in res.output)


def test_export_of_a_sample_id_in_an_empty_split_names_the_split(tmp_path):
    root = write_kitti_tree(tmp_path / "k", sequences=("00",), num_sweeps=24)
    line = _error(_run(["export", "-d", f"kitti={root}", "-s", "kitti-1s", "--sample", "00/000010",
                        "-o", str(tmp_path / "x.mcap")]))
    assert line == (f"pcfbench: error: --sample '00/000010': kitti:test has no sequence: the root {root} holds no "
                    "sequence of split test; its sequences are in split train (00): pick it with --split train")


def test_the_world_model_ceiling_names_its_own_option(tmp_path):
    torch = pytest.importorskip("torch")
    from pcfbench.errors import PcfbenchError
    from pcfbench.methods.copilot4d import ceiling

    root = write_kitti_tree(tmp_path / "k", sequences=("08",), num_sweeps=24)
    with pytest.raises(PcfbenchError) as err:
        ceiling.evaluate_ceiling(torch.nn.Module(), KittiOdometry(root), "test", "kitti-3s", log=lambda *a: None)
    assert str(err.value).endswith("the longest of its 1 sequence(s) has 24 (08); pick a setting of a shorter "
                                   "horizon: --ceiling kitti-1s (needs 19)"), err.value
