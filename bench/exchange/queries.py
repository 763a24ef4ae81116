"""The query file (``pcfbench queries``): every sample of a cell as a method elsewhere needs it.

One compressed NumPy archive (``.npz``), readable with NumPy alone and never executing code
(``np.load(path, allow_pickle=False)``). Members, for each sample id ``SID`` (``sequence/NNNNNN``):

    header.json                    0-d string: JSON (below)
    SID/past_points_ref/K          (N_k, 3) float32, past sweep K (oldest first; the last is t=0),
                                   ego returns removed, in the reference (t=0) sensor frame
    SID/past_T_ref_sensor          (P, 4, 4) float64     SID/past_timestamps_ns   (P,) int64
    SID/future_T_ref_sensor        (F, 4, 4) float64     SID/future_timestamps_ns (F,) int64
    SID/T_world_ref                (4, 4) float64
    SID/origins_ref                (F, 3) float64, each future sweep's ray origin
    SID/directions_ref/K           (M_k, 3) float32 unit vectors: future sweep K's query rays

``header.json`` holds ``format`` ("pcfbench-queries"), ``answers`` (what a submission copies into
its own header: :meth:`pcfbench.exchange.questions.Questions.answers`) and ``samples``: per
sample its ``sample_id``, ``sequence``, ``ref_index`` and the ``past`` and ``future`` sweeps'
identities (index in the sequence, timestamp, source file). Never a ground-truth depth: the
query rays are directions only.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pcfbench.data import Sample
from pcfbench.errors import PcfbenchError
from pcfbench.exchange.questions import EXCHANGE_VERSION, Questions

QUERIES_FORMAT = "pcfbench-queries"
HEADER = "header.json"


def sample_members(sample: Sample) -> Iterator[tuple[str, np.ndarray]]:
    """The archive members of one sample (name, array), as the module docstring lists them."""
    sid = sample.sample_id
    for k, pts in enumerate(sample.past_points_ref):
        yield f"{sid}/past_points_ref/{k}", np.asarray(pts, np.float32)
    yield f"{sid}/past_T_ref_sensor", sample.past_T_ref_sensor
    yield f"{sid}/past_timestamps_ns", sample.past_timestamps_ns
    yield f"{sid}/future_T_ref_sensor", sample.future_T_ref_sensor
    yield f"{sid}/future_timestamps_ns", sample.future_timestamps_ns
    yield f"{sid}/T_world_ref", sample.T_world_ref
    yield f"{sid}/origins_ref", np.stack([q.origin_ref for q in sample.queries]) if sample.queries else np.zeros((0, 3))
    for k, q in enumerate(sample.queries):
        yield f"{sid}/directions_ref/{k}", np.asarray(q.directions_ref, np.float32)


def _identities(questions: Questions, sequence: str, ref_index: int) -> dict[str, Any]:
    """Which sweeps a sample is made of: index, timestamp and source file of each."""
    seq = questions.builder.sequence(sequence)
    s = questions.builder.setting
    n = len(seq)

    def one(i: int) -> dict[str, Any]:
        inside = 0 <= i < n
        return {"index": i, "timestamp_ns": int(seq.timestamps_ns[i]) if inside else None,
                "source": (seq.points_source(i) if seq.points_source else "") if inside else ""}

    return {"past": [one(ref_index - k * s.stride) for k in range(s.past - 1, -1, -1)],
            "future": [one(ref_index + k * s.stride) for k in range(1, s.future + 1)]}


def header(questions: Questions) -> dict[str, Any]:
    samples = [{"sample_id": sid, "sequence": seq, "ref_index": i, **_identities(questions, seq, i)}
               for sid, (seq, i) in zip(questions.ids, questions.keys)]
    return {"format": QUERIES_FORMAT, "exchange_version": EXCHANGE_VERSION, "answers": questions.answers(),
            "samples": samples}


def write_queries(questions: Questions, path: Path, progress=None) -> dict[str, Any]:
    """Write the query file of ``questions`` to ``path`` (atomically: a temporary file, then a
    rename); returns its header. ``progress(n)`` is called after each sample."""
    path = Path(path)
    head = header(questions)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1, allowZip64=True) as zf:
            _write_member(zf, HEADER, np.array(json.dumps(head)))
            for key in questions.keys:
                sample, _truth = questions.builder.build(*key)  # the truth stays here
                for name, arr in sample_members(sample):
                    _write_member(zf, name, arr)
                if progress is not None:
                    progress(1)
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise PcfbenchError(f"cannot write the query file {path}: {exc.strerror or exc}") from None
    return head


def _write_member(zf: zipfile.ZipFile, name: str, arr: np.ndarray) -> None:
    """One ``.npy`` member, as ``np.savez_compressed`` writes it (fast deflate: directions and
    points are float32 noise to a compressor; level 1 costs a fifth of level 6's time)."""
    with zf.open(name + ".npy", "w", force_zip64=True) as fh:
        np.lib.format.write_array(fh, np.asarray(arr), allow_pickle=False)


def read_header(npz: Any, path: Path, fmt: str) -> dict[str, Any]:
    """The JSON header of an opened archive ``npz`` of format ``fmt``; one error naming ``path``
    when it has none, is not JSON, or is another format or version."""
    if HEADER not in npz.files:
        raise PcfbenchError(f"{path} has no {HEADER} member: not a {fmt} file (docs/bring-your-own-method.md)")
    try:
        head = json.loads(str(npz[HEADER][()]))
    except (ValueError, TypeError) as exc:
        raise PcfbenchError(f"{path}: its {HEADER} is not a JSON text ({exc})") from None
    if not isinstance(head, dict) or head.get("format") != fmt:
        got = head.get("format") if isinstance(head, dict) else type(head).__name__
        raise PcfbenchError(f"{path}: its {HEADER} says format {got!r}, expected {fmt!r}")
    if head.get("exchange_version") != EXCHANGE_VERSION:
        raise PcfbenchError(f"{path}: exchange version {head.get('exchange_version')!r}, this pcfbench reads version "
                            f"{EXCHANGE_VERSION}: write it again with this version's `pcfbench queries`")
    return head


def open_npz(path: Path) -> Any:
    """``np.load`` of an archive with pickles refused; one error naming ``path`` if unreadable."""
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise PcfbenchError(f"cannot read {path} as a NumPy .npz archive ({exc})") from None


def read_queries(path: Path) -> tuple[dict[str, Any], Any]:
    """The header and the opened archive of a query file."""
    npz = open_npz(Path(path))
    return read_header(npz, Path(path), QUERIES_FORMAT), npz
