"""The results store: one folder per cell, ``cell.json`` plus per-sweep rows in Parquet chunks.

Every write is a temporary file renamed into place, and the set of finished samples is
derived from the chunks themselves, so a run killed at any moment (SIGKILL included) resumes
without losing or duplicating rows: a chunk either exists whole or not at all.

A cell's folder is named by its :class:`CellSpec`; what its rows were computed with (method,
dataset and metric versions, sample ids, protocol version, setting, policy, ROI, dataset
options, the dataset files' fingerprint by content, a hash of the method's sources) is its
identity in ``cell.json``. A rerun whose identity differs stops with one error
(:func:`check_identity`) instead of adding rows.
A trained method's cell also records its checkpoint's sha256 and training data
(``pcfbench.training``), and its folder name carries the sha256, so each checkpoint has its
own cell.

Beside each chunk of rows, ``ranges/`` holds a file of the same name with the range bins of
its scored sweeps (``pcfbench.store.ranges``: what the report's error-by-range figure needs, so
that a report reads the store only). It is written just before its chunk; one whose chunk is
missing (a run killed between the two) is never read, and the next chunk of that name
replaces it.

Rows come in chunks of two names in ``rows/``: ``chunk-NNNNNN.parquet``, numbered in the order
the local executor flushes them, and ``shard-START-STOP.parquet``, the rows of the samples
``START <= i < STOP`` of the cell's sample list computed by one task of a distributed executor
(``pcfbench.running.ray_executor``). A shard is named by its samples, not by who wrote it, so a task
that runs twice (a retry) replaces its file instead of adding one.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pcfbench.errors import PcfbenchError

CELL_FILE = "cell.json"
#: what every cell.json names (its CellSpec) and what every chunk of rows has
SPEC_KEYS = ("method", "options", "options_hash", "dataset", "split", "setting")
ROWS_DIR = "rows"
#: Range bins of the scored sweeps (``pcfbench.store.ranges``), one file per rows chunk, of its name.
RANGES_DIR = "ranges"
#: The key under which a row dict (``pcfbench.running.runner.process_sample``) carries its sweep's
#: range bins to the store; split off into ``ranges/``, never a column of the rows.
RANGE_KEY = "_range_bins"
#: Columns every row has besides the metric values.
KEY_COLUMNS = ("sample_id", "step", "status")


@dataclass(frozen=True)
class CellSpec:
    """What identifies a cell: method + options x dataset x split x setting (+ policy, limit,
    subset)."""

    method: str
    options: dict[str, Any]
    options_hash: str
    dataset: str
    dataset_root: str | None
    split: str
    setting: str
    policy: str = "full-context"
    limit: int | None = None
    metrics: tuple[str, ...] = ()
    #: A trained method's checkpoint (``pcfbench.training``): its folder, the sha256 of its
    #: weights (a cell per checkpoint: the folder name carries it) and its training data.
    checkpoint: str | None = None
    checkpoint_sha256: str | None = None
    train_on: str | None = None
    #: At most this many of the policy's samples, evenly spaced
    #: (``pcfbench.protocol.settings.evenly_spaced``): a documented subset (the default run's for
    #: its costliest learned methods, ``Method.default_run_subset``; ``pcfbench run --subset``).
    #: Unlike ``limit`` it is not partial: complete once those samples are scored, it is ranked
    #: beside the full cells with its own sample count, and compared on the samples it shares.
    subset: int | None = None

    @property
    def partial(self) -> bool:
        return self.limit is not None

    @property
    def label(self) -> str:
        extra = f" limit={self.limit}" if self.limit is not None else ""
        if self.subset is not None:
            extra = f" subset={self.subset}{extra}"
        if self.policy != "full-context":
            extra = f" ({self.policy}){extra}"
        trained = f" [trained on {self.train_on}]" if self.train_on else ""
        return f"{self.method}{trained} | {self.dataset}:{self.split} | {self.setting}{extra}"

    def relpath(self) -> Path:
        setting = self.setting if self.policy == "full-context" else f"{self.setting}.{self.policy}"
        leaf = f"{self.method}.{self.options_hash}"
        if self.checkpoint_sha256:
            leaf += f".ck{self.checkpoint_sha256[:12]}"
        if self.subset is not None:
            leaf += f".subset{self.subset}"
        if self.limit is not None:
            leaf += f".limit{self.limit}"
        return Path(self.dataset) / setting / self.split / leaf


def atomic_write_bytes(path: Path, data: bytes, unique: bool = False) -> None:
    """Write ``path`` whole or not at all: a temporary file beside it, then a rename.
    ``unique``: name the temporary file by a random id too (writers on several machines of
    one shared filesystem may have the same process id)."""
    tag = f"{os.getpid()}.{uuid.uuid4().hex}" if unique else str(os.getpid())
    tmp = path.with_name(f".{path.name}.{tag}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise write_error(path, exc) from None


def write_error(path: Path, exc: OSError) -> PcfbenchError:
    """One line for a failed write into the store: which file, why, and what to do."""
    why = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return PcfbenchError(f"cannot write {path}: no space left on the device ({why}); free some space or pass "
                             "another --store ($PCFBENCH_STORE), then rerun: the run resumes from the rows already written")
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return PcfbenchError(f"cannot write {path}: the results store is not writable ({why}); pass a writable "
                             "--store ($PCFBENCH_STORE), or make it writable")
    return PcfbenchError(f"cannot write {path}: {why}")


def _mkdir(d: Path) -> None:
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(d, exc) from None


class CellLocked(PcfbenchError):
    """Another process holds the cell's lock (it is computing the cell)."""


