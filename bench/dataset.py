"""The dataset-adapter contract: one on-disk layout, sequences of sweeps, loaded lazily."""

from __future__ import annotations

import hashlib
import json
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterable

import numpy as np

from pcfbench.data import Sweep
from pcfbench.datacheck import POSE_ATOL, check_points, check_rigid, pose_is_rigid
from pcfbench.errors import DataError
from pcfbench.options import NoOptions
from pcfbench.boxes import EgoBox


@dataclass(frozen=True, eq=False)
class Sequence:
    """A time-ordered run of sweeps. Poses and timestamps are known up front; points load lazily.

    T_world_sensor: (T, 4, 4) float64; timestamps_ns: (T,) int64 strictly increasing.
    ``points_source`` and ``pose_source`` name, for errors, where sweep ``index``'s points and
    pose were read: the file (``KITTI sweep .../000003.bin``), and for a pose the line, row or
    record (``KITTI poses file .../08.txt line 4``); called only to word an error.
    """

    name: str
    T_world_sensor: np.ndarray
    timestamps_ns: np.ndarray
    loader: Callable[[str, int], np.ndarray]
    #: (N,) float32 per-point reflectance (intensity) of sweep ``index``, in the order of
    #: ``loader``'s points, as the dataset stores it; None: the layout has none. Read only by
    #: what shows sweeps (``pcfbench export``), never by a method or a metric.
    intensity_loader: Callable[[str, int], np.ndarray] | None = None
    points_source: Callable[[int], str] | None = None
    pose_source: Callable[[int], str] | None = None

    def __post_init__(self) -> None:
        # the arrays every sample is cut from: a wrong shape or order is refused here, where the
        # sequence is opened (by `run` and `datasets check` alike), not deep inside a sample
        ts, T = np.asarray(self.timestamps_ns), np.asarray(self.T_world_sensor)
        if ts.ndim != 1 or ts.dtype.kind not in "iu":
            raise DataError(f"sequence {self.name}: timestamps must be a 1-D integer array of ns, got {ts.dtype} {ts.shape}")
        if T.shape != (len(ts), 4, 4):
            raise DataError(f"sequence {self.name}: poses must have shape ({len(ts)}, 4, 4) (one 4x4 per sweep), got {T.shape}")
        if ts.size > 1 and np.any(np.diff(ts) <= 0):
            i = int(np.argmax(np.diff(ts) <= 0)) + 1
            raise DataError(f"sequence {self.name}: sweep {i} has timestamp {ts[i]} ns, not after sweep {i - 1}'s "
                            f"{ts[i - 1]} ns (expected strictly increasing timestamps)")

    def __len__(self) -> int:
        return int(self.timestamps_ns.shape[0])

    def load_points(self, index: int) -> np.ndarray:
        """(N, 3) float32 points of sweep ``index`` in its own sensor frame."""
        return self.loader(self.name, index)

    def load_intensity(self, index: int) -> np.ndarray | None:
        """(N,) float32 reflectance of sweep ``index``'s points (:meth:`load_points`' order), or
        None when the dataset has none."""
        if self.intensity_loader is None:
            return None
        return np.asarray(self.intensity_loader(self.name, index), np.float32)

    def where_points(self, index: int, dataset: str = "") -> str:
        """Where sweep ``index``'s points are read (``dataset``: the adapter's name, for the
        default wording when the adapter names no file)."""
        if self.points_source is not None:
            return self.points_source(index)
        return f"{dataset} sequence {self.name} sweep {index}".lstrip()

    def where_pose(self, index: int, dataset: str = "") -> str:
        """Where sweep ``index``'s pose is read (a file and line, a table and record)."""
        if self.pose_source is not None:
            return self.pose_source(index)
        return f"{dataset} sequence {self.name} sweep {index}'s pose".lstrip()

    def sweep(self, index: int, dataset: str = "", points: np.ndarray | None = None) -> Sweep:
        """Sweep ``index`` with its pose and timestamp (not validated: see :meth:`checked_sweep`)."""
        return Sweep(
            points_sensor=self.load_points(index) if points is None else points,
            T_world_sensor=self.T_world_sensor[index],
            timestamp_ns=int(self.timestamps_ns[index]),
            source=self.where_points(index, dataset),
        )

    def check_pose(self, index: int, dataset: str = "") -> None:
        """One ``DataError`` naming the file and line of sweep ``index``'s pose when it is not
        rigid within ``pcfbench.datacheck.POSE_ATOL`` (nothing is read)."""
        T = self.T_world_sensor[index]
        if not pose_is_rigid(T):
            check_rigid(T, self.where_pose(index, dataset), atol=POSE_ATOL)

    def checked_points(self, index: int, dataset: str = "") -> np.ndarray:
        """(N, 3) float32 points of sweep ``index``, or one ``DataError`` naming the file when
        they are not finite (x, y, z) floats."""
        return check_points(self.load_points(index), self.where_points(index, dataset))

    def checked_sweep(self, index: int, dataset: str = "") -> Sweep:
        """Sweep ``index`` as ``pcfbench run`` reads it (:meth:`check_pose`, then
        :meth:`checked_points`); ``pcfbench datasets check`` makes the same two checks of
        every sweep."""
        self.check_pose(index, dataset)
        return self.sweep(index, dataset, points=self.checked_points(index, dataset))


