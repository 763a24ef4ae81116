"""End to end through the CLI: train (and resume), report, tokenize on a tiny KITTI tree."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner


@pytest.mark.slow
def test_train_resume_report_tokenize(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    from pcfbench.cli import build_cli

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "06"), num_sweeps=4)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    reports = tmp_path / "reports"
    runner = CliRunner()
    cli = build_cli()
    args = ["train", "tokenizer", "--config", "tiny", "--dataset", f"kitti={root}", "--reports", str(reports)]
    r = runner.invoke(cli, args + ["--steps", "2", "--eval-split", ""])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, args + ["--steps", "3", "--eval-sweeps", "1"])
    assert r.exit_code == 0, r.output
    assert "resumed from" in r.output and "at step 2" in r.output
    report = json.loads((reports / "copilot4d" / "tokenizer-tiny-kitti-val.json").read_text())
    assert report["meta"]["steps"] == 3 and report["result"]["sweeps"] == 1
    for mode in ("skipping", "uniform"):
        assert np.isfinite(report["result"][mode]["l1_median"])
    curve = (reports / "copilot4d" / "tokenizer-tiny-kitti-curve.csv").read_text().splitlines()
    assert len(curve) == 1 + 2  # header + a row at the end of each call (log_every 10 > steps)
    r = runner.invoke(cli, ["tokenize", "--config", "tiny", "--dataset", f"kitti={root}", "--split", "val",
                            "--out", str(tmp_path / "tok")])
    assert r.exit_code == 0, r.output
    tok = np.load(tmp_path / "tok" / "06.npz")
    assert tok["tokens"].shape == (4, 32, 32) and tok["tokens"].max() < 512
    assert tok["T_world_sensor"].shape == (4, 4, 4)
