"""raycast-zbuffer: point-based rendering of the aggregated past with occlusion.

The past points are projected into the future sensor's spherical range image (azimuth
``atan2(y, x)``, elevation ``atan2(z, hypot(x, y))`` in the future sensor frame) and each bin
keeps the nearest range (a z-buffer), so a near occluder hides what is behind it. Bins are
``az_res_deg`` x ``el_res_deg`` (defaults match a KITTI-like 64-beam sensor: about 0.18 deg
between azimuth steps and 1/3 to 1/2 deg between beams; set them to the sensor's spacing).

Sparsity: a point is splatted as a small disc, the size of its footprint in its own sweep
(``splat * own_range * el_res``, the spacing of the beams where it was measured), seen from
the future origin, at most ``max_splat`` bins each way. Near surfaces the future sensor
approaches thus stay closed instead of letting background through the gaps between past
beams. A query ray whose bin is still empty takes the depth of the angularly nearest
non-empty bin (bin centres, within ``fill_ring`` bins), then the same search on 4x, 16x, ...
coarser min-pooled images, and only when the whole image is empty around it the range of
the angular nearest past point (exact, with azimuth wrap-around).

Per view, one vectorised pass projects every point (``fastmath.atan2``; the splat width uses
``cos(el) = h / r`` instead of a call to ``cos``), a serial pass splats them, and the views
go to threads (``common.map_views``). Measurements: docs/journal/performance-tuning-2026-11.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.execution import ExecutionContext
from pcfbench.method import Method
from pcfbench.options import option
from pcfbench.methods.raycast.common import aggregate, assemble, map_views, scratch, views
from pcfbench.methods.raycast.fastmath import atan2
from pcfbench.nn2d import NN2D


@dataclass(frozen=True)
class ZBufferOptions:
    az_res_deg: float = option(0.2, help="azimuth bin width of the range image, degrees", gt=0, max=360)
    el_res_deg: float = option(0.4, help="elevation bin height of the range image (the beam spacing), degrees",
                                gt=0, max=180)
    splat: float = option(1.0, help="splat diameter in units of the point's own beam spacing (0: one bin per point)",
                           min=0, max=100)
    max_splat: int = option(4, help="largest splat half-width, bins", min=0, max=256)
    fill_ring: int = option(8, help="an empty bin takes the angularly nearest non-empty bin within this many bins, "
                                    "then the same on coarser images", min=0, max=1800)
    constant_velocity: bool = option(False, help="extrapolate the future poses from the last two past poses "
                                                 "instead of using the sample's future poses")


@nb.njit(inline="always")
def _in_sensor(cols, i, origin, R):
    """Point ``i`` of (3, N) ``cols`` in the sensor frame at ``origin`` with rotation ``R``
    (sensor-to-reference): ``R.T @ (p - origin)``, plus its horizontal range ``h``."""
    rx = cols[0, i] - origin[0]
    ry = cols[1, i] - origin[1]
    rz = cols[2, i] - origin[2]
    x = R[0, 0] * rx + R[1, 0] * ry + R[2, 0] * rz
    y = R[0, 1] * rx + R[1, 1] * ry + R[2, 1] * rz
    z = R[0, 2] * rx + R[1, 2] * ry + R[2, 2] * rz
    return x, y, z, np.sqrt(x * x + y * y)


@nb.njit(nogil=True, parallel=True, cache=True)
def spherical(cols, origin, R):
    """Azimuth, elevation and range of (3, N) points (``cols``: x, y, z rows) seen from
    ``origin`` with rotation ``R`` (sensor-to-reference), i.e. in the sensor frame."""
    n = cols.shape[1]
    az = np.empty(n)
    el = np.empty(n)
    rng = np.empty(n)
    for i in nb.prange(n):
        x, y, z, h = _in_sensor(cols, i, origin, R)
        az[i] = atan2(y, x)
        el[i] = atan2(z, h)
        rng[i] = np.sqrt(h * h + z * z)
    return az, el, rng


@nb.njit(nogil=True, parallel=True, cache=True)
def _project(cols, own, origin, R, el0, az_res, el_res, splat, max_splat, ci, ri, hx, hy, rf):
    """Bin, range and splat half-widths of (3, N) points seen from ``origin`` (rotation ``R``)
    into ``ci`` (column), ``ri`` (row), ``hx`` (half-width in columns), ``hy`` (half-height in
    rows, -1: at the origin, skipped), ``rf`` (range, float32). One vectorised pass (see
    common.map_views on prange)."""
    n = cols.shape[1]
    for i in nb.prange(n):
        x, y, z, h = _in_sensor(cols, i, origin, R)
        r = np.sqrt(h * h + z * z)
        a = 0.5 * splat * own[i] * el_res / r  # angular radius of the point's footprint
        ci[i] = int(np.floor((atan2(y, x) + np.pi) / az_res))
        ri[i] = int(np.floor((atan2(z, h) - el0) / el_res))
        # cos(el) = h / r: no call to the C library's cos, which would stop the vectorisation
        hx[i] = min(int(a / (az_res * max(h / r, 0.05))), max_splat)
        hy[i] = min(int(a / el_res), max_splat) if r > 1e-3 else -1
        rf[i] = np.float32(r)
    return ci, ri, hx, hy, rf


@nb.njit(nogil=True, cache=True)
def _splat(ci, ri, hx, hy, rf, n_az, n_el):
    """The z-buffer: each point's range kept in the bins of its footprint where it is nearest."""
    img = np.full(n_el * n_az, np.inf, np.float32)
    for k in range(ci.shape[0]):
        b_hy = hy[k]
        b_ri = ri[k]
        if b_hy < 0 or b_ri + b_hy < 0 or b_ri - b_hy >= n_el:
            continue
        b_ci = ci[k]
        b_hx = hx[k]
        v = rf[k]
        if b_hy == 0 and b_hx <= 1 and 0 <= b_ri < n_el and 0 <= b_ci < n_az:
            # the common footprint, one row of 1 or 3 bins, without branches that the
            # processor mispredicts (a bin left out takes min(., inf), which leaves it)
            base = b_ri * n_az
            side = v if b_hx == 1 else np.float32(np.inf)
            cm = b_ci - 1 if b_ci > 0 else n_az - 1
            cp = b_ci + 1 if b_ci + 1 < n_az else 0
            img[base + cm] = min(img[base + cm], side)
            img[base + b_ci] = min(img[base + b_ci], v)
            img[base + cp] = min(img[base + cp], side)
            continue
        for dy in range(-b_hy, b_hy + 1):
            row = b_ri + dy
            if row < 0 or row >= n_el:
                continue
            base = row * n_az
            for dx in range(-b_hx, b_hx + 1):
                c = b_ci + dx  # wrap around in azimuth, without an integer division
                while c < 0:
                    c += n_az
                while c >= n_az:
                    c -= n_az
                if v < img[base + c]:
                    img[base + c] = v
    return img


