"""NeRF-style depth rendering along LiDAR rays (BEVWorld section 3.1, equation 3): uniform
samples t_i along a ray, a density sigma_i at each from the decoded feature volume,
alpha_i = 1 - exp(-sigma_i delta_i), weights w_i = alpha_i prod_{j<i} (1 - alpha_j) and the
expected depth D = sum_i w_i t_i + (1 - sum_i w_i) t_far. The last term is ours, not the
paper's: the mass a ray keeps past its last sample ends at its exit from the grid, so a ray that
meets nothing reads the box's edge rather than 0 m. Rays and samples live in the tokenizer's
grid frame."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pcfbench.methods.copilot4d.render import box_interval


def sample_depths(cfg, origins: torch.Tensor, dirs: torch.Tensor, n: int, jitter: bool):
    """(t, delta) (R, n) and t_far (R,): the ray's in-box segment [t_near, t_far] cut into ``n``
    equal bins, one sample per bin (its centre, or uniform inside it with ``jitter``), delta
    the bin's length."""
    t0, t1 = box_interval(cfg, origins, dirs)
    R = origins.shape[0]
    u = torch.arange(n, device=origins.device, dtype=origins.dtype)[None].expand(R, n) + 0.5
    if jitter:
        u = u + torch.rand(R, n, device=origins.device, dtype=origins.dtype) - 0.5
    length = (t1 - t0)[:, None]
    return t0[:, None] + u / n * length, (length / n).expand(R, n), t1


def ray_weights(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """(..., n) densities and sample spacings -> (..., n) weights w_i = alpha_i T_i,
    T_i = prod_{j<i} (1 - alpha_j) (by the exclusive cumulative sum of sigma delta, which stays
    exact where alpha reaches 1)."""
    sd = sigma * delta
    optical = torch.cumsum(sd, dim=-1) - sd  # sum_{j<i} sigma_j delta_j
    return (1.0 - torch.exp(-sd)) * torch.exp(-optical)


def expected_depth(w: torch.Tensor, t: torch.Tensor, t_far: torch.Tensor) -> torch.Tensor:
    """(..., n) weights and depths, (...) far ends -> (...) expected depths."""
    return (w * t).sum(dim=-1) + (1.0 - w.sum(dim=-1)) * t_far


def volume_features(cfg, volume: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Trilinear features of one volume (F, Z, X, Y) at points (..., 3) in the grid frame ->
    (..., F); points outside the box take the border's features (their density is then
    zeroed by the caller)."""
    lo = pts.new_tensor([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]])
    hi = pts.new_tensor([cfg.x_range[1], cfg.y_range[1], cfg.z_range[1]])
    norm = 2.0 * (pts - lo) / (hi - lo) - 1.0
    grid = torch.stack([norm[..., 1], norm[..., 0], norm[..., 2]], dim=-1)  # grid_sample's (W, H, D) = (y, x, z)
    shape = grid.shape[:-1]
    f = F.grid_sample(volume[None], grid.reshape(1, -1, 1, 1, 3).to(volume.dtype), mode="bilinear",
                      padding_mode="border", align_corners=False)
    return f[0, :, :, 0, 0].t().reshape(*shape, volume.shape[0])


def render_rays(model, volume: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, *, n: int, jitter: bool,
                chunk: int | None = None):
    """Expected depths (R,) of rays (origins, unit dirs (R, 3)) through one decoded volume
    (F, Z, X, Y) of ``model`` (a :class:`.tokenizer.LatentTokenizer`); also (t, w) (R, n).
    ``chunk`` rays at a time (inference, without the per-ray t and w)."""
    cfg = model.cfg
    if chunk is not None and origins.shape[0] > chunk:
        return torch.cat([render_rays(model, volume, origins[s:s + chunk], dirs[s:s + chunk], n=n, jitter=jitter)[0]
                          for s in range(0, origins.shape[0], chunk)]), None, None
    t, delta, far = sample_depths(cfg, origins, dirs, n, jitter)
    pts = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    sigma = model.density(volume_features(cfg, volume, pts))
    w = ray_weights(sigma.float(), delta.float())
    return expected_depth(w, t.float(), far.float()), t, w
