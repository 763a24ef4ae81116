"""Differentiable depth rendering on the neural feature grid (equation 4), spatial skipping
(figure 8) and the rendering loss (equation 5)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from pcfbench.methods.copilot4d.config import TokenizerConfig


def box_interval(cfg: TokenizerConfig, origins: torch.Tensor, dirs: torch.Tensor):
    """Slab test against the tokenizer's grid box: (t_enter, t_exit) per ray (t_enter >= 0)."""
    lo = origins.new_tensor([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]])
    hi = origins.new_tensor([cfg.x_range[1], cfg.y_range[1], cfg.z_range[1]])
    safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t1, t2 = (lo - origins) / safe, (hi - origins) / safe
    t_enter = torch.minimum(t1, t2).amax(dim=1).clamp(min=0.0)
    t_exit = torch.maximum(t1, t2).amin(dim=1)
    return t_enter, torch.maximum(t_exit, t_enter)


def pool_mask(cfg: TokenizerConfig, occ: torch.Tensor) -> torch.Tensor:
    """(B, X, Y, Z) 0/1 voxels -> (B, X/k, Y/k, Z) bool, max-pooled by k = skip_pool in BEV."""
    k = cfg.skip_pool
    B, X, Y, Z = occ.shape
    return occ.view(B, X // k, k, Y // k, k, Z).amax(dim=(2, 4)) > 0


def sample_along_rays(
    cfg: TokenizerConfig, origins: torch.Tensor, dirs: torch.Tensor, batch: torch.Tensor,
    mask: torch.Tensor | None, n_samples: int, jitter: bool, extra_uniform: int = 0,
) -> torch.Tensor:
    """(R, n_samples) sorted ray depths h_i.

    With a coarse ``mask`` (B, Xc, Yc, Z) (spatial skipping), samples are spread uniformly
    over the parts of the ray inside non-empty coarse voxels, found on candidate points every
    ``candidate_step`` metres; rays that meet no non-empty voxel, or calls without a mask,
    sample the whole in-box segment uniformly. ``jitter`` stratifies the samples randomly.
    ``extra_uniform`` more samples (stratified over the whole in-box segment) are merged in,
    giving (R, n_samples + extra_uniform) depths.
    """
    h = _sample_along_rays(cfg, origins, dirs, batch, mask, n_samples, jitter)
    if extra_uniform <= 0:
        return h
    extra = _sample_along_rays(cfg, origins, dirs, batch, None, extra_uniform, jitter)
    return torch.sort(torch.cat([h, extra], dim=1), dim=1).values


def _sample_along_rays(cfg, origins, dirs, batch, mask, n_samples, jitter):
    t0, t1 = box_interval(cfg, origins, dirs)
    R = origins.shape[0]
    u = (torch.arange(n_samples, device=origins.device, dtype=origins.dtype) + 0.5)[None].expand(R, -1)
    if jitter:
        u = u + (torch.rand(R, n_samples, device=origins.device, dtype=origins.dtype) - 0.5)
    u = u / n_samples  # (R, n) in [0, 1], sorted
    uniform = t0[:, None] + u * (t1 - t0)[:, None]
    if mask is None:
        return uniform
    step = cfg.candidate_step
    diag = max(abs(v) for v in (*cfg.x_range, *cfg.y_range)) * 1.5 + 5.0
    # Candidates past every ray's exit from the box are never occupied: stopping at the
    # farthest exit gives the very same depths (render_codes groups rays by exit distance).
    far = float(t1.max()) if R else 0.0
    nc = min(int(diag / step), int(far / step) + 1) + 1
    hc = (torch.arange(nc, device=origins.device, dtype=origins.dtype) + 0.5) * step  # (nc,)
    with torch.no_grad():
        pts = origins[:, None, :] + hc[None, :, None] * dirs[:, None, :]  # (R, nc, 3)
        B, Xc, Yc, Z = mask.shape
        lo = pts.new_tensor([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]])
        cell = pts.new_tensor([(cfg.x_range[1] - cfg.x_range[0]) / Xc, (cfg.y_range[1] - cfg.y_range[0]) / Yc,
                               (cfg.z_range[1] - cfg.z_range[0]) / Z])
        # cell indices in int32, one flat index per candidate (int64 only when the mask needs it)
        itype = torch.int32 if mask.numel() < 2 ** 31 else torch.int64
        ijk = torch.floor((pts - lo) / cell).to(itype)
        del pts
        dims = torch.tensor([Xc, Yc, Z], device=ijk.device, dtype=itype)
        inside = ((ijk >= 0) & (ijk < dims)).all(-1)
        inside &= (hc[None] >= t0[:, None]) & (hc[None] <= t1[:, None])
        ijk *= inside[..., None]  # outside: cell (0, 0, 0), masked out below
        flat = ((batch[:, None].to(itype) * Xc + ijk[..., 0]) * Yc + ijk[..., 1]) * Z + ijk[..., 2]
        del ijk
        occ = mask.reshape(-1)[flat] & inside  # (R, nc)
        seg = occ.to(origins.dtype) * step
        cdf = torch.cumsum(seg, dim=1)
        total = cdf[:, -1]
        target = u * total[:, None]
        j = torch.searchsorted(cdf.contiguous(), target.contiguous()).clamp(max=nc - 1)
        before = torch.gather(cdf - seg, 1, j)
        h = hc[j] - 0.5 * step + (target - before)
        has = total > 0
        return torch.where(has[:, None], h, uniform)


