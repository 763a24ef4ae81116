"""A submission's cost beside the plugin's: copy-last made outside pcfbench (the docs' example)
and scored, against copy-last run as a plugin, on the same samples with every metric.

Run: .venv/bin/python -m pytest tests/benchmarks/test_bench_exchange.py --benchmark-enable
With PCFBENCH_BENCH_FULL=1 the sweeps are KITTI-sized (about 120,000 points).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import write_tiny_kitti
from pcfbench.exchange.check import check_submission, open_submission
from pcfbench.exchange.method import Submission, SubmissionOptions
from pcfbench.exchange.queries import write_queries
from pcfbench.exchange.questions import open_questions
from pcfbench.exchange.submission import file_sha256
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import get_plugins
from pcfbench.running.runner import Resolved, process_sample

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"
SAMPLES = 8
DOC = Path(__file__).resolve().parents[2] / "docs" / "bring-your-own-method.md"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """SAMPLES kitti-1s samples, their query file and the docs' copy-last answer to it."""
    tmp = tmp_path_factory.mktemp("exchange")
    beams, az = (64, 2100) if FULL else (16, 360)
    root = write_tiny_kitti(tmp / "kitti", num_sweeps=8 + SAMPLES + 10, beams=beams, azimuths=az)
    q = open_questions("kitti", str(root), "test", "kitti-1s", "full-context")
    q.keys = q.keys[:SAMPLES]
    write_queries(q, tmp / "queries.npz")
    (code,) = re.findall(r"^```python\n(.*?)^```", DOC.read_text(encoding="utf-8"), re.S | re.M)
    sub = tmp / "copy-last.npz"
    subprocess.run([sys.executable, "-c", code, str(tmp / "queries.npz"), str(sub)], check=True)
    metrics = [get_plugins().metrics.get(n) for n in get_plugins().metrics.names()]
    return q, sub, metrics


def _score(q, method, metrics) -> list:
    res = Resolved(q.builder, method, metrics)
    return [row for key in q.keys for row in process_sample(res, key)]


def test_copy_last_as_a_plugin(benchmark, world):
    """The baseline: copy-last run in the process, every metric."""
    q, _sub, metrics = world
    rows = benchmark.pedantic(_score, args=(q, CopyLast(), metrics), rounds=3 if FULL else 1, iterations=1)
    assert all(r["status"] == "ok" for r in rows)
    benchmark.extra_info.update(samples_per_round=SAMPLES, points_per_sweep=int(rows[0]["n_gt"]))


def _submission(q, sub, metrics) -> list:
    """What `pcfbench score` does per sample: the whole file checked, then scored from it."""
    check_submission(open_submission(sub), q)
    method = Submission(SubmissionOptions("bench", str(sub), file_sha256(sub)))
    return _score(q, method, metrics)


def test_copy_last_as_a_submission(benchmark, world):
    """The same forecasts read from the docs' example's file, checked whole first."""
    q, sub, metrics = world
    rows = benchmark.pedantic(_submission, args=(q, sub, metrics), rounds=3 if FULL else 1, iterations=1)
    assert all(r["status"] == "ok" for r in rows)
    benchmark.extra_info.update(samples_per_round=SAMPLES, file_bytes=sub.stat().st_size)


def test_writing_the_query_file(benchmark, world, tmp_path):
    """`pcfbench queries` for the same samples (deflate level 1)."""
    q, _sub, _metrics = world
    benchmark.pedantic(write_queries, args=(q, tmp_path / "q.npz"), rounds=3 if FULL else 1, iterations=1)
    benchmark.extra_info.update(samples_per_round=SAMPLES, file_bytes=(tmp_path / "q.npz").stat().st_size)
