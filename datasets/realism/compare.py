"""The realism report: a generated domain beside a real dataset, statistic by statistic.

``pcfbench synthetic compare --real kitti=ROOT [--domain synthetic-town]`` reads a few sweeps
of each side and writes ``realism.md``, ``realism.csv`` and one figure per statistic under
``--out``. Every number is given for both sides and as the ratio synthetic / real:

* points per sweep, and returns per beam (points binned by elevation into the beams of the
  HDL-64E-like table of :mod:`pcfbench.datasets.synthetic.sensor`);
* the range histogram (1 m bins) and its distance to the real one: total variation
  ``0.5 * sum |p - q|`` (0: same, 1: disjoint) and the earth mover's distance in metres;
* elevation / azimuth coverage: the fraction of 1 deg x 0.5 deg (azimuth x elevation) cells
  inside the beam fan that hold a return, and the elevation span of the returns;
* the static-scene residual: each point of sweep i+1 (3-20 m), registered into sweep i by
  the poses, against the plane fitted to its neighbours in sweep i (median distance);
* local surface roughness: the same plane fit within one sweep (median RMS distance of the
  neighbourhood to its plane), overall and apart for level (ground-like) and vertical planes,
  and the share of each kind among the fitted planes (what the scene near the road is made of);
* the fraction of points on moving objects, where labels say so (generated domains, or
  SemanticKITTI labels ``>= 252``); and, on both sides whether labelled or not, free-space
  violations: the share of the points of the sweep ``MOVING_GAP_S`` later (above the ground,
  3-40 m), registered into sweep i by the poses, that lie at least ``FREE_MARGIN_M`` in front
  of every return of sweep i around their direction, in space sweep i saw empty. Moving
  objects do that, and so do still surfaces that rays pass now and then (car glass, hedges,
  fences): on the KITTI calibration drive nearly all of them recur at the same places as the
  car passes (where labels exist, the report gives how many are on moving objects);
* moving evidence, label-free: the share of the points of a sweep (judged as above) in
  space that the sweeps ``MOVING_GAP_S`` before and after both saw empty, with no return of
  either within ``STILL_M``: a moving object's place is empty before and after, a see-through
  still surface returns from it then. It reads every sweep ``MOVING_GAP_S`` apart over the
  whole split, not the sweeps above: one passing car sets a dozen sweeps' (where labels
  exist, the report gives how much of the evidence is on moving objects, and how much of the
  moving objects it finds);
* parallax: of the range-image bins of the sweep ``MOVING_GAP_S`` later whose nearest return
  is near (within ``BLEED_NEAR_M`` horizontally) and above the ground, the share holding a
  point of sweep i (registered into the later frame) ``FREE_MARGIN_M`` or more behind that
  return: background seen past a near surface's edge, which a forecast without occlusion
  (4D-Occ's nearest point in angle) can read as the depth; and how many such near bins a
  sweep has (how much of the view near surfaces fill);
* mixed pixels: along each beam of a range image, the share of depth jumps (the two
  neighbours of a return more than ``JUMP_M`` apart) whose middle return lies in between,
  more than ``BETWEEN_M`` from both: a return from neither surface;
* the ray-drop pattern: per beam, the share of azimuth columns without a return, the column
  count estimated from the fullest beams;
* the five baselines' flat means of chamfer_nf, l1_median and l1_mean at a setting, and the
  Kendall tau between the two rankings per metric, with how far it is to be trusted: a
  moving-block bootstrap over each side's samples (consecutive samples of a drive overlap,
  so blocks, not single samples) gives the tau's 95 % interval and the share of draws that
  reach 0.8, and the real ranking's agreement with itself when only its samples are redrawn.

Either side may pool several splits (``--split train,val,test``): the statistics read sweeps
spread over all of them, the baselines run a cell per split and pool every (sample, future
sweep) alike, and the report ranks each sequence on its own too (its tau against the other
side's pooled ranking, and the sequences' taus against each other): a ranking the sequences
of one side disagree on belongs to the scene, not to the dataset.

Both clouds are thinned to one point per ``VOXEL_M`` cube before the plane fits, so the
neighbourhoods have the same size whatever the sensor's point density.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pcfbench.errors import PcfbenchError

BASELINES = ("copy-last", "raycast-4docc", "raycast-freespace", "raycast-voxel", "raycast-zbuffer")
RANK_METRICS = ("chamfer_nf", "l1_median", "l1_mean")
RANGE_EDGES = np.arange(0.0, 121.0, 1.0)
ELEV_EDGES = np.arange(-30.0, 10.001, 0.25)
VOXEL_M = 0.15  # thinning before plane fits
NEIGHBOURS = 16  # points of a local plane
RADIUS_M = 0.6  # neighbours farther than this are not used
MIN_NEIGHBOURS = 8
PLANE_RANGE_M = (3.0, 20.0)  # points whose planes are fitted (near enough to be sampled densely)
QUERIES = 4000  # plane fits per sweep
LEVEL_NZ, WALL_NZ = 0.9, 0.3  # a plane is level (ground-like) above this normal |z|, vertical below that
MOVING_GAP_S = 0.5  # free-space test: the later sweep is the one nearest this long after sweep i
FREE_MARGIN_M = 1.0  # a later point this far in front of what sweep i saw around it violates free space
FREE_RANGE_M = (3.0, 40.0)  # later points judged: range from sweep i's sensor
FREE_ABOVE_M = -1.2  # ... and z above this in sweep i's sensor frame (off the ground near the car)
FREE_AZ_DEG, FREE_EL_DEG = 0.2, 0.4  # range-image bins (the HDL-64E's column and beam spacing)
FREE_EL_DEG_RANGE = (-30.0, 10.0)
STILL_M = 0.3  # moving evidence: no return of the sweep before or after within this of the point
BLEED_NEAR_M = 10.0  # parallax: later returns judged within this horizontal range (and above FREE_ABOVE_M)
DRIFT_GAP_S = 1.0  # ground drift: the later sweep is the one nearest this long after sweep i
DRIFT_BELOW_M = -1.3  # ground: z below this in its own sweep's sensor frame
DRIFT_RANGE_M = (4.0, 12.0)  # later ground points judged: range from their own sensor
DRIFT_EARLIER_M = 40.0  # earlier ground points used: horizontal range from their sensor
DRIFT_RADIUS_M = 0.3  # earlier ground points within this horizontal distance give the height
DRIFT_MIN = 3  # ... at least this many
DRIFT_FLAT_M = 0.15  # ... spanning at most this in z (not a curb or an object's foot)
DRIFT_OUTLIER_M = 0.15  # pairs whose heights differ by more are left out of the fit
FAR_M = 40.0  # far views: points of sweep i this far (horizontally) from the sensor DRIFT_GAP_S later
FAR_GONE_M = 2.0  # ... that close: no return of that later sweep within this of the point
JUMP_M = 1.0  # mixed pixels: a depth jump between the two neighbours of a return along its beam
BETWEEN_M = 0.3  # ... and the return lies this far from both of them, in between
#: SemanticKITTI classes of moving objects (moving-car ... moving-other-vehicle)
SEMANTIC_KITTI_MOVING = 252


# --- the statistics, each a plain function of arrays (tested against hand-computed cases) ------

def beam_edges(elevations_deg) -> np.ndarray:
    """Bin edges (deg, increasing) halfway between sorted beam elevations, open-ended by half a gap."""
    e = np.sort(np.asarray(elevations_deg, float))
    mid = (e[1:] + e[:-1]) / 2
    return np.concatenate([[e[0] - (e[1] - e[0]) / 2], mid, [e[-1] + (e[-1] - e[-2]) / 2]])


def elevation_deg(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, np.float64)
    return np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))


def azimuth_deg(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, np.float64)
    return np.degrees(np.arctan2(p[:, 1], p[:, 0]))


def returns_per_beam(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Points per elevation bin (beam), lowest beam first."""
    return np.histogram(elevation_deg(points), bins=edges)[0]


def drop_per_beam(counts_per_sweep: np.ndarray, quantile: float = 0.9) -> tuple[np.ndarray, float]:
    """Share of azimuth columns without a return, per beam, and the column count used.

    The sensor's columns per revolution are estimated as the ``quantile`` of the per-beam
    counts (the fullest beams see something in nearly every direction)."""
    c = np.asarray(counts_per_sweep, float)
    columns = float(np.quantile(c, quantile))
    if columns <= 0:
        return np.ones_like(c), 0.0
    return np.clip(1.0 - c / columns, 0.0, 1.0), columns


def histogram_distance(p: np.ndarray, q: np.ndarray) -> float:
    """Total variation distance between two histograms (normalised here): 0.5 * sum |p - q|."""
    p = np.asarray(p, float)
    q = np.asarray(q, float)
    return float(0.5 * np.abs(p / p.sum() - q / q.sum()).sum())


def emd_1d(p: np.ndarray, q: np.ndarray, edges: np.ndarray) -> float:
    """Earth mover's distance between two histograms on the same bins (bin-centre mass)."""
    p = np.asarray(p, float) / np.sum(p)
    q = np.asarray(q, float) / np.sum(q)
    widths = np.diff(edges)
    return float(np.sum(np.abs(np.cumsum(p - q))[:-1] * widths[:-1]))


