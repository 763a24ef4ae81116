"""Ray-casting baselines: contract, hand-built scenes with known answers, brute-force checks."""

from __future__ import annotations

import numpy as np
import pytest

from pcfbench.data import RayQuery, Sample
from pcfbench.geometry import se3, yaw_transform
from pcfbench.protocol import ROI
from pcfbench.boxes import Box
from pcfbench.testing import check_method
from pcfbench.metrics.nn import angles_4docc
from pcfbench.methods.raycast.common import aggregate, views
from pcfbench.methods.raycast.fastmath import atan2_array
from pcfbench.methods.raycast.fourdocc import RaycastFourDOcc, render_4docc_views
from pcfbench.methods.raycast.freespace import RaycastFreespace, carve
from pcfbench.methods.raycast.grid import FOLLOW_RANGE, VoxelGrid, anchored_lo, sym3_smallest
from pcfbench.methods.raycast.voxel import RaycastVoxel, build_grid, ground_height
from pcfbench.methods.raycast.zbuffer import RaycastZBuffer

ALL = [RaycastFourDOcc, RaycastZBuffer, RaycastVoxel, RaycastFreespace]
OCCLUSION_AWARE = [RaycastZBuffer, RaycastVoxel, RaycastFreespace]


def fan(az_deg: tuple[float, float, float], el_deg: tuple[float, float, float]) -> np.ndarray:
    """Unit directions on an azimuth x elevation grid, (start, stop, step) in degrees (stop included)."""
    az = np.deg2rad(np.arange(az_deg[0], az_deg[1] + 1e-9, az_deg[2]))
    el = np.deg2rad(np.arange(el_deg[0], el_deg[1] + 1e-9, el_deg[2]))
    A, E = np.meshgrid(az, el, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)


def cast_boxes(origin: np.ndarray, dirs: np.ndarray, boxes: list[tuple[tuple, tuple]]) -> np.ndarray:
    """Range of the first axis-aligned box each ray hits (inf when none)."""
    o = np.asarray(origin, dtype=np.float64)
    best = np.full(len(dirs), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        for lo, hi in boxes:
            t1 = (np.asarray(lo) - o) * inv
            t2 = (np.asarray(hi) - o) * inv
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tmax >= np.maximum(tmin, 0)) & (tmin > 0)
            best = np.where(hit & (tmin < best), tmin, best)
    return best


def scan(origin, dirs, boxes) -> np.ndarray:
    """The (N, 3) returns of rays ``dirs`` from ``origin`` against ``boxes`` (misses dropped)."""
    t = cast_boxes(origin, dirs, boxes)
    keep = np.isfinite(t)
    return (np.asarray(origin) + dirs[keep] * t[keep, None]).astype(np.float32)


def make_sample(past_points, past_origins, future_origins, future_dirs, dt_ns: int = 100_000_000) -> Sample:
    """A sample with identity rotations: past sweeps at ``past_origins``, queries from ``future_origins``."""
    P, F = len(past_points), len(future_origins)
    past_T = np.stack([se3(np.eye(3), o) for o in past_origins])
    fut_T = np.stack([se3(np.eye(3), o) for o in future_origins])
    queries = tuple(
        RayQuery(origin_ref=np.asarray(o, dtype=np.float64), directions_ref=np.asarray(d, dtype=np.float32))
        for o, d in zip(future_origins, future_dirs)
    )
    return Sample(
        sample_id="scene/000000", dataset="scene", sequence="scene", ref_index=P - 1,
        past_points_ref=tuple(np.asarray(p, dtype=np.float32) for p in past_points),
        past_T_ref_sensor=past_T,
        past_timestamps_ns=np.arange(-(P - 1), 1, dtype=np.int64) * dt_ns,
        future_T_ref_sensor=fut_T,
        future_timestamps_ns=np.arange(1, F + 1, dtype=np.int64) * dt_ns,
        queries=queries,
    )


WALL = ((20.0, -30.0, -3.0), (20.5, 30.0, 5.0))
PAST_FAN = fan((-50, 50, 0.2), (-10, 10, 0.4))


def truth(sample: Sample, boxes) -> list[np.ndarray]:
    return [cast_boxes(q.origin_ref, q.directions_ref.astype(np.float64), boxes) for q in sample.queries]


