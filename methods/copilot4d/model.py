"""The tokenizer: voxel PointNet + BEV pooling + Swin encoder, vector quantizer with K-means
dead-code re-initialisation, symmetric Swin decoder with a neural feature grid (NFG) branch
and a coarse occupancy branch (paper 4.1, A.2.1)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.copilot4d.config import TokenizerConfig
from pcfbench.methods.copilot4d.swin import PatchMerging, PatchUpsample, SwinStage, init_transformer_, sincos_2d


def voxelize(cfg: TokenizerConfig, points: torch.Tensor, batch: torch.Tensor):
    """Points (N, 3) in the sweep's sensor frame with batch indices (N,) -> integer voxel
    coordinates (M, 3) [ix, iy, iz], the batch index (M,) and normalised offsets (M, 3) of the
    points inside the grid to their voxel centres (in [-1, 1])."""
    lo = points.new_tensor([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]])
    size = points.new_tensor(cfg.voxel_size)
    rel = (points - lo) / size
    idx = torch.floor(rel).long()
    dims = points.new_tensor([cfg.grid_xy, cfg.grid_xy, cfg.grid_z]).long()
    inside = ((idx >= 0) & (idx < dims)).all(dim=1)
    idx, rel, b = idx[inside], rel[inside], batch[inside]
    offsets = 2.0 * (rel - idx.to(rel.dtype) - 0.5)
    return idx, b, offsets


def occupancy_grid(cfg: TokenizerConfig, points: torch.Tensor, batch: torch.Tensor, batch_size: int) -> torch.Tensor:
    """(B, X, Y, Z) float 0/1: which voxels hold at least one point (the coarse branch target)."""
    idx, b, _ = voxelize(cfg, points, batch)
    X, Z = cfg.grid_xy, cfg.grid_z
    occ = torch.zeros(batch_size * X * X * Z, device=points.device)
    occ[((b * X + idx[:, 0]) * X + idx[:, 1]) * Z + idx[:, 2]] = 1.0
    return occ.view(batch_size, X, X, Z)


class Encoder(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c = cfg.pointnet_dim
        # voxel-wise PointNet on offsets to the voxel centre; sum + LayerNorm aggregation
        self.pn1 = nn.Linear(3, c)
        self.pn_norm1 = nn.LayerNorm(c)
        self.pn2 = nn.Linear(c, c)
        self.pn_agg_norm = nn.LayerNorm(c)
        # z-pooling to BEV: Linear + learnable z embedding, sum + LayerNorm over z
        self.z_linear = nn.Linear(c, cfg.bev_dim)
        self.z_embed = nn.Parameter(torch.zeros(cfg.grid_z, cfg.bev_dim))
        self.bev_norm = nn.LayerNorm(cfg.bev_dim)
        p, (d1, d2) = cfg.patch_size, cfg.dims
        self.patch_embed = nn.Linear(p * p * cfg.bev_dim, d1)
        self.stage1 = SwinStage(d1, cfg.heads[0], cfg.depths[0], cfg.window, cfg.mlp_ratio)
        self.merge = PatchMerging(d1, d2)
        self.stage2 = SwinStage(d2, cfg.heads[1], cfg.depths[1], cfg.window, cfg.mlp_ratio)
        self.out_norm = nn.LayerNorm(d2)
        self.out_linear = nn.Linear(d2, d2)
        self.to_code = nn.Linear(d2, cfg.code_dim)

    def forward(self, points: torch.Tensor, batch: torch.Tensor, batch_size: int) -> torch.Tensor:
        cfg = self.cfg
        X, Z = cfg.grid_xy, cfg.grid_z
        idx, b, offsets = voxelize(cfg, points, batch)
        h = self.pn2(F.relu(self.pn_norm1(self.pn1(offsets))))
        vox_key = ((b * X + idx[:, 0]) * X + idx[:, 1]) * Z + idx[:, 2]
        keys, inverse = torch.unique(vox_key, return_inverse=True)
        vox = h.new_zeros(keys.shape[0], h.shape[1]).index_add_(0, inverse, h)
        vox = self.pn_agg_norm(vox)
        vz = keys % Z
        col = keys // Z  # (b * X + ix) * X + iy
        v = self.z_linear(vox) + self.z_embed[vz]
        bev = v.new_zeros(batch_size * X * X, v.shape[1]).index_add_(0, col, v)
        bev = self.bev_norm(bev).view(batch_size, X, X, -1)
        p = cfg.patch_size
        Hp = X // p
        x = bev.view(batch_size, Hp, p, Hp, p, -1).permute(0, 1, 3, 2, 4, 5).reshape(batch_size, Hp, Hp, -1)
        x = self.patch_embed(x)
        x = x + sincos_2d(Hp, Hp, x.shape[-1], x.device).to(x.dtype)
        x = self.stage2(self.merge(self.stage1(x)))
        return self.to_code(self.out_linear(F.gelu(self.out_norm(x))))  # (B, T, T, code_dim)


class VectorQuantizer(nn.Module):
    """Nearest-code quantisation with the straight-through estimator and
    L_vq = beta_codebook |sg[z] - z_hat|^2 + beta_commit |sg[z_hat] - z|^2.

    Dead codes (unused for ``dead_after`` iterations) trigger a K-means re-initialisation of
    the whole codebook from a memory bank of recent encoder outputs when more than
    ``dead_fraction`` of the codes are dead, at most every ``reinit_every`` iterations.
    """

    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        K, D = cfg.codebook_size, cfg.code_dim
        self.codebook = nn.Parameter(torch.randn(K, D) / math.sqrt(D))
        bank = cfg.memory_factor * K
        self.register_buffer("bank", torch.zeros(bank, D))
        self.register_buffer("bank_ptr", torch.zeros((), dtype=torch.long))
        self.register_buffer("bank_filled", torch.zeros((), dtype=torch.long))
        self.register_buffer("last_used", torch.zeros(K, dtype=torch.long))
        self.register_buffer("iteration", torch.zeros((), dtype=torch.long))
        self.register_buffer("last_reinit", torch.zeros((), dtype=torch.long))
        self.register_buffer("reinits", torch.zeros((), dtype=torch.long))

    def codes_for(self, z: torch.Tensor) -> torch.Tensor:
        flat = z.reshape(-1, z.shape[-1]).float()
        cb = self.codebook.float()
        d = flat.pow(2).sum(1, keepdim=True) - 2 * flat @ cb.t() + cb.pow(2).sum(1)[None]
        return d.argmin(dim=1).view(z.shape[:-1])

    def lookup(self, codes: torch.Tensor) -> torch.Tensor:
        return F.embedding(codes, self.codebook)

    def forward(self, z: torch.Tensor):
        codes = self.codes_for(z.detach())
        zq = self.lookup(codes).to(z.dtype)
        loss = self.cfg.beta_codebook * F.mse_loss(zq, z.detach()) + self.cfg.beta_commit * F.mse_loss(z, zq.detach())
        z_st = z + (zq - z).detach()
        if self.training:
            self._track(z.detach(), codes)
        return z_st, codes, loss

    @torch.no_grad()
    def _track(self, z: torch.Tensor, codes: torch.Tensor) -> None:
        self.iteration += 1
        self.last_used[codes.unique()] = self.iteration
        flat = z.reshape(-1, z.shape[-1]).float()
        n = self.bank.shape[0]
        if flat.shape[0] > n:
            flat = flat[torch.randperm(flat.shape[0], device=flat.device)[:n]]
        m = flat.shape[0]
        pos = (self.bank_ptr + torch.arange(m, device=flat.device)) % n
        self.bank[pos] = flat
        self.bank_ptr.copy_((self.bank_ptr + m) % n)
        self.bank_filled.copy_(torch.clamp(self.bank_filled + m, max=n))

    def dead_codes(self) -> torch.Tensor:
        return (self.iteration - self.last_used) >= self.cfg.dead_after

    @torch.no_grad()
    def maybe_reinit(self) -> bool:
        """Run the K-means re-initialisation if its conditions hold; True when it ran.

        With ``kmeans_init`` the codebook is also initialised by K-means as soon as the memory
        bank is first full (a data-dependent start; the paper does not say how codes start).
        """
        cfg = self.cfg
        if cfg.kmeans_init and self.reinits.item() == 0 and self.bank_filled.item() == self.bank.shape[0]:
            return self._reinit()
        if self.iteration - self.last_reinit < cfg.reinit_every:
            return False
        if self.dead_codes().float().mean().item() <= cfg.dead_fraction:
            return False
        if self.bank_filled.item() < self.codebook.shape[0]:
            return False
        return self._reinit()

    @torch.no_grad()
    def _reinit(self) -> bool:
        cfg = self.cfg
        data = self.bank[: int(self.bank_filled.item())]
        self.codebook.data.copy_(kmeans(data, self.codebook.shape[0], cfg.kmeans_iters).to(self.codebook.dtype))
        self.last_used.fill_(int(self.iteration.item()))
        self.last_reinit.copy_(self.iteration)
        self.reinits += 1
        return True


def codebook_after_step(vq: VectorQuantizer, opt: torch.optim.Optimizer, step: int, log) -> dict:
    """The training loop's ``after_step`` for a :class:`VectorQuantizer`: its K-means
    re-initialisation when due (the optimiser's stale moments of the codebook dropped, so
    they do not drag the new codes) and the share of codes alive, for the curve."""
    if vq.maybe_reinit():
        opt.state.pop(vq.codebook, None)
        log(f"step {step}: K-means re-initialised the codebook ({int(vq.reinits)} so far)")
    return {"alive_codes": 1.0 - vq.dead_codes().float().mean().item()}


@torch.no_grad()
def kmeans(data: torch.Tensor, k: int, iters: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Lloyd's K-means on (N, D) data; empty clusters are re-seeded with random data points."""
    n = data.shape[0]
    centers = data[torch.randperm(n, generator=generator, device="cpu")[:k].to(data.device)].clone()
    for _ in range(iters):
        d = data.pow(2).sum(1, keepdim=True) - 2 * data @ centers.t() + centers.pow(2).sum(1)[None]
        assign = d.argmin(1)
        sums = torch.zeros_like(centers).index_add_(0, assign, data)
        counts = torch.bincount(assign, minlength=k).to(data.dtype)
        empty = counts == 0
        centers = sums / counts.clamp(min=1)[:, None]
        if empty.any():
            centers[empty] = data[torch.randint(0, n, (int(empty.sum()),), generator=generator).to(data.device)]
    return centers


