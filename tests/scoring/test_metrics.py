"""Helpers shared by the metric tests: score one sweep with the fast suite and the reference."""

from __future__ import annotations

import numpy as np

from pcfbench.data import RayQuery
from pcfbench.metrics import reference
from pcfbench.metrics.base import SweepContext

NAMES = (
    "chamfer", "chamfer_nf", "chamfer_nf@4docc", "l1@4docc", "absrel@4docc", "l1_mean", "absrel_mean",
    "l1_median", "absrel_median", "l1_ray", "absrel_ray",
)


def suite():
    from pcfbench.plugins import get_plugins

    reg = get_plugins().metrics
    return [reg.get(n) for n in NAMES]


def make_ctx(gt, origin, pred=None, depths=None) -> SweepContext:
    gt = np.asarray(gt, np.float32).reshape(-1, 3)
    o = np.asarray(origin, np.float64)
    rel = gt.astype(np.float64) - o
    r = np.linalg.norm(rel, axis=1)
    dirs = (rel / np.where(r > 0, r, 1.0)[:, None]).astype(np.float32)
    pred = None if pred is None else np.asarray(pred, np.float32).reshape(-1, 3)
    depths = None if depths is None else np.asarray(depths, np.float32)
    return SweepContext(gt, RayQuery(o, dirs), pred, depths)


def fast(gt, origin, pred=None, depths=None) -> dict[str, float]:
    ctx = make_ctx(gt, origin, pred, depths)
    out = {}
    for m in suite():
        if len(ctx.gt_points) == 0 or (m.needs == "depths" and ctx.pred_depths is None):
            out[m.name] = float("nan")  # as score_sample does
        else:
            out[m.name] = m(ctx)
    return out


def slow(gt, origin, pred=None, depths=None) -> dict[str, float]:
    ctx = make_ctx(gt, origin, pred, depths)  # the same float32 inputs the fast suite sees
    return reference.all_metrics(ctx.gt_points, ctx.origin, ctx.pred_points, ctx.pred_depths)


def close(a: float, b: float, rel: float = 1e-6, abs_: float = 1e-12) -> bool:
    if np.isnan(a) or np.isnan(b):
        return bool(np.isnan(a) and np.isnan(b))
    return abs(a - b) <= max(rel * max(abs(a), abs(b)), abs_)


def check_both(expected: dict[str, float], gt, origin, pred=None, depths=None) -> None:
    """The fast suite and the reference both give the hand-computed values."""
    f, s = fast(gt, origin, pred, depths), slow(gt, origin, pred, depths)
    for name, want in expected.items():
        assert close(f[name], want), f"fast {name}: {f[name]} != {want}"
        assert close(s[name], want), f"reference {name}: {s[name]} != {want}"


# -- registration -----------------------------------------------------------------------------
def test_every_metric_is_registered_with_unit_and_version():
    units = {m.name: m.unit for m in suite()}
    assert units == {
        "chamfer": "m^2", "chamfer_nf": "m^2", "chamfer_nf@4docc": "m^2",
        "l1@4docc": "m", "absrel@4docc": "fraction", "l1_mean": "m", "absrel_mean": "fraction",
        "l1_median": "m", "absrel_median": "fraction", "l1_ray": "m", "absrel_ray": "fraction",
    }
    for m in suite():
        assert m.version and m.description and m.reference and m.empty_policy


# -- Chamfer ----------------------------------------------------------------------------------
def test_chamfer_hand_computed():
    # P->G: min(1, 4) = 1; G->P: (1 + 4) / 2 = 2.5; CD = (1 + 2.5) / 2
    check_both({"chamfer": 1.75, "chamfer_nf": 1.75, "chamfer_nf@4docc": 1.75},
               gt=[[1, 0, 0], [0, 2, 0]], origin=[0, 0, 0], pred=[[0, 0, 0]])


def test_near_field_chamfer_crops_independently():
    # g2 at x=72 leaves the ROI: p2 (x=69) is 3 m from g2 but 68 m (and 0.5 up) from g1.
    gt = [[1, 0, 0.5], [72, 0, 0]]
    pred = [[1, 0, 0], [69, 0, 0]]
    cd = 0.5 * ((0.25 + 9) / 2 + (0.25 + 9) / 2)
    nf = 0.5 * ((0.25 + 68**2 + 0.25) / 2 + 0.25)
    check_both({"chamfer": cd, "chamfer_nf": nf, "chamfer_nf@4docc": nf}, gt, [0, 0, 0], pred)


