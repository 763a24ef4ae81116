"""The data fingerprint's cost: by content, with an empty and a filled hash cache, beside the
stat-only fingerprint of earlier versions (each file's path, size and mtime; the baseline).

Run on a root of your own (``NAME=ROOT:SPLIT``) or, by default, a tiny generated KITTI tree::

    PCFBENCH_BENCH_FINGERPRINT=kitti=/data/kitti:test \\
        .venv/bin/python -m pytest tests/benchmarks/test_bench_fingerprint.py --benchmark-enable

The files are read once before timing (page cache warm), so "cold" is the hashing, not the disk.
"""

from __future__ import annotations

import hashlib
import os

import pytest

from pcfbench import contenthash
from pcfbench.dataset import fingerprint_files
from pcfbench.plugins import get_plugins
from conftest import write_tiny_kitti

ROUNDS = 5


@pytest.fixture(scope="module")
def split_files(tmp_path_factory):
    spec = os.environ.get("PCFBENCH_BENCH_FINGERPRINT")
    if spec:
        name, rest = spec.split("=", 1)
        root, split = rest.rsplit(":", 1)
    else:
        name, root, split = "kitti", write_tiny_kitti(tmp_path_factory.mktemp("kitti"), num_sweeps=40), "test"
    adapter = get_plugins().datasets.get(name)(root)
    files = adapter.data_files(split)
    for f in files:
        f.read_bytes()
    return adapter.root, files


def stat_only(root, files):
    """The fingerprint before content hashes: path, size and mtime of each file, hashed."""
    h = hashlib.sha256()
    for p in sorted(files):
        st = os.stat(p)
        h.update(f"{os.path.relpath(p, root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]


def test_fingerprint_stat_only_baseline(benchmark, split_files):
    benchmark.pedantic(stat_only, args=split_files, rounds=ROUNDS, iterations=1)


def test_fingerprint_content_cold_cache(benchmark, split_files, tmp_path, monkeypatch):
    monkeypatch.setattr(contenthash, "RACY_NS", -10**18)
    caches = iter(range(10**6))
    benchmark.pedantic(lambda: fingerprint_files(*split_files, tmp_path / f"{next(caches)}.sqlite3"),
                       rounds=ROUNDS, iterations=1)


def test_fingerprint_content_warm_cache(benchmark, split_files, tmp_path, monkeypatch):
    monkeypatch.setattr(contenthash, "RACY_NS", -10**18)
    fingerprint_files(*split_files, tmp_path / "c.sqlite3")
    benchmark.pedantic(fingerprint_files, args=(*split_files, tmp_path / "c.sqlite3"), rounds=ROUNDS, iterations=1)
