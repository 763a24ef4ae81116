"""A submission: forecasts made elsewhere, in a file, checked whole before any is scored.

Two layouts (docs/bring-your-own-method.md):

- **NumPy** (``.npz``, read with pickles refused): ``header.json`` (a 0-d string: JSON with
  ``format`` "pcfbench-submission", ``exchange_version`` and ``answers``, copied from the query
  file's header), then per sample id ``SID`` and future sweep ``K`` either or both of
  ``SID/depths/K`` ((M_k,) one depth in metres per query ray, in the query file's order) and
  ``SID/points_ref/K`` ((K_k, 3) points in the reference frame).
- **Argoverse 2 challenge JSON** (``.json``, :mod:`pcfbench.exchange.challenge`): one depth per
  query ray, keyed by log id and t=0 frame.

:func:`check_submission` refuses, with one error naming the file and the first offending sample:
another format or version, answers to other questions (protocol, dataset fingerprint, split,
setting, policy: each difference named), samples the cell does not have, samples missing
(unless partial), a future sweep missing or extra, and any forecast the runner would refuse
(wrong ray count or shape, NaN, inf, negative depths: :func:`pcfbench.protocol.validate.validate_forecast`).
"""

from __future__ import annotations

import hashlib
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import ForecastError, PcfbenchError
from pcfbench.exchange.questions import Questions, differences
from pcfbench.exchange.queries import HEADER, open_npz, read_header
from pcfbench.protocol.validate import validate_forecast

SUBMISSION_FORMAT = "pcfbench-submission"
#: what a forecast member may hold: per-ray depths or points
KINDS = ("depths", "points_ref")
_MEMBER = re.compile(r"^(?P<sid>.+)/(?P<kind>[^/]+)/(?P<step>[0-9]+)$")


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise PcfbenchError(f"cannot read the submission {path}: {exc.strerror or exc}") from None
    return h.hexdigest()


def sample_key(sample: Sample) -> str:
    """A NumPy submission's key of a sample: its id."""
    return sample.sample_id


@dataclass
class SubmissionFile:
    """An opened submission: its ``keys`` (what names a sample in it), the ``answers`` it
    echoes (None: it carries none, as a challenge file may not), and ``arrays(key)``: per
    kind, the arrays by future sweep of one sample. ``key_of`` gives a sample's key."""

    path: Path
    layout: str
    keys: set[Any]
    answers: Any
    arrays: Callable[[Any], dict[str, dict[int, np.ndarray]]]
    key_of: Callable[[Sample], Any] = sample_key
    #: the cell's horizon in the file (challenge files: "1s", "3s"); None: none
    horizon: str | None = None

    def forecast(self, sample: Sample) -> Forecast | None:
        """``sample``'s forecast as the file gives it (unchecked), None when it has none;
        a future sweep missing or extra is a ``ForecastError`` naming the sample."""
        key = self.key_of(sample)
        if key not in self.keys:
            return None
        by_kind = self.arrays(key)
        parts: dict[str, tuple[np.ndarray, ...]] = {}
        want = set(range(sample.num_future))
        for kind, steps in by_kind.items():
            if set(steps) != want:
                missing, extra = sorted(want - set(steps)), sorted(set(steps) - want)
                raise ForecastError(
                    f"sample {sample.sample_id}: {kind} for future sweeps {sorted(steps)}, expected 0..{sample.num_future - 1}"
                    + (f" (missing {missing})" if missing else "") + (f" (no sweep {extra} in this setting)" if extra else ""))
            parts[kind] = tuple(steps[k] for k in range(sample.num_future))
        return Forecast(points_ref=parts.get("points_ref"), depths=parts.get("depths"))


