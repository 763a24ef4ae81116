"""Ray casting the world with open3d's ``RaycastingScene``.

The static world (ground, structures, poles, vegetation, parked vehicles) goes into one scene
built once per sequence; the moving agents and the ego vehicle's own body go into a small
scene rebuilt for every sweep. Each ray takes the nearer of the two hits. Returns come out in
the sensor frame at the sweep's timestamp, i.e. like a perfectly motion-compensated sweep.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from pcfbench.datasets.synthetic.sensor import LidarConfig
from pcfbench.datasets.synthetic.world import EGO, STATIC_CLASSES, Agent, MeshSoup, merge, _place

# Reflectance-like intensity per class (ground, structure, pole, vegetation, parked, vehicle, cyclist, pedestrian, ego,
# trunk: bark, as dark as leaves).
ALBEDO = np.array([0.25, 0.45, 0.6, 0.3, 0.7, 0.7, 0.5, 0.35, 0.5, 0.3], np.float32)


def open3d():
    """open3d, imported on first use: only casting rays needs it. Reading generated data, as
    every worker of a run does, does not, and importing it takes seconds (it imports
    scikit-learn)."""
    import open3d

    return open3d


def _tensor_mesh(V: np.ndarray, T: np.ndarray):
    o3d = open3d()
    return (o3d.core.Tensor(np.ascontiguousarray(V, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(T, dtype=np.uint32)))


def _rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N, 3) float32 ``v @ R.T`` without a slow small-matrix matmul."""
    R = R.astype(np.float32)
    return v[:, 0:1] * R[:, 0] + v[:, 1:2] * R[:, 1] + v[:, 2:3] * R[:, 2]


class StaticScene:
    """The static classes of a :class:`MeshSoup` in one ray-casting scene, built once."""

    def __init__(self, soup: MeshSoup):
        self.scene = open3d().t.geometry.RaycastingScene()
        self.geometry_class: dict[int, int] = {}
        for cls in STATIC_CLASSES:
            V, T = soup.merged(cls)
            if len(T):
                gid = self.scene.add_triangles(*_tensor_mesh(V, T))
                self.geometry_class[gid] = cls
        self.class_of_id = np.full(max(self.geometry_class, default=0) + 2, -1, np.int64)
        for gid, cls in self.geometry_class.items():
            self.class_of_id[gid] = cls