# ---------------------------------------------------------------- contract and registration


@pytest.mark.parametrize("cls", ALL)
@pytest.mark.parametrize("cv", [False, True])
def test_contract_on_toy_world(cls, cv):
    forecast = check_method(cls(cls.Options(constant_velocity=cv)))
    assert len(forecast.points_ref) == 5
    if cv:
        assert forecast.depths is None  # points cast from extrapolated origins only
    else:
        assert forecast.depths is not None and all(len(d) > 1000 for d in forecast.depths)


@pytest.mark.parametrize("cls", ALL)
def test_missing_past_and_future_sweeps_are_fine(cls):
    # kitti-3s on the 30-sweep toy world at index 8: most past and the last future sweeps are missing
    forecast = check_method(cls(), setting="kitti-3s")
    assert [len(p) for p in forecast.points_ref][-2:] == [0, 0]
    assert len(forecast.points_ref[0]) > 1000


def test_registered():
    from pcfbench.plugins import get_plugins

    methods = get_plugins(reload=True).methods
    for cls in ALL:
        assert cls.name in methods.names()
        assert methods.get(cls.name) is cls


# ---------------------------------------------------------------- hand-built scenes


def wall_sample(future_origins=((1.0, 0.0, 0.0), (2.0, 0.3, 0.2)), boxes=(WALL,)):
    past_origins = [(-4.0 + k, 0.0, 0.0) for k in range(5)]
    past = [scan(o, PAST_FAN, list(boxes)) for o in past_origins]
    q = fan((-30, 30, 1.1), (-8, 8, 0.9))
    return make_sample(past, past_origins, future_origins, [q] * len(future_origins))


@pytest.mark.parametrize("cls", ALL)
def test_wall_at_known_distance(cls):
    sample = wall_sample()
    forecast = cls().forecast(sample)
    for d, t in zip(forecast.depths, truth(sample, [WALL])):
        err = np.abs(d - t)
        # the occlusion-aware casters are within a voxel; 4D-Occ picks a neighbouring point's range
        assert np.median(err) < (0.05 if cls in OCCLUSION_AWARE else 0.3)
        assert np.quantile(err, 0.95) < (0.15 if cls in OCCLUSION_AWARE else 0.6)


def test_occluder_in_front_of_wall_is_the_first_hit():
    occluder = ((8.0, -1.0, -1.0), (9.0, 1.0, 1.0))
    boxes = [WALL, occluder]
    # past sensors beside each other: between them they see the wall behind the occluder too
    past_origins = [(0.0, y, 0.0) for y in (-6.0, -3.0, 0.0, 3.0, 6.0)]
    past = [scan(o, PAST_FAN, boxes) for o in past_origins]
    q = fan((-5, 5, 0.5), (-5, 5, 0.5))
    sample = make_sample(past, past_origins, [(1.5, 0.0, 0.0)], [q])
    t = truth(sample, boxes)[0]
    on_box = t < 10
    assert on_box.sum() > 200
    for cls in (RaycastZBuffer, RaycastVoxel, RaycastFreespace):
        d = cls().forecast(sample).depths[0]
        err = np.abs(d - t)[on_box]
        assert np.quantile(err, 0.95) < 0.3, cls.name
    # the reference has no first-hit logic: wall points win where they are nearer in angle
    d = RaycastFourDOcc().forecast(sample).depths[0]
    assert np.mean(np.abs(d - t)[on_box] > 5.0) > 0.05


