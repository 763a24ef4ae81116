"""World physics 10 ("realism"): a sensor and surfaces closer to real LiDAR.

Physics 1 (every domain's default) casts clean rays at ideal surfaces. ``REALISM``, the
knobs below, is physics 10, the world of ``synthetic-town-realistic``; each knob is physics or
statistics of the world and the sensor, none of it tied to a scene:

* **the sensor**: 2048 columns a revolution (HDL-64E at 10 Hz); each beam's true elevation off
  its nominal one by the sensor's intrinsic error plus a fixed offset per beam, each shot by a
  random jitter, the point reported along the nominal direction as a real sensor does; range
  noise as a per-beam bias plus Gaussian noise; returns that fade with range, reflectance and
  incidence (detection probability ``1 / (1 + (r / r50)^6)``), car bodies with a specular
  drop; mixed pixels at depth discontinuities at the real rate; optionally a spinning sensor
  (``motion_distortion``, off: KITTI's odometry scans come de-skewed); the ego roof hiding the
  steepest beams' returns;
* **the surfaces**: every static surface displaced along its normal by smooth value noise of
  world position, amplitude and wavelength by class; vegetation a volume a ray returns from
  inside (an exponential depth, new every sweep); solid tree trunks (class TRUNK);
* **the poses**: the stored poses are estimates, the true ones off by a random walk and
  drifting upwards from the scans, as KITTI's do against its sweeps;
* **the town**: 2 m sidewalks with hedged yards, trees in the yards behind the buildings,
  street furniture kept off the carriageways, and the moving traffic SemanticKITTI's labelled
  sequences have.

What each version changed and why: ``datasets/synthetic/CHANGELOG.md``; how the world compares
with real sweeps and how to measure it: docs/realism.md.

Generation stays deterministic: the noise fields are functions of position, the random
draws come from the sequence's sensor generator.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numba as nb
import numpy as np

from pcfbench.datasets.synthetic.lidar import EGO_SHAPE, ALBEDO, SweepResult, _tensor_mesh, ego_hits, open3d
from pcfbench.datasets.synthetic.sensor import LidarConfig
from pcfbench.datasets.synthetic.world import (
    EGO, GROUND, PARKED, POLE, STRUCTURE, TRUNK, VEGETATION, VEHICLE, Agent, _place, merge,
)


@dataclass(frozen=True)
class Realism:
    """The knobs of physics version 2 and later (one set for every scene of a domain)."""

    #: the sensor's intrinsic elevation error, every beam alike: KITTI's HDL-64E scans need a
    #: 0.22 deg correction of their vertical angles (Deschaud, IMLS-SLAM, ICRA 2018)
    elevation_error_deg: float = 0.22
    beam_bias_deg: float = 0.06  # 1-sigma fixed elevation error per beam, on top
    jitter_deg: float = 0.03  # 1-sigma per-shot elevation and azimuth jitter
    range_bias_m: float = 0.02  # 1-sigma fixed range offset per beam
    range_noise_m: float = 0.015  # 1-sigma per-shot range noise (HDL-64E: < 2 cm)
    #: (class, amplitude m, wavelength m) of the surface displacement, two octaves; the
    #: ground's is the carriageway's (asphalt), ``verge_roughness`` the ground's off the road
    roughness: tuple = ((GROUND, 0.015, 0.4), (STRUCTURE, 0.02, 0.5), (POLE, 0.005, 0.3),
                        (VEGETATION, 0.10, 0.4), (PARKED, 0.01, 0.5), (TRUNK, 0.015, 0.2))
    verge_roughness: tuple = (0.06, 0.3)  # grass, soil and planted strips beyond the sidewalk
    #: shrubs: hedges along the yards and bushes, (hedges per 100 m of frontage, bushes per 100 m).
    #: Physics 6: 12 hedges (3-12 m long) per 100 m, from 4, and ``sidewalk_m`` below: hedges
    #: line most yards at the back of the sidewalk, as the realism report's label-free near-road
    #: statistics say the real street's do (CHANGELOG.md, physics 6)
    shrubs_per_100m: tuple = (12.0, 6.0)
    #: trees in the yards behind the buildings per 100 m of frontage, 12-28 m beyond the
    #: sidewalk, a crown's width off every road (physics 10: 20, from none; the blocks'
    #: interiors were bare, and the far facades seen through every gap closed a second later
    #: 3.3x as often as on the real drive: CHANGELOG.md, physics 10). Drawn without regard
    #: to the buildings: 40 % stand inside one (most hidden, 2 % with a crown through the roof)
    yard_trees_per_100m: float = 20.0
    #: the sidewalk's width (m; None: the town style's 3.5 m), which sets where the yards, their
    #: hedges and fences and the buildings begin: at 2.0 m the first yard edge stands 6 m from
    #: a sensor in the right lane, where the real drive's near surfaces are (physics 6)
    sidewalk_m: float | None = 2.0
    #: mean depth (m) a return comes from inside a tree crown, hedge or bush (an exponential
    #: draw, new every sweep). Physics 8: 0.1, from 0.35, where the realism report's roughness
    #: p90 is 1.05x the real drive's, from 1.24x (CHANGELOG.md, physics 8)
    crown_depth_m: float = 0.1
    mixed_gap_m: float = 0.5
    #: the share of such rays that return from in between. Physics 7: 0.04, from 0.35, where
    #: the realism report's mixed-pixel statistic (depth jumps along a beam with a return in
    #: between) is 1.17x the real drive's, from 1.57x: the floating in-between returns were
    #: what the voxel caster stopped on and carving cleared (CHANGELOG.md, physics 7)
    mixed_prob: float = 0.04
    r50_m: float = 110.0  # range at which a white, head-on target is detected half the time
    specular_drop: float = 0.12  # extra drop on car bodies
    base_drop: float = 0.02
    revolution_s: float = 0.1
    #: store each column as fired from its own pose (True), or de-skewed into the sweep's
    #: frame (False): KITTI's odometry scans come de-skewed, so the town's sensor does too
    motion_distortion: bool = False
    #: localisation error of the stored poses (estimates, as SLAM poses are): a random walk
    #: per sweep, 1-sigma steps in translation (m, per axis) and rotation (deg, per axis)
    pose_walk: tuple = (0.004, 0.01)
    #: ... and drift apart from the scans upwards at this rate (m/s, world z): registered by
    #: its poses, the ground a real KITTI sweep sees stands 2.0 cm above where the sweep 1 s
    #: earlier saw it from the same range (the realism report's ground drift; 0.4 cm without
    #: a drift), steadily over the drive whatever the speed. It sets the baselines' l1_median
    #: ranking: the forecast ground lies lower than the true one, by 4-8 cm of depth on the
    #: ground 5-10 m away, which the z-buffer's nearer-first splatting absorbs and the fitted
    #: surfaces do not (physics 5)
    pose_drift_m_s: float = 0.016
    #: moving vehicles, cyclists and pedestrians per km, as a share of the town style's.
    #: Physics 9: 0.085, for 0.24 % of the points on moving objects, the moving classes' share
    #: of SemanticKITTI's labelled sequences (the class content its API publishes); 0.4 of the
    #: traffic put 1.12 % of the seven towns' points on moving objects. Physics 5-8 had 0.4, set
    #: by the free-space violations, which on the real drive are mostly still surfaces seen
    #: through, not traffic (CHANGELOG.md, physics 9)
    traffic_share: float = 0.085
    #: poles and tree trunks stand at least this far outside every carriageway (m): placed
    #: along one road, some stood in a crossing road near its junction, and a drive passed a
    #: trunk 0.9 m from the sensor (physics 3)
    clearance_m: float = 0.3
    #: tree trunks are solid wood (class TRUNK: bark roughness, no return from inside) instead
    #: of VEGETATION, whose returns come from inside the volume as a crown's do (physics 4)
    solid_trunks: bool = True
    #: the ego vehicle's roof under the sensor (m below it; None: physics 1's 0.45 m). At 0.35
    #: m it hides the steepest beams' returns as KITTI's roof-rack mount does: the realism
    #: report's ray drop per beam (real: 98 % of the columns of the -25 deg beam, falling to
    #: 30 % at -22 deg; 0.45 m left 30 % and 25 %) (physics 4)
    roof_below_sensor_m: float | None = 0.35
    #: the physics version these knobs make (written in the manifest, part of the cache name)
    version: int = 10

    @property
    def ego_shape(self):
        """The ego vehicle the sensor sees (physics 1's, with this roof height if one is set)."""
        if self.roof_below_sensor_m is None:
            return EGO_SHAPE
        return replace(EGO_SHAPE, roof_below_sensor=self.roof_below_sensor_m)


REALISM = Realism()


# --- smooth value noise of position --------------------------------------------------------------

@nb.njit(cache=True, nogil=True, inline="always")
def _lattice(ix, iy, iz, salt):
    """A deterministic value in [-1, 1] for the integer lattice point (ix, iy, iz) (a hash of
    int64s that wrap on overflow, no random state)."""
    h = (ix * np.int64(73856093)) ^ (iy * np.int64(19349663)) ^ (iz * np.int64(83492791)) ^ salt
    h = (h ^ (h >> 13)) * np.int64(1274126177)
    h = h ^ (h >> 16)
    return (h & 0xFFFF) / 32767.5 - 1.0


@nb.njit(cache=True, nogil=True)
def _value_noise_kernel(p, wavelength, salt):
    """``value_noise`` one point at a time: the same float64 operations in the same order as the
    array form it replaced (tests/synthetic/test_synthetic_realism.py keeps that form as the reference
    and checks bit equality), without its eight corners' temporaries (12x faster on 110k points)."""
    out = np.zeros(p.shape[0])
    for n in range(p.shape[0]):
        qx, qy, qz = p[n, 0] / wavelength, p[n, 1] / wavelength, p[n, 2] / wavelength
        ix, iy, iz = np.int64(np.floor(qx)), np.int64(np.floor(qy)), np.int64(np.floor(qz))
        fx, fy, fz = qx - ix, qy - iy, qz - iz
        fx = fx * fx * (3 - 2 * fx)  # smooth step
        fy = fy * fy * (3 - 2 * fy)
        fz = fz * fz * (3 - 2 * fz)
        acc = 0.0
        for dx in range(2):
            wx = fx if dx else 1 - fx
            for dy in range(2):
                wy = fy if dy else 1 - fy
                for dz in range(2):
                    wz = fz if dz else 1 - fz
                    acc += wx * wy * wz * _lattice(ix + dx, iy + dy, iz + dz, salt)
        out[n] = acc
    return out


def value_noise(p: np.ndarray, wavelength: float, salt: int = 0) -> np.ndarray:
    """Trilinearly interpolated lattice noise at points ``p`` (N, 3), about in [-1, 1]: the
    ``_lattice`` values at the 8 corners of each point's lattice cell, weighted by the smooth
    step of its position in the cell."""
    q = np.ascontiguousarray(np.asarray(p, np.float64).reshape(-1, 3))
    return _value_noise_kernel(q, float(wavelength), np.int64(salt))


def _octaves(p: np.ndarray, lam: float, salt: int) -> np.ndarray:
    return 0.7 * value_noise(p, lam, salt=salt) + 0.3 * value_noise(p, lam / 3.7, salt=salt + 1)


def surface_displacement(points: np.ndarray, cls: np.ndarray, realism: Realism, ground=None) -> np.ndarray:
    """Displacement (m) along the surface normal at world ``points`` of class ``cls``: two
    octaves of value noise, amplitude and wavelength by class, zero for other classes. With
    ``ground`` (a :class:`~pcfbench.datasets.synthetic.world.Ground`), ground beyond the
    sidewalk takes ``verge_roughness``."""
    out = np.zeros(len(points))
    for c, amp, lam in realism.roughness:
        m = cls == c
        if m.any():
            out[m] = amp * _octaves(points[m], lam, 17 * c + 1)
    g = np.nonzero(cls == GROUND)[0]
    if ground is not None and len(g):
        verge = ground.farther_than(points[g, 0], points[g, 1], ground.half_road + ground.style.sidewalk_m)
        if verge.any():
            amp, lam = realism.verge_roughness
            out[g[verge]] = amp * _octaves(points[g[verge]], lam, 5)
    return out


def add_shrubs(soup, style, graph, ground, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray,
               realism: Realism) -> None:
    """Hedges (long low boxes) and bushes (ellipsoids) in the yards beyond the sidewalks, as
    vegetation: rays into them return from inside (``cast_sweep_realistic``); then the yard
    trees (``add_yard_trees``), whose draws come after all of theirs."""
    from pcfbench.datasets.synthetic.world import box, ellipsoid, road_sides

    edge_band = ground.half_road + style.sidewalk_m
    hedges, bushes = realism.shrubs_per_100m
    for _, line, tangent, normal, total in road_sides(graph, lo, hi):
        for _ in range(int(rng.poisson(hedges * total / 100))):
            length = rng.uniform(3.0, 12.0)
            s = rng.uniform(6.0, max(total - 6.0 - length, 6.5))
            i = min(int((s + length / 2) / 0.5), len(line) - 1)
            depth = rng.uniform(0.6, 1.2)
            c = line[i] + normal[i] * (edge_band + 0.2 + depth / 2)
            if lo[0] <= c[0] <= hi[0] and lo[1] <= c[1] <= hi[1]:
                yaw = np.arctan2(tangent[i, 1], tangent[i, 0])
                z = float(ground.height(c[0], c[1])) - 0.1
                soup.add(VEGETATION, *box(c[0], c[1], z, length, depth, rng.uniform(0.7, 1.7), yaw))
        for _ in range(int(rng.poisson(bushes * total / 100))):
            s = rng.uniform(4.0, max(total - 4.0, 4.5))
            i = min(int(s / 0.5), len(line) - 1)
            r = rng.uniform(0.4, 1.1)
            c = line[i] + normal[i] * (edge_band + r + rng.uniform(0.0, 2.0))
            if lo[0] <= c[0] <= hi[0] and lo[1] <= c[1] <= hi[1]:
                z = float(ground.height(c[0], c[1]))
                soup.add(VEGETATION, *ellipsoid(c[0], c[1], z + r * 0.6, r, r * rng.uniform(0.8, 1.3), r * 0.8))
    add_yard_trees(soup, ground, graph, rng, lo, hi, edge_band, realism)


def add_yard_trees(soup, ground, graph, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray,
                   edge_band: float, realism: Realism) -> None:
    """``realism.yard_trees_per_100m`` trees per 100 m of every road side's frontage, 12-28 m
    beyond ``edge_band`` (the carriageway's half width and the sidewalk), in the yards behind
    the buildings: a trunk 2-4 m tall (solid as ``solid_trunks`` says) and a vegetation crown
    2-4 m across; none within a crown's width of the edge band of any road (a yard point can
    lie near a crossing road). No draws at 0 (physics 9's world)."""
    from pcfbench.datasets.synthetic.world import cylinder, ellipsoid, road_sides

    per_100m = realism.yard_trees_per_100m
    if per_100m <= 0:
        return
    trunk_class = TRUNK if realism.solid_trunks else VEGETATION
    for _, line, _, normal, total in road_sides(graph, lo, hi):
        for _ in range(int(rng.poisson(per_100m * total / 100))):
            i = min(int(rng.uniform(0.0, total) / 0.5), len(line) - 1)
            c = line[i] + normal[i] * (edge_band + rng.uniform(12.0, 28.0))
            if not (lo[0] <= c[0] <= hi[0] and lo[1] <= c[1] <= hi[1]):
                continue
            trunk, crown, radius = rng.uniform(2.0, 4.0), rng.uniform(2.0, 4.0), rng.uniform(0.15, 0.35)
            if float(ground.road_distance(np.array(c[0]), np.array(c[1]))) < edge_band + crown:
                continue
            z = float(ground.height(c[0], c[1]))
            soup.add(trunk_class, *cylinder(c[0], c[1], z, radius, trunk + crown * 0.5))
            soup.add(VEGETATION, *ellipsoid(c[0], c[1], z + trunk + crown * 0.8, crown, crown,
                                            crown * rng.uniform(0.8, 1.3)))


def beam_calibration(sensor: LidarConfig, realism: Realism, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Per beam: fixed elevation error (rad) and range offset (m) of this sensor unit."""
    rng = np.random.default_rng(seed)
    el = np.deg2rad(rng.normal(0.0, realism.beam_bias_deg, sensor.beams))
    rb = rng.normal(0.0, realism.range_bias_m, sensor.beams)
    return el, rb


def pose_errors(count: int, realism: Realism, rng: np.random.Generator) -> np.ndarray:
    """(count, 4, 4) rigid errors of the stored poses: ``T_stored = T_true @ E``, a random walk
    in translation and small rotations, starting at the identity."""
    from scipy.spatial.transform import Rotation

    st, sr = realism.pose_walk
    trans = np.cumsum(rng.normal(0.0, st, (count, 3)), axis=0)
    rot = np.cumsum(rng.normal(0.0, np.deg2rad(sr), (count, 3)), axis=0)
    trans[0] = rot[0] = 0.0
    E = np.tile(np.eye(4), (count, 1, 1))
    E[:, :3, :3] = Rotation.from_rotvec(rot).as_matrix()
    E[:, :3, 3] = trans
    return E


def stored_poses(T_true: np.ndarray, times: np.ndarray, realism: Realism, rng: np.random.Generator) -> np.ndarray:
    """(N, 4, 4) the poses a sequence stores, estimates of the true ones ``T_true`` at
    ``times`` (s): off by ``pose_errors`` and risen ``pose_drift_m_s`` per second since the first."""
    T = T_true @ pose_errors(len(T_true), realism, rng)
    T[:, 2, 3] += realism.pose_drift_m_s * (np.asarray(times, np.float64) - times[0])
    return T


def street_style(style, realism: Realism):
    """``style`` with the sidewalk ``realism`` gives it (from physics 6; all else the same)."""
    return style if realism.sidewalk_m is None else replace(style, sidewalk_m=realism.sidewalk_m)


def with_traffic(style, realism: Realism):
    """``style`` with ``traffic_share`` of its moving agents per km (all else the same)."""
    share = realism.traffic_share
    return replace(style, vehicles_per_km=round(style.vehicles_per_km * share, 6),
                   cyclists_per_km=round(style.cyclists_per_km * share, 6),
                   pedestrians_per_km=round(style.pedestrians_per_km * share, 6))


def column_times(sensor: LidarConfig, realism: Realism) -> np.ndarray:
    """Firing time (s) of each azimuth column relative to the sweep's timestamp: the sensor
    spins clockwise seen from above (as Velodyne's do), the column facing forward (azimuth 0)
    fires at the timestamp, the one facing backwards half a revolution before or after."""
    az = np.linspace(-np.pi, np.pi, sensor.azimuth_steps, endpoint=False)
    return -az / (2 * np.pi) * realism.revolution_s if realism.motion_distortion else np.zeros(sensor.azimuth_steps)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(len(at), 4, 4) poses at times ``at`` from poses at sorted ``times``: translation
    linear, rotation of the nearer pose (the ego turns < 0.1 deg between two of them)."""
    out = np.empty((len(at), 4, 4))
    for k in range(3):
        out[:, k, 3] = np.interp(at, times, poses[:, k, 3])
    j = np.clip(np.searchsorted(times, at), 1, len(times) - 1)
    near = np.where(at - times[j - 1] < times[j] - at, j - 1, j)
    out[:, :3, :3] = poses[near, :3, :3]
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return out


def cast_sweep_realistic(sensor: LidarConfig, static, agents: list[Agent], ground, t: float,
                         column_poses: np.ndarray, rng: np.random.Generator, calibration,
                         realism: Realism = REALISM, agent_radius: float = 130.0) -> SweepResult:
    """One sweep at time ``t`` with physics version 2 or later.

    ``column_poses``: (azimuth_steps, 4, 4) sensor poses at each column's firing time (all
    the same without motion distortion). Points are returned in the sensor frame of each
    column's own pose (not de-skewed)."""
    n_az, n_b = sensor.azimuth_steps, sensor.beams
    el_bias, range_bias = calibration
    el0 = np.deg2rad(np.asarray(sensor.elevations_deg, np.float64))
    az0 = np.linspace(-np.pi, np.pi, n_az, endpoint=False)
    jit = np.deg2rad(realism.jitter_deg)
    E = el0[:, None] + el_bias[:, None] + np.deg2rad(realism.elevation_error_deg) + rng.normal(0.0, jit, (n_b, n_az))
    A = az0[None, :] + rng.normal(0.0, jit, (n_b, n_az))
    d_true = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    d_nominal = sensor.directions()
    col = np.tile(np.arange(n_az), n_b)  # rays are beam-major
    R = column_poses[col, :3, :3]
    o = column_poses[col, :3, 3]
    d_world = np.einsum("nij,nj->ni", R, d_true).astype(np.float32)
    rays = np.concatenate([o.astype(np.float32), d_world], axis=1)
    hit = static.scene.cast_rays(open3d().core.Tensor(np.ascontiguousarray(rays)))
    t_hit = hit["t_hit"].numpy().astype(np.float64)
    cls = static.class_of_id[np.minimum(hit["geometry_ids"].numpy().astype(np.int64), len(static.class_of_id) - 1)]
    normals = hit["primitive_normals"].numpy().astype(np.float64)

    # rough static surfaces: displaced along the normal, the ray meets them earlier or later
    fin = np.isfinite(t_hit)
    if fin.any():
        idx = np.nonzero(fin)[0]
        p = o[idx] + t_hit[idx, None] * d_world[idx]
        disp = surface_displacement(p, cls[idx], realism, ground)
        cosi = np.maximum(np.abs(np.sum(normals[idx] * d_world[idx], axis=1)), 0.08)
        t_hit[idx] = t_hit[idx] - np.clip(disp / cosi, -1.0, 1.0)

    # moving agents near the sensor (at the sweep's time) and the ego body
    T_mid = column_poses[n_az // 2]
    o_mid = T_mid[:3, 3]
    yaw_s = np.arctan2(T_mid[1, 0], T_mid[0, 0])
    parts, owner = [], []
    columns = np.zeros(n_az, bool)
    for k, agent in enumerate(agents):
        x, y, yaw = agent.pose(t)
        dist = np.hypot(x - o_mid[0], y - o_mid[1])
        if dist > agent_radius:
            continue
        z = float(ground.undulation(np.array(x), np.array(y)))
        parts.append(_place(agent.shape[0], agent.shape[1], x, y, z, yaw))
        owner.append(np.full(len(parts[-1][1]), k, np.int64))
        radius = agent.radius + 1.5  # the sensor moves during the revolution
        half = np.pi if dist <= radius else np.arcsin(radius / dist) + 0.1
        az = np.arctan2(y - o_mid[1], x - o_mid[0]) - yaw_s
        a0 = int(np.floor((az - half + np.pi) / (2 * np.pi) * n_az))
        a1 = int(np.ceil((az + half + np.pi) / (2 * np.pi) * n_az))
        columns[np.arange(a0, a1 + 1) % n_az] = True
    t_ego, n_ego = ego_hits(sensor, realism.ego_shape)
    ego = t_ego < t_hit
    if ego.any():
        t_hit = np.where(ego, t_ego, t_hit)
        cls = np.where(ego, EGO, cls)
        normals[ego] = np.einsum("nij,nj->ni", R[ego], n_ego[ego])
    inst = np.zeros(len(t_hit), np.int64)
    sel = np.nonzero(np.tile(columns, n_b))[0]
    if parts and len(sel):
        V, T = merge(parts)
        o3d = open3d()
        dyn = o3d.t.geometry.RaycastingScene()
        dyn.add_triangles(*_tensor_mesh(V, T))
        hd = dyn.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays[sel])))
        td = hd["t_hit"].numpy().astype(np.float64)
        nearer = td < t_hit[sel]
        if nearer.any():
            i2 = sel[nearer]
            own = np.concatenate(owner)[hd["primitive_ids"].numpy()[nearer].astype(np.int64)]
            t_hit[i2] = td[nearer]
            cls[i2] = np.array([a.cls for a in agents], np.int64)[own]
            normals[i2] = hd["primitive_normals"].numpy()[nearer]
            inst[i2] = own + 1

    # tree crowns are volumes: the return comes from inside
    veg = np.nonzero((cls == VEGETATION) & np.isfinite(t_hit))[0]
    t_hit[veg] += rng.exponential(realism.crown_depth_m, len(veg))

    # mixed pixels at depth discontinuities along the scan line
    img = np.where(np.isfinite(t_hit), t_hit, 1e3).reshape(n_b, n_az)
    nxt = np.roll(img, -1, axis=1)
    gap = np.abs(nxt - img) > realism.mixed_gap_m
    u_mix = rng.random((n_b, n_az))
    mix = gap & (u_mix < realism.mixed_prob) & (img < 1e3) & (nxt < 1e3)
    w = rng.random((n_b, n_az))
    img = np.where(mix, img + w * (nxt - img), img)
    t_hit = np.where(np.isfinite(t_hit), img.reshape(-1), t_hit)

    valid = np.nonzero(np.isfinite(t_hit) & (t_hit <= sensor.max_range_m) & (t_hit >= sensor.min_range_m))[0]
    tv = t_hit[valid]
    lab_v = np.where(cls[valid] < 0, 0, cls[valid])
    cos_inc = np.abs(np.sum(normals[valid] * d_world[valid], axis=1))
    albedo = ALBEDO[lab_v].astype(np.float64)
    r50 = realism.r50_m * np.sqrt(albedo * (0.15 + 0.85 * cos_inc))
    p_det = 1.0 / (1.0 + (tv / np.maximum(r50, 1e-3)) ** 6)
    p_drop = 1.0 - p_det * (1.0 - realism.base_drop)
    p_drop += realism.specular_drop * np.isin(lab_v, (VEHICLE, PARKED))
    u = rng.random(len(valid))
    noise = rng.normal(0.0, realism.range_noise_m, len(valid))
    keep_v = u >= np.clip(p_drop, 0.0, 1.0)
    keep = valid[keep_v]
    beam = keep // n_az
    r = tv[keep_v] + noise[keep_v] + range_bias[beam]
    pts = (d_nominal[keep].astype(np.float64) * r[:, None]).astype(np.float32)
    lab = lab_v[keep_v]
    intensity = np.clip(ALBEDO[lab] * (0.4 + 0.6 * cos_inc[keep_v]) * (1.0 - 0.4 * r / sensor.max_range_m), 0, 1)
    return SweepResult(pts, intensity.astype(np.float32), lab.astype(np.uint32), inst[keep].astype(np.uint32),
                       beam.astype(np.int16), len(valid), int(len(valid) - len(keep)))
