"""A submission file: forecasts made elsewhere, opened (``pcfbench.exchange.check`` checks it).

Two layouts (docs/bring-your-own-method.md):

- **NumPy** (``.npz``, read with pickles refused): ``header.json`` (a 0-d string: JSON with
  ``format`` "pcfbench-submission", ``exchange_version`` and ``answers``, copied from the query
  file's header), then per sample id ``SID`` and future sweep ``K`` either or both of
  ``SID/depths/K`` ((M_k,) one depth in metres per query ray, in the query file's order) and
  ``SID/points_ref/K`` ((K_k, 3) points in the reference frame).
- **Argoverse 2 challenge JSON** (``.json``, :mod:`pcfbench.exchange.challenge`): one depth per
  query ray, keyed by log id and t=0 frame.

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
from pcfbench.exchange.queries import HEADER, open_npz, read_header

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
