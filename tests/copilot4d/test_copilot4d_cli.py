"""End to end through the CLI: the tokenizer as the trained method copilot4d-token-copy on a tiny
KITTI tree: pcfbench train (and resume), tokenizer-report, tokenize, and run with its checkpoint."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner


@pytest.mark.slow
def test_train_resume_report_tokenize_run(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    from pcfbench.cli import build_cli

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "06", "08"), num_sweeps=24)
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    reports = tmp_path / "reports"
    runner = CliRunner()
    cli = build_cli()
    r = runner.invoke(cli, ["train", "copilot4d-token-copy:steps=3", "--dataset", f"kitti={root}", "--max-minutes", "0"])
    assert r.exit_code == 0, r.output
    assert "1 steps on kitti:train" in r.output and "not finished" in r.output
    r = runner.invoke(cli, ["train", "copilot4d-token-copy:steps=3", "--dataset", f"kitti={root}"])
    assert r.exit_code == 0, r.output
    assert "resuming" in r.output and "at step 1" in r.output and "3 steps on kitti:train" in r.output
    (manifest,) = (tmp_path / "cache" / "checkpoints").rglob("manifest.json")
    m = json.loads(manifest.read_text())
    assert m["steps"] == 3 and m["complete"] and m["config"]["tokenizer"]["name"] == "tiny"
    assert (manifest.parent / "curve.csv").is_file()
    tok = ["--method", "copilot4d-token-copy:steps=3", "--train-on", f"kitti={root}"]
    r = runner.invoke(cli, ["tokenizer-report", *tok, "--dataset", f"kitti={root}", "--split", "val", "--sweeps", "1",
                            "--reports", str(reports)])
    assert r.exit_code == 0, r.output
    report = json.loads((reports / "copilot4d" / "tokenizer-tiny-kitti-on-kitti-val.json").read_text())
    assert report["meta"]["steps"] == 3 and report["result"]["sweeps"] == 1
    assert report["meta"]["weights_sha256"] == m["weights_sha256"]
    for mode in ("skipping", "uniform"):
        assert np.isfinite(report["result"][mode]["l1_median"])
    r = runner.invoke(cli, ["tokenize", *tok, "--dataset", f"kitti={root}", "--split", "val", "--out", str(tmp_path / "t")])
    assert r.exit_code == 0, r.output
    t = np.load(tmp_path / "t" / "06.npz")
    assert t["tokens"].shape == (24, 64, 64) and t["tokens"].max() < 512
    r = runner.invoke(cli, ["run", "-m", "copilot4d-token-copy:steps=3", "--checkpoint", str(manifest), "-d",
                            f"kitti={root}", "-s", "kitti-1s", "--limit", "1", "-q", "--reports", str(reports)])
    assert r.exit_code == 0, r.output
    assert "[trained on kitti:train] | kitti:test | kitti-1s limit=1: 1 samples (1 now, 0 failed)" in r.output