@dataclass(frozen=True)
class EgoShape:
    """The ego vehicle in the sensor frame (x forward, origin at the sensor): a lower body
    (bonnet and boot height) and a narrower cabin under the roof-mounted sensor."""

    x_min: float = -2.75
    x_max: float = 1.85
    half_width: float = 0.95
    body_below_sensor: float = 0.9  # top of bonnet / boot
    cabin_x: tuple[float, float] = (-1.5, 0.5)
    cabin_half_width: float = 0.7
    roof_below_sensor: float = 0.45

    def boxes(self, mount_height: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Axis-aligned (lo, hi) corners of the body and the cabin in the sensor frame."""
        bottom = -mount_height + 0.3
        body = (np.array([self.x_min, -self.half_width, bottom]), np.array([self.x_max, self.half_width, -self.body_below_sensor]))
        cabin = (np.array([self.cabin_x[0], -self.cabin_half_width, bottom]),
                 np.array([self.cabin_x[1], self.cabin_half_width, -self.roof_below_sensor]))
        return [body, cabin]


EGO_SHAPE = EgoShape()


def _slab(d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry distance (inf: miss) and outward normal of rays from the origin into box [lo, hi]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = lo / d
        t2 = hi / d
    t_near = np.minimum(t1, t2)
    enter = np.max(t_near, axis=1)
    axis = np.argmax(t_near, axis=1)
    hit = (enter <= np.min(np.maximum(t1, t2), axis=1)) & (enter > 0)
    normals = np.zeros_like(d)
    rows = np.arange(len(d))
    normals[rows, axis] = -np.sign(d[rows, axis])
    return np.where(hit, enter, np.inf), normals


@functools.lru_cache(maxsize=8)
def ego_hits(sensor: LidarConfig, shape: EgoShape = EGO_SHAPE) -> tuple[np.ndarray, np.ndarray]:
    """Per ray of ``sensor``: distance to the ego vehicle (inf: misses) and its normal there.

    The vehicle is two axis-aligned boxes in the sensor frame, so slab tests are exact, and
    the result is the same for every sweep.
    """
    d = sensor.directions().astype(np.float64)
    t, normals = np.full(len(d), np.inf), np.zeros_like(d)
    for lo, hi in shape.boxes(sensor.mount_height_m):
        tb, nb = _slab(d, lo, hi)
        nearer = tb < t
        t = np.where(nearer, tb, t)
        normals[nearer] = nb[nearer]
    return t.astype(np.float32), normals.astype(np.float32)


@dataclass
class SweepResult:
    points: np.ndarray  # (N, 3) float32, sensor frame
    intensity: np.ndarray  # (N,) float32 in [0, 1]
    labels: np.ndarray  # (N,) uint32 class ids
    instance: np.ndarray  # (N,) uint32: agent index + 1 for moving agents, else 0
    beam: np.ndarray  # (N,) int16 beam index
    rays_hit: int  # rays that hit something within the maximum range
    rays_dropped: int  # of those, dropped by the drop model


def cast_sweep(sensor: LidarConfig, static: StaticScene, agents: list[Agent], ground, t: float,
               T_world_sensor: np.ndarray, rng: np.random.Generator, directions: np.ndarray | None = None,
               agent_radius: float = 130.0) -> SweepResult:
    """Simulate one sweep at time ``t`` from pose ``T_world_sensor``; ``ground.undulation`` places agents."""
    d_sensor = sensor.directions() if directions is None else directions
    R = T_world_sensor[:3, :3]
    o = T_world_sensor[:3, 3]
    d_world = _rotate(d_sensor, R)
    rays = np.concatenate([np.broadcast_to(o.astype(np.float32), d_world.shape), d_world], axis=1)
    rays_t = open3d().core.Tensor(np.ascontiguousarray(rays))
    hit = static.scene.cast_rays(rays_t)
    t_hit = hit["t_hit"].numpy()
    cls = static.class_of_id[np.minimum(hit["geometry_ids"].numpy().astype(np.int64), len(static.class_of_id) - 1)]
    normals = hit["primitive_normals"].numpy()

    # Moving agents near the sensor plus the ego body, in one small scene for this sweep. Only
    # the azimuth columns an agent can cover are cast against it.
    parts, owner = [], []
    n_az = sensor.azimuth_steps
    columns = np.zeros(n_az, bool)
    yaw_s = np.arctan2(R[1, 0], R[0, 0])
    for k, agent in enumerate(agents):
        x, y, yaw = agent.pose(t)
        dist = np.hypot(x - o[0], y - o[1])
        if dist > agent_radius:
            continue
        z = float(ground.undulation(np.array(x), np.array(y)))
        V, T = _place(agent.shape[0], agent.shape[1], x, y, z, yaw)
        parts.append((V, T))
        owner.append(np.full(len(T), k, np.int64))
        radius = agent.radius + 0.5
        half = np.pi if dist <= radius else np.arcsin(radius / dist) + 0.05
        az = np.arctan2(y - o[1], x - o[0]) - yaw_s  # sensor azimuth (approximate under pitch / roll)
        a0 = int(np.floor((az - half + np.pi) / (2 * np.pi) * n_az))
        a1 = int(np.ceil((az + half + np.pi) / (2 * np.pi) * n_az))
        columns[np.arange(a0, a1 + 1) % n_az] = True
    # The ego body is fixed in the sensor frame: its hits are the same every sweep.
    t_ego, n_ego = ego_hits(sensor)
    ego = t_ego < t_hit
    if ego.any():
        t_hit = np.where(ego, t_ego, t_hit)
        cls = np.where(ego, EGO, cls)
        normals = normals.copy()
        normals[ego] = _rotate(n_ego[ego], R)
    inst = np.zeros(len(t_hit), np.int64)
    sel = np.nonzero(np.tile(columns, sensor.beams))[0]  # rays are beam-major
    if parts and len(sel):
        V, T = merge(parts)
        o3d = open3d()
        dyn = o3d.t.geometry.RaycastingScene()
        dyn.add_triangles(*_tensor_mesh(V, T))
        hd = dyn.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays[sel])))
        td = hd["t_hit"].numpy()
        nearer_sel = td < t_hit[sel]
    else:
        nearer_sel = np.zeros(0, bool)
    if nearer_sel.any():
        idx = sel[nearer_sel]
        prim = hd["primitive_ids"].numpy()[nearer_sel].astype(np.int64)
        own = np.concatenate(owner)[prim]
        agent_cls = np.array([a.cls for a in agents], np.int64)
        t_hit = t_hit.copy()
        t_hit[idx] = td[nearer_sel]
        cls = cls.copy()
        cls[idx] = agent_cls[own]
        normals = normals.copy()
        normals[idx] = hd["primitive_normals"].numpy()[nearer_sel]
        inst[idx] = own + 1

    valid = np.nonzero(np.isfinite(t_hit) & (t_hit <= sensor.max_range_m) & (t_hit >= sensor.min_range_m))[0]
    tv = t_hit[valid]
    cos_inc = np.abs(np.sum(normals[valid] * d_world[valid], axis=1))
    p_drop = sensor.drop_probability(tv, cos_inc)
    u = rng.random(len(valid))
    noise = rng.normal(0.0, sensor.range_noise_m, len(valid))
    keep_v = u >= p_drop
    keep = valid[keep_v]
    r = (tv[keep_v] + noise[keep_v]).astype(np.float64)
    pts = d_sensor[keep] * r[:, None].astype(np.float32)
    lab = np.where(cls[keep] < 0, 0, cls[keep])
    intensity = np.clip(ALBEDO[lab] * (0.4 + 0.6 * cos_inc[keep_v]) * (1.0 - 0.4 * r / sensor.max_range_m), 0, 1)
    beam = (keep // sensor.azimuth_steps).astype(np.int16)
    return SweepResult(pts, intensity.astype(np.float32), lab.astype(np.uint32), inst[keep].astype(np.uint32),
                       beam, len(valid), int(len(valid) - len(keep)))