def test_ray_grazing_a_voxel_face():
    box = Box((0.0, 0.0, 0.0), (3.2, 3.2, 3.2))
    grid = VoxelGrid(np.array([[1.1, 0.1, 0.1]]), voxel=0.2, box=box, levels=2)
    o = np.array([0.05, 0.0, 0.1])
    dirs = np.array([[1.0, 0.0, 0.0]] * 4)
    starts = np.array([[0.05, 0.2 - 1e-6, 0.1], [0.05, 0.2 + 1e-6, 0.1], [0.05, 1e-6, 0.1], [0.05, 0.1, 0.2 - 1e-6]])
    depths = np.array([grid.cast(s, d[None])[0] for s, d in zip(starts, dirs)])
    # inside the face by 1 um: hit, at the voxel's point (x = 1.1); outside by 1 um: no hit
    assert depths[0] == pytest.approx(1.05, abs=1e-9)
    assert np.isnan(depths[1])
    assert depths[2] == pytest.approx(1.05, abs=1e-9)
    assert depths[3] == pytest.approx(1.05, abs=1e-9)
    # diagonal rays (x - y = c) past the voxel's corner at (1.0, 0.2): clipping the corner by
    # 0.1 mm hits (the traversal steps 10 um past each cell face), passing it by 1 um misses
    d = np.array([[1.0, 1.0, 0.0]]) / np.sqrt(2.0)
    assert np.isfinite(grid.cast(np.array([0.8 + 1e-4, 0.0, 0.1]), d)[0])
    assert np.isnan(grid.cast(np.array([0.8 - 1e-6, 0.0, 0.1]), d)[0])
    # and from a start inside the grid along -x, the same voxel is met from the other side
    assert grid.cast(o + np.array([2.0, 0.1, 0.0]), -dirs[:1])[0] == pytest.approx(2.0 + 0.05 - 1.1, abs=1e-9)


def test_ray_leaving_the_grid_takes_the_fallback():
    far_wall = ((100.0, -60.0, -8.0), (100.5, 60.0, 8.0))  # beyond the 70 m ROI
    past_origins = [(0.0, 0.0, 0.0)] * 3
    past = [scan(o, fan((-20, 20, 0.2), (-3, 3, 0.4)), [far_wall]) for o in past_origins]
    q = fan((-10, 10, 0.7), (-2, 2, 0.7))
    sample = make_sample(past, past_origins, [(2.0, 0.0, 0.0)], [q])
    t = truth(sample, [far_wall])[0]
    grid = VoxelGrid(np.concatenate(past).astype(np.float64))
    assert np.isnan(grid.cast(np.array([2.0, 0.0, 0.0]), q)).all()  # nothing in the grid
    for cls in (RaycastVoxel, RaycastFreespace):
        d = cls().forecast(sample).depths[0]
        assert np.quantile(np.abs(d - t), 0.95) < 0.5, cls.name


def test_ray_entering_the_grid_from_outside():
    grid = VoxelGrid(np.array([[10.1, 0.1, 0.1]]))
    d = grid.cast(np.array([-80.0, 0.1, 0.1]), np.array([[1.0, 0.0, 0.0]]))[0]
    assert d == pytest.approx(90.1, abs=1e-6)


def test_sparse_far_wall_that_a_naive_caster_misses():
    far = ((60.0, -40.0, -4.0), (60.3, 40.0, 8.0))
    past_origins = [(0.0, 0.0, 0.0)] * 5  # a parked car: the same beams five times
    past = [scan(o, fan((-15, 15, 0.2), (-2.8, 6, 0.4)), [far]) for o in past_origins]
    origin = (5.0, 0.0, 0.37)
    q = fan((-10, 10, 0.5), (-2.0, 4.5, 0.13))
    sample = make_sample(past, past_origins, [origin], [q])
    t = truth(sample, [far])[0]
    grid = VoxelGrid(np.concatenate(past).astype(np.float64))
    naive = grid.cast(np.array(origin), q.astype(np.float64))  # thin rays
    assert np.isnan(naive).mean() > 0.3  # they slip between the rows of past points
    d = RaycastVoxel().forecast(sample).depths[0]
    assert np.median(np.abs(d - t)) < 0.4
    assert np.quantile(np.abs(d - t), 0.99) < 1.0


def moving_box_sample():
    past_origins = [(0.0, 0.0, 0.0)] * 5
    past = []
    for k in range(5):
        yc = -6.0 + 3.0 * k
        car = ((10.0, yc - 1.0, -1.0), (14.0, yc + 1.0, 0.5))
        past.append(scan(past_origins[k], fan((-60, 60, 0.25), (-6, 6, 0.4)), [WALL, car]))
    q = fan((-32, -4, 0.8), (-3, 2, 0.8))  # where the car was, now only the wall
    return make_sample(past, past_origins, [(0.0, 0.0, 0.0)], [q])