def _read_chunk(path: Path, columns: list[str] | None = None) -> pa.Table:
    """One chunk of rows; a damaged or foreign file is one error naming it and the fix."""
    fix = ("delete that file and rerun the cell (only its samples are recomputed), or rerun it with --force")
    try:
        table = pq.read_table(path, columns=columns)
    except (pa.ArrowException, OSError) as exc:
        raise PcfbenchError(f"rows file {path} is damaged or cut short ({exc}); {fix}") from None
    missing = [c for c in (columns or KEY_COLUMNS) if c not in table.column_names]
    if missing:
        raise PcfbenchError(f"rows file {path} has no column {', '.join(missing)}: it is not a pcfbench chunk; {fix}")
    return table


def check_meta(path: Path, meta: Any) -> dict[str, Any]:
    """``meta`` (read from the cell.json ``path``) if it has what every cell.json has, else
    one error naming the file: a cut-short or edited cell.json must not drop its cell unseen."""
    spec = meta.get("spec") if isinstance(meta, dict) else None
    missing = [k for k in SPEC_KEYS if not isinstance(spec, dict) or k not in spec]
    if not isinstance(meta, dict) or missing or not isinstance(meta.get("status"), str):
        what = "not a JSON object" if not isinstance(meta, dict) else (
            f"spec without {', '.join(missing)}" if missing else "no status")
        raise PcfbenchError(f"{path} is not a complete cell.json ({what}): delete the folder {path.parent} "
                            "or rerun its cell with --force")
    return meta