def test_near_field_chamfer_empty_crop():
    # the prediction has no point in the ROI: NFCD skipped, 0 under the reference code's policy
    check_both({"chamfer": 99.0**2, "chamfer_nf": float("nan"), "chamfer_nf@4docc": 0.0},
               gt=[[1, 0, 0]], origin=[0, 0, 0], pred=[[100, 0, 0]])
    # same for an empty crop of the ground truth
    check_both({"chamfer_nf": float("nan"), "chamfer_nf@4docc": 0.0},
               gt=[[100, 0, 0]], origin=[0, 0, 0], pred=[[1, 0, 0]])


def test_empty_prediction():
    nan = float("nan")
    expected = {n: nan for n in NAMES}
    expected["chamfer_nf@4docc"] = 0.0
    check_both(expected, gt=[[10, 0, 0], [0, 5, 1]], origin=[0, 0, 0], pred=np.zeros((0, 3)))


def test_empty_ground_truth_is_skipped_everywhere():
    check_both({n: float("nan") for n in NAMES}, gt=np.zeros((0, 3)), origin=[0, 0, 0], pred=[[1, 2, 0]])
    check_both({n: float("nan") for n in NAMES}, gt=np.zeros((0, 3)), origin=[0, 0, 0], depths=np.zeros(0))


# -- depth errors -----------------------------------------------------------------------------
def test_depth_errors_simple_ray():
    # one ray along +x, true depth 10, predicted point at 8: err 2, absrel 0.2
    e = {"l1@4docc": 2.0, "absrel@4docc": 0.2, "l1_mean": 2.0, "absrel_mean": 0.2, "l1_median": 2.0,
         "absrel_median": 0.2, "l1_ray": float("nan")}
    check_both(e, gt=[[10, 0, 0]], origin=[0, 0, 0], pred=[[8, 0, 0]])


def test_ray_leaving_the_roi_is_clamped():
    # ground truth at x=100 clamps to 70; a prediction at 80 clamps to 70 too: no error
    check_both({"l1_mean": 0.0, "l1@4docc": 0.0}, gt=[[100, 0, 0]], origin=[0, 0, 0], pred=[[80, 0, 0]])
    # a prediction at 50: err 20, absrel 20 / 70
    check_both({"l1_mean": 20.0, "absrel_mean": 20 / 70, "l1_median": 20.0},
               gt=[[100, 0, 0]], origin=[0, 0, 0], pred=[[50, 0, 0]])
    # straight up: the ROI top is z=4.5 above an origin at z=0
    check_both({"l1_mean": 4.5 - 3.0, "absrel_mean": 1.5 / 4.5}, gt=[[0, 0, 9]], origin=[0, 0, 0], pred=[[0, 0, 3]])


def test_origin_outside_the_roi():
    # origin at x=-80: the ray along +x enters the ROI at t=10; g at t=80 -> clamped range 70
    o = [-80, 0, 0]
    check_both({"l1_mean": 10.0, "absrel_mean": 10 / 70}, gt=[[0, 0, 0]], origin=o, pred=[[-10, 0, 0]])
    # a prediction before the entry clamps to the entry point: err 70, absrel 1
    check_both({"l1_mean": 70.0, "absrel_mean": 1.0}, gt=[[0, 0, 0]], origin=o, pred=[[-75, 0, 0]])
    # a ray that misses the ROI is dropped: the mean keeps one ray, the 4D-Occ sum divides by two
    gt = [[0, 0, 0], [-80, 10, 0]]
    check_both({"l1_mean": 10.0, "l1_median": 10.0, "l1@4docc": 5.0, "absrel@4docc": 10 / 70 / 2},
               gt=gt, origin=o, depths=[70.0, 3.0])
    # a ground-truth point before the entry has clamped range 0 <= 1 cm: dropped as well
    check_both({"l1_mean": float("nan"), "l1@4docc": 0.0}, gt=[[-75, 0, 0]], origin=o, pred=[[-60, 0, 0]])


def _at(az: float, r: float, z: float = 0.0):
    return [r * np.cos(az), r * np.sin(az), z]


