"""Copy-last: the t=0 sweep, already in the reference frame, is every future sweep."""

from __future__ import annotations

from pcfbench.data import Forecast, Sample
from pcfbench.method import Method


class CopyLast(Method):
    """A static-world baseline with no re-rendering: the forecast ignores the future poses."""

    name = "copy-last"
    version = "1"

    def forecast(self, sample: Sample) -> Forecast:
        last = sample.past_points_ref[-1]
        return Forecast(points_ref=tuple(last for _ in range(sample.num_future)))