def test_moving_box_is_carved_away_by_freespace():
    sample = moving_box_sample()
    t = truth(sample, [WALL])[0]
    ghost = np.abs(RaycastVoxel().forecast(sample).depths[0] - t) > 3.0
    assert ghost.mean() > 0.3  # without carving, the car's past positions stop the rays
    for renderer in ("voxel", "zbuffer"):
        d = RaycastFreespace(RaycastFreespace.Options(renderer=renderer)).forecast(sample).depths[0]
        assert np.mean(np.abs(d - t) < 0.3) > 0.95, renderer


def test_freespace_keeps_a_static_wall_and_floor():
    floor = ((-30.0, -30.0, -1.9), (30.0, 30.0, -1.7))
    past_origins = [(-4.0 + k, 0.0, 0.0) for k in range(5)]
    past = [scan(o, fan((-50, 50, 0.2), (-24, 4, 0.4)), [WALL, floor]) for o in past_origins]
    q = fan((-30, 30, 1.1), (-20, 3, 0.9))
    sample = make_sample(past, past_origins, [(1.0, 0.0, 0.0)], [q])
    t = truth(sample, [WALL, floor])[0]
    for cls in (RaycastVoxel, RaycastFreespace):
        d = cls().forecast(sample).depths[0]
        assert np.quantile(np.abs(d - t), 0.9) < 0.3, cls.name


# ---------------------------------------------------------------- 4D-Occ against brute force


def test_4docc_matches_brute_force_on_random_data():
    rng = np.random.default_rng(3)
    past = [rng.uniform(-30, 30, size=(400, 3)).astype(np.float32) for _ in range(4)]
    past_origins = [(0.0, 0.0, 0.0)] * 4
    origins = [rng.uniform(-3, 3, 3) for _ in range(3)]
    dirs = []
    for _ in origins:
        d = rng.normal(size=(500, 3))
        dirs.append((d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32))
    sample = make_sample(past, past_origins, origins, dirs)
    forecast = RaycastFourDOcc().forecast(sample)
    pts = np.concatenate(past).astype(np.float64)
    for o, d, got, gp in zip(origins, dirs, forecast.depths, forecast.points_ref):
        rel = pts - o
        a = np.stack([np.arctan2(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 2], rel[:, 1])], 1)
        dd = d.astype(np.float64)
        b = np.stack([np.arctan2(dd[:, 0], dd[:, 1]), np.arctan2(dd[:, 2], dd[:, 1])], 1)
        nearest = ((b[:, None, :] - a[None]) ** 2).sum(-1).argmin(1)
        expect = np.linalg.norm(rel[nearest], axis=1)
        np.testing.assert_allclose(got, expect, rtol=1e-6)
        np.testing.assert_allclose(gp, o + dd * expect[:, None], atol=1e-4)


