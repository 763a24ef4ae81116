"""Content hashes of files, read once and cached by a key an in-place write cannot keep.

A file's sha256 is cached under its absolute path with the device, inode, change time
(ctime), size and modification time of the file it was read from. Writing a file, renaming
another onto its path or restoring its modification time with ``os.utime`` each give it a new
ctime (which no user call can set back), so a cached hash is never read for other content;
``cp -a``, ``rsync -a`` and restores from backup, which keep size and mtime, are noticed.

The cache is a SQLite file in the cache folder (``pcfbench.config.cache_dir``). It is an
accelerator only: when it cannot be opened, read or written, files are hashed afresh.
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
import time
from pathlib import Path
from typing import Iterable

__all__ = ["CACHE_FILE", "RACY_NS", "file_sha256", "hash_files"]

CACHE_FILE = "content-hashes.sqlite3"
#: A file changed this recently is hashed but not cached: a second write within the clock's
#: grain of the first (file times are coarse, up to a second or two on some file systems)
#: could keep its ctime, so the hash is kept only once the file has been still for longer.
RACY_NS = 3 * 10**9
_SCHEMA = ("CREATE TABLE IF NOT EXISTS hashes (path TEXT PRIMARY KEY, dev INTEGER, ino INTEGER, "
           "ctime_ns INTEGER, size INTEGER, mtime_ns INTEGER, sha256 TEXT)")


def file_sha256(path: Path) -> str:
    """sha256 (hex) of the bytes of ``path``."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def _key(st: os.stat_result) -> tuple[int, int, int, int, int]:
    return (int(st.st_dev), int(st.st_ino), int(st.st_ctime_ns), int(st.st_size), int(st.st_mtime_ns))


def _open_cache(cache: Path | None) -> sqlite3.Connection | None:
    if cache is None:
        from pcfbench.config import cache_dir

        cache = cache_dir() / CACHE_FILE
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        con = sqlite3.connect(cache, timeout=30)
        con.execute(_SCHEMA)
        return con
    except (sqlite3.Error, OSError):
        return None  # unreadable, damaged or not writable: hash without it


def hash_files(paths: Iterable[tuple[Path, os.stat_result]], cache: Path | None = None,
               use_cache: bool = True) -> dict[Path, str]:
    """The sha256 of each ``(path, stat)``'s content, from the cache where its key (device,
    inode, ctime, size, mtime) is the file's ``stat``, else read (and then cached).

    ``stat`` is the caller's ``os.stat`` of the path; a file whose stat differs after reading
    (written meanwhile) is not cached. ``cache``: the SQLite file (default: the cache folder's).
    """
    items = [(Path(p), st) for p, st in paths]
    con = _open_cache(cache) if use_cache and items else None
    known: dict[str, tuple] = {}
    if con is not None:
        try:
            wanted = sorted({os.path.abspath(p) for p, _ in items})
            for i in range(0, len(wanted), 500):  # SQLite's limit on a statement's parameters
                part = wanted[i:i + 500]
                rows = con.execute("SELECT path, dev, ino, ctime_ns, size, mtime_ns, sha256 FROM hashes WHERE path IN "
                                   f"({','.join('?' * len(part))})", part)
                known.update((row[0], row) for row in rows)
        except sqlite3.Error:
            known = {}
    out: dict[Path, str] = {}
    fresh = []
    now = time.time_ns()
    for p, st in items:
        absolute = os.path.abspath(p)
        key = _key(st)
        row = known.get(absolute)
        if row is not None and tuple(row[1:6]) == key:
            out[p] = row[6]
            continue
        digest = file_sha256(p)
        out[p] = digest
        try:
            still = _key(os.stat(p)) == key
        except OSError:
            still = False
        if still and now - max(st.st_ctime_ns, st.st_mtime_ns) > RACY_NS:
            fresh.append((absolute, *key, digest))
    if con is not None:
        try:
            if fresh:
                with con:
                    con.executemany("INSERT OR REPLACE INTO hashes VALUES (?, ?, ?, ?, ?, ?, ?)", fresh)
        except sqlite3.Error:
            pass  # the hashes are right; only the next run reads the files again
        finally:
            con.close()
    return out