def coverage(points: np.ndarray, el_range=(-24.0, 2.0), az_bin=1.0, el_bin=0.5) -> float:
    """Fraction of (azimuth x elevation) cells inside ``el_range`` holding at least one return."""
    el = elevation_deg(points)
    az = azimuth_deg(points)
    inside = (el >= el_range[0]) & (el < el_range[1])
    n_az = int(round(360 / az_bin))
    n_el = int(round((el_range[1] - el_range[0]) / el_bin))
    ia = np.clip(((az[inside] + 180.0) / az_bin).astype(int), 0, n_az - 1)
    ie = np.clip(((el[inside] - el_range[0]) / el_bin).astype(int), 0, n_el - 1)
    return float(len(np.unique(ia * n_el + ie)) / (n_az * n_el))


def range_image_bins(points: np.ndarray, az_res: float = FREE_AZ_DEG, el_res: float = FREE_EL_DEG,
                     el_range=FREE_EL_DEG_RANGE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's (azimuth bin, elevation bin) in a spherical image of ``az_res`` x ``el_res``
    degrees (azimuth bin 0 starts at -180 deg, elevation bin 0 at ``el_range[0]``), and whether
    it falls inside ``el_range``."""
    n_az = int(round(360 / az_res))
    ia = np.floor((azimuth_deg(points) + 180.0) / az_res).astype(np.int64) % n_az
    e = np.floor((elevation_deg(points) - el_range[0]) / el_res)
    inside = (e >= 0) & (e < int(round((el_range[1] - el_range[0]) / el_res)))
    return ia, np.where(inside, e, 0).astype(np.int64), inside


def free_space_violations(earlier: np.ndarray, later: np.ndarray, margin: float = FREE_MARGIN_M,
                          ranges=FREE_RANGE_M, above: float = FREE_ABOVE_M, az_res: float = FREE_AZ_DEG,
                          el_res: float = FREE_EL_DEG, el_range=FREE_EL_DEG_RANGE) -> tuple[np.ndarray, np.ndarray]:
    """Points of a later sweep (``later``, registered into the earlier sweep's sensor frame) in
    space the earlier sweep saw empty. Returns (judged, violating), (N,) bool each: a later point
    is judged when its range from the earlier sensor is within ``ranges``, its z is above
    ``above``, and the earlier sweep has a return in its range-image bin or one of the 8 around
    it (azimuth wraps); it violates when it lies ``margin`` or more in front of the nearest of
    those returns."""
    n_az = int(round(360 / az_res))
    n_el = int(round((el_range[1] - el_range[0]) / el_res))
    img = np.full((n_az, n_el + 2), np.inf)  # one padding row of elevation bins each side
    ia, ie, inside = range_image_bins(earlier, az_res, el_res, el_range)
    np.minimum.at(img, (ia[inside], ie[inside] + 1), np.linalg.norm(earlier[inside], axis=1))
    near = img.copy()
    for da in (-1, 0, 1):
        for de in (-1, 0, 1):
            if da or de:
                near = np.minimum(near, np.roll(np.roll(img, da, axis=0), de, axis=1))
    near = near[:, 1:-1]  # the padding rows only fed their neighbours
    r = np.linalg.norm(later, axis=1)
    ja, je, ok = range_image_bins(later, az_res, el_res, el_range)
    seen = near[ja, je]
    judged = ok & (r >= ranges[0]) & (r < ranges[1]) & (later[:, 2] > above) & np.isfinite(seen)
    return judged, judged & (r <= seen - margin)


def moving_evidence(current: np.ndarray, before: np.ndarray, T_before_current: np.ndarray, after: np.ndarray,
                    T_after_current: np.ndarray, still: float = STILL_M) -> tuple[np.ndarray, np.ndarray]:
    """Points of ``current`` (its own sensor frame) on something that moved, label-free.

    ``before`` and ``after`` are the sweeps ``MOVING_GAP_S`` earlier and later, each in its own
    sensor frame; ``T_before_current`` and ``T_after_current`` register ``current`` into them.
    A point is judged when :func:`free_space_violations` judges it against both; it is moving
    evidence when it violates the free space of both (the space was seen empty before and
    after) and neither sweep has a return within ``still`` of it. A still surface that rays
    pass now and then (car glass, a hedge, a fence) violates free space too, but returns from
    the same place before or after; a moving object's place is empty both times. Returns
    (judged, moving), (N,) bool each."""
    from pcfbench.geometry import transform_points

    jb, vb = free_space_violations(before, transform_points(T_before_current, current))
    ja, va = free_space_violations(after, transform_points(T_after_current, current))
    moving = vb & va
    idx = np.flatnonzero(moving)
    for sweep, T in ((before, T_before_current), (after, T_after_current)):
        if idx.size and len(sweep):
            d, _ = cKDTree(transform_points(np.linalg.inv(T), sweep)).query(current[idx], distance_upper_bound=still)
            idx = idx[~np.isfinite(d)]
    moving = np.zeros(len(current), bool)
    moving[idx] = True
    return jb & ja, moving


def parallax_bleed(earlier: np.ndarray, later: np.ndarray, margin: float = FREE_MARGIN_M, near_m: float = BLEED_NEAR_M,
                   above: float = FREE_ABOVE_M, az_res: float = FREE_AZ_DEG, el_res: float = FREE_EL_DEG,
                   el_range=FREE_EL_DEG_RANGE) -> tuple[int, int]:
    """Near surfaces in front of what an earlier sweep saw. ``later`` is a sweep in its own
    sensor frame, ``earlier`` an earlier sweep registered into that frame. A bin of the later
    sweep's range image (``az_res`` x ``el_res`` degrees) is judged when its nearest return is
    within ``near_m`` horizontally and its z above ``above``; it bleeds when an earlier point in
    the same bin lies ``margin`` or more behind that return: background the earlier sensor saw
    past the surface's edge. A forecast that answers a ray with the past point nearest in
    angle, with no occlusion (4D-Occ's ray casting), can read such a point as the depth.
    Returns (bleeding bins, judged bins)."""
    n_az = int(round(360 / az_res))
    n_el = int(round((el_range[1] - el_range[0]) / el_res))
    ia, ie, ok = range_image_bins(later, az_res, el_res, el_range)
    r = np.linalg.norm(later, axis=1)
    first = np.full(n_az * n_el, np.inf)  # each bin's nearest return: its range, and whether it is judged
    near = np.zeros(n_az * n_el, bool)
    by_far = np.flatnonzero(ok)[np.argsort(-r[ok], kind="stable")]  # the last write of a bin is its nearest
    cell = ia[by_far] * n_el + ie[by_far]
    first[cell] = r[by_far]
    near[cell] = (np.linalg.norm(later[by_far, :2], axis=1) < near_m) & (later[by_far, 2] > above)
    ea, ee, eok = range_image_bins(earlier, az_res, el_res, el_range)
    ecell = ea * n_el + ee
    behind = eok & near[ecell] & (np.linalg.norm(earlier, axis=1) >= first[ecell] + margin)
    return int(len(np.unique(ecell[behind]))), int(near.sum())


def ground_height_pairs(earlier: np.ndarray, later: np.ndarray, later_origin: np.ndarray,
                        below: float = DRIFT_BELOW_M, ranges=DRIFT_RANGE_M, earlier_range: float = DRIFT_EARLIER_M,
                        radius: float = DRIFT_RADIUS_M, min_points: int = DRIFT_MIN,
                        flat: float = DRIFT_FLAT_M) -> tuple[np.ndarray, np.ndarray]:
    """The same ground seen by two sweeps: (r_earlier - r_later, z_later - z_earlier) per judged point.

    ``earlier`` in its own sensor frame; ``later`` registered into it by the poses, its sensor
    at ``later_origin``; ``later`` points are judged where they were ground in their own sweep
    (z below ``below`` relative to ``later_origin``, range within ``ranges`` of it). Each takes
    the mean height of the earlier sweep's ground points (z below ``below``, within
    ``earlier_range`` horizontally) within ``radius`` of it horizontally, where there are at
    least ``min_points`` of them spanning at most ``flat`` in z. A sensor whose beams point
    off their nominal elevations places the ground lower (or higher) the farther it is, so the
    height difference grows with the range difference; stored poses that drift apart from the
    scans shift it by the same amount everywhere (``fit_ground_drift``)."""
    from scipy.spatial import cKDTree

    e = earlier[(earlier[:, 2] < below) & (np.hypot(earlier[:, 0], earlier[:, 1]) < earlier_range)]
    rel = later - later_origin
    r_later = np.linalg.norm(rel, axis=1)
    q = later[(rel[:, 2] < below) & (r_later >= ranges[0]) & (r_later < ranges[1])]
    if len(e) < min_points or not len(q):
        return np.zeros(0), np.zeros(0)
    tree, k = cKDTree(e[:, :2]), min(32, len(e))
    while True:  # every earlier point within the radius: more neighbours while any query gets k of them
        dist, idx = tree.query(q[:, :2], k=k, distance_upper_bound=radius)
        dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
        if k == len(e) or not np.isfinite(dist[:, -1]).any():
            break
        k = min(4 * k, len(e))
    near = np.isfinite(dist)
    count = near.sum(axis=1)
    enough = count >= min_points
    z = e[np.minimum(idx[enough], len(e) - 1), 2]
    m = near[enough]
    span = np.where(m, z, -np.inf).max(axis=1) - np.where(m, z, np.inf).min(axis=1)
    ok = span <= flat
    z_mean = np.where(m, z, 0.0).sum(axis=1)[ok] / count[enough][ok]
    q = q[enough][ok]
    dr = np.linalg.norm(q, axis=1) - np.linalg.norm(q - later_origin, axis=1)
    return dr, q[:, 2] - z_mean


def far_views_closing(earlier: np.ndarray, later: np.ndarray, later_origin: np.ndarray, far_m: float = FAR_M,
                      gone_m: float = FAR_GONE_M, above: float = DRIFT_BELOW_M, roi=None) -> tuple[int, int, int]:
    """Far structure a later sweep no longer sees: (closed, judged, in the ROI) points of ``earlier``.

    ``earlier`` in its own sensor frame; ``later`` registered into it by the poses, its sensor
    at ``later_origin``. The points of ``earlier`` inside the protocol's ROI box (``roi``;
    default the active protocol's) count; of those, the ones ``far_m`` or more horizontally
    from ``later_origin`` and with z above ``above`` (off the ground near the car) are judged,
    and one closes when no point of ``later`` lies within ``gone_m`` of it: a view down a
    street or through a gap that the later position no longer has. Copying the earlier sweep
    keeps such points, and so does a forecast that answers rays with past points (4D-Occ's);
    near-field Chamfer charges them their whole distance to what the later sweep sees."""
    from scipy.spatial import cKDTree

    if roi is None:
        from pcfbench.protocol import ROI as roi
    in_roi = roi.contains(earlier)
    judged = in_roi & (np.hypot(earlier[:, 0] - later_origin[0], earlier[:, 1] - later_origin[1]) >= far_m) \
        & (earlier[:, 2] > above)
    if not judged.any():
        return 0, 0, int(in_roi.sum())
    if not len(later):
        return int(judged.sum()), int(judged.sum()), int(in_roi.sum())
    d = cKDTree(later).query(earlier[judged], distance_upper_bound=gone_m)[0]
    return int(np.isinf(d).sum()), int(judged.sum()), int(in_roi.sum())


def fit_ground_drift(dr: np.ndarray, dz: np.ndarray, outlier: float = DRIFT_OUTLIER_M) -> tuple[float, float]:
    """Least-squares ``dz = slope * dr + drift`` over the pairs with |dz| <= ``outlier``:
    (slope in degrees, the elevation error's effect; drift in metres, the height the later
    sweep's ground stands above the earlier one's where both saw it from the same range).
    NaNs without pairs."""
    keep = np.abs(dz) <= outlier
    if keep.sum() < 2:
        return float("nan"), float("nan")
    A = np.stack([dr[keep], np.ones(int(keep.sum()))], axis=1)
    (slope, drift), *_ = np.linalg.lstsq(A, dz[keep], rcond=None)
    return float(np.degrees(np.arctan(slope))), float(drift)


def mixed_pixel_share(points: np.ndarray, edges: np.ndarray, columns: float, jump: float = JUMP_M,
                      between: float = BETWEEN_M) -> tuple[int, int]:
    """Mixed pixels at depth jumps, in one sweep: (jumps with a return in between, jumps).

    Returns are placed in a range image: the beam by ``edges`` (elevation bins), the column by
    azimuth in ``columns`` columns per revolution, the nearest return where a cell has several.
    Along each beam, every three consecutive filled columns (a, b, c; the beam wraps) whose
    outer two differ in range by more than ``jump`` are a jump; it has a return in between when
    b's range is more than ``between`` from both a's and c's and lies between them: a return
    from neither surface, as when the beam's footprint straddles the edge."""
    n_col = max(int(round(columns)), 3)
    beam = np.searchsorted(edges, elevation_deg(points), side="right") - 1
    ok = (beam >= 0) & (beam < len(edges) - 1)
    col = np.floor((azimuth_deg(points[ok]) + 180.0) / (360.0 / n_col)).astype(np.int64) % n_col
    img = np.full((len(edges) - 1, n_col), np.inf)
    np.minimum.at(img, (beam[ok], col), np.linalg.norm(points[ok], axis=1))
    a, b, c = np.roll(img, 1, axis=1), img, np.roll(img, -1, axis=1)
    filled = np.isfinite(a) & np.isfinite(b) & np.isfinite(c)
    lo, hi = np.minimum(a, c), np.maximum(a, c)
    gap = np.zeros_like(img)
    gap[filled] = hi[filled] - lo[filled]  # empty cells are inf
    jumps = gap > jump
    inside = jumps & (b > lo + between) & (b < hi - between)
    return int(inside.sum()), int(jumps.sum())


def voxel_thin(points: np.ndarray, voxel: float = VOXEL_M) -> np.ndarray:
    """One point (the first) per ``voxel`` cube."""
    if not len(points):
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def plane_residuals(queries: np.ndarray, cloud: np.ndarray, exclude_self: bool,
                    k: int = NEIGHBOURS, radius: float = RADIUS_M, min_neighbours: int = MIN_NEIGHBOURS,
                    planarity: float = 0.1, normals: bool = False) -> tuple[np.ndarray, ...]:
    """Per query point: (distance of the query to its neighbours' plane, RMS distance of the
    neighbours to that plane), NaN where fewer than ``min_neighbours`` lie within ``radius``
    or the neighbourhood is a line (second eigenvalue below ``planarity`` x the largest).
    With ``normals``, a third array: the plane normal's |z| (1: level ground, 0: a wall)."""
    queries = np.asarray(queries, np.float64)
    cloud = np.asarray(cloud, np.float64)
    out_q = np.full(len(queries), np.nan)
    out_rms = np.full(len(queries), np.nan)
    out_nz = np.full(len(queries), np.nan)
    done = (out_q, out_rms, out_nz) if normals else (out_q, out_rms)
    if len(cloud) < min_neighbours or not len(queries):
        return done
    kk = min(k + int(exclude_self), len(cloud))
    d, idx = cKDTree(cloud).query(queries, k=kk, distance_upper_bound=radius)
    if exclude_self:
        d, idx = d[:, 1:], idx[:, 1:]
    ok = np.isfinite(d)
    n = ok.sum(1)
    use = n >= min_neighbours
    if not use.any():
        return done
    d, idx, ok, n = d[use], idx[use], ok[use], n[use]
    nb = cloud[np.where(ok, idx, 0)]  # (Q, k, 3); masked entries weigh zero
    w = ok[..., None].astype(float)
    mean = (nb * w).sum(1) / n[:, None]
    c = (nb - mean[:, None]) * w
    cov = np.einsum("qki,qkj->qij", c, c) / n[:, None, None]
    evals, evecs = np.linalg.eigh(cov)  # ascending
    normal = evecs[:, :, 0]
    flat = evals[:, 1] >= planarity * np.maximum(evals[:, 2], 1e-12)
    rq = np.abs(np.sum((queries[use] - mean) * normal, axis=1))
    rms = np.sqrt(np.maximum(evals[:, 0], 0.0))
    out_q[np.nonzero(use)[0][flat]] = rq[flat]
    out_rms[np.nonzero(use)[0][flat]] = rms[flat]
    out_nz[np.nonzero(use)[0][flat]] = np.abs(normal[flat, 2])
    return done


def kendall_tau(a, b) -> float:
    """Kendall's tau-a of two score lists over the same items (ties count zero)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    n = len(a)
    if n < 2 or len(b) != n:
        raise PcfbenchError(f"kendall_tau needs two equally long lists of at least 2 scores, got {len(a)} and {len(b)}")
    s = 0.0
    for i in range(n):
        for j in range(i + 1, n):
            s += np.sign(a[i] - a[j]) * np.sign(b[i] - b[j])
    return float(s / (n * (n - 1) / 2))


TAU_BAR = 0.8  # the agreement issue 16 asks for
BOOTSTRAP_DRAWS = 2000
BOOTSTRAP_BLOCK = 10  # samples per block: kitti-1s samples one sweep apart share 9 of their 10 sweeps


def kendall_tau_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`kendall_tau` of each row of ``a`` (D, M) against the same row of ``b`` (D, M)
    (or against ``b`` (M,) for every row)."""
    a = np.atleast_2d(np.asarray(a, float))
    b = np.broadcast_to(np.asarray(b, float), a.shape)
    i, j = np.triu_indices(a.shape[1], 1)
    return (np.sign(a[:, i] - a[:, j]) * np.sign(b[:, i] - b[:, j])).sum(1) / len(i)


def block_bootstrap_indices(n: int, draws: int, block: int, rng: np.random.Generator) -> np.ndarray:
    """(draws, n) sample indices of a moving-block bootstrap: blocks of ``block`` consecutive
    samples starting anywhere, joined until there are ``n`` (a block longer than the series is
    the whole series)."""
    block = max(1, min(block, n))
    per = -(-n // block)
    starts = rng.integers(0, n - block + 1, (draws, per))
    return (starts[:, :, None] + np.arange(block)).reshape(draws, per * block)[:, :n]


def tau_bootstrap(real: np.ndarray, synthetic: np.ndarray, draws: int = BOOTSTRAP_DRAWS, block: int = BOOTSTRAP_BLOCK,
                  seed: int = 0) -> dict:
    """How much a Kendall tau between two rankings of M methods can be trusted, from per-sample
    scores ``real`` (Nr, M) and ``synthetic`` (Ns, M), rows in drive order (NaN rows skipped).

    Each draw redraws both sides' samples by :func:`block_bootstrap_indices` and ranks the
    methods by their means. Returns the tau of the full means, its 95 % interval over the
    draws, the share of draws with tau >= :data:`TAU_BAR`, and the real ranking against itself
    (a redraw of the real samples against all of them): if that rarely reaches the bar, the
    real ranking is a near-tie that 0.8 cannot be asked of."""
    real = np.asarray(real, float)
    synthetic = np.asarray(synthetic, float)
    real = real[np.isfinite(real).all(1)]
    synthetic = synthetic[np.isfinite(synthetic).all(1)]
    if len(real) < 2 or len(synthetic) < 2:
        raise PcfbenchError(f"tau_bootstrap needs at least 2 complete samples a side, got {len(real)} real and "
                            f"{len(synthetic)} synthetic")
    rng = np.random.default_rng(seed)
    r_draw = real[block_bootstrap_indices(len(real), draws, block, rng)].mean(1)  # (draws, M)
    s_draw = synthetic[block_bootstrap_indices(len(synthetic), draws, block, rng)].mean(1)
    taus = kendall_tau_rows(r_draw, s_draw)
    self_taus = kendall_tau_rows(r_draw, real.mean(0))
    return {"tau": float(kendall_tau(real.mean(0), synthetic.mean(0))),
            "interval": [float(np.quantile(taus, 0.025)), float(np.quantile(taus, 0.975))],
            "share_at_bar": float(np.mean(taus >= TAU_BAR - 1e-9)),
            "real_self_median": float(np.median(self_taus)),
            "real_self_share_at_bar": float(np.mean(self_taus >= TAU_BAR - 1e-9)),
            "draws": draws, "block": block, "samples": [len(real), len(synthetic)]}


# --- reading a dataset -------------------------------------------------------------------------

@dataclass
class SideStats:
    """Everything the report says about one dataset."""

    label: str
    sweeps: int = 0
    points: list = field(default_factory=list)
    beam_counts: np.ndarray | None = None  # (beams,) summed over sweeps
    range_hist: np.ndarray | None = None
    elev_hist: np.ndarray | None = None
    az_hist: np.ndarray | None = None
    coverage: list = field(default_factory=list)
    elev_span: tuple[float, float] = (np.nan, np.nan)
    static_residual: list = field(default_factory=list)
    roughness: list = field(default_factory=list)
    normal_z: list = field(default_factory=list)  # |z| of each roughness plane's normal
    moving: list = field(default_factory=list)  # (moving points, labelled points) per sweep
    free_space: list = field(default_factory=list)  # (violating, judged) later points per sweep pair
    free_space_moving: list = field(default_factory=list)  # (violating on labelled moving objects, violating)
    moving_evidence: list = field(default_factory=list)  # (moving evidence, judged) points per sweep
    evidence_on_moving: list = field(default_factory=list)  # (evidence on labelled moving objects, evidence)
    moving_caught: list = field(default_factory=list)  # (labelled moving points with evidence, judged labelled moving)
    bleed: list = field(default_factory=list)  # (bleeding, judged) near bins of the later sweep per sweep pair
    mixed: list = field(default_factory=list)  # (jumps with a return in between, jumps) per sweep
    ground_pairs: list = field(default_factory=list)  # (r_i - r_j, z_j - z_i) arrays per sweep pair DRIFT_GAP_S apart
    far_views: list = field(default_factory=list)  # (closed, judged, in the ROI) per sweep pair DRIFT_GAP_S apart
    seconds: float = 0.0

    @property
    def evidence_sweeps(self) -> int:
        """How many sweeps the moving evidence read."""
        return len(self.moving_evidence)

    def summary(self, edges: np.ndarray) -> dict:
        beams = self.beam_counts / max(self.sweeps, 1)
        drop, columns = drop_per_beam(beams)
        sr = np.concatenate(self.static_residual) if self.static_residual else np.zeros(0)
        ro = np.concatenate(self.roughness) if self.roughness else np.zeros(0)
        nz = np.concatenate(self.normal_z) if self.normal_z else np.zeros(0)
        level, wall = nz > LEVEL_NZ, nz < WALL_NZ
        if self.ground_pairs:
            slope, drift = fit_ground_drift(*(np.concatenate(x) for x in zip(*self.ground_pairs)))
        else:
            slope, drift = float("nan"), float("nan")

        def median(x):
            return float(np.median(x)) if x.size else float("nan")
        return {
            "points per sweep": float(np.mean(self.points)),
            "returns per beam (median)": float(np.median(beams)),
            "columns per beam (estimated)": columns,
            "ray drop (mean over beams)": float(np.mean(drop)),
            "coverage (1x0.5 deg cells)": float(np.mean(self.coverage)),
            "elevation span low (deg)": self.elev_span[0],
            "elevation span high (deg)": self.elev_span[1],
            "median range (m)": _hist_median(self.range_hist, RANGE_EDGES),
            "static-scene residual median (m)": float(np.median(sr)) if sr.size else float("nan"),
            "static-scene residual p90 (m)": float(np.quantile(sr, 0.9)) if sr.size else float("nan"),
            "roughness median (m)": float(np.median(ro)) if ro.size else float("nan"),
            "roughness p90 (m)": float(np.quantile(ro, 0.9)) if ro.size else float("nan"),
            "level surfaces (share of planes)": float(level.mean()) if nz.size else float("nan"),
            "vertical surfaces (share of planes)": float(wall.mean()) if nz.size else float("nan"),
            "roughness median, level surfaces (m)": median(ro[level]),
            "roughness median, vertical surfaces (m)": median(ro[wall]),
            "moving-object points (fraction)": _share(self.moving),
            f"free-space violations at {MOVING_GAP_S:g} s (fraction)": _share(self.free_space),
            "free-space violations on labelled moving objects (share)": _share(self.free_space_moving),
            f"moving evidence: points in space seen empty {MOVING_GAP_S:g} s before and after, no return near "
            "them then (fraction)": _share(self.moving_evidence),
            "moving evidence on labelled moving objects (share)": _share(self.evidence_on_moving),
            "labelled moving points with moving evidence (share)": _share(self.moving_caught),
            f"parallax: near above-ground bins with a return {MOVING_GAP_S:g} s earlier behind them (share)":
                _share(self.bleed),
            "near above-ground range-image bins per sweep": (float(np.mean([b for _, b in self.bleed]))
                                                             if self.bleed else float("nan")),
            "mixed pixels: depth jumps with a return in between (share)": _share(self.mixed),
            f"ground drift: height of the ground seen {DRIFT_GAP_S:g} s later at the same range (m)": drift,
            "ground drop with range: elevation error (deg)": slope,
            f"far views: points {FAR_M:g} m or more from the sensor {DRIFT_GAP_S:g} s later, off the ground "
            "(share of the ROI's points)": _share([(j, n) for _, j, n in self.far_views]),
            f"far views that close: far points with no return {DRIFT_GAP_S:g} s later within {FAR_GONE_M:g} m "
            "(share)": _share([(c, j) for c, j, _ in self.far_views]),
        }


def _share(pairs: list) -> float:
    """sum of parts / sum of wholes over (part, whole) pairs; NaN when there is no whole (unknown, not 0)."""
    whole = sum(b for _, b in pairs)
    return sum(a for a, _ in pairs) / whole if whole else float("nan")


def _hist_median(h, edges) -> float:
    c = np.cumsum(h) / max(np.sum(h), 1)
    i = int(np.searchsorted(c, 0.5))
    return float(edges[min(i + 1, len(edges) - 1)])


def _moving_mask(adapter, seq_name: str, index: int, n: int) -> np.ndarray | None:
    """Per point: on a moving object? None where the dataset has no labels."""
    root = getattr(adapter, "root", None)
    if root is None:
        return None
    path = Path(root) / "sequences" / seq_name / "labels" / f"{index:06d}.label"
    if not path.is_file():
        return None
    lab = np.fromfile(path, dtype=np.uint32) & 0xFFFF
    if len(lab) != n:
        raise PcfbenchError(f"{path}: {len(lab)} labels for {n} points (expected one uint32 per point)")
    from pcfbench.datasets.synthetic.adapter import SyntheticKitti
    from pcfbench.datasets.synthetic.world import MOVING_CLASSES

    if isinstance(adapter, SyntheticKitti):
        return np.isin(lab, MOVING_CLASSES)
    return lab >= SEMANTIC_KITTI_MOVING


def split_list(split) -> tuple[str, ...]:
    """``"test"`` or ``"train,val,test"`` (or a sequence of names) -> the split names, checked:
    none empty, none twice (its samples would count twice)."""
    parts = tuple(p.strip() for p in split.split(",")) if isinstance(split, str) else tuple(split)
    if not parts or not all(parts):
        raise PcfbenchError(f"split {split!r}: expected NAME or NAME,NAME,...")
    if len(set(parts)) != len(parts):
        raise PcfbenchError(f"split {split!r} names a split twice: its samples would count twice")
    return parts


def pick_sweeps(adapter, split, count: int) -> list[tuple[str, int]]:
    """``count`` (sequence, index) pairs spread evenly over the split, or over several splits'
    sequences in turn (each pair has a next sweep)."""
    pairs = []
    for sp in split_list(split):
        for name in adapter.sequence_names(sp):
            n = len(adapter.sequence(name))
            pairs += [(name, i) for i in range(n - 1)]
    if not pairs:
        raise PcfbenchError(f"dataset {adapter.name} split {split!r} has no two consecutive sweeps to compare")
    take = np.unique(np.linspace(0, len(pairs) - 1, min(count, len(pairs))).round().astype(int))
    return [pairs[i] for i in take]


def _sweep_at(ts: np.ndarray, i: int, gap_s: float) -> int | None:
    """The sweep nearest ``gap_s`` after sweep ``i`` (timestamps ``ts``, ns; ``gap_s`` < 0:
    before it), if within 10 % of ``|gap_s|`` of it."""
    side = np.arange(i + 1, len(ts)) if gap_s > 0 else np.arange(i)
    if not side.size:
        return None
    j = int(side[np.argmin(np.abs(ts[side] - ts[i] - gap_s * 1e9))])
    return j if abs(ts[j] - ts[i] - gap_s * 1e9) <= 0.1 * abs(gap_s) * 1e9 else None


def evidence_sweeps(adapter, split) -> list[tuple[str, int]]:
    """(sequence, index) of the sweeps the moving evidence reads: in each sequence of the
    split(s), the first sweep with one ``MOVING_GAP_S`` before it, then each sweep
    ``MOVING_GAP_S`` after the last chosen, while it has one ``MOVING_GAP_S`` after it."""
    out = []
    for sp in split_list(split):
        for name in adapter.sequence_names(sp):
            ts = adapter.sequence(name).timestamps_ns
            i = _sweep_at(ts, 0, MOVING_GAP_S)
            while i is not None and _sweep_at(ts, i, MOVING_GAP_S) is not None:
                out.append((name, i))
                i = _sweep_at(ts, i, MOVING_GAP_S)
    return out


def _kept(adapter, raw: np.ndarray) -> np.ndarray:
    """(N,) bool: the points of a sweep the statistics read, outside the ego box and beyond the
    protocol's minimum range."""
    from pcfbench.protocol import MIN_RANGE_M

    return ~adapter.ego_box.inside(raw) & (np.linalg.norm(raw, axis=1) > MIN_RANGE_M)


def sweep_moving_evidence(adapter, seq, i: int, points: np.ndarray | None = None):
    """:func:`moving_evidence` of sweep ``i`` of ``seq`` (an ``adapter`` sequence) against the
    sweeps ``MOVING_GAP_S`` before and after it: (judged, moving) over ``points`` (sweep i
    without the ego box and the points nearer than the protocol's minimum range; read when not
    given), or None when the sequence has no such sweeps."""
    ts, W = seq.timestamps_ns, seq.T_world_sensor
    k, j = _sweep_at(ts, i, -MOVING_GAP_S), _sweep_at(ts, i, MOVING_GAP_S)
    if k is None or j is None:
        return None
    if points is None:
        raw = np.asarray(seq.load_points(i), np.float64)
        points = raw[_kept(adapter, raw)]

    def load(n):
        p = np.asarray(seq.load_points(n), np.float64)
        return p[~adapter.ego_box.inside(p)]
    return moving_evidence(points, load(k), np.linalg.inv(W[k]) @ W[i], load(j), np.linalg.inv(W[j]) @ W[i])


def measure(adapter, split: str, count: int, label: str, edges: np.ndarray, seed: int = 0,
            progress: bool = False) -> SideStats:
    """Read ``count`` sweeps (and each one's successor) of ``adapter`` and gather the statistics
    (a progress bar over them and the moving evidence's sweeps when ``progress``: on a long real
    split the evidence alone reads thousands, about 0.2 s each on a 2-core machine)."""
    from tqdm import tqdm

    from pcfbench.geometry import transform_points

    t0 = time.perf_counter()
    picked, evidence = pick_sweeps(adapter, split, count), evidence_sweeps(adapter, split)
    bar = tqdm(total=len(picked) + len(evidence), desc=f"statistics {label}", unit="sweep", leave=True,
               dynamic_ncols=True, file=sys.stderr, disable=not progress or None)
    rng = np.random.default_rng(seed)
    st = SideStats(label)
    st.beam_counts = np.zeros(len(edges) - 1)
    st.range_hist = np.zeros(len(RANGE_EDGES) - 1)
    st.elev_hist = np.zeros(len(ELEV_EDGES) - 1)
    st.az_hist = np.zeros(180)
    lows, highs = [], []
    seqs = {}
    for name, i in picked:
        bar.update(1)
        seq = seqs.setdefault(name, adapter.sequence(name))
        raw = np.asarray(seq.load_points(i), np.float64)
        keep = _kept(adapter, raw)
        pts = raw[keep]
        st.sweeps += 1
        st.points.append(len(pts))
        per_beam = returns_per_beam(pts, edges)
        st.beam_counts += per_beam
        st.mixed.append(mixed_pixel_share(pts, edges, drop_per_beam(per_beam)[1]))
        r = np.linalg.norm(pts, axis=1)
        st.range_hist += np.histogram(r, bins=RANGE_EDGES)[0]
        el = elevation_deg(pts)
        st.elev_hist += np.histogram(el, bins=ELEV_EDGES)[0]
        st.az_hist += np.histogram(azimuth_deg(pts), bins=180, range=(-180, 180))[0]
        st.coverage.append(coverage(pts))
        lows.append(np.quantile(el, 0.001))
        highs.append(np.quantile(el, 0.999))
        mask = _moving_mask(adapter, name, i, len(raw))
        if mask is not None:
            st.moving.append((int(mask[keep].sum()), int(keep.sum())))
        # planes: thinned clouds, queries 3-20 m
        near = (r > PLANE_RANGE_M[0]) & (r < PLANE_RANGE_M[1])
        thin = voxel_thin(pts)
        q = pts[near]
        if len(q) > QUERIES:
            q = q[rng.choice(len(q), QUERIES, replace=False)]
        _, rms, nz = plane_residuals(q, thin, exclude_self=True, normals=True)
        st.roughness.append(rms[np.isfinite(rms)])
        st.normal_z.append(nz[np.isfinite(nz)])
        nxt = np.asarray(seq.load_points(i + 1), np.float64)
        nxt = nxt[~adapter.ego_box.inside(nxt)]
        rn = np.linalg.norm(nxt, axis=1)
        qn = nxt[(rn > PLANE_RANGE_M[0]) & (rn < PLANE_RANGE_M[1])]
        if len(qn) > QUERIES:
            qn = qn[rng.choice(len(qn), QUERIES, replace=False)]
        T = np.linalg.inv(seq.T_world_sensor[i]) @ seq.T_world_sensor[i + 1]
        res, _ = plane_residuals(transform_points(T, qn), thin, exclude_self=False)
        st.static_residual.append(res[np.isfinite(res)])
        # free space: the sweep MOVING_GAP_S later (when the sequence has it)
        ts = seq.timestamps_ns
        j = _sweep_at(ts, i, MOVING_GAP_S)
        if j is not None:
            later_raw = np.asarray(seq.load_points(j), np.float64)
            keep_later = ~adapter.ego_box.inside(later_raw)
            T = np.linalg.inv(seq.T_world_sensor[i]) @ seq.T_world_sensor[j]
            judged, viol = free_space_violations(pts, transform_points(T, later_raw[keep_later]))
            st.free_space.append((int(viol.sum()), int(judged.sum())))
            st.bleed.append(parallax_bleed(transform_points(np.linalg.inv(T), pts), later_raw[keep_later]))
            later_moving = _moving_mask(adapter, name, j, len(later_raw))
            if later_moving is not None:
                st.free_space_moving.append((int((viol & later_moving[keep_later]).sum()), int(viol.sum())))
        # ground drift: the sweep DRIFT_GAP_S later
        j = _sweep_at(ts, i, DRIFT_GAP_S)
        if j is not None:
            later_raw = np.asarray(seq.load_points(j), np.float64)
            T = np.linalg.inv(seq.T_world_sensor[i]) @ seq.T_world_sensor[j]
            later = transform_points(T, later_raw[~adapter.ego_box.inside(later_raw)])
            st.ground_pairs.append(ground_height_pairs(pts, later, T[:3, 3]))
            st.far_views.append(far_views_closing(pts, later, T[:3, 3]))
    # moving evidence: not the sweeps above (one passing car sets a dozen's), but every sweep
    # MOVING_GAP_S apart over the whole split, each against the sweeps that far before and after
    for name, i in evidence:
        bar.update(1)
        seq = seqs.setdefault(name, adapter.sequence(name))
        raw = np.asarray(seq.load_points(i), np.float64)
        keep = _kept(adapter, raw)
        judged, moving = sweep_moving_evidence(adapter, seq, i, raw[keep])
        st.moving_evidence.append((int(moving.sum()), int(judged.sum())))
        mask = _moving_mask(adapter, name, i, len(raw))
        if mask is not None:
            m = mask[keep]
            st.evidence_on_moving.append((int((moving & m).sum()), int(moving.sum())))
            st.moving_caught.append((int((moving & m).sum()), int((judged & m).sum())))
    bar.close()
    st.elev_span = (float(np.median(lows)), float(np.median(highs)))
    st.seconds = time.perf_counter() - t0
    return st


# --- the baselines -----------------------------------------------------------------------------

def baseline_means(dataset: str, root: str, split, setting: str, store: Path, limit: int | None,
                   methods=BASELINES, metrics=RANK_METRICS, progress: bool = False, threads: int | None = None,
                   policy: str = "full-context") -> dict:
    """method -> {metric: flat mean over (sample, future sweep), "per_sample": {"sample_id": [...],
    metric: [...]}} (each sample's mean over its future sweeps, in drive order, sequence by
    sequence), "per_sequence": {sequence: {"samples": n, metric: flat mean, "rows": {metric: n}}}};
    cells run (or resumed) in ``store``. ``split`` may name several splits (``"train,val,test"``):
    one cell each (``limit`` samples each), pooled so that every (sample, future sweep) weighs
    the same. ``policy`` is the protocol's sample policy of the cells (``every-third``,
    ``subsample-500``: samples spread over a long split, where ``limit`` takes its first ones)."""
    out = {}
    for m in methods:
        t0 = time.perf_counter()
        ok, samples = baseline_rows(dataset, root, split, setting, store, limit, m, progress, threads, policy)
        row = {k: float(np.nanmean(ok[k].to_numpy(float))) for k in metrics}
        by = ok.groupby(["sequence", "ref_index"], sort=True)
        row["per_sample"] = {"sample_id": by["sample_id"].first().tolist(),
                             **{k: by[k].mean().astype(float).tolist() for k in metrics}}
        row["per_sequence"] = {
            str(seq): {"samples": int(g["sample_id"].nunique()),
                       **{k: float(np.nanmean(g[k].to_numpy(float))) for k in metrics},
                       "rows": {k: int(np.isfinite(g[k].to_numpy(float)).sum()) for k in metrics}}
            for seq, g in ok.groupby("sequence", sort=True)}
        row["samples"] = samples
        row["seconds"] = time.perf_counter() - t0
        out[m] = row
    return out


def baseline_rows(dataset: str, root: str, split, setting: str, store: Path, limit: int | None, method: str,
                  progress: bool = False, threads: int | None = None, policy: str = "full-context"):
    """(the per-(sample, future sweep) rows of ``method`` whose status is ok, pooled over the
    splits ``split`` names, the samples evaluated): its cells run (or resumed) in ``store``."""
    import pandas as pd

    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.running.runner import RunOptions, default_metrics, run_cell
    from pcfbench.store.cells import Cell, CellSpec

    plugins = get_plugins()
    spec_m = resolve_method(method, plugins)
    frames, samples = [], 0
    for sp in split_list(split):
        spec = CellSpec(spec_m.name, dict(spec_m.raw), spec_m.options_hash, dataset, root, sp, setting,
                        policy, limit, default_metrics(plugins))
        samples += run_cell(spec, store, RunOptions(progress=progress, threads=threads), plugins=plugins).samples
        frames.append(Cell(store, spec).read_rows())
    df = pd.concat(frames, ignore_index=True)
    return df[df["status"] == "ok"], samples


def sequence_rankings(base: dict, against: dict, metrics=RANK_METRICS) -> dict:
    """Each sequence of ``base`` (``baseline_means``' output) ranked on its own: {sequence:
    {metric: Kendall tau of its flat means against ``against``'s pooled flat means}}; the
    methods are ``against``'s."""
    methods = list(against)
    out = {}
    for seq in _ranked_sequences(base, methods, metrics):
        out[seq] = {k: kendall_tau([against[m][k] for m in methods], [base[m]["per_sequence"][seq][k] for m in methods])
                    for k in metrics}
    return out


def _ranked_sequences(base: dict, methods, metrics) -> list[str]:
    """The sequences where every method has a finite flat mean of every metric: elsewhere a
    missing or NaN score would count as a tie and lower a tau without a word."""
    seqs = sorted(set().union(*(base[m]["per_sequence"] for m in methods)))
    return [s for s in seqs if all(s in base[m]["per_sequence"]
                                   and all(np.isfinite(base[m]["per_sequence"][s][k]) for k in metrics) for m in methods)]


def between_sequences(base: dict, metrics=RANK_METRICS) -> dict:
    """How far a side's sequences agree with each other: {metric: {"mean": mean Kendall tau over
    every pair of sequences, "lowest": the lowest, "pairs": how many}}; empty with fewer than
    two sequences. A low mean says the ranking belongs to the scene, not to the dataset."""
    methods = list(base)
    seqs = _ranked_sequences(base, methods, metrics)
    if len(seqs) < 2:
        return {}
    out = {}
    for k in metrics:
        means = {s: [base[m]["per_sequence"][s][k] for m in methods] for s in seqs}
        taus = [kendall_tau(means[a], means[b]) for i, a in enumerate(seqs) for b in seqs[i + 1:]]
        out[k] = {"mean": float(np.mean(taus)), "lowest": float(min(taus)), "pairs": len(taus)}
    return out


# --- the report --------------------------------------------------------------------------------

def _ratio(a: float, b: float) -> float:
    return a / b if b and np.isfinite(a) and np.isfinite(b) else float("nan")


def _fmt(x) -> str:
    if isinstance(x, str):
        return x
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return f"{x:.4g}" if abs(x) < 1000 else f"{x:.0f}"


def _score_matrix(base: dict, metric: str) -> np.ndarray:
    """(samples, methods) per-sample scores of ``metric``, on the samples every method has, in
    drive order (``baseline_means``' ``per_sample``)."""
    ids = [base[m]["per_sample"]["sample_id"] for m in base]
    common = set(ids[0]).intersection(*ids[1:])
    order = [i for i in ids[0] if i in common]
    cols = []
    for m in base:
        ps = base[m]["per_sample"]
        at = dict(zip(ps["sample_id"], ps[metric]))
        cols.append([at[i] for i in order])
    return np.array(cols, float).T.reshape(len(order), len(base))


def pairs_phrase(n: int) -> str:
    return f"{n} pair" + ("" if n == 1 else "s")


def _samples_phrase(policy: str | None, limit: int | None) -> str:
    """How a side's samples were chosen, for the report: `` (every-third, the first 40 of each
    split)``; empty for every full-context sample."""
    said = [p for p in (policy if policy != "full-context" else None,
                        f"the first {limit} of each split" if limit else None) if p]
    return f" ({', '.join(said)})" if said else ""


def _several_sequences(base_syn: dict, base_real: dict) -> bool:
    return any(len(next(iter(b.values()))["per_sequence"]) > 1 for b in (base_syn, base_real))


def _at_col(head: list, value, col: int) -> list:
    """A csv row with ``value`` in column ``col`` (1 synthetic, 2 real) of the report's four."""
    row = head + ["", "", ""]
    row[col] = value
    return row


def _sequence_section(base_syn: dict, base_real: dict, by_seq: dict, agree: dict) -> list[str]:
    """realism.md's tables of each sequence's flat means and ranking, metric by metric."""
    methods = list(base_syn)
    lines = ["## Sequence by sequence", "",
             "Each sequence's flat means, and the Kendall tau of its ranking against the other side's "
             "(all its sequences pooled). Where a side's sequences disagree with each other, the ranking "
             "belongs to the scene, not to the dataset, and one sequence a side cannot set it.", ""]
    for k in RANK_METRICS:
        lines += [f"### {k}", "", "| side | sequence | samples | " + " | ".join(methods) + " | tau against the other side |",
                  "|---|---|---|" + "---|" * (len(methods) + 1)]
        for side, base, other in (("real", base_real, base_syn), ("synthetic", base_syn, base_real)):
            for seq, tk in by_seq[side].items():
                ps = [base[m]["per_sequence"][seq] for m in methods]
                lines.append(f"| {side} | {seq} | {ps[0]['samples']} | " + " | ".join(_fmt(p[k]) for p in ps)
                             + f" | {tk[k]:+.2f} |")
            n = len(by_seq[side])
            if n > 1:
                pooled = [base[m][k] for m in methods]
                lines.append(f"| {side} | all {n} pooled | {base[methods[0]]['samples']} | "
                             + " | ".join(_fmt(x) for x in pooled)
                             + f" | {kendall_tau([other[m][k] for m in methods], pooled):+.2f} |")
        said = [f"{side} mean tau {a[k]['mean']:+.2f} over {pairs_phrase(a[k]['pairs'])} (lowest {a[k]['lowest']:+.2f})"
                for side, a in agree.items() if a]
        lines += ["", "Sequences against each other: " + "; ".join(said) + ".", ""]
    return lines


def write_report(out: Path, syn: SideStats, real: SideStats, edges: np.ndarray, base_syn: dict | None,
                 base_real: dict | None, meta: dict) -> dict:
    """realism.md, realism.csv, realism.json and the figures under ``out``; returns the numbers."""
    out.mkdir(parents=True, exist_ok=True)
    s, r = syn.summary(edges), real.summary(edges)
    rows = [(k, s[k], r[k], _ratio(s[k], r[k])) for k in s]
    tv = histogram_distance(syn.range_hist, real.range_hist)
    emd = emd_1d(syn.range_hist, real.range_hist, RANGE_EDGES)
    tv_el = histogram_distance(syn.elev_hist, real.elev_hist)
    result = {"meta": meta, "synthetic": s, "real": r,
              "range histogram distance (TV)": tv, "range histogram EMD (m)": emd,
              "elevation histogram distance (TV)": tv_el}
    base_rows, taus, trust = [], {}, {}
    if base_syn and base_real:
        for m in base_syn:
            base_rows.append((m, *[(base_real[m][k], base_syn[m][k], _ratio(base_syn[m][k], base_real[m][k])) for k in RANK_METRICS]))
        for k in RANK_METRICS:
            taus[k] = kendall_tau([base_real[m][k] for m in base_syn], [base_syn[m][k] for m in base_syn])
        if min(len(_score_matrix(b, RANK_METRICS[0])) for b in (base_real, base_syn)) >= 2:  # else nothing to redraw
            trust = {k: tau_bootstrap(_score_matrix(base_real, k), _score_matrix(base_syn, k)) for k in RANK_METRICS}
        by_seq = {"synthetic": sequence_rankings(base_syn, base_real), "real": sequence_rankings(base_real, base_syn)}
        agree = {"synthetic": between_sequences(base_syn), "real": between_sequences(base_real)}
        result["baselines"] = {"synthetic": base_syn, "real": base_real, "kendall_tau": taus,
                               "kendall_tau_bootstrap": trust, "kendall_tau_per_sequence": by_seq,
                               "between_sequences": agree}
    with open(out / "realism.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["statistic", "synthetic", "real", "ratio_synthetic_over_real"])
        for k, a, b, q in rows:
            w.writerow([k, a, b, q])
        w.writerow(["range histogram distance (TV)", tv, "", ""])
        w.writerow(["range histogram EMD (m)", emd, "", ""])
        w.writerow(["elevation histogram distance (TV)", tv_el, "", ""])
        for m, *vals in base_rows:
            for k, (rv, sv, q) in zip(RANK_METRICS, vals):
                w.writerow([f"{m} {k}", sv, rv, q])
        for k, t in taus.items():
            w.writerow([f"kendall tau {k}", t, "", ""])
            b = trust.get(k)
            if b is None:
                continue
            w.writerow([f"kendall tau {k} 95% interval low", b["interval"][0], "", ""])
            w.writerow([f"kendall tau {k} 95% interval high", b["interval"][1], "", ""])
            w.writerow([f"kendall tau {k} share of draws >= {TAU_BAR}", b["share_at_bar"], "", ""])
            w.writerow([f"kendall tau {k} real against itself, share of draws >= {TAU_BAR}", "",
                        b["real_self_share_at_bar"], ""])
        if base_rows and _several_sequences(base_syn, base_real):
            for side, base, col in (("synthetic", base_syn, 1), ("real", base_real, 2)):
                for seq, tk in by_seq[side].items():
                    for k in RANK_METRICS:
                        for m in base_syn:
                            w.writerow(_at_col([f"{side} sequence {seq} {m} {k}"], base[m]["per_sequence"][seq][k], col))
                        w.writerow(_at_col([f"{side} sequence {seq} kendall tau {k}"], tk[k], col))
                for k, a in agree[side].items():
                    w.writerow(_at_col([f"{side} sequences against each other: mean kendall tau {k}"], a["mean"], col))
    (out / "realism.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    figures = _figures(out, syn, real, edges, base_syn, base_real)
    lines = [f"# Realism report: {meta['synthetic']} vs {meta['real']}", "",
             f"{syn.sweeps} synthetic sweeps ({meta['synthetic_split']}) and {real.sweeps} real sweeps "
             f"({meta['real_split']}), each with its successor (and the sweeps {MOVING_GAP_S:g} s and "
             f"{DRIFT_GAP_S:g} s later for the free-space test and the ground drift); the moving evidence reads "
             f"every sweep {MOVING_GAP_S:g} s apart over the whole split (synthetic {syn.evidence_sweeps}, real "
             f"{real.evidence_sweeps}). Ratios are synthetic / real.", "",
             "| statistic | synthetic | real | ratio |", "|---|---|---|---|"]
    lines += [f"| {k} | {_fmt(a)} | {_fmt(b)} | {_fmt(q)} |" for k, a, b, q in rows]
    lines += ["", f"Range histogram distance: total variation {tv:.3f} (0 same, 1 disjoint), "
                  f"earth mover's {emd:.2f} m. Elevation histogram total variation {tv_el:.3f}.", ""]
    if base_rows:
        lines += [f"## Baselines at {meta['setting']} (flat means)", "",
                  "| method | " + " | ".join(f"real {k} | synthetic {k} | ratio" for k in RANK_METRICS) + " |",
                  "|---|" + "---|---|---|" * len(RANK_METRICS)]
        for m, *vals in base_rows:
            lines.append(f"| {m} | " + " | ".join(f"{_fmt(a)} | {_fmt(b)} | {_fmt(q)}" for a, b, q in vals) + " |")
        lines += ["", "Kendall tau between the rankings: " + ", ".join(f"{k} {t:+.2f}" for k, t in taus.items()),
                  f"(samples: real {next(iter(base_real.values()))['samples']}"
                  f"{_samples_phrase(meta.get('real_policy'), meta.get('real_limit'))}, "
                  f"synthetic {next(iter(base_syn.values()))['samples']}"
                  f"{_samples_phrase(meta.get('policy'), meta.get('limit'))})", ""]
        b0 = next(iter(trust.values()), None)
        if b0 is None:
            lines += ["Too few samples on one side (fewer than 2) to say how far the taus can be trusted.", ""]
        else:
            lines += [f"How far each tau can be trusted ({b0['draws']} moving-block bootstrap draws of "
                  f"{b0['block']} consecutive samples, both sides redrawn; the real ranking against "
                  "itself: its samples redrawn, ranked against all of them):", "",
                  f"| metric | tau | 95 % interval | draws with tau >= {TAU_BAR} | real against itself: median tau "
                  f"| its draws >= {TAU_BAR} |", "|---|---|---|---|---|---|"]
            lines += [f"| {k} | {taus[k]:+.2f} | {b['interval'][0]:+.2f} .. {b['interval'][1]:+.2f} | "
                      f"{b['share_at_bar']:.0%} | {b['real_self_median']:+.2f} | {b['real_self_share_at_bar']:.0%} |"
                      for k, b in trust.items()]
            lines += [""]
        if _several_sequences(base_syn, base_real):
            lines += _sequence_section(base_syn, base_real, by_seq, agree)
    lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    (out / "realism.md").write_text("\n".join(lines))
    return result


def _figures(out: Path, syn: SideStats, real: SideStats, edges, base_syn, base_real) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []

    def save(fig, name):
        fig.tight_layout()
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        names.append(name)

    sides = ((syn, "synthetic", "tab:orange"), (real, "real", "tab:blue"))
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.bar([0, 1], [np.mean(syn.points), np.mean(real.points)], color=["tab:orange", "tab:blue"])
    ax.set_xticks([0, 1], ["synthetic", "real"])
    ax.set_ylabel("points per sweep")
    save(fig, "points_per_sweep.png")

    centres = (edges[1:] + edges[:-1]) / 2
    fig, axes = plt.subplots(1, 2, figsize=(9, 3))
    for st, lab, col in sides:
        beams = st.beam_counts / max(st.sweeps, 1)
        axes[0].plot(centres, beams, color=col, label=lab)
        axes[1].plot(centres, drop_per_beam(beams)[0], color=col, label=lab)
    axes[0].set(xlabel="beam elevation (deg)", ylabel="returns per beam per sweep")
    axes[1].set(xlabel="beam elevation (deg)", ylabel="columns without return (ray drop)")
    axes[0].legend()
    save(fig, "returns_per_beam_and_ray_drop.png")

    fig, ax = plt.subplots(figsize=(6, 3))
    for st, lab, col in sides:
        ax.stairs(st.range_hist / st.range_hist.sum(), RANGE_EDGES, color=col, label=lab)
    ax.set(xlabel="range (m)", ylabel="share of points", yscale="log")
    ax.legend()
    save(fig, "range_histogram.png")

    fig, axes = plt.subplots(1, 2, figsize=(9, 3))
    for st, lab, col in sides:
        axes[0].stairs(st.elev_hist / st.elev_hist.sum(), ELEV_EDGES, color=col, label=lab)
        axes[1].stairs(st.az_hist / st.az_hist.sum(), np.linspace(-180, 180, 181), color=col, label=lab)
    axes[0].set(xlabel="elevation (deg)", ylabel="share of points")
    axes[1].set(xlabel="azimuth (deg)", ylabel="share of points")
    axes[0].legend()
    save(fig, "elevation_azimuth_coverage.png")

    for attr, title, name in (("static_residual", "static-scene residual to the previous sweep's plane (m)", "static_residual.png"),
                              ("roughness", "local surface roughness: RMS to the local plane (m)", "roughness.png")):
        fig, ax = plt.subplots(figsize=(6, 3))
        for st, lab, col in sides:
            v = np.sort(np.concatenate(getattr(st, attr))) if getattr(st, attr) else np.zeros(0)
            if v.size:
                ax.plot(v, np.arange(1, v.size + 1) / v.size, color=col, label=lab)
        ax.set(xlabel=title, ylabel="cumulative share", xscale="log")
        ax.legend()
        save(fig, name)

    fig, axes = plt.subplots(1, 4, figsize=(16, 3))
    for x, (st, lab, col) in enumerate(sides):
        fs, mixed, bleed = _share(st.free_space), _share(st.mixed), _share(st.bleed)
        closing = _share([(c, j) for c, j, _ in st.far_views])
        if np.isfinite(closing):
            axes[3].bar(x, closing, color=col)
        if np.isfinite(bleed):
            axes[2].bar(x, bleed, color=col)
        if np.isfinite(fs):
            axes[0].bar(x, fs, color=col)
            on = _share(st.free_space_moving)
            if np.isfinite(on):  # the part on labelled moving objects, hatched
                axes[0].bar(x, fs * on, color=col, hatch="//", edgecolor="black", label=f"{lab}: on labelled moving objects")
                axes[0].legend(fontsize=7)
        if np.isfinite(mixed):
            axes[1].bar(x, mixed, color=col)
    for ax in axes:
        ax.set_xticks([0, 1], ["synthetic", "real"])
    axes[0].set_ylabel(f"free-space violations at {MOVING_GAP_S:g} s")
    axes[1].set_ylabel("depth jumps with a return in between")
    axes[2].set_ylabel(f"near bins with a return {MOVING_GAP_S:g} s earlier behind")
    axes[3].set_ylabel(f"far points unseen {DRIFT_GAP_S:g} s later")
    save(fig, "free_space_and_mixed_pixels.png")

    fig, ax = plt.subplots(figsize=(6, 3.2))
    for st, lab, col in sides:
        if not st.ground_pairs:
            continue
        dr, dz = (np.concatenate(x) for x in zip(*st.ground_pairs))
        keep = np.abs(dz) <= DRIFT_OUTLIER_M
        dr, dz = dr[keep], dz[keep]
        if not dr.size:  # sweep pairs without a judged ground point between them
            continue
        bins = np.arange(np.floor(dr.min()), np.ceil(dr.max()) + 1.0, 1.0)
        which = np.digitize(dr, bins)
        mid = [(bins[b - 1] + 0.5, np.median(dz[which == b])) for b in np.unique(which) if (which == b).sum() >= 50]
        if mid:
            ax.plot(*np.array(mid).T, "o", color=col, ms=3, label=f"{lab}: median per 1 m")
        slope, drift = fit_ground_drift(dr, dz)
        xs = np.array([bins[0], bins[-1]])
        ax.plot(xs, drift + np.tan(np.deg2rad(slope)) * xs, color=col,
                label=f"{lab}: fit, {slope:.2f} deg, drift {100 * drift:+.1f} cm")
    ax.axhline(0.0, color="grey", lw=0.5)
    if not ax.get_legend_handles_labels()[0]:
        ax.text(0.5, 0.5, f"no ground seen twice {DRIFT_GAP_S:g} s apart", transform=ax.transAxes, ha="center")
    ax.set(xlabel=f"range from the earlier sweep - from the one {DRIFT_GAP_S:g} s later (m)",
           ylabel="later ground height - earlier (m)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    save(fig, "ground_drift.png")

    if base_syn and base_real:
        fig, axes = plt.subplots(1, len(RANK_METRICS), figsize=(12, 3.2))
        methods = list(base_syn)
        x = np.arange(len(methods))
        for ax, k in zip(axes, RANK_METRICS):
            ax.bar(x - 0.2, [base_real[m][k] for m in methods], 0.4, color="tab:blue", label="real")
            ax.bar(x + 0.2, [base_syn[m][k] for m in methods], 0.4, color="tab:orange", label="synthetic")
            ax.set_xticks(x, [m.replace("raycast-", "rc-") for m in methods], rotation=30)
            ax.set_title(k)
        axes[0].legend()
        save(fig, "baselines.png")
    return names


def open_side(spec: str, progress: bool = True):
    """``NAME[=ROOT[?opts]]`` -> (name, root string, adapter)."""
    from pcfbench import config
    from pcfbench.plugins import get_plugins

    plugins = get_plugins()
    names, roots = config.parse_dataset_args((spec,))
    if len(names) != 1:
        raise PcfbenchError(f"{spec!r}: expected one NAME[=ROOT]")
    name = names[0]
    cls = plugins.datasets.get(name)
    root = config.resolve_root(name, cls, roots, progress)
    return name, root, config.open_adapter(name, cls, root)


def default_split(adapter, preferred: str | None) -> str:
    """``preferred`` (one split or several, comma-separated; each checked against the adapter's
    splits, and no sequence in two of them), else the adapter's default split if it has
    sequences, else the first that has."""
    if preferred:
        seen = {}
        for sp in split_list(preferred):
            if sp not in adapter.splits():
                raise PcfbenchError(f"dataset {adapter.name} under {adapter.root} has no split {sp!r} "
                                    f"(it has: {', '.join(adapter.splits())})")
            for name in adapter.sequence_names(sp):
                if name in seen:
                    raise PcfbenchError(f"dataset {adapter.name}: sequence {name} is in split {seen[name]!r} and in "
                                        f"{sp!r}: pooled, its samples would count twice")
                seen[name] = sp
        return ",".join(split_list(preferred))
    for sp in (adapter.default_split, *adapter.splits()):
        if sp in adapter.splits() and adapter.sequence_names(sp):
            return sp
    raise PcfbenchError(f"dataset {adapter.name} under {adapter.root} has no split with sequences")


def compare(real: str, domain: str, out: Path, sweeps: int = 12, setting: str = "kitti-1s",
            limit: int | None = None, real_limit: int | None = None, baselines: bool = True,
            store: Path | None = None, real_split: str | None = None, synthetic_split: str | None = None,
            progress: bool = True, threads: int | None = None, policy: str = "full-context",
            real_policy: str = "full-context") -> dict:
    """Measure both sides and write the report; returns its numbers (also in realism.json).
    ``policy`` / ``real_policy``: the sample policy of each side's baseline cells."""
    from pcfbench.datasets.synthetic.sensor import HDL64

    s_name, s_root, s_ad = open_side(domain, progress)
    r_name, r_root, r_ad = open_side(real, progress)
    s_split, r_split = default_split(s_ad, synthetic_split), default_split(r_ad, real_split)
    edges = beam_edges(HDL64.elevations_deg)
    syn = measure(s_ad, s_split, sweeps, s_name, edges, progress=progress)
    rea = measure(r_ad, r_split, sweeps, r_name, edges, progress=progress)
    base_syn = base_real = None
    t_base = {}
    if baselines:
        store = Path(store) if store is not None else Path(out) / "store"
        t0 = time.perf_counter()
        base_syn = baseline_means(s_name, s_root, s_split, setting, store, limit, progress=progress, threads=threads,
                                  policy=policy)
        t_base["synthetic"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        base_real = baseline_means(r_name, r_root, r_split, setting, store, real_limit, progress=progress,
                                   threads=threads, policy=real_policy)
        t_base["real"] = time.perf_counter() - t0
    meta = {"synthetic": s_name, "synthetic_root": s_root, "synthetic_split": s_split, "real": r_name,
            "real_root": r_root, "real_split": r_split, "setting": setting, "sweeps": sweeps, "limit": limit,
            "real_limit": real_limit, "policy": policy, "real_policy": real_policy, "statistics_seconds": {"synthetic": syn.seconds, "real": rea.seconds},
            "baseline_seconds": t_base}
    return write_report(Path(out), syn, rea, edges, base_syn, base_real, meta)