#: Above this many folders, a fingerprint's summary groups files by their top-level folder.
MAX_FINGERPRINT_GROUPS = 256


#: What ``data_fingerprint`` is a hash of (a cell records it as ``data_fingerprint_kind``):
#: each file's path, size and content sha256. Cells whose cell.json lacks it were keyed by
#: file sizes and modification times only.
FINGERPRINT_KIND = "content-sha256"


@dataclass(frozen=True)
class DataFingerprint:
    """The identity of the files a split reads: each file's path relative to the root, its
    size and the sha256 of its content, hashed. Modification times are kept to say what
    changed, never part of the digest: a file touched but not changed is the same data, and a
    file edited with its size and time restored is not.

    Content hashes come from :mod:`pcfbench.contenthash`: read once, then cached by a key an
    in-place write cannot keep. ``files`` is sorted by path.
    """

    root: str
    files: tuple[tuple[str, int, int, str], ...]  # (relative path, bytes, mtime ns, content sha256)

    @staticmethod
    def _hash(files: "Iterable[tuple[str, int, int, str]]") -> str:
        h = hashlib.sha256()
        for rel, size, _mtime_ns, sha in files:
            h.update(f"{rel}\0{size}\0{sha}\n".encode("utf-8", "surrogateescape"))
        return h.hexdigest()[:16]

    @property
    def digest(self) -> str:
        return self._hash(self.files)

    def _grouped(self) -> dict[str, list[tuple[str, int, int, str]]]:
        def parent(rel: str, depth: int | None) -> str:
            parts = rel.split("/")[:-1]
            return "/".join(parts[:depth]) or "."

        for depth in (None, 1):
            groups: dict[str, list[tuple[str, int, int, str]]] = {}
            for f in self.files:
                groups.setdefault(parent(f[0], depth), []).append(f)
            if len(groups) <= MAX_FINGERPRINT_GROUPS:
                break
        return groups

    def summary(self) -> dict[str, Any]:
        """What ``cell.json`` keeps to say later which folder changed: per folder the file
        count, bytes, newest modification time and digest."""
        groups = {
            key: {
                "files": len(fs),
                "bytes": sum(f[1] for f in fs),
                "mtime_ns_max": max(f[2] for f in fs),
                "digest": self._hash(fs),
            }
            for key, fs in sorted(self._grouped().items())
        }
        return {"digest": self.digest, "files": len(self.files), "bytes": sum(f[1] for f in self.files), "groups": groups}

    def changes_since(self, old: dict[str, Any] | None, most: int = 5) -> str:
        """Which folders (and, where cheap, which files) differ from an older ``summary()``."""
        old_groups = (old or {}).get("groups") or {}
        new_groups = self.summary()["groups"]
        grouped = self._grouped()
        lines = []
        for key in sorted(set(old_groups) | set(new_groups)):
            o, n = old_groups.get(key), new_groups.get(key)
            if o is not None and n is not None and o.get("digest") == n["digest"]:
                continue  # the same contents (a file touched, not changed, included)
            if o is None:
                lines.append(f"{key}: {n['files']} new file(s)")
            elif n is None:
                lines.append(f"{key}: its {o['files']} file(s) are gone")
            else:
                parts = []
                if o.get("files") != n["files"]:
                    parts.append(f"{o.get('files')} -> {n['files']} files")
                newer = [f[0] for f in grouped[key] if f[2] > o.get("mtime_ns_max", 0)]
                if newer:
                    more = f" and {len(newer) - most} more" if len(newer) > most else ""
                    parts.append(f"modified since: {', '.join(newer[:most])}{more}")
                if o.get("bytes") != n["bytes"]:
                    before = o.get("bytes")
                    parts.append(f"{before:,}" if isinstance(before, int) else repr(before))
                    parts[-1] += f" -> {n['bytes']:,} bytes"
                lines.append(f"{key}: {'; '.join(parts) or SAME_STAT_EDIT}")
        if not lines:
            return SAME_STAT_EDIT
        more = f"; and {len(lines) - most} more folder(s)" if len(lines) > most else ""
        return "; ".join(lines[:most]) + more


