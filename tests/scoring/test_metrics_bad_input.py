"""A bad forecast becomes that sample's recorded failure, naming the sample and the sweep."""

from __future__ import annotations

import numpy as np
import pytest
from test_metrics import suite

from pcfbench.data import Forecast
from pcfbench.method import Method
from pcfbench.protocol import SETTINGS, SampleBuilder
from pcfbench.running.runner import Resolved, process_sample
from pcfbench.testing import InMemoryDataset


class Scripted(Method):
    """Answers copy-last points, then breaks sweep ``bad`` with ``breaker``."""

    name = "scripted"

    def __init__(self, breaker, kind: str = "points", bad: int = 1) -> None:
        super().__init__()
        self.breaker, self.kind, self.bad = breaker, kind, bad

    def forecast(self, sample):
        last = sample.past_points_ref[-1]
        if self.kind == "points":
            pts = [last.copy() for _ in sample.queries]
            pts[self.bad] = self.breaker(pts[self.bad])
            return Forecast(points_ref=tuple(pts))
        depths = [np.full(len(q), 10.0, np.float32) for q in sample.queries]
        depths[self.bad] = self.breaker(depths[self.bad])
        return Forecast(depths=tuple(depths))


@pytest.fixture(scope="module")
def builder():
    return SampleBuilder(InMemoryDataset(num_sweeps=20, beams=8, azimuths=90), SETTINGS["kitti-1s"])


def _nan(a):
    a = a.copy()
    a[0] = np.nan
    return a


def _inf(a):
    a = a.copy()
    a[-1] = np.inf
    return a


def _neg(a):
    a = a.copy()
    a[2] = -1.0
    return a


@pytest.mark.parametrize(
    "kind,breaker,message",
    [
        ("points", _nan, "NaN or inf"),
        ("points", _inf, "NaN or inf"),
        ("points", lambda a: a.astype(np.int32), "floating point"),
        ("points", lambda a: a[:, :2], "shape (N, 3)"),
        ("depths", _nan, "NaN or inf"),
        ("depths", _neg, "negative"),
        ("depths", lambda a: a[:-1], "one per query ray"),
        ("depths", lambda a: a.astype(str), "numeric"),
    ],
)
def test_bad_forecast_is_the_samples_recorded_failure(builder, kind, breaker, message):
    key = builder.sample_keys("test")[0]
    res = Resolved(builder, Scripted(breaker, kind, bad=3), suite())
    rows = process_sample(res, key)
    assert len(rows) == 1 and rows[0]["status"] == "failed", rows
    err = rows[0]["error"]
    assert err.startswith("ForecastError"), err
    assert f"sample {rows[0]['sample_id']}" in err and "future sweep 3" in err and message in err, err


def test_good_forecast_scores_every_sweep(builder):
    key = builder.sample_keys("test")[0]
    rows = process_sample(Resolved(builder, Scripted(lambda a: a, "depths"), suite()), key)
    assert [r["step"] for r in rows] == list(range(SETTINGS["kitti-1s"].future))
    for r in rows:
        assert r["status"] == "ok"
        assert r["l1_ray"] >= 0 and np.isfinite(r["chamfer"]) and np.isfinite(r["l1_mean"]), r