def render_depth(decoder, nfg: torch.Tensor, cfg: TokenizerConfig, origins: torch.Tensor, dirs: torch.Tensor,
                 batch: torch.Tensor, h: torch.Tensor):
    """Equation 4: alpha_i from the NFG at r(h_i), w_i = alpha_i prod_{j<i}(1 - alpha_j),
    D = sum_i w_i h_i. Returns (D (R,), w (R, n))."""
    B, Fd, Zn, Xn, Yn = nfg.shape
    pts = origins[:, None, :] + h[..., None] * dirs[:, None, :]  # (R, n, 3)
    lo = pts.new_tensor([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]])
    hi = pts.new_tensor([cfg.x_range[1], cfg.y_range[1], cfg.z_range[1]])
    norm = 2.0 * (pts - lo) / (hi - lo) - 1.0  # [-1, 1] over the box (align_corners=False)
    inside = ((norm >= -1) & (norm <= 1)).all(-1)
    # grid_sample on (B, F, D=Z, H=X, W=Y): grid's last axis is ordered (W, H, D) = (y, x, z)
    grid = torch.stack([norm[..., 1], norm[..., 0], norm[..., 2]], dim=-1)
    if B == 1:  # one grid (inference): no per-grid selection and scatter
        f = F.grid_sample(nfg, grid[None, :, :, None, :].to(nfg.dtype), mode="bilinear", padding_mode="border",
                          align_corners=False)
        alpha = decoder.occupancy(f[0, :, :, :, 0].permute(1, 2, 0)).float() * inside.float()
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1] + 1e-7], dim=1), dim=1)
        w = alpha * trans
        return (w * h.float()).sum(dim=1), w
    feats = []
    for b in range(B):
        sel = batch == b
        g = grid[sel][None, :, :, None, :]  # (1, r, n, 1, 3)
        f = F.grid_sample(nfg[b: b + 1], g.to(nfg.dtype), mode="bilinear", padding_mode="border", align_corners=False)
        feats.append((sel.nonzero(as_tuple=True)[0], f[0, :, :, :, 0].permute(1, 2, 0)))  # (r, n, F)
    out = nfg.new_zeros(h.shape[0], h.shape[1], Fd)
    for rows, f in feats:
        out = out.index_copy(0, rows, f)
    alpha = decoder.occupancy(out).float() * inside.float()
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1] + 1e-7], dim=1), dim=1)
    w = alpha * trans
    return (w * h.float()).sum(dim=1), w


def render_loss(depth: torch.Tensor, w: torch.Tensor, h: torch.Tensor, gt: torch.Tensor, eps: float):
    """Equation 5's ray terms: L1 on depth and the weight mass farther than eps from the surface."""
    l1 = (depth - gt).abs().mean()
    far = ((h - gt[:, None]).abs() > eps).float()
    conc = (w * far).sum(dim=1).mean()
    return l1, conc


def logistic_noise_mask(cfg: TokenizerConfig, logits: torch.Tensor, noise: bool = True,
                        generator: torch.Generator | None = None, threshold: float = 0.5) -> torch.Tensor:
    """Inference-time spatial skipping: logits (+ Logistic noise) thresholded at probability
    ``threshold`` (the paper does not give it; 0.5 by default), then max-pooled by
    ``skip_pool`` in BEV."""
    logits = logits - math.log(threshold / (1.0 - threshold))
    if noise:
        u = torch.rand(logits.shape, generator=generator, device="cpu").to(logits.device).clamp(1e-6, 1 - 1e-6)
        logits = logits + torch.log(u) - torch.log1p(-u)
    return pool_mask(cfg, (logits > 0).to(torch.float32))