class Decoder(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d1, d2 = cfg.dims
        self.from_code = nn.Linear(cfg.code_dim, d2)
        self.stage2 = SwinStage(d2, cfg.heads[1], cfg.depths[1], cfg.window, cfg.mlp_ratio)
        self.upsample = PatchUpsample(d2, d1)
        self.stage1 = SwinStage(d1, cfg.heads[0], cfg.depths[0], cfg.window, cfg.mlp_ratio)
        # NFG branch: LayerNorm -> Linear(d1, up^2 * Z_nfg * F) -> 3-D feature volume
        self.nfg_norm = nn.LayerNorm(d1)
        self.nfg_linear = nn.Linear(d1, cfg.nfg_up ** 2 * cfg.nfg_z * cfg.nfg_dim)
        # coarse branch: LayerNorm -> Linear(d1, p^2 * Z) voxel logits, bias -5
        self.coarse_norm = nn.LayerNorm(d1)
        self.coarse_linear = nn.Linear(d1, cfg.patch_size ** 2 * cfg.grid_z)
        # occupancy MLP on interpolated NFG features: 2 layers, hidden 32, ReLU, sigmoid
        self.mlp1 = nn.Linear(cfg.nfg_dim, cfg.mlp_hidden)
        self.mlp2 = nn.Linear(cfg.mlp_hidden, 1)

    def forward(self, zq: torch.Tensor, channels_last: bool = False):
        """BEV codes (B, T, T, code_dim) -> NFG volume (B, F, Z_nfg, X_nfg, Y_nfg) and coarse
        logits (B, X, Y, Z). With ``channels_last`` the volume's memory is laid out as
        (B, X_nfg, Y_nfg, Z_nfg, F) (the same shape and values, a permuted view: what the CPU
        ray march reads, without a second copy)."""
        cfg = self.cfg
        B, T = zq.shape[0], zq.shape[1]
        x = self.from_code(zq)
        x = x + sincos_2d(T, T, x.shape[-1], x.device).to(x.dtype)
        x = self.stage1(self.upsample(self.stage2(x)))  # (B, 2T, 2T, d1)
        H = x.shape[1]
        u, Zn, Fd = cfg.nfg_up, cfg.nfg_z, cfg.nfg_dim
        nfg = self.nfg_linear(self.nfg_norm(x)).view(B, H, H, u, u, Zn, Fd)
        if channels_last:  # (B, X, Y, Z, F) in memory, X = (row, its u), Y = (column, its u)
            nfg = nfg.permute(0, 1, 3, 2, 4, 5, 6).reshape(B, H * u, H * u, Zn, Fd).permute(0, 4, 3, 1, 2)
        else:
            nfg = nfg.permute(0, 6, 5, 1, 3, 2, 4).reshape(B, Fd, Zn, H * u, H * u)
        p, Z = cfg.patch_size, cfg.grid_z
        coarse = self.coarse_linear(self.coarse_norm(x)).view(B, H, H, p, p, Z)
        coarse = coarse.permute(0, 1, 3, 2, 4, 5).reshape(B, H * p, H * p, Z)
        return nfg, coarse

    def occupancy(self, feats: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
        """Interpolated NFG features (..., F) -> occupancy alpha in [0, 1]. Without autograd
        (inference) the MLP runs on ``chunk`` rows at a time, whose hidden layer stays in
        cache: the same numbers, about 4x faster on the CPU than one pass (measured)."""
        if torch.is_grad_enabled() or feats.numel() <= chunk * feats.shape[-1]:
            return torch.sigmoid(self.mlp2(F.relu(self.mlp1(feats)))).squeeze(-1)
        x = feats.reshape(-1, feats.shape[-1])
        w1, b1, w2, b2 = self.mlp1.weight.t(), self.mlp1.bias, self.mlp2.weight.t(), self.mlp2.bias
        out = x.new_empty(x.shape[0], 1)
        for s in range(0, x.shape[0], chunk):
            hidden = torch.addmm(b1, x[s: s + chunk], w1).relu_()
            torch.addmm(b2, hidden, w2, out=out[s: s + chunk])
        return torch.sigmoid(out).view(feats.shape[:-1])


class Tokenizer(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.vq = VectorQuantizer(cfg)
        self.decoder = Decoder(cfg)
        self._init()

    def _init(self) -> None:
        cfg = self.cfg
        init_transformer_(self, residual_layers=1)  # fan-in init everywhere ...
        for stage, depth in ((self.encoder.stage1, cfg.depths[0]), (self.encoder.stage2, cfg.depths[1]),
                             (self.decoder.stage1, cfg.depths[0]), (self.decoder.stage2, cfg.depths[1])):
            init_transformer_(stage, residual_layers=2 * depth)  # ... and GPT-2 residual scaling
        nn.init.normal_(self.encoder.z_embed, 0.0, 0.02)
        nn.init.constant_(self.decoder.coarse_linear.bias, cfg.coarse_bias)

    def encode(self, points: torch.Tensor, batch: torch.Tensor, batch_size: int):
        z = self.encoder(points, batch, batch_size)
        return self.vq(z)

    def decode_codes(self, codes: torch.Tensor, channels_last: bool = False):
        return self.decoder(self.vq.lookup(codes), channels_last=channels_last)