#: How :meth:`DataFingerprint.changes_since` names a change that only the contents show.
SAME_STAT_EDIT = ("file contents differ with the same sizes and modification times "
                  "(edited in place, or copied or restored with their times kept)")


def fingerprint_files(root: Path | None, paths: "Iterable[Path]", cache: Path | None = None) -> DataFingerprint:
    """The :class:`DataFingerprint` of ``paths``, named relative to ``root``: each file's
    stat, and its content's sha256 (read once, then cached: :mod:`pcfbench.contenthash`;
    ``cache`` names the cache file, default the cache folder's)."""
    from pcfbench.contenthash import hash_files

    base = None if root is None else (Path(root) if Path(root).is_dir() else Path(root).parent)
    stats: dict[str, tuple[Path, os.stat_result]] = {}
    for p in paths:
        p = Path(p)
        try:
            st = os.stat(p)
        except OSError as exc:
            raise DataError(f"dataset file {p} cannot be read for the data fingerprint: {exc.strerror or exc}") from None
        rel = p.as_posix() if base is None else Path(os.path.relpath(p, base)).as_posix()
        stats[rel] = (p, st)
    try:
        shas = hash_files(stats.values(), cache)
    except OSError as exc:
        name = exc.filename or "a dataset file"
        raise DataError(f"dataset file {name} cannot be read for the data fingerprint: {exc.strerror or exc}") from None
    files = tuple((rel, int(st.st_size), int(st.st_mtime_ns), shas[p]) for rel, (p, st) in sorted(stats.items()))
    return DataFingerprint(str(root), files)


def options_identity(adapter: "DatasetAdapter", raw: dict[str, str]) -> dict[str, Any]:
    """The root options a cell is computed with (JSON-ready): the adapter's typed ``options``,
    defaults included, plus any raw ``ROOT?key=value`` option that is not one of their fields
    (an adapter that reads its keywords itself)."""
    from pcfbench.options import options_dict

    typed = options_dict(getattr(adapter, "options", None))
    out = {**{k: v for k, v in raw.items() if k not in typed}, **typed}
    return json.loads(json.dumps(dict(sorted(out.items())), default=str))


def files_under(root: Path) -> list[Path]:
    """Every file under ``root`` (symbolic links to folders followed, each folder once)."""
    out: list[Path] = []
    seen: set[str] = set()
    stack = [Path(root)]
    while stack:
        d = stack.pop()
        real = os.path.realpath(d)
        if real in seen:
            continue
        seen.add(real)
        with os.scandir(d) as it:
            for entry in it:
                if entry.is_dir():  # follows symbolic links
                    stack.append(Path(entry.path))
                elif entry.is_file():
                    out.append(Path(entry.path))
    return out


@dataclass
class CheckReport:
    """What ``pcfbench datasets check`` prints: what was found and every problem."""

    layout: str
    root: str
    found: dict[str, object] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


#: ``datasets check`` lists this many of a sequence's bad sweeps, then counts the rest.
MAX_SWEEP_PROBLEMS = 10


def sweep_problems(seq: Sequence, dataset: str = "", most: int = MAX_SWEEP_PROBLEMS) -> list[str]:
    """Every reason ``pcfbench run`` would refuse a sweep of ``seq``: the two checks of
    :meth:`Sequence.checked_sweep` (pose, points) on every sweep, the first ``most`` problems
    in full and a count of the rest."""
    problems: list[str] = []
    for i in range(len(seq)):
        for step in (seq.check_pose, seq.checked_points):
            try:
                step(i, dataset)
            except Exception as exc:  # noqa: BLE001 - a check collects every problem
                problems.append(str(exc))
    if len(problems) > most:
        problems[most:] = [f"sequence {seq.name}: {len(problems) - most} more bad sweep(s) like the above"]
    return problems