@nb.njit(nogil=True, cache=True)
def _lookup(img, qaz, qel, el0, az_res, el_res, n_az, n_el, max_ring):
    """Depth per query: its bin, else the nearest (in angle) non-empty bin centre within
    ``max_ring`` bins (exact ring search in angle distance), else NaN."""
    m = qaz.shape[0]
    out = np.full(m, np.nan)
    for j in range(m):
        fa = (qaz[j] + np.pi) / az_res
        fe = (qel[j] - el0) / el_res
        ci = int(np.floor(fa)) % n_az
        ri = int(np.floor(fe))
        if 0 <= ri < n_el:
            v = img[ri * n_az + ci]
            if v < np.inf:
                out[j] = v
                continue
        # hole: rings of bins around the query's bin, nearest bin centre in angle
        sx = az_res * max(np.cos(qel[j]), 0.05)
        best = np.inf
        bv = np.nan
        for r in range(1, max_ring + 1):
            for dy in range(-r, r + 1):
                row = ri + dy
                if row < 0 or row >= n_el:
                    continue
                step = 1 if (dy == -r or dy == r) else 2 * r
                for dx in range(-r, r + 1, step):
                    v = img[row * n_az + (ci + dx) % n_az]
                    if v < np.inf:
                        ex = (int(np.floor(fa)) + dx + 0.5 - fa) * sx
                        ey = (row + 0.5 - fe) * el_res
                        dd = ex * ex + ey * ey
                        if dd < best:
                            best = dd
                            bv = v
            # bins beyond ring r are at least r - 0.5 bins away along some axis
            lim = (r - 0.5) * min(sx, el_res)
            if best < np.inf and best <= lim * lim:
                break
        out[j] = bv
    return out


def angular_nn_ranges(az, el, rng, qaz, qel, wrap: float = 0.2) -> np.ndarray:
    """Range of the angular nearest point (azimuth/elevation, azimuth wrapping at +-pi)."""
    if len(az) == 0:
        return np.zeros(len(qaz))
    lo = az < -np.pi + wrap
    hi = az > np.pi - wrap
    a = np.concatenate([az, az[lo] + 2 * np.pi, az[hi] - 2 * np.pi])
    e = np.concatenate([el, el[lo], el[hi]])
    r = np.concatenate([rng, rng[lo], rng[hi]])
    nearest = NN2D(np.stack([a, e], axis=1)).query(np.stack([qaz, qel], axis=1))
    return r[nearest]


@dataclass
class RangeImage:
    """The z-buffer of one view, and what is needed to read rays from it."""

    img: np.ndarray
    el0: float
    az_res: float
    el_res: float
    n_az: int
    n_el: int


