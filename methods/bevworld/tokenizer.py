"""BEVWorld's LiDAR tokenizer (section 3.1, the L -> L setting): an encoder from a sweep to a
continuous BEV latent of C' channels, a decoder from the latent to a 3-D feature volume, and
depth rendered along the sweep's rays through that volume (:mod:`.render`); L1 on depth.
No vector quantisation. The per-channel statistics of the latents seen in training are kept
(running, in the weights), so the world model works on standardised latents (section 3.2).

The encoder is Copilot4D's (voxel PointNet, z-pooling to BEV, two Swin stages with a patch
merge) ending in C' channels: the paper's pillars feed a Swin backbone too; Copilot4D's
voxels keep the heights a pillar would average. The decoder mirrors it (a Swin stage, a
2 x 2 up-sampling, a Swin stage) and a linear map of each BEV cell to ``vol_up^2 x vol_z``
cells of ``vol_dim`` features; a 2-layer MLP gives each sample's density (softplus).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.bevworld.config import TokenizerConfig
from pcfbench.methods.copilot4d.model import Encoder
from pcfbench.methods.copilot4d.swin import PatchUpsample, SwinStage, init_transformer_, sincos_2d


class VolumeDecoder(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d1, d2 = cfg.dims
        self.from_latent = nn.Linear(cfg.latent_channels, d2)
        self.stage2 = SwinStage(d2, cfg.heads[1], cfg.depths[1], cfg.window, cfg.mlp_ratio)
        self.upsample = PatchUpsample(d2, d1)
        self.stage1 = SwinStage(d1, cfg.heads[0], cfg.depths[0], cfg.window, cfg.mlp_ratio)
        self.vol_norm = nn.LayerNorm(d1)
        self.vol_linear = nn.Linear(d1, cfg.vol_up ** 2 * cfg.vol_z * cfg.vol_dim)
        self.mlp1 = nn.Linear(cfg.vol_dim, cfg.mlp_hidden)
        self.mlp2 = nn.Linear(cfg.mlp_hidden, 1)

    def forward(self, z: torch.Tensor, channels_last: bool = False) -> torch.Tensor:
        """Latents (B, H, W, C') -> volumes (B, F, Z, X, Y), X = 2 H vol_up. With
        ``channels_last`` the volume's memory is laid out as (B, X, Y, Z, F) (the same shape and
        values, a permuted view: what the CPU ray march reads, without a second copy)."""
        cfg = self.cfg
        B, H = z.shape[0], z.shape[1]
        x = self.from_latent(z)
        x = x + sincos_2d(H, H, x.shape[-1], x.device).to(x.dtype)
        x = self.stage1(self.upsample(self.stage2(x)))  # (B, 2H, 2H, d1)
        S, u, Zn, Fd = x.shape[1], cfg.vol_up, cfg.vol_z, cfg.vol_dim
        v = self.vol_linear(self.vol_norm(x)).view(B, S, S, u, u, Zn, Fd)
        if channels_last:  # X = (row, its u), Y = (column, its u)
            return v.permute(0, 1, 3, 2, 4, 5, 6).reshape(B, S * u, S * u, Zn, Fd).permute(0, 4, 3, 1, 2)
        return v.permute(0, 6, 5, 1, 3, 2, 4).reshape(B, Fd, Zn, S * u, S * u)

    def density(self, feats: torch.Tensor) -> torch.Tensor:
        """(..., F) features -> (...,) densities (1/m), >= 0. Inference on the CPU repeats this
        arithmetic in numba (``raymarch._march``; its tests hold the two together)."""
        return F.softplus(self.mlp2(F.relu(self.mlp1(feats)))).squeeze(-1)


class LatentTokenizer(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.decoder = VolumeDecoder(cfg)
        C = cfg.latent_channels
        self.register_buffer("latent_mean", torch.zeros(C))
        self.register_buffer("latent_var", torch.ones(C))
        self.register_buffer("stats_updates", torch.zeros((), dtype=torch.long))
        init_transformer_(self, residual_layers=1)
        for stage, depth in ((self.encoder.stage1, cfg.depths[0]), (self.encoder.stage2, cfg.depths[1]),
                             (self.decoder.stage1, cfg.depths[0]), (self.decoder.stage2, cfg.depths[1])):
            init_transformer_(stage, residual_layers=2 * depth)
        nn.init.normal_(self.encoder.z_embed, 0.0, 0.02)

    def encode(self, points: torch.Tensor, batch: torch.Tensor, batch_size: int) -> torch.Tensor:
        """Points (N, 3) in the grid frame with batch indices (N,) -> raw latents (B, H, W, C');
        in training mode the per-channel statistics take in this batch."""
        z = self.encoder(points, batch, batch_size)
        if self.training:
            self._track(z.detach())
        return z

    @torch.no_grad()
    def _track(self, z: torch.Tensor) -> None:
        """Running per-channel mean and variance over every latent cell: the plain average of
        the batches so far until 1 / updates falls below ``stats_momentum``, then an
        exponential average with that momentum (the encoder keeps changing in training)."""
        flat = z.reshape(-1, z.shape[-1]).float()
        mean, var = flat.mean(0), flat.var(0, unbiased=False)
        self.stats_updates += 1
        m = max(1.0 / float(self.stats_updates), self.cfg.stats_momentum)
        # the variance about the new mean: the mixture of the two distributions
        new_mean = (1 - m) * self.latent_mean + m * mean
        self.latent_var.copy_((1 - m) * (self.latent_var + (self.latent_mean - new_mean) ** 2)
                              + m * (var + (mean - new_mean) ** 2))
        self.latent_mean.copy_(new_mean)

    def normalise(self, z: torch.Tensor) -> torch.Tensor:
        return (z - self.latent_mean) / torch.sqrt(self.latent_var + 1e-6)

    def denormalise(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sqrt(self.latent_var + 1e-6) + self.latent_mean

    def decode(self, z: torch.Tensor, channels_last: bool = False) -> torch.Tensor:
        """Raw latents (B, H, W, C') -> volumes (B, F, Z, X, Y) (``channels_last``: see
        :meth:`VolumeDecoder.forward`)."""
        return self.decoder(z, channels_last)

    def density(self, feats: torch.Tensor) -> torch.Tensor:
        return self.decoder.density(feats)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def tokenizer_losses(model: LatentTokenizer, batch) -> dict:
    """One training step's forward: encode the batch's sweeps (Copilot4D's
    :class:`~pcfbench.methods.copilot4d.data.Batch`), decode, render each sweep's rays with
    jittered samples; L1 between expected and measured depth."""
    from pcfbench.methods.bevworld.render import render_rays

    cfg = model.cfg
    vol = model.decode(model.encode(batch.points, batch.point_batch, batch.size))
    depths = []
    for b in range(batch.size):
        sel = batch.ray_batch == b
        d, _, _ = render_rays(model, vol[b], batch.origins[sel], batch.dirs[sel], n=cfg.samples_per_ray, jitter=True)
        depths.append((d, batch.depth[sel]))
    pred = torch.cat([d for d, _ in depths])
    gt = torch.cat([g for _, g in depths])
    l1 = (pred - gt).abs().mean()
    return {"loss": l1, "l1": l1, "median": (pred - gt).abs().median()}
