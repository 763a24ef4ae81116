"""Golden numbers: a fixed pair of clouds whose metric values may only change together with the
metric's version and a line in bench/metrics/CHANGELOG.md."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from test_metrics import close, fast, slow, suite

CHANGELOG = Path(__file__).resolve().parents[2] / "bench" / "metrics" / "CHANGELOG.md"

#: name -> (version, value on the point forecast, value on the depth forecast)
GOLDEN = {
    "chamfer": ("1", 2.1118822836484137, 1.706484137925742),
    "chamfer_nf": ("1", 0.9908486763713245, 0.769415816504555),
    "chamfer_nf@4docc": ("1", 0.9908486763713245, 0.769415816504555),
    "l1@4docc": ("1", 0.7907546952260085, 0.5102533991128717),
    "absrel@4docc": ("1", 0.0331213794467308, 0.02378696461325587),
    "l1_mean": ("1", 0.6718961595745223, 0.5102533991128717),
    "absrel_mean": ("1", 0.029849650364061838, 0.02378696461325587),
    "l1_median": ("1", 0.47394726200502113, 0.40690219119652404),
    "absrel_median": ("1", 0.022734587327988304, 0.020128034090332855),
    "l1_ray": ("1", float("nan"), 0.9927283036203772),
    "absrel_ray": ("1", float("nan"), 0.03394546421305313),
}


def golden_pair():
    """A spinning-LiDAR-like pair: 12 beams x 160 azimuths of ground truth, every other ray
    predicted 5% off with a small offset; the upper beams reach past the ROI. Analytic, no RNG."""
    el = np.deg2rad(np.linspace(-20.0, 3.0, 12))
    az = np.linspace(-np.pi, np.pi, 160, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    E, A = E.ravel(), A.ravel()
    origin = np.array([1.5, -0.5, 1.7])
    r_gt = 25.0 + 12.0 * np.cos(2 * A) + 5.0 * np.sin(5 * A) * np.cos(3 * E)
    r_gt = np.where(E > 0.03, 90.0, r_gt)
    r_pred = r_gt * (1.0 + 0.05 * np.sin(7 * A + 2 * E)) + 0.3
    gt = (origin + d * r_gt[:, None]).astype(np.float32)
    pred = (origin + d[::2] * r_pred[::2, None] + np.array([0.2, -0.1, 0.05])).astype(np.float32)
    return gt, origin, pred, r_pred.astype(np.float32)


@pytest.mark.parametrize("mode", ["points", "depths"])
def test_golden_numbers(mode):
    gt, origin, pred, depths = golden_pair()
    kw = {"pred": pred} if mode == "points" else {"depths": depths}
    got, ref = fast(gt, origin, **kw), slow(gt, origin, **kw)
    versions = {m.name: m.version for m in suite()}
    col = 1 if mode == "points" else 2
    for name, entry in GOLDEN.items():
        assert versions[name] == entry[0], (
            f"{name} is now version {versions[name]}: update GOLDEN and add a CHANGELOG line"
        )
        assert close(got[name], entry[col], rel=1e-9), f"{name} ({mode}): {got[name]!r} != golden {entry[col]!r}"
        assert close(ref[name], entry[col], rel=1e-9), f"reference {name} ({mode}): {ref[name]!r}"


def test_every_metric_version_has_a_changelog_line():
    text = CHANGELOG.read_text()
    for m in suite():
        assert re.search(rf"^- `{re.escape(m.name)}` {re.escape(m.version)}:", text, re.M), (
            f"bench/metrics/CHANGELOG.md has no line for {m.name} version {m.version}"
        )
    assert set(GOLDEN) == {m.name for m in suite()}


@pytest.mark.parametrize("threads", [2, 3])
def test_shared_out_searches_give_the_golden_numbers(threads):
    """With more than one thread, share_out runs the searches and what the metrics compute from
    them (the crops' NN distances, the per-ray errors, their medians) on the pool before any
    metric asks; every metric still reads the golden value, bit for bit the serial context's."""
    from test_metrics import make_ctx

    from pcfbench.execution import ExecutionContext
    from pcfbench.metrics.base import ANGLES, NN

    gt, origin, pred, _ = golden_pair()
    serial = fast(gt, origin, pred=pred)
    ctx = make_ctx(gt, origin, pred)
    ctx.execution = ExecutionContext(threads)
    ctx.share_out({NN, ANGLES})
    for name in ("nn_pred_to_gt_roi", "nn_gt_to_pred_roi", "ray_errors_4docc", "ray_errors_wrapped",
                 "ray_error_medians"):
        assert name in ctx.__dict__, f"{name} was not computed by share_out"
    for m in suite():
        got = m(ctx)
        assert close(got, GOLDEN[m.name][1], rel=1e-9), f"{m.name}: {got!r}"
        assert got == serial[m.name] or (np.isnan(got) and np.isnan(serial[m.name])), m.name


@pytest.mark.parametrize("threads", [1, 2])
def test_a_ground_truth_outside_the_roi_scores_the_same_shared_out(threads):
    """Every ground-truth point beyond the ROI, the forecast inside it: NFCD is undefined (NaN,
    0 for the 4D-Occ variant) and the rest scores, on one thread or shared out over two (the
    pool once asked for the crops' passes anyway and failed on the empty crop)."""
    from test_metrics import make_ctx

    from pcfbench.execution import ExecutionContext
    from pcfbench.metrics.base import ANGLES, NN

    rng = np.random.default_rng(0)
    gt = rng.normal(size=(300, 3)) * 2 + [100.0, 0.0, 0.0]
    pred = rng.normal(size=(300, 3)) * 2 + [10.0, 0.0, 0.0]
    ctx = make_ctx(gt, np.zeros(3), pred)
    ctx.execution = ExecutionContext(threads)
    ctx.share_out({NN, ANGLES})
    got = {m.name: m(ctx) for m in suite()}
    assert np.isnan(got["chamfer_nf"]) and got["chamfer_nf@4docc"] == 0.0
    serial = fast(gt, np.zeros(3), pred=pred)
    for name, v in got.items():
        assert v == serial[name] or (np.isnan(v) and np.isnan(serial[name])), name