@pytest.mark.parametrize("n_views", [3, 5])
def test_4docc_views_shared_over_threads_match_one_thread(n_views):
    """With more views than share out evenly, the leftover view's queries go to all threads in
    pieces (``render_4docc_views``): the same depths as one thread taking every view whole."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread: nothing is shared")
    rng = np.random.default_rng(8)
    cols = np.ascontiguousarray(rng.uniform(-30, 30, size=(3, 5000)))
    origins = [rng.uniform(-3, 3, 3) for _ in range(n_views)]
    dirs = [rng.normal(size=(900 + 37 * k, 3)) for k in range(n_views)]
    sample = make_sample([cols.T.astype(np.float32)], [(0.0, 0.0, 0.0)], origins,
                         [(d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32) for d in dirs])
    vws = views(sample, False)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        serial = render_4docc_views(cols, vws)
        numba.set_num_threads(2)
        shared = render_4docc_views(cols, vws)
    finally:
        numba.set_num_threads(before)
    for a, b in zip(serial, shared):
        np.testing.assert_array_equal(a, b)


def test_fast_atan2_matches_the_c_library_to_2_ulp():
    rng = np.random.default_rng(2)
    y = np.concatenate([rng.normal(size=20000) * rng.choice([1e-6, 1.0, 1e6], 20000), [0.0, -0.0, 0.0, 1.0, -1.0, 1.0]])
    x = np.concatenate([rng.normal(size=20000), [-1.0, -1.0, 1.0, 0.0, 0.0, 1.0]])
    got = atan2_array(y, x)
    ref = np.arctan2(y, x)
    assert np.all(np.abs(got - ref) <= 2 * np.spacing(np.abs(ref)) + 1e-300)
    assert np.array_equal(np.signbit(got), np.signbit(ref))  # signed zeros and +-pi
    assert got[-3] == ref[-3] == np.pi / 2 and got[-1] == ref[-1] == np.pi / 4


def test_4docc_angle_space_is_the_reference_quirk():
    # (atan2(x, y), atan2(z, y)): straight ahead along +y is (0, 0); along +x it is (pi/2, 0)
    a = angles_4docc(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 1.0]]))
    np.testing.assert_allclose(a, [[0, 0], [np.pi / 2, 0], [0, np.pi / 4]], atol=1e-12)


# ---------------------------------------------------------------- constant velocity


def test_constant_velocity_option_ignores_the_given_future_poses():
    sample = wall_sample(future_origins=((1.0, 0.0, 0.0),))
    # the past sensors moved +1 m per 0.1 s along x: extrapolation puts the t=+0.1 s origin at x = 1
    moved = Sample(**{**sample.__dict__, "future_T_ref_sensor": np.stack([yaw_transform(0.3, (5.0, 4.0, 0.0))]),
                      "queries": (RayQuery(np.array([5.0, 4.0, 0.0]), sample.queries[0].directions_ref),)})
    for cls in ALL:
        a = cls(cls.Options(constant_velocity=True)).forecast(sample).points_ref[0]
        b = cls(cls.Options(constant_velocity=True)).forecast(moved).points_ref[0]
        np.testing.assert_array_equal(a, b)
        exact = cls().forecast(sample).points_ref[0]
        np.testing.assert_allclose(a, exact, atol=1e-3)


def test_slab_field_matches_brute_force():
    rng = np.random.default_rng(3)
    box = Box((0.0, 0.0, 0.0), (6.4, 9.6, 3.2))
    grid = VoxelGrid(rng.uniform(box.lo, box.hi, size=(40, 3)), voxel=0.2, box=box, levels=2)
    nx, ny, nz = (int(v) for v in grid.dims[1])
    occ = np.zeros((nx, ny, nz), bool)
    a, b, c = (grid.ukeys // (grid.dims[0, 1] * grid.dims[0, 2])), (grid.ukeys // grid.dims[0, 2]) % grid.dims[0, 1], grid.ukeys % grid.dims[0, 2]
    occ[a >> 1, b >> 1, c >> 1] = True
    want = np.full((nx, ny, nz), 255)
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    for i, j, k in zip(*np.nonzero(occ)):
        want[:, :, k] = np.minimum(want[:, :, k], np.maximum(np.abs(ii - i), np.abs(jj - j)))
    assert np.array_equal(grid.field.reshape(nx, ny, nz), want)


@pytest.mark.parametrize("cone", [0.0, 0.007, 0.03])
def test_slab_field_jumps_change_no_depth(cone):
    """Casting with the empty-box jumps meets the same voxels as the plain pyramid traversal
    (the jumps disabled by all-zero fields), on random clutter over a ground plane: the same
    rays hit, at the same depths up to the 10 um the traversal steps past each cell face (a
    grazing hit answers its entry point, which such a step can move where faces nearly meet)."""
    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(-70, 70, 60_000), rng.uniform(-70, 70, 60_000), rng.normal(-1.73, 0.02, 60_000)])
    posts = rng.uniform([-60, -60, -4], [60, 60, 4], size=(400, 3))
    grid = VoxelGrid(np.concatenate([ground, posts]))
    origin = np.array([3.0, 0.4, 0.1])
    dirs = fan((-180, 179.9, 0.7), (-25, 5, 0.45))
    with_jumps = grid.cast(origin, dirs, cone=cone, max_level=3)
    field, ftop = grid.field, grid.ftop
    grid.field, grid.ftop = np.zeros_like(field), np.zeros_like(ftop)
    try:
        plain = grid.cast(origin, dirs, cone=cone, max_level=3)
    finally:
        grid.field, grid.ftop = field, ftop
    assert (field >= 2).mean() > 0.3 and (ftop >= 2).mean() > 0.2  # the jumps do happen
    np.testing.assert_array_equal(np.isnan(with_jumps), np.isnan(plain))
    hit = ~np.isnan(plain)
    assert hit.mean() > 0.4
    assert np.abs(with_jumps[hit] - plain[hit]).max() < 1e-5
    assert np.mean(with_jumps[hit] != plain[hit]) < 0.005


@pytest.mark.parametrize("cone", [0.007, 0.03])
def test_cone_levels_from_range_thresholds_match_the_distance(cone):
    """With the cone centred on the ray's origin the caster picks the cone's level by comparing
    the range with precomputed thresholds; a centre one ulp away takes the distance at every
    step instead. Both must give the same depths, including rays from an origin on voxel faces
    (whose cells the division decides)."""
    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(-70, 70, 40_000), rng.uniform(-70, 70, 40_000), rng.normal(-1.73, 0.02, 40_000)])
    posts = rng.uniform([-60, -60, -4], [60, 60, 4], size=(400, 3))
    grid = VoxelGrid(np.concatenate([ground, posts]))
    dirs = fan((-180, 179.9, 0.9), (-25, 5, 0.6))
    for origin in (np.array([3.0, 0.4, 0.1]), np.array([0.2, -0.4, 0.0])):
        by_range = grid.cast(origin, dirs, cone=cone, max_level=3)
        by_distance = grid.cast(origin, dirs, cone=cone, max_level=3, cone_center=np.nextafter(origin, np.inf))
        assert np.isfinite(by_range).mean() > 0.4
        np.testing.assert_array_equal(by_range, by_distance)


# ---------------------------------------------------------------- surfaces and the ground-aligned grid


def test_sym3_smallest_matches_numpy_eigh():
    rng = np.random.default_rng(11)
    for i in range(500):
        a = rng.normal(size=(3, 3))
        a = a @ a.T * rng.uniform(1e-4, 10.0)
        if i % 4 == 0:  # flat point sets: one tiny eigenvalue, as for a patch of ground
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            a = q @ np.diag([rng.uniform(0, 1e-6), rng.uniform(0.01, 0.1), rng.uniform(0.1, 1.0)]) @ q.T
        w, v = np.linalg.eigh(a)
        l0, l1, *n = sym3_smallest(a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2])
        n = np.array(n)
        assert l0 == pytest.approx(w[0], abs=1e-12 * w[2])
        assert l1 == pytest.approx(w[1], abs=1e-12 * w[2])
        assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
        assert np.linalg.norm(a @ n - l0 * n) < 1e-10 * w[2]
    # a multiple of the identity: any unit vector
    l0, l1, *n = sym3_smallest(2.0, 0.0, 0.0, 2.0, 0.0, 2.0)
    assert (l0, l1) == (2.0, 2.0) and np.linalg.norm(n) == pytest.approx(1.0)


def test_anchored_lo_puts_a_face_of_every_level_on_the_anchor():
    assert anchored_lo(-4.5, -1.63, 3.2) == pytest.approx(-4.83)
    assert anchored_lo(-4.5, -4.6, 3.2) == pytest.approx(-4.6)  # anchor below the box: the grid starts there
    assert anchored_lo(-4.5, -4.5, 3.2) == pytest.approx(-4.5)
    assert anchored_lo(-4.5, 9.0, 3.2) == pytest.approx(9.0 - 5 * 3.2)
    grid = VoxelGrid(np.array([[1.0, 1.0, -1.7]]), anchor_z=-1.63)
    assert grid.lo[2] == pytest.approx(-4.83) and grid.lo[2] <= ROI.lo[2]
    assert grid.lo[2] + grid.dims[0, 2] * grid.voxel >= ROI.hi[2]  # it still covers the ROI
    top = grid.voxel * 2 ** (len(grid.dims) - 1)
    assert ((-1.63 - grid.lo[2]) / top) == pytest.approx(1.0)


def test_ground_height_is_the_ground_under_clutter():
    rng = np.random.default_rng(2)
    ground = np.column_stack([rng.uniform(-25, 25, (20_000, 2)), rng.normal(-1.73, 0.02, 20_000)])
    clutter = rng.uniform([-25, -25, -1.5], [25, 25, 4.0], size=(8_000, 3))  # walls, posts, cars
    below = rng.uniform([-25, -25, -4.5], [25, 25, -2.5], size=(500, 3))
    far = np.column_stack([rng.uniform(30, 60, (5_000, 2)), np.full(5_000, 0.5)])  # a flat roof out of reach
    assert ground_height(np.concatenate([ground, clutter, below, far])) == pytest.approx(-1.73, abs=0.005)
    assert ground_height(far) is None


def ground_plane_grid(height: float, anchor: float | None, slope: float = 0.0, n: int = 200_000, noise: float = 0.01):
    """A grid of noisy ground points ``z = height + slope * x`` around the origin."""
    rng = np.random.default_rng(9)
    xy = rng.uniform(-40, 40, (n, 2))
    z = height + slope * xy[:, 0] + rng.normal(0, noise, n)
    return VoxelGrid(np.column_stack([xy, z]), anchor_z=anchor)


@pytest.mark.parametrize("anchor", [None, -1.63])
@pytest.mark.parametrize("slope", [0.0, 0.03])
def test_grazing_rays_end_on_the_ground_surface(anchor, slope):
    """Rays down onto a noisy ground plane (1 cm noise; the hand-computed crossing as the
    truth): on the voxels' fitted surfaces the error is millimetres in height whatever the
    grid's phase (the ground across a face, or half a voxel below one); the projection of the
    hit voxel's mean (``surface=False``) is several times worse, most of all when the ray
    enters the ground's voxel well above the ground."""
    grid = ground_plane_grid(-1.73, anchor, slope)
    o = np.array([0.0, 0.0, 0.0])
    dirs = fan((-60, 60, 2.0), (-14, -3, 0.5))
    t = -1.73 / (dirs[:, 2] - slope * dirs[:, 0])  # the crossing of o + t d with z = -1.73 + slope * x
    inside = (t > 0) & (np.abs(dirs[:, :2] * t[:, None]) < 38).all(axis=1)  # where the ground has points
    assert inside.sum() > 1000
    dirs, t = dirs[inside], t[inside]
    on_surface = grid.cast(o, dirs, surface=True)
    by_mean = grid.cast(o, dirs, surface=False)
    hit = np.isfinite(on_surface)
    assert hit.mean() > 0.99  # a few thin rays slip through voxels the random points left empty
    dirs, t, on_surface, by_mean = dirs[hit], t[hit], on_surface[hit], by_mean[hit]
    # along a grazing ray a height error h is h / sin(elevation) long: compare heights too
    drop = np.abs(dirs[:, 2] - slope * dirs[:, 0])
    assert np.median(np.abs(on_surface - t) * drop) < 0.01
    assert np.quantile(np.abs(on_surface - t) * drop, 0.95) < 0.03
    assert np.median(np.abs(on_surface - t)) < 0.06
    assert np.median(np.abs(by_mean - t)) > 3 * np.median(np.abs(on_surface - t))
    if anchor is not None:
        assert np.median(np.abs(by_mean - t) * drop) > 0.05