def read_cell_json(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise PcfbenchError(f"cannot read {path}: {exc.strerror or exc}") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PcfbenchError(f"{path} is not valid JSON ({exc}; {len(text)} bytes, cut short?): delete the folder "
                            f"{path.parent} or rerun its cell with --force") from None
    return check_meta(path, meta)


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n").encode())


class Cell:
    """One cell's folder. Use as a context manager to hold its lock while writing."""

    def __init__(self, root: Path, spec: CellSpec, wait: bool = False) -> None:
        self.spec = spec
        self.dir = Path(root) / spec.relpath()
        #: when another process holds the lock: wait for it (True) or raise CellLocked
        self.wait = wait
        self._lock_fh = None

    @classmethod
    def at(cls, root: Path, relpath: str | Path) -> "Cell":
        """The cell in the folder ``root / relpath``, to read it (its spec is in its cell.json)."""
        cell = cls.__new__(cls)
        cell.spec, cell.dir, cell.wait, cell._lock_fh = None, Path(root) / relpath, False, None
        return cell

    # -- locking ------------------------------------------------------------------------
    def __enter__(self) -> "Cell":
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            self._lock_fh = open(self.dir / ".lock", "w")
        except OSError as exc:
            raise write_error(self.dir / ".lock", exc) from None
        try:
            fcntl.flock(self._lock_fh, fcntl.LOCK_EX if self.wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock_fh.close()
            raise CellLocked(f"cell {self.dir} is being computed by another pcfbench process") from None
        for stale in self.dir.rglob(".*.tmp"):
            stale.unlink(missing_ok=True)  # left by a killed writer; never read
        return self

    def __exit__(self, *exc: object) -> None:
        if self._lock_fh is not None:
            fcntl.flock(self._lock_fh, fcntl.LOCK_UN)
            self._lock_fh.close()
            self._lock_fh = None

    # -- metadata -----------------------------------------------------------------------
    def read_meta(self) -> dict[str, Any] | None:
        path = self.dir / CELL_FILE
        if not path.is_file():
            return None
        return read_cell_json(path)

    def write_meta(self, meta: dict[str, Any]) -> None:
        _mkdir(self.dir)
        atomic_write_json(self.dir / CELL_FILE, meta)

    def clear(self) -> None:
        for child in self.dir.iterdir():
            if child.name == ".lock":
                continue
            shutil.rmtree(child) if child.is_dir() else child.unlink()

    # -- rows ---------------------------------------------------------------------------
    def chunk_paths(self) -> list[Path]:
        """Every chunk of rows: the numbered ones in order, then the shards in sample order."""
        d = self.dir / ROWS_DIR
        return sorted(d.glob("chunk-*.parquet")) + sorted(d.glob("shard-*.parquet")) if d.is_dir() else []

    def append_rows(self, rows: list[dict[str, Any]]) -> Path:
        """Write one chunk atomically; its sample ids are then done for good."""
        d = self.dir / ROWS_DIR
        _mkdir(d)
        existing = sorted(d.glob("chunk-*.parquet"))
        index = int(existing[-1].stem.split("-")[1]) + 1 if existing else 0
        path = d / f"chunk-{index:06d}.parquet"
        rows, ranges = split_ranges(rows)
        if ranges is not None:  # first: a chunk is never there without its range bins
            self.write_ranges_for(path, ranges)
        atomic_write_bytes(path, rows_to_parquet(rows))
        return path

    def read_rows(self) -> pd.DataFrame:
        """All rows, deduplicated on (sample_id, step) in chunk order."""
        paths = self.chunk_paths()
        if not paths:
            return pd.DataFrame(columns=list(KEY_COLUMNS))
        df = pd.concat([_read_chunk(p).to_pandas() for p in paths], ignore_index=True)
        return df.drop_duplicates(subset=["sample_id", "step"], keep="first").reset_index(drop=True)

    # -- range bins (pcfbench.store.ranges) ---------------------------------------------------------
    def write_ranges_for(self, chunk: Path, ranges: list[dict[str, Any]], unique: bool = False) -> Path:
        """Write the range rows of the rows chunk ``chunk`` (its file in ``ranges/``), atomically."""
        d = self.dir / RANGES_DIR
        _mkdir(d)
        path = d / Path(chunk).name
        atomic_write_bytes(path, ranges_to_parquet(ranges), unique=unique)
        return path

    def read_ranges_for(self, chunk: Path) -> pd.DataFrame | None:
        """The range rows of one rows chunk; None when it has none."""
        path = self.dir / RANGES_DIR / Path(chunk).name
        if not path.is_file():
            return None
        try:
            return pq.read_table(path).to_pandas()
        except (pa.ArrowException, OSError) as exc:
            raise PcfbenchError(f"range file {path} is damaged or cut short ({exc}); delete it and run "
                                "`pcfbench backfill-ranges` to recompute it") from None

    def read_ranges(self) -> pd.DataFrame:
        """The range rows of every chunk of rows, deduplicated on (sample_id, step) in chunk
        order, as :meth:`read_rows`; a file whose chunk of rows is gone is not read."""
        frames = [f for f in (self.read_ranges_for(p) for p in self.chunk_paths()) if f is not None and len(f)]
        if not frames:
            return pd.DataFrame(columns=["sample_id", "step", *RANGE_COLUMNS])
        df = pd.concat(frames, ignore_index=True)
        return df.drop_duplicates(subset=["sample_id", "step"], keep="first").reset_index(drop=True)

    def done_ids(self) -> set[str]:
        ids: set[str] = set()
        for p in self.chunk_paths():
            ids.update(_read_chunk(p, ["sample_id"]).column("sample_id").to_pylist())
        return ids


def shard_name(start: int, stop: int) -> str:
    """The chunk file of the samples ``start <= i < stop`` of a cell's sample list."""
    return f"shard-{start:06d}-{stop:06d}.parquet"


#: the range rows' lists, one entry per 10 m bin (``pcfbench.store.ranges``)
RANGE_COLUMNS = ("bin", "rays", "l1_sum", "absrel_sum")
RANGES_SCHEMA = pa.schema([("sample_id", pa.string()), ("step", pa.int64()), ("bin", pa.list_(pa.int64())),
                           ("rays", pa.list_(pa.int64())), ("l1_sum", pa.list_(pa.float64())),
                           ("absrel_sum", pa.list_(pa.float64()))])


def split_ranges(rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], list[dict[str, Any]] | None]:
    """``rows`` without the range bins they carry (``RANGE_KEY``), each row's other keys in
    their order (the rows' columns are those of a run that records none), and those bins as
    range rows; None when no row carries any (a cell that records none, or a chunk of failed
    samples only: nothing to record)."""
    if not any(RANGE_KEY in r for r in rows):
        return rows, None
    clean, ranges = [], []
    for r in rows:
        bins = r.get(RANGE_KEY)
        clean.append({k: v for k, v in r.items() if k != RANGE_KEY})
        if bins is not None:
            ranges.append({"sample_id": r["sample_id"], "step": int(r["step"]), **bins})
    return clean, ranges


def ranges_to_parquet(ranges: list[dict[str, Any]]) -> bytes:
    table = pa.Table.from_pylist(ranges, schema=RANGES_SCHEMA)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def read_chunk_frame(path: Path) -> pd.DataFrame:
    """One chunk of rows as a frame (a damaged file: one error naming it)."""
    return _read_chunk(path).to_pandas()


def rows_to_parquet(rows: list[dict[str, Any]]) -> bytes:
    table = pa.Table.from_pandas(pd.DataFrame(rows), preserve_index=False)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def write_shard(cell_dir: Path, start: int, stop: int, rows: list[dict[str, Any]]) -> Path:
    """Publish one shard's rows as one chunk, atomically and without the cell's lock (a task
    of a distributed run, on any machine that sees the store): a second write of the same
    shard replaces the first, so a retried task never duplicates rows."""
    d = Path(cell_dir) / ROWS_DIR
    d.mkdir(parents=True, exist_ok=True)
    path = d / shard_name(start, stop)
    rows, ranges = split_ranges(rows)
    if ranges is not None:  # first, as Cell.append_rows
        r = Path(cell_dir) / RANGES_DIR
        r.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(r / path.name, ranges_to_parquet(ranges), unique=True)
    atomic_write_bytes(path, rows_to_parquet(rows), unique=True)
    return path


def iter_cells(root: Path) -> Iterator[tuple[Path, dict[str, Any]]]:
    """Every cell folder under ``root`` with its metadata."""
    root = Path(root)
    if not root.is_dir():
        return
    for meta_path in sorted(root.rglob(CELL_FILE)):
        yield meta_path.parent, read_cell_json(meta_path)


#: Identity fields of cells written since the protocol became versioned data. A cell.json
#: without them predates that: it is reused only when complete (no rows are added to it).
PROTOCOL_IDENTITY = (
    "protocol_version", "roi", "min_range_m", "setting_params", "sample_policy", "ego_box",
    "dataset_options", "data_fingerprint",
)


#: Identity fields of cells written since data is known by content and code by hash. A cell
#: with the protocol identity but without them was keyed by its files' sizes and modification
#: times and by its method's version only: "data identity changed format", recompute it.
CONTENT_IDENTITY = ("data_fingerprint_kind", "method_code")


def _plain(value: Any) -> Any:
    """``value`` as it reads back from cell.json (tuples become lists, keys strings)."""
    return json.loads(json.dumps(value, sort_keys=True, default=str))


def _difference(old: Any, new: Any) -> str:
    if isinstance(old, dict) and isinstance(new, dict):
        keys = sorted(set(old) | set(new), key=str)
        return ", ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in keys if old.get(k) != new.get(k))
    return f"{old!r} -> {new!r}"


def _code_changes(old: Any, new: dict[str, str], most: int = 5) -> str:
    """Which source files differ between two ``method_code_files`` maps."""
    old = old if isinstance(old, dict) else {}
    edited = [f for f in sorted(set(old) & set(new)) if old[f] != new[f]]
    parts = [f"{what}: {', '.join(fs[:most])}{f' and {len(fs) - most} more' if len(fs) > most else ''}"
             for what, fs in (("edited", edited), ("new", sorted(set(new) - set(old))), ("gone", sorted(set(old) - set(new))))
             if fs]
    return "; ".join(parts)


def check_identity(cell_dir: Path, meta: dict[str, Any], identity: dict[str, Any], fingerprint: Any = None,
                   code_files: dict[str, str] | None = None) -> None:
    """Raise one error naming every identity field on which ``meta`` (a cell's cell.json) and
    ``identity`` (this run's) differ, and how to recompute; return when the cell may be reused.

    ``fingerprint`` (a :class:`pcfbench.dataset.DataFingerprint`) says which dataset files
    changed, from the summary the cell keeps under ``data_files``; ``code_files`` (each
    source file's hash) which of the method's files changed, from ``method_code_files``.
    """
    identity = _plain(identity)
    legacy = "protocol_version" not in meta
    if not legacy and any(k in identity and k not in meta for k in CONTENT_IDENTITY):
        raise PcfbenchError(
            f"cell {cell_dir} predates content identities: data identity changed format (its data was known by "
            "file sizes and modification times, which an in-place edit or a copy with times kept can preserve, and "
            "its method's code by its version alone; now files are known by their contents and code by a hash of "
            "its sources), so it cannot be told whether its rows match this data and code: rerun with --force "
            "to recompute it"
        )
    fields = [k for k in identity if not (legacy and k in PROTOCOL_IDENTITY + CONTENT_IDENTITY)]
    changed = [k for k in fields if meta.get(k) != identity[k]]
    if changed:
        details = []
        for k in changed:
            if k == "data_fingerprint" and fingerprint is not None:
                details.append(f"dataset files changed: {fingerprint.changes_since(meta.get('data_files'))}")
            elif k == "method_code":
                which = _code_changes(meta.get("method_code_files"), code_files or {})
                same = (f", its version {identity['method_version']!r} unchanged"
                        if "method_version" not in changed and "method_version" in identity else "")
                details.append(f"the method's code changed ({which or _difference(meta.get(k), identity[k])}"
                               f"{same}; a plugin author bumps the version with each change)")
            else:
                details.append(f"{k}: {_difference(meta.get(k), identity[k])}")
        raise PcfbenchError(
            f"cell {cell_dir} was computed with a different {', '.join(changed)} ({'; '.join(details)}); "
            "its rows must not mix with new ones: rerun with --force to recompute it"
        )
    if legacy and meta.get("status") != "complete":
        missing = ", ".join(k for k in PROTOCOL_IDENTITY if k in identity)
        raise PcfbenchError(
            f"cell {cell_dir} is incomplete and its cell.json predates the protocol identity ({missing}), "
            "so new rows could not be told apart from rows computed on other data or settings: "
            "rerun with --force to recompute it"
        )


def spec_from_meta(meta: dict[str, Any]) -> CellSpec:
    spec = dict(meta["spec"])
    spec["metrics"] = tuple(spec.get("metrics", ()))
    return CellSpec(**spec)


def spec_to_meta(spec: CellSpec) -> dict[str, Any]:
    return asdict(spec)