def test_azimuth_seam_wraps_in_corrected_metrics():
    for sign in (1, -1):
        gt = [_at(sign * (np.pi - 0.01), 10.0)]
        a = _at(-sign * (np.pi - 0.01), 12.0)  # 0.02 rad away across the seam
        b = _at(sign * (np.pi - 0.1), 20.0)  # 0.09 rad away on the same side
        f, s = fast(gt, [0, 0, 0], [a, b]), slow(gt, [0, 0, 0], [a, b])
        assert close(f["l1_mean"], 2.0) and close(s["l1_mean"], 2.0), (f, s)


def test_4docc_angle_space_has_no_wrap():
    # 4D-Occ's first angle atan2(x, y) has its seam where x = 0, y < 0
    gt = [[0.1, -10, 0]]  # atan2(x, y) = pi - 0.01
    a = [-0.1, -10, 0]  # -pi + 0.01: truly 0.02 rad away, 2 pi - 0.02 in the 4D-Occ space
    b = [1.0, -10, 0]  # pi - 0.0997
    d_a, d_b = np.hypot(0.1, 10), np.hypot(1.0, 10)
    d_gt = d_a
    f, s = fast(gt, [0, 0, 0], [a, b]), slow(gt, [0, 0, 0], [a, b])
    for out in (f, s):
        assert close(out["l1@4docc"], abs(d_b - d_gt)), out  # picks b
        assert close(out["l1_mean"], 0.0, abs_=1e-6), out  # picks a (same range)


def test_ray_query_mode():
    gt = [[10, 0, 0], [0, 4, 0], [0, 100, 0]]  # the last ray leaves the ROI (clamped to 70)
    depths = [12.0, 3.0, 90.0]
    f = fast(gt, [0, 0, 0], depths=depths)
    assert close(f["l1_ray"], (2 + 1 + 10) / 3)
    assert close(f["absrel_ray"], (0.2 + 0.25 + 0.1) / 3)
    # the clamped metrics use the same depths directly: errors 2, 1, 0
    assert close(f["l1_mean"], 1.0) and close(f["l1_median"], 1.0) and close(f["l1@4docc"], 1.0)
    assert close(f["absrel_mean"], (0.2 + 0.25) / 3)
    check_both(f, gt, [0, 0, 0], depths=depths)
    # a points-only forecast has no ray-query answer: skipped
    assert np.isnan(fast(gt, [0, 0, 0], pred=[[1, 1, 0]])["l1_ray"])


def test_ray_box_interval_hand_cases():
    from pcfbench.boxes import Box, clamp_ranges_to_box, ray_box_interval

    box = Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    o = np.zeros(3)
    d = np.array([[1, 0, 0], [0, -1, 0], [0.6, 0.8, 0]], float)
    t0, t1 = ray_box_interval(o, d, box)
    np.testing.assert_allclose(t0, [0, 0, 0])
    np.testing.assert_allclose(t1, [1, 1, 1 / 0.8])
    # origin outside: enters at 2, leaves at 4; a ray pointing away or parallel outside misses
    o = np.array([-3.0, 0, 0])
    d = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0]], float)
    t0, t1 = ray_box_interval(o, d, box)
    assert t0[0] == 2 and t1[0] == 4
    assert not t0[1] <= t1[1] and not t0[2] <= t1[2]
    # origin on a face, parallel to it: inside (bounds inclusive)
    t0, t1 = ray_box_interval(np.array([0, 1.0, 0]), np.array([[1.0, 0, 0]]), box)
    assert t0[0] == 0 and t1[0] == 1
    start, end, kept = clamp_ranges_to_box(np.array([-3.0, 0, 0]), np.array([[1.0, 0, 0]] * 3),
                                           np.array([1.0, 3.0, 9.0]), box)
    np.testing.assert_allclose(start, [2, 2, 2])
    np.testing.assert_allclose(end, [2, 3, 4])
    assert kept.all()


def test_depths_only_forecast_turns_into_points_for_chamfer():
    gt = [[10, 0, 0], [0, 4, 0]]
    f = fast(gt, [0, 0, 0], depths=[12.0, 4.0])
    # points (12,0,0), (0,4,0): P->G (4 + 0) / 2 = 2, G->P 2; CD = 2
    assert close(f["chamfer"], 2.0)