def image_geometry(qel, az_res_deg, el_res_deg) -> tuple[float, float, float, int, int]:
    """(el0, az_res, el_res, n_az, n_el) of a range image covering the query elevations ``qel``."""
    az_res = np.deg2rad(az_res_deg)
    el_res = np.deg2rad(el_res_deg)
    n_az = max(1, int(np.ceil(2 * np.pi / az_res)))
    az_res = 2 * np.pi / n_az
    lo = float(qel.min()) if len(qel) else -0.5
    hi = float(qel.max()) if len(qel) else 0.5
    el0 = lo - 2 * el_res
    n_el = max(1, int(np.ceil((hi - lo) / el_res)) + 4)
    return el0, az_res, el_res, n_az, n_el


def build_image(cols, own, origin, R, qel, az_res_deg, el_res_deg, splat, max_splat) -> RangeImage:
    """The z-buffer of (3, N) points ``cols`` seen from ``origin`` with rotation ``R``, over the rows of ``qel``."""
    el0, az_res, el_res, n_az, n_el = image_geometry(qel, az_res_deg, el_res_deg)
    n = cols.shape[1]
    proj = (scratch("zb.ci", n, np.int32), scratch("zb.ri", n, np.int32), scratch("zb.hx", n, np.int32),
            scratch("zb.hy", n, np.int32), scratch("zb.rf", n, np.float32))
    _project(
        cols, np.ascontiguousarray(own, dtype=np.float64), np.asarray(origin, dtype=np.float64),
        np.ascontiguousarray(R, dtype=np.float64), el0, az_res, el_res, float(splat), int(max_splat), *proj,
    )
    img = _splat(*proj, n_az, n_el)
    return RangeImage(img, el0, az_res, el_res, n_az, n_el)


def coarsen(im: RangeImage, f: int) -> RangeImage:
    """Min-pool the range image by ``f`` in both directions (nearest range wins)."""
    n_el = -(-im.n_el // f) * f
    n_az = -(-im.n_az // f) * f
    img = np.full((n_el, n_az), np.inf, np.float32)
    img[: im.n_el, : im.n_az] = im.img.reshape(im.n_el, im.n_az)
    img = img.reshape(n_el // f, f, n_az // f, f).min(axis=(1, 3))
    # a partly padded last azimuth column makes the wrap-around slightly uneven; this is a fallback
    return RangeImage(img.ravel(), im.el0, im.az_res * f, im.el_res * f, n_az // f, n_el // f)


def render_zbuffer(cols, own_range, view, opts) -> np.ndarray:
    """Depth per query ray of ``view``: the z-buffer bin, else the angular nearest point.
    ``cols``: the (3, N) past points (``Aggregate.cols``), ``own_range``: their own ranges."""
    R = np.ascontiguousarray(view.T_ref_sensor[:3, :3])
    qaz, qel, _ = spherical(view.dcols, np.zeros(3), R)
    if cols.shape[1] == 0:
        return np.zeros(len(qaz))
    im = build_image(cols, own_range, view.origin, R, qel, opts.az_res_deg, opts.el_res_deg, opts.splat, opts.max_splat)
    depth = _lookup(im.img, qaz, qel, im.el0, im.az_res, im.el_res, im.n_az, im.n_el, int(opts.fill_ring))
    empty = np.isnan(depth)
    while empty.any() and im.n_az > 4 and im.n_el > 1:
        # wider holes: the same ring search on a 4x coarser (min-pooled) image
        im = coarsen(im, 4)
        sub = np.flatnonzero(empty)
        depth[sub] = _lookup(im.img, qaz[sub], qel[sub], im.el0, im.az_res, im.el_res, im.n_az, im.n_el, int(opts.fill_ring))
        empty = np.isnan(depth)
    if empty.any():  # rare: no point within reach of the coarsest image; project them all again
        az, el, rng = spherical(cols, view.origin, R)
        depth[empty] = angular_nn_ranges(az, el, rng, qaz[empty], qel[empty])
    return depth


def render_zbuffer_views(cols, own_range, vws, opts, execution: ExecutionContext | None = None) -> list[np.ndarray]:
    """``render_zbuffer`` of each view of ``vws``, the views shared out over the threads of
    ``execution`` (default: the process's)."""
    return map_views(lambda v: render_zbuffer(cols, own_range, v, opts), vws, execution)


class RaycastZBuffer(Method):
    name = "raycast-zbuffer"
    version = "1"
    Options = ZBufferOptions

    def forecast(self, sample: Sample) -> Forecast:
        agg = sample.derive(aggregate)
        vws = sample.derive(views, self.options.constant_velocity)
        depths = render_zbuffer_views(agg.cols, agg.own_range, vws, self.options, self.execution)
        return assemble(sample, vws, depths, self.options.constant_velocity)