def test_surface_depth_cases():
    """One flat patch's surface, hand-computed: a crossing inside the hit voxel, one behind its
    entry, one beyond its exit (within and beyond ``FOLLOW_RANGE``), and a voxel without a
    surface."""
    box = Box((0.0, 0.0, 0.0), (3.2, 3.2, 3.2))
    rng = np.random.default_rng(4)
    # a flat patch at z = 1.05 filling the voxels of layer z in [1.0, 1.2) over x in [1.0, 3.2)
    patch = np.column_stack([rng.uniform(1.0, 3.2, 4000), rng.uniform(0.0, 3.2, 4000), np.full(4000, 1.05)])
    grid = VoxelGrid(patch, voxel=0.2, box=box, levels=2)

    def cast(origin, direction, surface=True):
        return grid.cast(np.asarray(origin, float), np.asarray([direction], float), surface=surface)[0]

    # straight down from above: the crossing, inside the voxel
    assert cast([1.1, 1.1, 3.0], [0.0, 0.0, -1.0]) == pytest.approx(3.0 - 1.05, abs=1e-9)
    # into the patch's side face at x = 1.0, above the surface and rising: the crossing lies
    # behind, the depth is the entry (plus the traversal's 10 um step past the face)
    a = np.deg2rad(2.0)
    d = cast([0.001, 1.1, 1.1], [np.cos(a), 0.0, np.sin(a)])
    assert d == pytest.approx(0.999 / np.cos(a), abs=2e-5)
    # a grazing ray down through the top face at x = 1.3: it meets the surface 0.15 / sin(a)
    # further on, beyond the voxel's exit (the voxel is 0.2 m wide)
    a = np.deg2rad(5.0)
    ray = np.array([np.cos(a), 0.0, -np.sin(a)])
    start = np.array([1.3, 1.1, 1.2]) - ray * (1.299 / np.cos(a))
    entry = 1.299 / np.cos(a)
    assert cast(start, ray) == pytest.approx(entry + 0.15 / np.sin(a), abs=1e-9)
    assert 0.15 / np.sin(a) > 1.0
    # at 1 degree the surface is 8.6 m on: farther than FOLLOW_RANGE, the mean's projection instead
    a = np.deg2rad(1.0)
    ray = np.array([np.cos(a), 0.0, -np.sin(a)])
    start = np.array([1.3, 1.1, 1.2]) - ray * (1.299 / np.cos(a))
    entry = 1.299 / np.cos(a)
    assert 0.15 / np.sin(a) > FOLLOW_RANGE
    d = cast(start, ray)
    assert d == cast(start, ray, surface=False)
    assert entry <= d <= entry + 0.2 / np.cos(a) + 1e-9
    # a lone point: no surface, the mean's projection
    lone = VoxelGrid(np.array([[1.1, 1.13, 1.1]]), voxel=0.2, box=box, levels=2)
    d = lone.cast(np.array([0.05, 1.1, 1.1]), np.array([[1.0, 0.0, 0.0]]), surface=True)[0]
    assert d == pytest.approx(1.05, abs=1e-9)


