"""The ``submission`` method: the forecasts of a submission file, scored as any method's are.

``pcfbench score`` checks the whole file first (:func:`pcfbench.exchange.submission.check_submission`)
and then runs an ordinary cell of this method, so a submission's rows are made, validated and
scored by the very code a plugin's are. Its options name the submission (``name``: the row's
label), its file (``path``) and the file's ``sha256``: part of the options, so of the cell's
folder and identity, so a file changed after scoring makes a new cell; a file that changed
since its cell was set up is refused.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from pcfbench.data import Forecast, Sample
from pcfbench.errors import ForecastError, PcfbenchError
from pcfbench.method import Method
from pcfbench.options import option


@dataclasses.dataclass(frozen=True)
class SubmissionOptions:
    name: str = option("", help="the submission's name (its leaderboard label)")
    path: str = option("", help="the submission file (.npz, or the AV2 challenge's .json)")
    sha256: str = option("", help="the file's sha256 (set by `pcfbench score`; a changed file is refused)")


class Submission(Method):
    """Forecasts read from a file made outside pcfbench (``pcfbench score``)."""

    name = "submission"
    version = "1"
    Options = SubmissionOptions
    #: not one of the methods a plain ``pcfbench run`` runs: it needs a file (``pcfbench score``)
    in_default_runs: ClassVar[bool] = False

    def __init__(self, options: SubmissionOptions | None = None) -> None:
        from pcfbench.exchange.check import open_submission
        from pcfbench.exchange.submission import file_sha256

        super().__init__(options)
        o = self.options
        if not o.path or not o.sha256:
            raise PcfbenchError("method submission needs path= and sha256=: score a file with `pcfbench score FILE`")
        sha = file_sha256(o.path)
        if sha != o.sha256:
            raise PcfbenchError(f"submission {o.path} changed since its cell was set up (sha256 {sha[:12]}, the cell is "
                                f"keyed by {o.sha256[:12]}): score the new file with `pcfbench score`, a new cell")
        self.file = open_submission(o.path)

    def forecast(self, sample: Sample) -> Forecast:
        forecast = self.file.forecast(sample)
        if forecast is None:  # a partial submission's sample (the cell is marked partial)
            raise ForecastError(f"sample {sample.sample_id} is not in the partial submission {self.options.path}")
        return forecast
