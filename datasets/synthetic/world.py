"""A procedural town from a seed: road graph, ground with curbs and slopes, static objects, routes.

Everything is a function of a :class:`TownStyle` and a ``numpy.random.Generator``, so the
same seed gives the same world. Geometry is kept as plain numpy triangle soups per semantic
class; :mod:`pcfbench.datasets.synthetic.lidar` turns them into open3d ray-casting scenes.

Conventions: world frame x east, y north, z up, metres; a route is a polyline resampled every
``ROUTE_STEP`` metres with its yaw; right-hand traffic (vehicles keep to the right lane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

ROUTE_STEP = 0.25  # metres between route samples

# Semantic classes of every generated point (stored as SemanticKITTI-style .label files).
# TRUNK (SemanticKITTI's "trunk", solid wood under the leaves) exists from world physics 4;
# earlier physics label tree trunks VEGETATION, as physics 1's frozen bytes do.
GROUND, STRUCTURE, POLE, VEGETATION, PARKED, VEHICLE, CYCLIST, PEDESTRIAN, EGO, TRUNK = range(10)
CLASS_NAMES = ("ground", "structure", "pole", "vegetation", "parked-vehicle", "vehicle", "cyclist", "pedestrian", "ego",
               "trunk")
MOVING_CLASSES = (VEHICLE, CYCLIST, PEDESTRIAN)
STATIC_CLASSES = (GROUND, STRUCTURE, POLE, VEGETATION, PARKED, TRUNK)


@dataclass(frozen=True)
class TownStyle:
    """What a town looks like and how busy it is."""

    name: str
    block_m: tuple[float, float]  # block size range (road centreline spacing)
    node_jitter_m: float  # random displacement of intersections
    curve_bulge_m: float  # max sideways bulge of a road between intersections (curves)
    lane_width_m: float
    parking_width_m: float  # parking strip beyond the driving lane (road half width = lane + parking)
    sidewalk_m: float
    curb_m: float
    slope_amp_m: float  # ground undulation amplitude
    slope_wavelength_m: float
    building_setback_m: tuple[float, float]
    building_frontage_m: tuple[float, float]
    building_depth_m: tuple[float, float]
    building_height_m: tuple[float, float]
    building_gap_m: tuple[float, float]
    fence_prob: float  # chance a gap between buildings gets a fence or wall
    tree_spacing_m: float
    pole_spacing_m: float
    parked_prob: float  # per parking slot
    vehicles_per_km: float  # moving vehicles per km of road
    cyclists_per_km: float
    pedestrians_per_km: float
    ego_speed_mps: tuple[float, float]
    stop_prob: float  # chance the ego / an agent stops at an intersection


TOWN = TownStyle(
    name="town", block_m=(55.0, 85.0), node_jitter_m=4.0, curve_bulge_m=3.0, lane_width_m=3.5,
    parking_width_m=2.3, sidewalk_m=3.5, curb_m=0.15, slope_amp_m=1.5, slope_wavelength_m=260.0,
    building_setback_m=(0.5, 3.0), building_frontage_m=(10.0, 28.0), building_depth_m=(10.0, 22.0),
    building_height_m=(7.0, 24.0), building_gap_m=(0.0, 6.0), fence_prob=0.3, tree_spacing_m=14.0,
    pole_spacing_m=25.0, parked_prob=0.45, vehicles_per_km=22.0, cyclists_per_km=5.0, pedestrians_per_km=14.0,
    ego_speed_mps=(7.0, 12.0), stop_prob=0.35,
)

SUBURB = TownStyle(
    name="suburb", block_m=(90.0, 140.0), node_jitter_m=10.0, curve_bulge_m=12.0, lane_width_m=3.2,
    parking_width_m=1.2, sidewalk_m=2.0, curb_m=0.12, slope_amp_m=3.5, slope_wavelength_m=180.0,
    building_setback_m=(6.0, 14.0), building_frontage_m=(8.0, 14.0), building_depth_m=(8.0, 12.0),
    building_height_m=(3.5, 7.5), building_gap_m=(8.0, 18.0), fence_prob=0.7, tree_spacing_m=9.0,
    pole_spacing_m=40.0, parked_prob=0.15, vehicles_per_km=8.0, cyclists_per_km=3.0, pedestrians_per_km=4.0,
    ego_speed_mps=(9.0, 14.0), stop_prob=0.2,
)

TOWN_STYLES = {s.name: s for s in (TOWN, SUBURB)}


# --- triangle-soup primitives -------------------------------------------------------------------

@dataclass
class MeshSoup:
    """Vertices and triangles accumulated per semantic class."""

    parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)

    def add(self, cls: int, verts: np.ndarray, tris: np.ndarray) -> None:
        self.parts.setdefault(cls, []).append((np.asarray(verts, np.float64), np.asarray(tris, np.int64)))

    def merged(self, cls: int) -> tuple[np.ndarray, np.ndarray]:
        return merge(self.parts.get(cls, []))


def merge(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    V = np.concatenate([v for v, _ in parts])
    T = np.concatenate([t + o for (_, t), o in zip(parts, offsets)])
    return V, T


_BOX_V = np.array([[x, y, z] for z in (0.0, 1.0) for y in (-0.5, 0.5) for x in (-0.5, 0.5)])
_BOX_T = np.array(
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
     [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]]
)


def box(cx: float, cy: float, z0: float, length: float, width: float, height: float, yaw: float):
    """A box with its bottom face centred at (cx, cy, z0), long axis along ``yaw``."""
    v = _BOX_V * np.array([length, width, height])
    c, s = np.cos(yaw), np.sin(yaw)
    x = v[:, 0] * c - v[:, 1] * s + cx
    y = v[:, 0] * s + v[:, 1] * c + cy
    return np.stack([x, y, v[:, 2] + z0], axis=1), _BOX_T


def _cylinder_template(n: int = 8):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    V = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.ones(n)], [[0, 0, 0], [0, 0, 1]]])
    T = []
    for i in range(n):
        j = (i + 1) % n
        T += [[i, j, n + i], [j, n + j, n + i], [2 * n, j, i], [2 * n + 1, n + i, n + j]]
    return V, np.array(T)


_CYL_V, _CYL_T = _cylinder_template()


def cylinder(cx: float, cy: float, z0: float, radius: float, height: float):
    return _CYL_V * np.array([radius, radius, height]) + np.array([cx, cy, z0]), _CYL_T


def _icosphere():
    t = (1 + 5**0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    T = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    # one subdivision: 80 faces
    verts = [tuple(v) for v in V]
    index = {}

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in index:
            verts.append(tuple((np.asarray(verts[a]) + np.asarray(verts[b])) / 2))
            index[key] = len(verts) - 1
        return index[key]

    out = []
    for a, b, c in T:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        out += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    V = np.asarray(verts)
    return V / np.linalg.norm(V, axis=1, keepdims=True), np.array(out)


_SPH_V, _SPH_T = _icosphere()


def ellipsoid(cx: float, cy: float, cz: float, rx: float, ry: float, rz: float):
    return _SPH_V * np.array([rx, ry, rz]) + np.array([cx, cy, cz]), _SPH_T


# --- the road graph ----------------------------------------------------------------------------

@dataclass
class RoadGraph:
    nodes: np.ndarray  # (K, 2)
    edges: list[tuple[int, int]]
    polylines: list[np.ndarray]  # per edge, (M, 2) from nodes[a] to nodes[b]
    neighbours: dict[int, list[int]]  # node -> edge indices

    def edge_polyline(self, e: int, start: int) -> np.ndarray:
        a, b = self.edges[e]
        return self.polylines[e] if start == a else self.polylines[e][::-1]

    def other(self, e: int, node: int) -> int:
        a, b = self.edges[e]
        return b if node == a else a


def make_road_graph(style: TownStyle, rng: np.random.Generator, n_blocks: int = 5) -> RoadGraph:
    """A jittered grid of (n_blocks + 1)^2 intersections joined by straight or curved roads."""
    def lines():
        sizes = rng.uniform(*style.block_m, size=n_blocks)
        xs = np.concatenate([[0.0], np.cumsum(sizes)])
        return xs - xs[-1] / 2

    xs, ys = lines(), lines()
    n = n_blocks + 1
    nodes = np.array([[x, y] for y in ys for x in xs]) + rng.uniform(-1, 1, size=(n * n, 2)) * style.node_jitter_m
    edges, polylines = [], []
    neighbours: dict[int, list[int]] = {i: [] for i in range(n * n)}
    for j in range(n):
        for i in range(n):
            k = j * n + i
            for k2 in ([k + 1] if i + 1 < n else []) + ([k + n] if j + 1 < n else []):
                p, q = nodes[k], nodes[k2]
                d = q - p
                length = np.linalg.norm(d)
                normal = np.array([-d[1], d[0]]) / length
                bulge = rng.uniform(-1, 1) * style.curve_bulge_m if rng.random() < 0.6 else 0.0
                m = max(int(length / 2.0), 2)
                t = np.linspace(0, 1, m + 1)[:, None]
                ctrl = (p + q) / 2 + normal * 2 * bulge  # quadratic Bezier: apex displaced by ``bulge``
                pts = (1 - t) ** 2 * p + 2 * (1 - t) * t * ctrl + t**2 * q
                neighbours[k].append(len(edges))
                neighbours[k2].append(len(edges))
                edges.append((k, k2))
                polylines.append(pts)
    return RoadGraph(nodes, edges, polylines, neighbours)


# --- routes ------------------------------------------------------------------------------------

@dataclass
class Route:
    xy: np.ndarray  # (M, 2) resampled every ROUTE_STEP metres
    yaw: np.ndarray  # (M,)
    node_s: np.ndarray  # arc length of each intersection passed
    curvature: np.ndarray  # (M,)

    @property
    def length(self) -> float:
        return (len(self.xy) - 1) * ROUTE_STEP

    def at(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Position (..., 2) and yaw (...) at arc length ``s`` (clamped to the route)."""
        f = np.clip(np.asarray(s, dtype=np.float64) / ROUTE_STEP, 0, len(self.xy) - 1.000001)
        i = np.floor(f).astype(int)
        w = (f - i)[..., None]
        xy = self.xy[i] * (1 - w) + self.xy[i + 1] * w
        dyaw = np.angle(np.exp(1j * (self.yaw[i + 1] - self.yaw[i])))
        return xy, self.yaw[i] + dyaw * w[..., 0]


