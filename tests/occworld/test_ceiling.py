"""OccWorld's ceiling (methods/occworld/ceiling.py) and its command."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcfbench.methods.occworld.config import TokenizerConfig


class _Perfect(torch.nn.Module):
    """A tokenizer whose tokens are the labels themselves (see the test)."""

    def __init__(self, cfg) -> None:
        super().__init__()
        self.cfg = cfg
        self.w = torch.nn.Parameter(torch.zeros(1))


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_ceiling_renders_each_target_from_the_right_origin(tmp_path, monkeypatch, frame):
    """With a perfect tokenizer (tokens = the occupancy labels; decoded: occupied voxels certain,
    the rest free) the ceiling's rays end in the voxel of their own return, in either frame:
    the target's points, the frame they are labelled in and the rays' origin and directions in
    that frame all agree, so its median depth error is within a voxel (0.5 m). The occupancy
    copy and copy-last, in the same loop, do worse."""
    from conftest import write_tiny_kitti

    from pcfbench.methods.copilot4d.data import open_dataset
    from pcfbench.methods.occworld import occ_copy as oc
    from pcfbench.methods.occworld.ceiling import evaluate_ceiling, write_ceiling
    from pcfbench.methods.occworld.occupancy import OCCUPIED

    monkeypatch.setattr(oc, "tokenize_labels", lambda model, labels: torch.from_numpy(labels))
    monkeypatch.setattr(oc, "decode_probability", lambda model, codes: (np.asarray(codes) == OCCUPIED) * 1.0)
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24)
    adapter = open_dataset("kitti", root)
    cfg = TokenizerConfig("test", dims=(280, 280, 18))  # 0.5 m voxels over the ROI
    res = evaluate_ceiling(_Perfect(cfg), adapter, "test", "kitti-1s", frame=frame, log=lambda *a: None)
    o, cp, c = (res["means"][k] for k in ("ceiling", "occworld-occ-copy", "copy-last"))
    assert res["samples"] > 0 and res["sweeps"] == 5 * res["samples"]
    assert o["l1_median"] < 0.5, o
    assert o["l1_median"] < cp["l1_median"] and o["chamfer_nf"] < cp["chamfer_nf"], (o, cp)
    assert 0 < res["changed"]["mean"] <= 1
    md, csv_path = write_ceiling(res, {"config": "test"}, tmp_path / "rep", "ceiling")
    assert "sees the future" in md.read_text() and csv_path.read_text().startswith("entry,")


def test_ceiling_frame_is_checked():
    from pcfbench.errors import PcfbenchError
    from pcfbench.methods.occworld.ceiling import evaluate_ceiling

    with pytest.raises(PcfbenchError, match="frame"):
        evaluate_ceiling(_Perfect(TokenizerConfig("x")), None, "test", "kitti-1s", frame="world")


def test_the_command_scores_a_trained_tokenizer(tmp_path, monkeypatch):
    from click.testing import CliRunner
    from conftest import write_tiny_kitti

    from pcfbench.cli import build_cli

    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=24, beams=8, azimuths=180)
    runner, cli = CliRunner(), build_cli()
    spec = "occworld-occ-copy:config=micro,steps=2,frame=t0"
    r = runner.invoke(cli, ["train", spec, "--dataset", f"kitti={root}"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, ["occworld-ceiling", "--method", spec, "--train-on", f"kitti={root}", "--dataset",
                            f"kitti={root}", "--samples", "1", "--reports", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert "ceiling (kitti-1s, frame t0, 1 samples) / occworld-occ-copy: chamfer_nf" in r.output
    md = next((tmp_path / "rep" / "occworld").glob("ceiling-micro-kitti-on-kitti-test-kitti-1s-t0.md"))
    assert "pcfbench occworld-ceiling --method" in md.read_text()
