"""A submission checked whole against the questions of a cell, before any of it is scored.

:func:`check_submission` refuses, with one error naming the file and the first offending sample:
another format or version, answers to other questions (protocol, dataset fingerprint, split,
setting, policy: each difference named), samples the cell does not have, samples missing
(unless partial), a future sweep missing or extra, and any forecast the runner would refuse
(wrong ray count or shape, NaN, inf, negative depths: :func:`pcfbench.protocol.validate.validate_forecast`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pcfbench.errors import ForecastError, PcfbenchError
from pcfbench.exchange.challenge import challenge_key, open_challenge_submission
from pcfbench.exchange.questions import Questions, differences
from pcfbench.exchange.submission import SubmissionFile, open_npz_submission
from pcfbench.protocol.validate import validate_forecast


def open_submission(path: str | Path) -> SubmissionFile:
    """The submission at ``path``: a ``.json`` file is read as the AV2 challenge's layout,
    anything else as a NumPy archive."""
    path = Path(path)
    if not path.is_file():
        raise PcfbenchError(f"submission {path} does not exist")
    if path.suffix.lower() == ".json":
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
    seq = questions.builder.sequence(sequence)
    return challenge_key(sequence, int(seq.timestamps_ns[ref_index]))
