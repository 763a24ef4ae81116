"""The simulated LiDAR matches its configured sensor: points, beams, elevations, ranges, drop."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pcfbench.datasets.synthetic.domains import get_domain
from pcfbench.datasets.synthetic.generate import simulate_sequence
from pcfbench.datasets.synthetic.lidar import EGO_SHAPE, StaticScene, cast_sweep, ego_hits
from pcfbench.datasets.synthetic.sensor import HDL32, HDL64
from pcfbench.datasets.synthetic.world import EGO, GROUND, STRUCTURE, MeshSoup, box


@pytest.fixture(scope="module", params=["synthetic-town", "synthetic-suburb"])
def sweeps(request):
    dom = get_domain(request.param)
    dom = dataclasses.replace(dom, splits={"test": (("05", 2),)})
    return dom, simulate_sequence(dom, "05")


def elevations_deg(points: np.ndarray) -> np.ndarray:
    return np.rad2deg(np.arcsin(points[:, 2] / np.linalg.norm(points, axis=1)))


def test_points_per_sweep_match_the_sensor(sweeps):
    dom, seq = sweeps
    n = [len(p) for p in seq.points]
    rays = dom.sensor.num_rays
    # Open sky and space beyond the max range return nothing. KITTI's HDL-64E (beams up to +2 deg,
    # in a town) returns ~90 % of its rays; the suburb's +10 deg beams see open sky more often.
    lo, hi = {"synthetic-town": (0.75, 0.95), "synthetic-suburb": (0.6, 0.9)}[dom.name]
    assert all(lo * rays < k < hi * rays for k in n), (n, rays)
    expected = {"synthetic-town": (24_000, 32_000), "synthetic-suburb": (22_000, 31_000)}[dom.name]
    assert all(expected[0] < k < expected[1] for k in n), n


def test_every_beam_present_at_its_table_elevation(sweeps):
    dom, seq = sweeps
    table = np.asarray(dom.sensor.elevations_deg)
    el = elevations_deg(seq.points[0].astype(np.float64))
    nearest = np.abs(el[:, None] - table[None, :])
    beam = np.argmin(nearest, axis=1)
    assert np.max(np.min(nearest, axis=1)) < 0.01  # range noise is along the ray: elevation exact
    assert len(np.unique(beam)) == dom.sensor.beams == {"synthetic-town": 64, "synthetic-suburb": 32}[dom.name]
    spread = el.max() - el.min()
    assert spread == pytest.approx(table.max() - table.min(), abs=0.05)
    span = {"synthetic-town": 26.8, "synthetic-suburb": 41.34}[dom.name]
    assert table.max() - table.min() == pytest.approx(span, abs=0.01)
    az = np.arctan2(seq.points[0][:, 1], seq.points[0][:, 0])
    columns = np.unique(np.round((az + np.pi) / (2 * np.pi) * dom.sensor.azimuth_steps).astype(int) % dom.sensor.azimuth_steps)
    assert len(columns) > 0.95 * dom.sensor.azimuth_steps


def test_range_distribution(sweeps):
    dom, seq = sweeps
    r = np.linalg.norm(seq.points[0], axis=1)
    s = dom.sensor
    assert r.min() > s.min_range_m - 5 * s.range_noise_m
    assert r.max() < s.max_range_m + 5 * s.range_noise_m
    lab = seq.labels[0] & 0xFFFF
    # Most returns are near (ground rings), a real tail reaches far structure.
    assert 4.0 < np.median(r) < 25.0
    assert np.mean(r > 30.0) > 0.02
    # ground rings: the lowest beam hits the ground near mount_height / tan(elevation)
    ground = (lab == GROUND) & (np.abs(elevations_deg(seq.points[0]) - min(s.elevations_deg)) < 0.01)
    expected = s.mount_height_m / np.tan(np.deg2rad(-min(s.elevations_deg)))
    assert np.median(np.hypot(*seq.points[0][ground, :2].T)) == pytest.approx(expected, rel=0.35)


def test_drop_rate_in_sequence_stats(sweeps):
    dom, seq = sweeps
    assert dom.sensor.drop_base < seq.stats["drop_rate"] < 0.3


def _wall_scene(distance: float) -> StaticScene:
    soup = MeshSoup()
    soup.add(STRUCTURE, *box(distance + 0.5, 0.0, -50.0, 1.0, 400.0, 100.0, 0.0))
    return StaticScene(soup)


class _Flat:
    def undulation(self, x, y):
        return np.zeros_like(np.asarray(x, dtype=float))


@pytest.mark.parametrize("distance", [15.0, 90.0])
def test_ray_drop_and_range_noise_on_a_known_wall(distance):
    """A wall facing the sensor: drop rate and range noise match the configured model."""
    sensor = HDL64
    scene = _wall_scene(distance)
    rng = np.random.default_rng(0)
    T = np.eye(4)
    res = cast_sweep(sensor, scene, [], _Flat(), 0.0, T, rng)
    wall = res.labels == STRUCTURE
    pts = res.points[wall].astype(np.float64)
    d = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    true_range = distance / d[:, 0]
    noise = np.linalg.norm(pts, axis=1) - true_range
    assert np.std(noise) == pytest.approx(sensor.range_noise_m, rel=0.05)
    assert abs(np.mean(noise)) < 0.002
    # expected drop rate over the rays that hit the wall (all front-facing rays within max range)
    dirs = sensor.directions().astype(np.float64)
    front = dirs[:, 0] > 0
    t = distance / dirs[front, 0]
    inside = (t <= sensor.max_range_m) & (t >= sensor.min_range_m) & (np.abs(dirs[front, 1] * t) < 199) & \
        (np.abs(dirs[front, 2] * t) < 49)
    t_ego, _ = ego_hits(sensor)
    inside &= ~np.isfinite(t_ego[front])
    p = sensor.drop_probability(t[inside], dirs[front][inside, 0])
    expected = p.mean()
    hits = inside.sum()
    measured = 1.0 - wall.sum() / hits
    assert res.rays_hit - np.sum(res.labels == EGO) >= hits - 5
    assert measured == pytest.approx(expected, abs=4 * np.sqrt(expected * (1 - expected) / hits) + 1e-3)
    if distance > 50:
        assert expected > sensor.drop_base + 0.1  # far returns drop more
    else:
        assert expected < sensor.drop_base + 0.05


def test_grazing_ground_drops_more_than_head_on():
    sensor = HDL32
    soup = MeshSoup()
    soup.add(GROUND, np.array([[-300, -300, 0], [300, -300, 0], [300, 300, 0], [-300, 300, 0]], float),
             np.array([[0, 1, 2], [0, 2, 3]]))
    T = np.eye(4)
    T[2, 3] = sensor.mount_height_m
    res = cast_sweep(sensor, StaticScene(soup), [], _Flat(), 0.0, T, np.random.default_rng(1))
    ground = res.labels == GROUND
    r = np.hypot(*res.points[ground, :2].T)
    beams = res.beam[ground]
    near = beams == sensor.beams - 1  # steepest beam
    far = beams == np.min(beams)  # shallowest beam that still hits the ground within range
    t_ego, _ = ego_hits(sensor)
    clear = np.isfinite(t_ego).reshape(sensor.beams, sensor.azimuth_steps) == 0  # rays that miss the ego body
    per_beam = np.bincount(beams, minlength=sensor.beams) / np.maximum(clear.sum(axis=1), 1)
    assert per_beam[sensor.beams - 1] > 0.9
    assert per_beam[np.min(beams)] < per_beam[sensor.beams - 1] - 0.1
    assert r[near].mean() < r[far].mean()
    # the ego body is seen by the steep beams only within its footprint
    assert np.all(res.points[res.labels == EGO, 0] > EGO_SHAPE.x_min - 0.1)