class DatasetAdapter(ABC):
    """Base class of every dataset plugin.

    Subclasses set ``name``, ``version``, ``rate_hz``, ``ego_box`` and ``default_settings``,
    take the dataset root (and options) in ``__init__`` and implement ``splits``,
    ``sequence_names`` and ``sequence``. Axis convention: x forward, y left, z up unless the
    adapter says otherwise in ``axes``. Root options (``ROOT?key=value&...``) are the fields
    of ``Options``, a frozen dataclass declared with ``pcfbench.option(default, help=...)``
    like a method's; ``self.options`` holds them, typed.
    """

    name: ClassVar[str]
    version: ClassVar[str] = "1"
    rate_hz: ClassVar[float]
    ego_box: ClassVar[EgoBox]
    default_settings: ClassVar[tuple[str, ...]] = ()
    default_split: ClassVar[str] = "test"
    #: the sample policy of the protocol file that ``pcfbench run`` and ``ls samples`` use for
    #: this dataset when ``--policy`` is not given
    default_policy: ClassVar[str] = "full-context"
    axes: ClassVar[str] = "x forward, y left, z up"
    #: True for a dataset that makes its own data (generated on first use): the default of
    #: ``pcfbench run`` when no dataset is named.
    embedded: ClassVar[bool] = False
    #: the root options (a frozen dataclass); none by default
    Options: ClassVar[type] = NoOptions

    @classmethod
    def default_root(cls, progress: bool = True) -> Path:
        """The root to use when none is configured (an embedded dataset prepares it here)."""
        from pcfbench.config import env_var_for
        from pcfbench.errors import PcfbenchError

        raise PcfbenchError(
            f"dataset {cls.name!r} needs a root: pass --dataset {cls.name}=/path/to/data, set "
            f"{env_var_for(cls.name)}, or add it under [datasets] in the config file"
        )

    @classmethod
    def recipe(cls, split: str) -> dict[str, Any] | None:
        """What makes ``split`` of the data at :meth:`default_root`, for a dataset that makes
        its own data: its definition and the generator's version, the very things its cache is
        keyed by (JSON-able). None (the default): recorded data, known only by its bytes.

        A checkpoint shipped for such a dataset records it (sha256), so a run finds the
        checkpoint without making the training data (``pcfbench.training.find_shipped``)."""
        return None

    @classmethod
    def detect(cls, root: Path) -> bool:
        """True when ``root`` looks like this adapter's layout (used by ``datasets check``)."""
        return False

    def __init__(self, root: str | Path | None, options: Any = None, **raw: object) -> None:
        """``options``: an instance of ``Options``; or give them as keywords (``raw``: values
        or strings, as in ``ROOT?key=value``), read by the same typed parser as a method's."""
        from pcfbench.errors import PcfbenchError
        from pcfbench.options import parse_options

        self.root = Path(root) if root is not None else None
        if options is None:
            options = parse_options(type(self).Options, raw, f"dataset {self.name}")
        elif raw:
            raise PcfbenchError(f"dataset {self.name}: pass options as an Options instance or as keywords, not both")
        elif not isinstance(options, type(self).Options):
            raise PcfbenchError(f"dataset {self.name}: options must be a {type(self).Options.__qualname__}, got {options!r}")
        self.options = options

    @abstractmethod
    def splits(self) -> tuple[str, ...]:
        """The split names this dataset knows."""

    @abstractmethod
    def sequence_names(self, split: str) -> list[str]:
        """Sequences of ``split`` present under the root, in a stable order."""

    @abstractmethod
    def sequence(self, name: str) -> Sequence:
        """Open one sequence: poses and timestamps now, points on demand."""

    def data_files(self, split: str) -> list[Path]:
        """The files whose change could change a number of ``split`` (the fingerprint's input).

        Default: every file under the root (the root itself when it is a file). Adapters may
        narrow it to what the split reads, so that other splits or side files do not change
        the fingerprint, but never below that.
        """
        if self.root is None:
            return []
        if self.root.is_file():
            return [self.root]
        if not self.root.is_dir():
            raise DataError(f"dataset {self.name!r}: root {self.root} does not exist")
        return files_under(self.root)

    def fingerprint(self, split: str) -> DataFingerprint:
        """Paths, sizes and content hashes of :meth:`data_files`, hashed: part of a cell's identity."""
        return fingerprint_files(self.root, self.data_files(split))

    def check(self) -> CheckReport:
        """Walk the whole dataset and report what was found and every problem (never raises).

        Each sequence is opened as ``pcfbench run`` opens it and each sweep read through
        :meth:`Sequence.checked_sweep`, the check ``run`` makes, so whatever ``run`` would
        refuse is reported, naming the file (and line). It reads every sweep once."""
        report = CheckReport(layout=self.name, root=str(self.root))
        for split in self.splits():
            try:
                names = self.sequence_names(split)
            except Exception as exc:  # noqa: BLE001 - a check collects every problem
                report.problems.append(f"split {split}: {exc}")
                continue
            report.found[f"split {split}"] = f"{len(names)} sequence(s)"
            for seq_name in names:
                try:
                    seq = self.sequence(seq_name)
                    n = len(seq)
                    dt = np.diff(seq.timestamps_ns) / 1e9
                    rate = f", {1.0 / np.median(dt):.2f} Hz" if dt.size else ""
                    report.found[f"sequence {seq_name}"] = f"{n} sweeps{rate}"
                except Exception as exc:  # noqa: BLE001
                    report.problems.append(str(exc))
                    continue
                report.problems.extend(sweep_problems(seq, self.name))
        return report
