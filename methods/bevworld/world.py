"""BEVWorld's latent world model (section 3.2, figure 4): a spatio-temporal diffusion transformer
over standardised BEV latents. A window's frames (the clean past and the noisy future) are cut
into p x p patches, embedded, and pass ``depth`` pairs of blocks: temporal attention over the
frames at each patch position (causal: a frame sees itself and earlier frames), then spatial
attention over the patches of each frame. Every block is modulated by AdaLN-Zero (DiT) from its
frame's condition, the concatenation of the action (an MLP of the frame's pose in the t=0 frame)
and the diffusion timestep (sinusoidal + MLP; t = 0 marks a clean frame). The output is each
frame's noise prediction.

Parameters (``dim`` d, MLP hidden h = mlp_ratio d, condition 2d, patch p, C' channels, F frames,
frequency size f), all Linear layers with biases, LayerNorms without affine weights:

- a block (attention + MLP + AdaLN): (3d^2 + 3d) + (d^2 + d) + (2 d h + h + d) + (2d 6d + 6d);
  ``depth`` temporal and ``depth`` spatial ones;
- embeddings: patch (p^2 C' d + d), frames (F d), timestep (f d + d + d^2 + d), action
  (9 d + d + d^2 + d), the null action for guidance (d);
- the output: AdaLN (2d 2d + 2d) and the projection (d p^2 C' + p^2 C').

``paper`` (d 768, 6 pairs, h 3072, p 2, C' 4, F 10, f 256): a block 14,167,296, the embeddings
1,407,744, the output 2,373,136; 12 x 14,167,296 + 1,407,744 + 2,373,136 = 173,788,432
(:data:`PAPER_PARAMETERS`; recomputed in the tests).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.bevworld.config import WorldConfig
from pcfbench.methods.copilot4d.swin import sincos_2d

PAPER_PARAMETERS = 173_788_432


def timestep_features(t: torch.Tensor, dim: int) -> torch.Tensor:
    """(...) integer timesteps -> (..., dim) sinusoidal features (DiT's, max period 10,000)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    a = t.float()[..., None] * freqs
    return torch.cat([torch.cos(a), torch.sin(a)], dim=-1)


def pose_features(T_s0_s: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) poses in the t=0 sensor frame -> (..., 9): translation, the rotation's first two columns."""
    return torch.cat([T_s0_s[..., :3, 3], T_s0_s[..., :3, 0], T_s0_s[..., :3, 1]], dim=-1)


def _modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale) + shift


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, causal: bool) -> torch.Tensor:
        n, L, d = x.shape
        q, k, v = self.qkv(x).view(n, L, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v, is_causal=causal)
        return self.proj(out.transpose(1, 2).reshape(n, L, d))


class Block(nn.Module):
    """Attention + MLP under AdaLN-Zero; ``temporal`` attends over frames (causally), else over
    the patches of a frame. Tokens (B, T, N, d), conditions (B, T, 2d)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, temporal: bool) -> None:
        super().__init__()
        self.temporal = temporal
        hidden = int(dim * mlp_ratio)
        self.norm1 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)
        self.ada = nn.Linear(2 * dim, 6 * dim)

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        B, T, N, d = x.shape
        s1, k1, g1, s2, k2, g2 = self.ada(F.silu(c))[:, :, None, :].chunk(6, dim=-1)
        h = _modulate(self.norm1(x), s1, k1)
        if self.temporal:
            h = self.attn(h.transpose(1, 2).reshape(B * N, T, d), causal=True).view(B, N, T, d).transpose(1, 2)
        else:
            h = self.attn(h.reshape(B * T, N, d), causal=False).view(B, T, N, d)
        x = x + g1 * h
        return x + g2 * self.fc2(F.gelu(self.fc1(_modulate(self.norm2(x), s2, k2)), approximate="tanh"))


class WorldModel(nn.Module):
    def __init__(self, cfg: WorldConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d, p, C = cfg.dim, cfg.patch, cfg.latent_channels
        self.patch_embed = nn.Linear(p * p * C, d)
        self.frame_embed = nn.Parameter(torch.zeros(cfg.frames, d))
        self.t_mlp = nn.Sequential(nn.Linear(cfg.freq_dim, d), nn.SiLU(), nn.Linear(d, d))
        self.action_mlp = nn.Sequential(nn.Linear(cfg.pose_dim, d), nn.SiLU(), nn.Linear(d, d))
        self.null_action = nn.Parameter(torch.zeros(d))
        self.blocks = nn.ModuleList(Block(d, cfg.heads, cfg.mlp_ratio, temporal=(i % 2 == 0))
                                    for i in range(2 * cfg.depth))
        self.final_norm = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.final_ada = nn.Linear(2 * d, 2 * d)
        self.out = nn.Linear(d, p * p * C)
        self.register_buffer("pos", sincos_2d(cfg.token_grid, cfg.token_grid, d).reshape(-1, d), persistent=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """DiT's: Xavier-uniform Linear layers, zero biases, N(0, 0.02) embeddings, and the AdaLN
        and output layers zero (every block starts as the identity)."""
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
        for e in (self.frame_embed, self.null_action, self.t_mlp[0].weight, self.t_mlp[2].weight,
                  self.action_mlp[0].weight, self.action_mlp[2].weight):
            nn.init.normal_(e, 0.0, 0.02)
        for m in [b.ada for b in self.blocks] + [self.final_ada, self.out]:
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)

    def condition(self, t: torch.Tensor, poses: torch.Tensor, drop_action: torch.Tensor | None = None) -> torch.Tensor:
        """(B, T) timesteps, (B, T, 4, 4) poses in the t=0 frame -> (B, T, 2d); windows where
        ``drop_action`` (B,) holds take the learned null action (classifier-free guidance)."""
        a = self.action_mlp(pose_features(poses.float()))
        if drop_action is not None:
            a = torch.where(drop_action[:, None, None], self.null_action.expand_as(a), a)
        return torch.cat([a, self.t_mlp(timestep_features(t, self.cfg.freq_dim))], dim=-1)

    def forward(self, x: torch.Tensor, t: torch.Tensor, poses: torch.Tensor, frames: torch.Tensor | None = None,
                drop_action: torch.Tensor | None = None) -> torch.Tensor:
        """Latents (B, T, H, W, C') (clean past and noisy future), timesteps (B, T) (0: clean),
        poses (B, T, 4, 4) -> predicted noise (B, T, H, W, C'). ``frames`` (T,): each input frame's
        index into the frame embeddings (default 0..T-1; a shorter window of the curriculum
        keeps its frames' places relative to t=0)."""
        cfg = self.cfg
        B, T, H, W, C = x.shape
        p = cfg.patch
        if frames is None:
            frames = torch.arange(T, device=x.device)
        h = x.view(B, T, H // p, p, W // p, p, C).permute(0, 1, 2, 4, 3, 5, 6).reshape(B, T, -1, p * p * C)
        h = self.patch_embed(h) + self.pos[None, None] + self.frame_embed[frames][None, :, None, :]
        c = self.condition(t, poses, drop_action)
        for blk in self.blocks:
            h = blk(h, c)
        shift, scale = self.final_ada(F.silu(c))[:, :, None, :].chunk(2, dim=-1)
        out = self.out(_modulate(self.final_norm(h), shift, scale))
        return out.view(B, T, H // p, W // p, p, p, C).permute(0, 1, 2, 4, 3, 5, 6).reshape(B, T, H, W, C)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())

