"""Inference rendering of one decoded BEVWorld feature volume on the CPU, one ray at a time
(numba).

The same arithmetic as the differentiable torch path that training uses
(:func:`~.render.render_rays` without jitter), fused per ray so that no (rays x samples x
features) tensor is ever built:

1. the ray's in-box segment [t_near, t_far] (:func:`~pcfbench.methods.copilot4d.render.box_interval`,
   computed by torch before the kernel) cut into ``n`` equal bins, a sample at each centre;
2. each sample's features by trilinear interpolation (``grid_sample``'s: align_corners False,
   border padding), the density MLP ``softplus(W2 relu(W1 f + b1) + b2)``;
3. equation 3's weights w_i = (1 - exp(-sigma_i delta)) exp(-sum_{j<i} sigma_j delta) and the
   expected depth sum_i w_i t_i + (1 - sum_i w_i) t_far.

A ray stops before the first sample whose transmittance exp(-sum_{j<i} sigma_j delta) is below
``stop`` (default ``STOP``): the weight left then lands at t_far, as the remainder past the last
sample always does. The samples it skips weigh less than that transmittance in all, so the
depth moves by less than ``stop * (t_far - t_near)``: 1e-5 m on a 100-m segment, about one
float32 ulp of a 100-m depth (7.6e-6 m). ``stop=0`` marches every sample.

Float32 throughout, in the torch path's order of operations within a sample; sums run in
sample order here, pairwise in torch, which the tests bound (docs/bevworld.md, "Inference
time").
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from pcfbench.execution import ExecutionContext
from pcfbench.methods.copilot4d.raymarch import azimuth_order, march_pieces

#: a ray stops when its transmittance falls below this (see the module docstring); 0: never
STOP = 1e-7
#: rays per piece of a render shared out over threads (any value gives the same depths)
CHUNK = 8192


@nb.njit(cache=True, nogil=True)
def _march(origin, dirs, t_near, t_far, lo, span, vol, w1, b1, w2, b2, n, stop, out, stopped):
    f32 = np.float32
    R = dirs.shape[0]
    Xn, Yn, Zn, Fd = vol.shape[0], vol.shape[1], vol.shape[2], vol.shape[3]
    H = w1.shape[0]
    w1t = np.ascontiguousarray(w1.T)  # (F, H): the hidden layer as F axpys over contiguous rows
    feat = np.empty(Fd, np.float32)
    hid = np.empty(H, np.float32)
    size = np.empty(3, np.float32)
    size[0], size[1], size[2] = f32(Xn), f32(Yn), f32(Zn)
    top = np.empty(3, np.float32)
    top[0], top[1], top[2] = f32(Xn - 1), f32(Yn - 1), f32(Zn - 1)
    idx = np.empty(3, np.float32)
    for r in range(R):
        t0 = t_near[r]
        t1 = t_far[r]
        length = t1 - t0
        delta = length / f32(n)
        optical = f32(0.0)
        acc_w = f32(0.0)
        acc_wt = f32(0.0)
        for s in range(n):
            trans = f32(math.exp(-optical))
            if stop > 0 and trans < stop:
                stopped[0] += 1
                break
            t = t0 + (f32(s) + f32(0.5)) / f32(n) * length
            for a in range(3):
                p = origin[a] + t * dirs[r, a]
                g = f32(2.0) * (p - lo[a]) / span[a] - f32(1.0)
                c = ((g + f32(1.0)) * size[a] - f32(1.0)) / f32(2.0)  # grid_sample, align_corners False
                idx[a] = min(max(c, f32(0.0)), top[a])  # border padding
            ix0 = int(math.floor(idx[0]))
            iy0 = int(math.floor(idx[1]))
            iz0 = int(math.floor(idx[2]))
            fx = idx[0] - f32(ix0)
            fy = idx[1] - f32(iy0)
            fz = idx[2] - f32(iz0)
            ix1 = min(ix0 + 1, Xn - 1)
            iy1 = min(iy0 + 1, Yn - 1)
            iz1 = min(iz0 + 1, Zn - 1)
            gx, gy, gz = f32(1.0) - fx, f32(1.0) - fy, f32(1.0) - fz
            c000, c001 = gx * gy * gz, gx * gy * fz
            c010, c011 = gx * fy * gz, gx * fy * fz
            c100, c101 = fx * gy * gz, fx * gy * fz
            c110, c111 = fx * fy * gz, fx * fy * fz
            for k in range(Fd):
                feat[k] = (c000 * vol[ix0, iy0, iz0, k] + c001 * vol[ix0, iy0, iz1, k]
                           + c010 * vol[ix0, iy1, iz0, k] + c011 * vol[ix0, iy1, iz1, k]
                           + c100 * vol[ix1, iy0, iz0, k] + c101 * vol[ix1, iy0, iz1, k]
                           + c110 * vol[ix1, iy1, iz0, k] + c111 * vol[ix1, iy1, iz1, k])
            for j in range(H):
                hid[j] = f32(0.0)
            for k in range(Fd):
                fk = feat[k]
                for j in range(H):
                    hid[j] += w1t[k, j] * fk
            logit = b2
            for j in range(H):
                hj = hid[j] + b1[j]
                if hj > 0:
                    logit += w2[j] * hj
            sigma = logit if logit > f32(20.0) else f32(math.log1p(math.exp(logit)))  # torch's softplus
            sd = sigma * delta
            w = (f32(1.0) - f32(math.exp(-sd))) * trans
            optical += sd
            acc_w += w
            acc_wt += w * t
        out[r] = acc_wt + (f32(1.0) - acc_w) * t1


def march(volume_cl: np.ndarray, origin: np.ndarray, dirs: np.ndarray, t_near: np.ndarray, t_far: np.ndarray,
          box: tuple, mlp: tuple, *, samples: int, stop: float = STOP, stats: dict | None = None,
          execution: ExecutionContext | None = None) -> np.ndarray:
    """Expected depths (float32, (R,)) along unit rays ``dirs`` (R, 3) from ``origin`` (3,) in
    the tokenizer's grid frame, each sampled over its in-box segment [``t_near``, ``t_far``]
    (R,), through one decoded volume ``volume_cl`` (X, Y, Z, F) float32 (features last);
    ``box`` the grid's (lo (3,), hi (3,)) corners, ``mlp`` the density MLP's (W1 (H, F), b1
    (H,), W2 (1, H), b2 (1,)). ``stats``, if given, receives ``stopped``: how many rays stopped
    before their last sample.

    Rays are marched in order of azimuth (each depth is independent of the order), cut into
    ``CHUNK``-ray pieces that ``execution``'s threads (default: the process's) march as they
    come free; the depths are the same whatever the thread count."""
    f32 = np.float32
    lo, hi = (np.asarray(v, f32) for v in box)
    w1, b1, w2, b2 = (np.ascontiguousarray(a, dtype=f32) for a in mlp)
    dirs = np.asarray(dirs, dtype=f32)
    order = azimuth_order(dirs)
    sorted_dirs = np.ascontiguousarray(dirs[order])
    near = np.ascontiguousarray(np.asarray(t_near, f32)[order])
    far = np.ascontiguousarray(np.asarray(t_far, f32)[order])
    vol = np.ascontiguousarray(volume_cl, dtype=f32)
    origin32 = np.ascontiguousarray(origin, dtype=f32)

    def piece(a: int, b: int, out: np.ndarray, stopped: np.ndarray) -> None:
        _march(origin32, sorted_dirs[a:b], near[a:b], far[a:b], lo, hi - lo, vol, w1, b1, w2.reshape(-1),
               f32(b2.reshape(-1)[0]), samples, f32(stop), out, stopped)

    depth, stopped = march_pieces(order, piece, CHUNK, execution)
    if stats is not None:
        stats["stopped"] = stopped
    return depth
