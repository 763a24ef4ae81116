"""OccWorld's ceiling (methods/occworld/ceiling.py) and its command."""

from __future__ import annotations

import pytest

from pcfbench.methods.occworld.config import TokenizerConfig


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_ceiling_renders_each_target_from_the_right_origin(tmp_path, frame):
    """With a perfect tokenizer (tokens = the occupancy labels; decoded: occupied voxels certain,
    the rest free) the ceiling's rays end in the voxel of their own return, in either frame:
    the target's points, the frame they are labelled in and the rays' origin and directions in
    that frame all agree, so its median depth error is within a voxel (0.5 m). The occupancy
    copy and copy-last, in the same loop, do worse."""
    from conftest import write_tiny_kitti

    from pcfbench.methods.copilot4d.data import open_dataset
    from pcfbench.methods.occworld.ceiling import LabelTokens, evaluate_ceiling, write_ceiling

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24)
    adapter = open_dataset("kitti", root)
    cfg = TokenizerConfig("test", dims=(280, 280, 18))  # 0.5 m voxels over the ROI
    res = evaluate_ceiling(LabelTokens(cfg), adapter, "test", "kitti-1s", frame=frame, log=lambda *a: None)
    o, cp, c = (res["means"][k] for k in ("ceiling", "occworld-occ-copy", "copy-last"))
    assert res["samples"] > 0 and res["sweeps"] == 5 * res["samples"]
    assert o["l1_median"] < 0.5, o
    assert o["l1_median"] < cp["l1_median"] and o["chamfer_nf"] < cp["chamfer_nf"], (o, cp)
    assert 0 < res["changed"]["mean"] <= 1
    md, csv_path = write_ceiling(res, {"config": "test"}, tmp_path / "rep", "ceiling")
    assert "sees the future" in md.read_text() and csv_path.read_text().startswith("entry,")


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_sub_voxel_planes_cut_the_perfect_median_error(tmp_path, frame):
    """On the paper grid (0.7 x 0.7 x 0.5625 m), perfect labels rendered at the middle of the
    first occupied voxel miss by about half a metre (rays come down into ground voxels that other
    returns made occupied); with the labels' sub-voxel planes (``surface="front"``) the median
    error falls to a fraction of that, and the ceiling beats the occupancy copy rendered the same
    way on the issue's three columns."""
    from conftest import write_tiny_kitti

    from pcfbench.methods.copilot4d.data import open_dataset
    from pcfbench.methods.occworld.ceiling import LabelTokens, evaluate_ceiling

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24)
    adapter = open_dataset("kitti", root)
    cfg = TokenizerConfig("test", dims=(200, 200, 16))
    run = {s: evaluate_ceiling(LabelTokens(cfg), adapter, "test", "kitti-1s", frame=frame, surface=s, max_samples=2,
                               log=lambda *a: None) for s in ("none", "front")}
    old, new = run["none"]["means"]["ceiling"], run["front"]["means"]["ceiling"]
    copy = run["front"]["means"]["occworld-occ-copy"]
    assert new["l1_median"] < 0.5 * old["l1_median"], (old, new)
    assert all(new[n] < copy[n] for n in ("chamfer_nf", "l1_mean", "l1_median")), (new, copy)
    assert run["front"]["readout"] == "surface=front"


def test_surface_needs_perfect_tokens():
    from pcfbench.errors import PcfbenchError
    from pcfbench.methods.occworld.ceiling import LabelTokens, evaluate_ceiling

    with pytest.raises(PcfbenchError, match="surface 'plane'"):
        evaluate_ceiling(LabelTokens(TokenizerConfig("x")), None, "test", "kitti-1s", surface="plane")
    with pytest.raises(PcfbenchError, match="only with perfect tokens"):
        evaluate_ceiling(object(), None, "test", "kitti-1s", surface="front")


def test_ceiling_frame_is_checked():
    from pcfbench.errors import PcfbenchError
    from pcfbench.methods.occworld.ceiling import LabelTokens, evaluate_ceiling

    with pytest.raises(PcfbenchError, match="frame"):
        evaluate_ceiling(LabelTokens(TokenizerConfig("x")), None, "test", "kitti-1s", frame="world")


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
    # named by the tokenizer's non-default steps: it never writes over the default tokenizer's report
    md = next((tmp_path / "rep" / "occworld").glob("ceiling-micro-steps2-kitti-32x32x4-on-kitti-test-kitti-1s-t0-1-samples.md"))
    assert "pcfbench occworld-ceiling --method" in md.read_text()
    # the representation's own bound needs no checkpoint; another grid only with it
    r = runner.invoke(cli, ["occworld-ceiling", "--method", "occworld-occ-copy:config=micro", "--perfect", "--grid",
                            "40x40x6", "--dataset", f"kitti={root}", "--samples", "1", "--reports", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    # (the method's default readout=surface: the labels' planes, surface=front)
    md = (tmp_path / "rep" / "occworld" / "ceiling-perfect-40x40x6-on-kitti-test-kitti-1s-t0-surface-front-1-samples.md")
    assert "perfect (the labels as tokens" in md.read_text() and "--perfect --grid 40x40x6" in md.read_text()
    r = runner.invoke(cli, ["occworld-ceiling", "--method", "occworld-occ-copy:config=micro", "--perfect", "--surface",
                            "none", "--dataset", f"kitti={root}", "--samples", "1", "--reports", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    md = (tmp_path / "rep" / "occworld" / "ceiling-perfect-32x32x4-on-kitti-test-kitti-1s-t0-1-samples.md").read_text()
    assert "(surface=" not in md
    r = runner.invoke(cli, ["occworld-ceiling", "--grid", "40x40x6", "--dataset", f"kitti={root}"])
    assert r.exit_code != 0 and "--grid: only with --perfect" in r.output
    # the sub-voxel planes: only with --perfect; their own report
    r = runner.invoke(cli, ["occworld-ceiling", "--surface", "front", "--dataset", f"kitti={root}"])
    assert r.exit_code != 0 and "--surface: only with --perfect" in r.output
    r = runner.invoke(cli, ["occworld-ceiling", "--method", "occworld-occ-copy:config=micro", "--perfect", "--surface",
                            "front", "--dataset", f"kitti={root}", "--samples", "1", "--reports", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    md = (tmp_path / "rep" / "occworld" / "ceiling-perfect-32x32x4-on-kitti-test-kitti-1s-t0-surface-front-1-samples.md").read_text()
    assert "--perfect --surface front" in md and "(surface=front depth)" in md


def test_report_names_carry_every_non_default_tokenizer_option():
    """A tokenizer trained with other options (tokens, steps, surface, ...) names its ceiling's
    files by them, so its report never lands on the default tokenizer's."""
    from pcfbench.methods.occworld.occ_copy import OccCopyOptions
    from pcfbench.methods.occworld.plugin import _non_default

    skip = ("config", "frame")
    assert _non_default(OccCopyOptions(), skip) == []
    assert _non_default(OccCopyOptions(config="micro", frame="own"), skip) == []
    assert _non_default(OccCopyOptions(tokens=100, surface="mean", steps=300), skip) == \
        ["tokens100", "surface-mean", "steps300"]
    assert _non_default(OccCopyOptions(surface="mean")) == ["surface-mean"]
