"""Inference rendering of one decoded token map on the CPU, one ray at a time (numba).

The same arithmetic as the differentiable torch path that training uses
(:func:`~.render.sample_along_rays` with a mask and no jitter, then
:func:`~.render.render_depth` and the readout of :func:`~.evaluate.render_codes`), fused per
ray so that no (rays x samples) tensor is ever built:

1. spatial skipping: candidate points every ``candidate_step`` metres along the ray, each
   looked up in the coarse mask; the ray's ``n`` samples spread uniformly over the occupied
   candidates' segments (the whole in-box segment when none is occupied, or without a mask);
2. each sample's NFG feature by trilinear interpolation (``grid_sample``'s, align_corners
   False, border padding; zero occupancy outside the grid box), the occupancy MLP, alpha;
3. equation 4's weights w_i = alpha_i prod_{j<i} (1 - alpha_j + 1e-7);
4. the readout: ``median`` (the first sample whose cumulative weight reaches half of the
   ray's total; the box exit when the total is 0) or ``expected`` (sum w_i h_i, plus the
   transmittance left times the box exit with ``far_bound``).

The median readout stops a ray early once its answer cannot change: when the transmittance
left (an upper bound on the weight still to come) is too small to move the half-total across
any cumulative weight already reached. That is exact, not an approximation: the test
compares every ray against the same kernel marched to the end.

Float32 throughout, in the torch path's order of operations; it agrees with the torch path to
float rounding (sums are sequential here, pairwise in torch), which the tests bound. Measured
in docs/journal/performance-tuning-2026-11.md.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from pcfbench.execution import ExecutionContext, current

READOUT_CODES = {"expected": 0, "median": 1}
#: rays per piece of a march shared out over threads (any value gives the same depths)
CHUNK = 8192


@nb.njit(cache=True, nogil=True)
def _march(origin, dirs, lo, hi, mask, mask_cell, use_mask, nfg, nfg_cell, w1, b1, w2, b2,
           n, step, n_cand_max, readout, far_bound, early_stop, out, stopped):
    f32 = np.float32
    R = dirs.shape[0]
    Xc, Yc, Zc = mask.shape[0], mask.shape[1], mask.shape[2]
    Xn, Yn, Zn, Fd = nfg.shape[0], nfg.shape[1], nfg.shape[2], nfg.shape[3]
    H = w1.shape[0]
    w1t = np.ascontiguousarray(w1.T)
    hid = np.empty(H, np.float32)
    u = np.empty(n, np.float32)
    for i in range(n):
        u[i] = (f32(i) + f32(0.5)) / f32(n)
    cand_occ = np.zeros(n_cand_max, np.bool_)
    h = np.empty(n, np.float32)
    w = np.empty(n, np.float32)
    cdf = np.empty(n, np.float32)
    feat = np.empty(Fd, np.float32)
    for r in range(R):
        o0, o1, o2 = origin[0], origin[1], origin[2]
        d0, d1, d2 = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        # --- slab test against the grid box (box_interval)
        t_enter = f32(-np.inf)
        t_exit = f32(np.inf)
        for ax_ in range(3):
            o = origin[ax_]
            d = dirs[r, ax_]
            if abs(d) < 1e-9:
                d = f32(1e-9)
            ta = (lo[ax_] - o) / d
            tb = (hi[ax_] - o) / d
            t_enter = max(t_enter, min(ta, tb))
            t_exit = min(t_exit, max(ta, tb))
        t0 = max(t_enter, f32(0.0))
        t1 = max(t_exit, t0)
        # --- sample depths (sample_along_rays, no jitter)
        total = f32(0.0)
        nc = 0
        if use_mask:
            nc = n_cand_max
            for c in range(n_cand_max):
                hc = (f32(c) + f32(0.5)) * step
                if hc > t1:
                    nc = c
                    break
                occ = False
                if hc >= t0:
                    i = int(math.floor(((o0 + hc * d0) - lo[0]) / mask_cell[0]))
                    j = int(math.floor(((o1 + hc * d1) - lo[1]) / mask_cell[1]))
                    k = int(math.floor(((o2 + hc * d2) - lo[2]) / mask_cell[2]))
                    if 0 <= i < Xc and 0 <= j < Yc and 0 <= k < Zc:
                        occ = mask[i, j, k]
                cand_occ[c] = occ
                if occ:
                    total += step
        if total > 0:
            c = 0
            while not cand_occ[c]:
                c += 1
            cum = step  # cdf up to and including candidate c
            for s in range(n):
                target = u[s] * total
                while cum < target and c < nc - 1:
                    c += 1
                    if cand_occ[c]:
                        cum += step
                hc = (f32(c) + f32(0.5)) * step
                before = cum - step if cand_occ[c] else cum
                h[s] = hc - f32(0.5) * step + (target - before)
        else:
            for s in range(n):
                h[s] = t0 + u[s] * (t1 - t0)
        # --- march: trilinear NFG feature, occupancy MLP, weights
        trans = f32(1.0)
        acc = f32(0.0)
        depth_sum = f32(0.0)
        last = n - 1
        for s in range(n):
            hs = h[s]
            px = o0 + hs * d0
            py = o1 + hs * d1
            pz = o2 + hs * d2
            alpha = f32(0.0)
            if lo[0] <= px <= hi[0] and lo[1] <= py <= hi[1] and lo[2] <= pz <= hi[2]:
                fx = min(max((px - lo[0]) / nfg_cell[0] - f32(0.5), f32(0.0)), f32(Xn - 1))
                fy = min(max((py - lo[1]) / nfg_cell[1] - f32(0.5), f32(0.0)), f32(Yn - 1))
                fz = min(max((pz - lo[2]) / nfg_cell[2] - f32(0.5), f32(0.0)), f32(Zn - 1))
                x0 = int(math.floor(fx))
                y0 = int(math.floor(fy))
                z0 = int(math.floor(fz))
                ax, ay, az = fx - f32(x0), fy - f32(y0), fz - f32(z0)
                x1, y1, z1 = min(x0 + 1, Xn - 1), min(y0 + 1, Yn - 1), min(z0 + 1, Zn - 1)
                for q in range(Fd):
                    feat[q] = f32(0.0)
                for corner in range(8):
                    zi = z1 if corner & 4 else z0
                    xi = x1 if corner & 2 else x0
                    yi = y1 if corner & 1 else y0
                    wc = ((az if corner & 4 else f32(1.0) - az) * (ax if corner & 2 else f32(1.0) - ax)
                          * (ay if corner & 1 else f32(1.0) - ay))
                    for q in range(Fd):
                        feat[q] += wc * nfg[xi, yi, zi, q]
                for j in range(H):  # hidden layer, vectorised over the hidden units
                    hid[j] = b1[j]
                for q in range(Fd):
                    fq = feat[q]
                    for j in range(H):
                        hid[j] += w1t[q, j] * fq
                logit = b2
                for j in range(H):
                    if hid[j] > 0:
                        logit += w2[j] * hid[j]
                alpha = f32(1.0) / (f32(1.0) + math.exp(-logit))
            w[s] = alpha * trans
            trans = trans * (f32(1.0) - alpha + f32(1e-7))
            acc += w[s]
            cdf[s] = acc
            depth_sum += w[s] * hs
            if early_stop and readout == 1 and acc > 0 and trans < 1e-4 * acc:
                # every later weight is at most trans * (1 + 1e-7) ** n: the total lies in
                # [acc, acc + bound]; stop when the first cdf >= half of any such total is known
                bound = trans * f32(1.001) + acc * f32(1e-5)
                lo_half = f32(0.5) * acc
                hi_half = f32(0.5) * (acc + bound)
                known = False
                for j in range(s + 1):
                    if cdf[j] >= lo_half:
                        known = cdf[j] >= hi_half
                        break
                if known:
                    last = s
                    if s < n - 1:  # samples skipped: the ray stopped early
                        stopped[0] += 1
                    break
        if readout == 1:
            if acc > 0:
                half = f32(0.5) * acc
                j = 0
                while j < last and cdf[j] < half:
                    j += 1
                out[r] = h[j]
            else:
                out[r] = t1
        else:
            d = depth_sum
            if far_bound:
                d += max(f32(1.0) - acc, f32(0.0)) * t1
            out[r] = d


def march(cfg, nfg_cl: np.ndarray, mask: np.ndarray | None, origin: np.ndarray, dirs: np.ndarray, mlp: tuple,
          *, samples: int, readout: str, far_bound: bool = True, early_stop: bool = True,
          stats: dict | None = None, execution: ExecutionContext | None = None) -> np.ndarray:
    """Depth (float32, (R,)) along unit rays ``dirs`` (R, 3) from ``origin`` (3,), both in the
    tokenized sweep's sensor frame, through one decoded token map: ``nfg_cl`` the NFG channels
    last (X, Y, Z, F) float32, ``mask`` the pooled coarse mask (Xc, Yc, Z) bool or None (no
    spatial skipping), ``mlp`` the occupancy MLP's (W1 (H, F), b1 (H,), W2 (1, H), b2 (1,)).
    ``stats``, if given, receives ``stopped``: how many rays the median readout stopped early.

    Rays are marched in order of azimuth (each depth is independent of the order): rays next
    to each other then read the same NFG columns, which keeps them in cache (the NFG is tens
    of MB; 15 % faster on a synthetic-town sweep, whose rays come beam by beam).

    ``execution`` (default: the process's, ``pcfbench.execution.current()``): the azimuth-sorted
    rays are cut into ``CHUNK``-ray pieces that its threads march as they come free (the kernel
    releases the GIL). A ray's depth does not depend on the piece it is in, so the depths are
    the same whatever the thread count."""
    f32 = np.float32
    lo = np.array([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]], f32)
    hi = np.array([cfg.x_range[1], cfg.y_range[1], cfg.z_range[1]], f32)
    Xn, Yn, Zn, _ = nfg_cl.shape
    nfg_cell = (hi - lo) / np.array([Xn, Yn, Zn], f32)
    use_mask = mask is not None
    if mask is None:
        mask = np.zeros((1, 1, 1), np.bool_)
    mask_cell = (hi - lo) / np.array(mask.shape, f32)
    step = f32(cfg.candidate_step)
    diag = max(abs(v) for v in (*cfg.x_range, *cfg.y_range)) * 1.5 + 5.0
    n_cand = int(diag / cfg.candidate_step) + 1  # as sample_along_rays: candidates out to diag
    w1, b1, w2, b2 = (np.ascontiguousarray(a, dtype=f32) for a in mlp)
    dirs = np.asarray(dirs, dtype=f32)
    order = azimuth_order(dirs)
    sorted_dirs = np.ascontiguousarray(dirs[order])
    args = (np.ascontiguousarray(mask, dtype=np.bool_), mask_cell, use_mask, np.ascontiguousarray(nfg_cl, dtype=f32),
            nfg_cell, w1, b1, w2.reshape(-1), f32(b2.reshape(-1)[0]), samples, step, n_cand, READOUT_CODES[readout],
            far_bound, early_stop)
    origin32 = np.ascontiguousarray(origin, dtype=f32)

    def piece(a: int, b: int, out: np.ndarray, stopped: np.ndarray) -> None:
        _march(origin32, sorted_dirs[a:b], lo, hi, *args, out, stopped)

    depth, stopped = march_pieces(order, piece, CHUNK, execution)
    if stats is not None:
        stats["stopped"] = stopped
    return depth


def azimuth_order(dirs: np.ndarray) -> np.ndarray:
    """The rays ``dirs`` (R, 3) in order of azimuth (stable): marched so, rays next to each other
    read the same columns of a volume, which keeps them in cache."""
    return np.argsort(np.arctan2(dirs[:, 1], dirs[:, 0]), kind="stable")


def march_pieces(order: np.ndarray, piece, chunk: int, execution: ExecutionContext | None = None):
    """(float32 depths (R,) in the rays' own order, rays stopped early): the rays taken in
    ``order`` cut into ``chunk``-ray pieces that ``execution``'s threads (default: the
    process's) march as they come free; ``piece(a, b, out, stopped)`` marches sorted rays
    [a, b) into ``out`` (b - a,) and adds its early stops to ``stopped[0]``. A ray's depth does
    not depend on its piece, so the depths are the same whatever the thread count."""
    out = np.empty(len(order), np.float32)

    def run(bounds: tuple[int, int]) -> int:
        a, b = bounds
        stopped = np.zeros(1, np.int64)
        piece(a, b, out[a:b], stopped)
        return int(stopped[0])

    cuts = list(range(0, len(order), chunk)) + [len(order)]
    stopped = sum((execution or current()).map(run, zip(cuts[:-1], cuts[1:])))
    depth = np.empty_like(out)
    depth[order] = out
    return depth, stopped