def open_npz_submission(path: Path) -> SubmissionFile:
    npz = open_npz(path)
    head = read_header(npz, path, SUBMISSION_FORMAT)
    members: dict[str, dict[str, dict[int, str]]] = {}
    for name in npz.files:
        if name == HEADER:
            continue
        m = _MEMBER.match(name)
        if m is None or m["kind"] not in KINDS:
            raise PcfbenchError(f"submission {path}: member {name!r} is not SAMPLE_ID/depths/K or SAMPLE_ID/points_ref/K "
                                "(docs/bring-your-own-method.md)")
        members.setdefault(m["sid"], {}).setdefault(m["kind"], {})[int(m["step"])] = name

    def member(name: str) -> np.ndarray:
        try:
            return npz[name]
        except (ValueError, OSError, zipfile.BadZipFile) as exc:  # a pickled object array among them: refused
            raise PcfbenchError(f"submission {path}: member {name!r} is not a plain NumPy array ({exc})") from None

    def arrays(sid: str) -> dict[str, dict[int, np.ndarray]]:
        return {kind: {k: member(name) for k, name in steps.items()} for kind, steps in members[sid].items()}

    return SubmissionFile(path, "npz", set(members), head.get("answers"), arrays)


def open_submission(path: str | Path) -> SubmissionFile:
    """The submission at ``path``: a ``.json`` file is read as the AV2 challenge's layout,
    anything else as a NumPy archive."""
    path = Path(path)
    if not path.is_file():
        raise PcfbenchError(f"submission {path} does not exist")
    if path.suffix.lower() == ".json":
        from pcfbench.exchange.challenge import open_challenge_submission

        return open_challenge_submission(path)
    return open_npz_submission(path)


@dataclass(frozen=True)
class Checked:
    """What :func:`check_submission` found: samples answered, and the ids of those missing."""

    answered: int
    missing: tuple[str, ...]


def _first(items: list[str], most: int = 3) -> str:
    return ", ".join(items[:most]) + (f" and {len(items) - most} more" if len(items) > most else "")


def check_submission(sub: SubmissionFile, questions: Questions, partial: bool = False, progress=None) -> Checked:
    """Check ``sub`` against ``questions`` whole (module docstring); raise one
    :class:`~pcfbench.errors.PcfbenchError` naming the file and what is wrong."""
    where = f"submission {sub.path}"
    horizon = f"{questions.builder.setting.horizon_s:g}s"
    if sub.horizon is not None and sub.horizon != horizon:
        raise PcfbenchError(f"{where} answers horizon {sub.horizon!r}, setting {questions.setting} is {horizon!r}")
    if sub.answers is not None:
        diff = differences(sub.answers, questions.answers())
        if diff:
            raise PcfbenchError(f"{where} answers other questions than {questions.dataset}:{questions.split} "
                                f"{questions.setting} ({questions.policy}): {'; '.join(diff)}. Write the queries "
                                "again with `pcfbench queries` and answer those")
    keys = {}
    for sid, (seq, i) in zip(questions.ids, questions.keys):
        keys[sub_key(sub, questions, seq, i, sid)] = ((seq, i), sid)
    extra = sorted(map(str, sub.keys - set(keys)))
    if extra:
        raise PcfbenchError(f"{where} has {len(extra)} sample(s) that {questions.dataset}:{questions.split} "
                            f"{questions.setting} ({questions.policy}) does not have: {_first(extra)}")
    missing = [sid for k, (_, sid) in keys.items() if k not in sub.keys]
    if missing and not partial:
        raise PcfbenchError(f"{where} misses {len(missing)} of the {len(keys)} samples: {_first(missing)}; pass --partial "
                            "to score the samples it has (the cell is then marked partial and never ranked)")
    if len(missing) == len(keys):
        raise PcfbenchError(f"{where} answers none of the {len(keys)} samples")
    for k, (key, sid) in keys.items():
        if k not in sub.keys:
            continue
        sample, _truth = questions.builder.build(*key)
        try:
            validate_forecast(sample, sub.forecast(sample))
        except ForecastError as exc:
            raise PcfbenchError(f"{where}: {exc}") from None
        if progress is not None:
            progress(1)
    return Checked(len(keys) - len(missing), tuple(missing))


def sub_key(sub: SubmissionFile, questions: Questions, sequence: str, ref_index: int, sid: str) -> Any:
    """The key naming sample ``sid`` in ``sub``: its id, or the challenge's (log id, frame)."""
    if sub.layout == "npz":
        return sid
    from pcfbench.exchange.challenge import challenge_key

    seq = questions.builder.sequence(sequence)
    return challenge_key(sequence, int(seq.timestamps_ns[ref_index]))