def road_sides(graph, lo: np.ndarray, hi: np.ndarray, margin: float = 150.0):
    """Each road's two sides near [lo, hi] (its midpoint within ``margin``): (side, -1 or 1; the
    line resampled every 0.5 m; unit tangents; unit normals towards that side; length in m),
    road by road, side -1 first: the frontage along which buildings, yards and trees stand."""
    for poly in graph.polylines:
        mid = poly[len(poly) // 2]
        if not (lo[0] - margin <= mid[0] <= hi[0] + margin and lo[1] - margin <= mid[1] <= hi[1] + margin):
            continue
        line = _resample(poly, 0.5)
        seg = np.gradient(line, axis=0)
        tangent = seg / (np.linalg.norm(seg, axis=1, keepdims=True) + 1e-12)
        total = (len(line) - 1) * 0.5
        for side in (-1.0, 1.0):
            yield side, line, tangent, side * np.stack([-tangent[:, 1], tangent[:, 0]], axis=1), total


def _resample(pts: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    pts = pts[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    t = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def make_route(graph: RoadGraph, rng: np.random.Generator, min_length: float, offset: float,
               start_edge: int | None = None, turn_radius: float = 9.0) -> Route:
    """A random walk over the graph (no U-turns), corners rounded, offset ``offset`` m to the right."""
    e = int(rng.integers(len(graph.edges))) if start_edge is None else start_edge
    node = graph.edges[e][int(rng.integers(2))]
    pieces, corners, length = [], [], 0.0
    while length < min_length + 2 * turn_radius:
        poly = graph.edge_polyline(e, node)
        nxt = graph.other(e, node)
        pieces.append(poly)
        corners.append(graph.nodes[nxt])
        length += float(np.sum(np.linalg.norm(np.diff(poly, axis=0), axis=1)))
        options = [x for x in graph.neighbours[nxt] if x != e] or [e]
        e, node = options[int(rng.integers(len(options)))], nxt
    # Stitch: cut each piece ``turn_radius`` short of its end nodes and join with a Bezier
    # through the intersection centre.
    pts = []
    for k, poly in enumerate(pieces):
        dist_start = np.linalg.norm(poly - poly[0], axis=1)
        dist_end = np.linalg.norm(poly - poly[-1], axis=1)
        keep = (dist_end > turn_radius) & ((dist_start > turn_radius) | (k == 0))
        body = poly[keep]
        if k > 0 and len(pts):
            a, c = pts[-1][-1], body[0] if len(body) else poly[-1]
            b = poly[0]
            t = np.linspace(0, 1, 12)[1:-1, None]
            pts.append((1 - t) ** 2 * a + 2 * (1 - t) * t * b + t**2 * c)
        pts.append(body)
    line = _resample(np.concatenate([p for p in pts if len(p)]), ROUTE_STEP)
    tangent = np.gradient(line, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True) + 1e-12
    right = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    line = _resample(line + right * offset, ROUTE_STEP)
    d = np.gradient(line, axis=0)
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    # light smoothing of the heading so curvature is continuous
    k = 9
    yaw_s = np.convolve(np.pad(yaw, k, mode="edge"), np.ones(2 * k + 1) / (2 * k + 1), mode="same")[k:-k]
    curvature = np.abs(np.gradient(yaw_s)) / ROUTE_STEP
    tree = cKDTree(line)
    node_s = np.sort(np.array([tree.query(c)[1] * ROUTE_STEP for c in corners]))
    return Route(line, yaw_s, node_s, curvature)


def speed_profile(route: Route, rng: np.random.Generator, cruise: float, stop_prob: float,
                  a_max: float = 2.0, b_max: float = 3.0, a_lat: float = 2.2, duration: float = 30.0,
                  start_speed: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and speed at times ``0, dt, 2 dt, ...`` (dt = 0.01 s) of a vehicle on ``route``.

    Speed is capped by ``cruise`` (varying slowly), by lateral acceleration in curves, and by
    stops at some intersections (dwell 1-4 s); acceleration and braking are limited.
    """
    n = len(route.xy)
    s_grid = np.arange(n) * ROUTE_STEP
    wobble = 1.0 + 0.15 * np.sin(s_grid / rng.uniform(40, 90) + rng.uniform(0, 6.3))
    v = np.minimum(cruise * wobble, np.sqrt(a_lat / np.maximum(route.curvature, 1e-4)))
    stops = [s for s in route.node_s if s > 5.0 and rng.random() < stop_prob]
    for s in stops:
        v[int(round(s / ROUTE_STEP))] = 0.0
    v[-1] = 0.0
    if start_speed is not None:
        v[0] = min(v[0], start_speed)
    vl = v.tolist()
    for i in range(1, n):  # forward: acceleration limit
        vl[i] = min(vl[i], math.sqrt(vl[i - 1] ** 2 + 2 * a_max * ROUTE_STEP))
    for i in range(n - 2, -1, -1):  # backward: braking limit
        vl[i] = min(vl[i], math.sqrt(vl[i + 1] ** 2 + 2 * b_max * ROUTE_STEP))
    v = np.asarray(vl)
    # Time at each route sample: integrate ds / v (crawling at >= 0.4 m/s); every stop adds a
    # breakpoint that holds the arc length for a dwell of 1-4 s. Then invert: s at t = k * dt.
    dt = 0.01
    v_mid = np.maximum(0.5 * (v[1:] + v[:-1]), 0.4)
    dtime = np.concatenate([[0.0], ROUTE_STEP / v_mid])
    stop_idx = sorted({min(int(round(s / ROUTE_STEP)), n - 1) for s in stops})
    t_bp = list(np.cumsum(dtime))
    s_bp = list(s_grid)
    shift = 0.0
    t_new, s_new = [], []
    stop_set = set(stop_idx)
    for i in range(n):
        t_new.append(t_bp[i] + shift)
        s_new.append(s_bp[i])
        if i in stop_set:
            shift += rng.uniform(1.0, 4.0)
            t_new.append(t_bp[i] + shift)
            s_new.append(s_bp[i])
    t_grid = np.arange(int(round(duration / dt)) + 1) * dt
    s_out = np.interp(t_grid, np.asarray(t_new), np.asarray(s_new))
    speed = np.gradient(s_out, dt)
    return s_out, speed


# --- the static world --------------------------------------------------------------------------

class Ground:
    """Ground height: gentle undulation everywhere plus a curb step off the carriageway."""

    def __init__(self, style: TownStyle, graph: RoadGraph, rng: np.random.Generator):
        self.style = style
        self.phase = rng.uniform(0, 2 * np.pi, size=4)
        self.k = 2 * np.pi / style.slope_wavelength_m
        dense = np.concatenate([_resample(p, 0.5) for p in graph.polylines])
        self.tree = cKDTree(dense)
        self.half_road = style.lane_width_m + style.parking_width_m

    def undulation(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        p = self.phase
        return self.style.slope_amp_m * (0.6 * np.sin(self.k * x + p[0]) * np.cos(0.7 * self.k * y + p[1])
                                         + 0.4 * np.sin(0.5 * self.k * (x + y) + p[2]))

    def road_distance(self, x: np.ndarray, y: np.ndarray, bound: float = np.inf) -> np.ndarray:
        """Distance of each point to the nearest road centre line; inf for those farther than
        ``bound`` (a bounded KD-tree search ends early for them)."""
        xy = np.stack([np.ravel(x), np.ravel(y)], axis=1)
        return self.tree.query(xy, distance_upper_bound=bound)[0].reshape(np.shape(x))

    def farther_than(self, x: np.ndarray, y: np.ndarray, distance: float) -> np.ndarray:
        """``road_distance(x, y) > distance``, searched only just past ``distance`` (about 2x faster)."""
        bound = distance * (1 + 1e-9) + 1e-9  # every point within ``distance`` still gets its exact distance
        return self.road_distance(x, y, bound) > distance

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        d = self.road_distance(x, y)
        curb = self.style.curb_m * np.clip((d - self.half_road) / 0.2, 0.0, 1.0)
        return self.undulation(x, y) + curb

    def mesh(self, lo: np.ndarray, hi: np.ndarray, res: float = 0.5):
        xs = np.arange(lo[0], hi[0] + res, res)
        ys = np.arange(lo[1], hi[1] + res, res)
        X, Y = np.meshgrid(xs, ys, indexing="xy")
        Z = self.height(X, Y)
        V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        nx = len(xs)
        i, j = np.meshgrid(np.arange(nx - 1), np.arange(len(ys) - 1), indexing="xy")
        a = (j * nx + i).ravel()
        T = np.concatenate([np.stack([a, a + 1, a + nx], 1), np.stack([a + 1, a + nx + 1, a + nx], 1)])
        return V, T


def build_static(style: TownStyle, graph: RoadGraph, ground: Ground, rng: np.random.Generator,
                 lo: np.ndarray, hi: np.ndarray, clearance: float | None = None,
                 trunk_class: int = VEGETATION) -> MeshSoup:
    """Ground, buildings, walls and fences, poles and signs, trees and parked vehicles in [lo, hi].

    Poles and trees are placed along each road; near a junction that can put one inside the
    crossing road's carriageway. With ``clearance`` (m; world physics 3 and later) a pole or
    trunk whose footprint comes nearer than that to any carriageway is left out, after its
    random draws, so that everything else stays as it was; ``None`` keeps physics 1 as it is.
    Tree trunks take ``trunk_class``: VEGETATION up to physics 3 (so a realistic sensor saw
    into them as into leaves), TRUNK from physics 4.
    """
    soup = MeshSoup()
    soup.add(GROUND, *ground.mesh(lo, hi))
    half = ground.half_road
    edge_band = half + style.sidewalk_m

    def inside(x, y, margin=0.0):
        return lo[0] - margin <= x <= hi[0] + margin and lo[1] - margin <= y <= hi[1] + margin

    def off_the_road(p, radius):
        return clearance is None or float(ground.road_distance(np.array(p[0]), np.array(p[1]))) - radius >= half + clearance

    occupied: list[tuple[float, float, float]] = []  # (x, y, radius) of placed footprints

    def free(x, y, r):
        if ground.road_distance(np.array(x), np.array(y)) < edge_band + r * 0.7:
            return False
        return all((x - ox) ** 2 + (y - oy) ** 2 > (r + orad) ** 2 for ox, oy, orad in occupied[-400:])

    for side, line, tangent, normal, total in road_sides(graph, lo, hi):
        # Buildings (or fences and walls in the gaps) along the frontage.
        s = rng.uniform(6.0, 12.0)
        while s < total - 10.0:
            front = rng.uniform(*style.building_frontage_m)
            depth = rng.uniform(*style.building_depth_m)
            setback = rng.uniform(*style.building_setback_m)
            j = min(int((s + front / 2) / 0.5), len(line) - 1)
            yaw = np.arctan2(tangent[j, 1], tangent[j, 0])
            c = line[j] + normal[j] * (edge_band + setback + depth / 2)
            r = 0.5 * np.hypot(front, depth)
            if inside(*c) and free(c[0], c[1], r * 0.8):
                h = rng.uniform(*style.building_height_m)
                z0 = float(ground.undulation(c[0], c[1])) - 0.5
                soup.add(STRUCTURE, *box(c[0], c[1], z0, front, depth, h + 0.5, yaw))
                if rng.random() < 0.3:  # a lower annex or roof structure
                    soup.add(STRUCTURE, *box(c[0], c[1], z0 + h + 0.5, front * 0.4, depth * 0.5, rng.uniform(1.5, 3.5), yaw))
                occupied.append((c[0], c[1], r * 0.8))
            gap = rng.uniform(*style.building_gap_m)
            if gap > 3.0 and rng.random() < style.fence_prob:
                k = min(int((s + front + gap / 2) / 0.5), len(line) - 1)
                f = line[k] + normal[k] * (edge_band + 0.3)
                if inside(*f):
                    yawk = np.arctan2(tangent[k, 1], tangent[k, 0])
                    wall = rng.random() < 0.4
                    height = rng.uniform(1.8, 2.6) if wall else rng.uniform(0.9, 1.5)
                    soup.add(STRUCTURE, *box(f[0], f[1], float(ground.height(f[0], f[1])) - 0.1, gap, 0.25 if wall else 0.08, height, yawk))
            s += front + gap
        # Poles (street lights) and signs along the sidewalk.
        s = rng.uniform(3.0, style.pole_spacing_m)
        while s < total - 3.0:
            i = int(s / 0.5)
            p = line[i] + normal[i] * (half + 0.6)
            if inside(*p):
                z = float(ground.height(p[0], p[1]))
                height = rng.uniform(6.0, 8.5)
                if off_the_road(p, 0.12):
                    soup.add(POLE, *cylinder(p[0], p[1], z, 0.12, height))
            s += style.pole_spacing_m * rng.uniform(0.8, 1.2)
        for end in (8.0, total - 8.0):  # a sign near each intersection
            if rng.random() < 0.5:
                i = int(end / 0.5)
                p = line[i] + normal[i] * (half + 0.4)
                if inside(*p) and off_the_road(p, 0.04):
                    z = float(ground.height(p[0], p[1]))
                    soup.add(POLE, *cylinder(p[0], p[1], z, 0.04, 2.6))
                    yaw = np.arctan2(tangent[i, 1], tangent[i, 0]) + np.pi / 2
                    soup.add(POLE, *box(p[0], p[1], z + 2.1, 0.7, 0.04, 0.6, yaw))
        # Trees in the sidewalk strip and front yards.
        s = rng.uniform(2.0, style.tree_spacing_m)
        while s < total - 4.0:
            i = int(s / 0.5)
            off = half + style.sidewalk_m * 0.6 + (rng.uniform(0, style.building_setback_m[0]) if rng.random() < 0.5 else 0)
            p = line[i] + normal[i] * off
            if inside(*p) and rng.random() < 0.8:
                z = float(ground.height(p[0], p[1]))
                trunk = rng.uniform(1.8, 3.2)
                crown = rng.uniform(1.3, 3.0)
                radius = rng.uniform(0.12, 0.3)
                squash = rng.uniform(0.8, 1.3)
                if off_the_road(p, radius):
                    soup.add(trunk_class, *cylinder(p[0], p[1], z, radius, trunk + crown * 0.5))
                    soup.add(VEGETATION, *ellipsoid(p[0], p[1], z + trunk + crown * 0.8, crown, crown, crown * squash))
            s += style.tree_spacing_m * rng.uniform(0.6, 1.4)
        # Parked vehicles in the parking strip, away from intersections.
        s = 14.0
        while s < total - 14.0:
            i = int(s / 0.5)
            if rng.random() < style.parked_prob:
                p = line[i] + normal[i] * (style.lane_width_m + style.parking_width_m * 0.45 + 0.2)
                if inside(*p):
                    yaw = np.arctan2(tangent[i, 1], tangent[i, 0]) + (np.pi if side > 0 else 0.0)
                    z = float(ground.undulation(p[0], p[1]))
                    for v, t in vehicle_parts(rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95), rng.uniform(1.4, 1.7)):
                        soup.add(PARKED, *_place(v, t, p[0], p[1], z, yaw))
            s += rng.uniform(5.5, 8.0)
    return soup


# --- agents ------------------------------------------------------------------------------------

def vehicle_parts(length: float, width: float, height: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """A car in its own frame (x forward, origin on the ground under its centre): body + cabin."""
    body = box(0.0, 0.0, 0.3, length, width, height * 0.45, 0.0)
    cabin = box(-0.1 * length, 0.0, 0.3 + height * 0.45, length * 0.55, width * 0.9, height * 0.55 - 0.3, 0.0)
    return [body, cabin]


def _place(v: np.ndarray, t: np.ndarray, x: float, y: float, z: float, yaw: float):
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.empty_like(v)
    out[:, 0] = v[:, 0] * c - v[:, 1] * s + x
    out[:, 1] = v[:, 0] * s + v[:, 1] * c + y
    out[:, 2] = v[:, 2] + z
    return out, t


@dataclass
class Agent:
    """A moving road user: a shape in its own frame, a route and arc length over time."""

    cls: int
    shape: tuple[np.ndarray, np.ndarray]  # vertices, triangles in the agent frame
    route: Route
    s_t: np.ndarray  # arc length at t = k * 0.01 s
    t0: float  # the agent's clock at the sequence's t = 0

    @property
    def radius(self) -> float:
        """Horizontal radius of the shape around the agent's origin."""
        return float(np.max(np.hypot(self.shape[0][:, 0], self.shape[0][:, 1])))

    def positions(self, times: np.ndarray) -> np.ndarray:
        """(len(times), 2) positions at sequence times ``times``."""
        k = np.clip((np.asarray(times) + self.t0) / 0.01, 0.0, len(self.s_t) - 1.0)
        s = np.interp(k, np.arange(len(self.s_t)), self.s_t)
        return self.route.at(s)[0]

    def pose(self, t: float) -> tuple[float, float, float]:
        k = min(max((t + self.t0) / 0.01, 0.0), len(self.s_t) - 1.0)
        i = int(k)
        j = min(i + 1, len(self.s_t) - 1)
        s = self.s_t[i] * (1 - (k - i)) + self.s_t[j] * (k - i)
        xy, yaw = self.route.at(s)
        return float(xy[0]), float(xy[1]), float(yaw)


def make_agents(style: TownStyle, graph: RoadGraph, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray,
                duration: float) -> list[Agent]:
    """Vehicles, cyclists and pedestrians on routes near the region [lo, hi]."""
    near = [e for e, p in enumerate(graph.polylines)
            if np.all(p.min(0) < hi + 40) and np.all(p.max(0) > lo - 40)]
    road_km = sum(float(np.sum(np.linalg.norm(np.diff(graph.polylines[e], axis=0), axis=1))) for e in near) / 1000
    half = style.lane_width_m + style.parking_width_m
    kinds = (
        (VEHICLE, style.vehicles_per_km, style.lane_width_m / 2, (6.0, 13.0)),
        (CYCLIST, style.cyclists_per_km, style.lane_width_m - 0.6, (3.5, 6.5)),
        (PEDESTRIAN, style.pedestrians_per_km, half + style.sidewalk_m * 0.4, (1.0, 1.7)),
    )
    agents = []
    for cls, per_km, offset, speed in kinds:
        for _ in range(int(rng.poisson(per_km * road_km))):
            cruise = rng.uniform(*speed)
            horizon = duration + 20.0
            route = make_route(graph, rng, cruise * horizon * 1.3 + 20.0, offset,
                               start_edge=near[int(rng.integers(len(near)))], turn_radius=8.0 if cls == VEHICLE else 5.0)
            s_t, _ = speed_profile(route, rng, cruise, style.stop_prob if cls != PEDESTRIAN else 0.1,
                                   a_max=1.0 if cls != VEHICLE else 2.5, duration=horizon,
                                   start_speed=None)
            if cls == VEHICLE:
                if rng.random() < 0.12:  # a van or small truck
                    parts = [box(0.0, 0.0, 0.35, rng.uniform(5.5, 7.5), 2.1, rng.uniform(2.3, 3.0), 0.0)]
                else:
                    parts = vehicle_parts(rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95), rng.uniform(1.4, 1.7))
            elif cls == CYCLIST:
                parts = [box(0.0, 0.0, 0.25, 1.7, 0.12, 0.75, 0.0), box(-0.1, 0.0, 0.9, 0.55, 0.45, 0.85, 0.0)]
            else:
                parts = [box(0.0, 0.0, 0.0, 0.35, 0.5, rng.uniform(1.55, 1.9), 0.0)]
            agents.append(Agent(cls, merge(parts), route, s_t, rng.uniform(0.0, 15.0)))
    return agents