def test_voxels_without_a_surface_take_their_coarser_cells_normal():
    """Sparse points on a tilted plane, one or two per voxel (too few for a surface of their
    own): the coarser cells gather enough, so every voxel gets the plane's normal, with the
    offset through its own mean."""
    rng = np.random.default_rng(6)
    box = Box((0.0, 0.0, 0.0), (3.2, 3.2, 3.2))
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    xy = rng.uniform(0.2, 3.0, (60, 2))
    z = 1.6 - (n[0] * (xy[:, 0] - 1.6) + n[1] * (xy[:, 1] - 1.6)) / n[2]
    grid = VoxelGrid(np.column_stack([xy, z]), voxel=0.2, box=box, levels=3)
    sparse = grid.hits < 3
    assert sparse.mean() > 0.9
    has = np.abs(grid.planes[:, :3]).sum(axis=1) > 0
    assert has[sparse].mean() > 0.9  # (cells cut by the plane at a corner may hold too few points)
    sign = np.sign(grid.planes[has, 2])[:, None]
    np.testing.assert_allclose(grid.planes[has, :3] * sign, np.broadcast_to(n, (has.sum(), 3)), atol=1e-9)
    np.testing.assert_allclose(grid.planes[has, 3] * sign[:, 0], grid.means[has] @ n, atol=1e-9)
    # one lone point has no flat neighbourhood at any level: no surface
    lone = VoxelGrid(np.array([[1.1, 1.13, 1.1]]), voxel=0.2, box=box, levels=3)
    assert (lone.planes == 0).all()


def test_freespace_carving_refits_the_surfaces_of_what_is_kept():
    """After carving, the surfaces are those of the surviving voxels alone: the same as a grid
    built at the same phase from only the points carving kept."""
    sample = moving_box_sample()
    opts = RaycastFreespace.Options()
    agg = aggregate(sample)
    whole = build_grid(agg.points, opts)
    ukeys, occ = whole.ukeys.copy(), whole.occ.copy()
    grid, keep = carve(whole, agg.origins, agg.points, agg.own_range, opts)
    assert len(grid.ukeys) < len(whole.ukeys) - 50  # the car's past positions are carved away
    # the grid carved is left as it was (raycast-voxel may share it)
    np.testing.assert_array_equal(whole.ukeys, ukeys)
    np.testing.assert_array_equal(whole.occ, occ)
    kept = VoxelGrid(agg.points[keep], anchor_z=float(grid.lo[2]))
    assert kept.lo[2] == grid.lo[2]
    np.testing.assert_array_equal(kept.ukeys, grid.ukeys)
    assert (np.abs(grid.planes[:, :3]).sum(axis=1) > 0).mean() > 0.5
    np.testing.assert_allclose(grid.planes, kept.planes, rtol=0, atol=1e-9)
