"""Issue 45: a cell knows its data by content. An edit that keeps a file's size and
modification time (``cp -a``, ``rsync -a``, a restore from backup) is never read as the old
data; content hashes are cached by a key such an edit cannot keep; cells keyed the old way
(sizes and times only) are refused by name."""

from __future__ import annotations

import json
import os
import sqlite3

import pytest

from pcfbench import contenthash
from pcfbench.datasets.kitti import KittiOdometry, read_bin
from pcfbench.dataset import SAME_STAT_EDIT, fingerprint_files
from pcfbench.errors import PcfbenchError
from pcfbench.method import options_hash
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CONTENT_IDENTITY, Cell, CellSpec

METRICS = ("chamfer",)


def _spec(root):
    return CellSpec("copy-last", {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


def _scale_in_place(path, factor):
    """Scale a sweep's points in place and put its size and times back, as a copy that keeps
    times does; only its ctime (which no user call sets) tells."""
    st = path.stat()
    pts = read_bin(path)
    pts[:, :3] *= factor
    with open(path, "r+b") as fh:  # the same inode, rewritten
        fh.write(pts.tobytes())
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = path.stat()
    assert (after.st_size, after.st_mtime_ns, after.st_ino) == (st.st_size, st.st_mtime_ns, st.st_ino)


def test_an_edit_that_keeps_size_and_mtime_is_not_reused(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    first = run_cell(spec, store, RunOptions(progress=False))
    assert first.processed == 6
    old = Cell(store, spec).read_rows().chamfer.tolist()
    _scale_in_place(tiny_kitti / "sequences" / "08" / "velodyne" / "000012.bin", 1.5)
    with pytest.raises(PcfbenchError, match=r"(?s)different data_fingerprint \(dataset files changed: "
                                            r"sequences/08/velodyne: file contents differ with the same sizes and "
                                            r"modification times.*--force"):
        run_cell(spec, store, RunOptions(progress=False))
    assert Cell(store, spec).read_rows().chamfer.tolist() == old  # untouched
    redone = run_cell(spec, store, RunOptions(progress=False, force=True))
    assert redone.processed == 6 and Cell(store, spec).read_rows().chamfer.tolist() != old


def test_a_file_touched_but_not_changed_is_the_same_data(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    run_cell(spec, store, RunOptions(progress=False))
    sweep = tiny_kitti / "sequences" / "08" / "velodyne" / "000012.bin"
    os.utime(sweep, ns=(1, sweep.stat().st_mtime_ns + 10**9))
    assert run_cell(spec, store, RunOptions(progress=False)).processed == 0


def test_the_cell_records_the_fingerprint_kind(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    run_cell(spec, store, RunOptions(progress=False))
    meta = json.loads((Cell(store, spec).dir / "cell.json").read_text())
    assert meta["data_fingerprint_kind"] == "content-sha256"
    assert meta["data_fingerprint"] == KittiOdometry(tiny_kitti).fingerprint("test").digest


def test_a_cell_keyed_by_sizes_and_times_is_refused_by_name(tiny_kitti, store):
    spec = _spec(tiny_kitti)
    run_cell(spec, store, RunOptions(progress=False))
    path = Cell(store, spec).dir / "cell.json"
    old = {k: v for k, v in json.loads(path.read_text()).items() if k not in CONTENT_IDENTITY}
    path.write_text(json.dumps(old))  # as written before content identities
    with pytest.raises(PcfbenchError, match=r"predates content identities: data identity changed format.*--force"):
        run_cell(spec, store, RunOptions(progress=False))
    assert run_cell(spec, store, RunOptions(progress=False, force=True)).processed == 6


# -- the content-hash cache ---------------------------------------------------------------------

@pytest.fixture
def counted(monkeypatch):
    """Count the files read for their hash; let every hash be cached at once (no racy window)."""
    reads = []
    real = contenthash.file_sha256
    monkeypatch.setattr(contenthash, "file_sha256", lambda p: reads.append(p.name) or real(p))
    monkeypatch.setattr(contenthash, "RACY_NS", -10**18)
    return reads


def test_hashes_are_read_once_then_cached(tmp_path, counted):
    cache = tmp_path / "cache.sqlite3"
    files = []
    for i in range(3):
        files.append(tmp_path / f"{i}.bin")
        files[-1].write_bytes(bytes([i]) * 32)
    first = fingerprint_files(tmp_path, files, cache)
    assert sorted(counted) == ["0.bin", "1.bin", "2.bin"]
    counted.clear()
    assert fingerprint_files(tmp_path, files, cache) == first and counted == []


def test_an_in_place_edit_with_times_restored_misses_the_cache(tmp_path, counted):
    cache = tmp_path / "cache.sqlite3"
    f = tmp_path / "a.bin"
    f.write_bytes(b"\0" * 64)
    before = fingerprint_files(tmp_path, [f], cache)
    st = f.stat()
    with open(f, "r+b") as fh:
        fh.write(b"\1" * 64)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    counted.clear()
    after = fingerprint_files(tmp_path, [f], cache)
    assert counted == ["a.bin"] and after.digest != before.digest
    assert after.files[0][3] == contenthash.file_sha256(f)
    assert after.changes_since(before.summary()) == f".: {SAME_STAT_EDIT}"


def test_a_recent_file_is_hashed_but_not_cached(tmp_path, monkeypatch):
    cache = tmp_path / "cache.sqlite3"
    f = tmp_path / "a.bin"
    f.write_bytes(b"x")
    fingerprint_files(tmp_path, [f], cache)  # written just now: within the clock's grain
    assert sqlite3.connect(cache).execute("SELECT COUNT(*) FROM hashes").fetchone() == (0,)


def test_a_damaged_cache_is_read_past(tmp_path, counted):
    cache = tmp_path / "cache.sqlite3"
    cache.write_bytes(b"not a database" * 100)
    f = tmp_path / "a.bin"
    f.write_bytes(b"abc")
    assert fingerprint_files(tmp_path, [f], cache).files[0][3] == contenthash.file_sha256(f)
