"""Swin Transformer pieces (Liu et al. 2021): (shifted) window attention blocks, Patch Merging,
and the paper's Patch Upsample. Feature maps are channels-last: (B, H, W, C)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


#: cuDNN's fused attention fails ("mha_graph.execute(...).is_good()") on a batch of 2^16 or
#: more sequences (PyTorch issue 181085, fixed after 2.11): the paper world model's temporal
#: blocks reach it at 4 sequences of 128 x 128 locations. CUDA batches are cut below it.
CUDA_SDPA_MAX_BATCH = 32768


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: torch.Tensor,
              max_batch: int | None = None) -> torch.Tensor:
    """``F.scaled_dot_product_attention`` over (n, heads, L, d) in batches of at most
    ``max_batch`` sequences (default: :data:`CUDA_SDPA_MAX_BATCH` on CUDA, unbounded on the
    CPU); ``attn_mask`` has a batch dimension of n or 1. Sequences are independent, so the
    result is the same however the batch is cut."""
    n = q.shape[0]
    if max_batch is None:
        max_batch = CUDA_SDPA_MAX_BATCH if q.is_cuda else n
    if n <= max_batch:
        return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)
    parts = []
    for s in range(0, n, max_batch):
        m = attn_mask if attn_mask.shape[0] == 1 else attn_mask[s:s + max_batch]
        parts.append(F.scaled_dot_product_attention(q[s:s + max_batch], k[s:s + max_batch], v[s:s + max_batch],
                                                    attn_mask=m))
    return torch.cat(parts)


def _windows(x: torch.Tensor, w: int) -> torch.Tensor:
    """(B, H, W, C) -> (B * nW, w*w, C)."""
    B, H, W, C = x.shape
    x = x.view(B, H // w, w, W // w, w, C).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, w * w, C)


def _unwindows(x: torch.Tensor, w: int, B: int, H: int, W: int) -> torch.Tensor:
    C = x.shape[-1]
    x = x.view(B, H // w, W // w, w, w, C).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(B, H, W, C)


class WindowAttention(nn.Module):
    """Multi-head self-attention inside w x w windows with a learned relative position bias."""

    def __init__(self, dim: int, heads: int, window: int) -> None:
        super().__init__()
        self.heads, self.window = heads, window
        self.qkv = nn.Linear(dim, 3 * dim, bias=True)
        self.proj = nn.Linear(dim, dim, bias=False)
        self.rel_bias = nn.Parameter(torch.zeros((2 * window - 1) ** 2, heads))
        coords = torch.stack(torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")).flatten(1)
        rel = coords[:, :, None] - coords[:, None, :] + window - 1  # (2, w*w, w*w)
        self.register_buffer("rel_index", rel[0] * (2 * window - 1) + rel[1], persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        n, L, C = x.shape
        q, k, v = self.qkv(x).view(n, L, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        out = attention(q, k, v, self._bias(n, mask, q.dtype))
        return self.proj(out.transpose(1, 2).reshape(n, L, C))

    def _bias(self, n: int, mask: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor:
        """The relative position bias (1, h, L, L), plus ``mask`` (nW, L, L) additive repeated
        over the n // nW images: (n, h, L, L). Without autograd it is kept for the next call
        of the same shape while the bias parameter is unchanged (its version counter and
        storage say so): inference passes rebuild the same tensor otherwise."""
        key = None
        if not torch.is_grad_enabled():
            key = (n, None if mask is None else (mask.data_ptr(), tuple(mask.shape)), dtype, self.rel_bias.device,
                   self.rel_bias.data_ptr(), self.rel_bias._version)
            hit = getattr(self, "_bias_cache", None)
            if hit is not None and hit[0] == key:
                return hit[1]
        bias = self.rel_bias[self.rel_index].permute(2, 0, 1).unsqueeze(0)  # (1, h, L, L)
        if mask is not None:  # (nW, L, L) additive, repeated over the batch
            nW = mask.shape[0]
            bias = (bias + mask.unsqueeze(1)).repeat(n // nW, 1, 1, 1)
        bias = bias.to(dtype)
        if key is not None:
            self._bias_cache = (key, bias)
        return bias


class SwinBlock(nn.Module):
    """Pre-norm block: x + WindowAttention(LN(x)); x + MLP(LN(x)); optionally shifted by w/2."""

    def __init__(self, dim: int, heads: int, window: int, shift: bool, mlp_ratio: float) -> None:
        super().__init__()
        self.window, self.shift = window, shift
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim, heads, window)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim, bias=False)
        self._mask_cache: dict[tuple, torch.Tensor] = {}

    def _mask(self, H: int, W: int, device: torch.device) -> torch.Tensor | None:
        if not self.shift or (H <= self.window and W <= self.window):
            return None
        key = (H, W, str(device))
        if key not in self._mask_cache:
            w, s = self.window, self.window // 2
            region = torch.zeros(1, H, W, 1, device=device)
            cnt = 0
            for hs in (slice(0, -w), slice(-w, -s), slice(-s, None)):
                for ws in (slice(0, -w), slice(-w, -s), slice(-s, None)):
                    region[:, hs, ws] = cnt
                    cnt += 1
            r = _windows(region, w).squeeze(-1)  # (nW, L)
            m = (r[:, :, None] != r[:, None, :]).float() * -1e4
            self._mask_cache[key] = m
        return self._mask_cache[key]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, H, W, C = x.shape
        w = min(self.window, H, W)
        shift = self.shift and w == self.window and H > w
        y = self.norm1(x)
        if shift:
            y = torch.roll(y, shifts=(-(w // 2), -(w // 2)), dims=(1, 2))
        y = _unwindows(self.attn(_windows(y, w), self._mask(H, W, x.device) if shift else None), w, B, H, W)
        if shift:
            y = torch.roll(y, shifts=(w // 2, w // 2), dims=(1, 2))
        x = x + y
        return x + self.fc2(F.gelu(self.fc1(self.norm2(x))))


class SwinStage(nn.Module):
    def __init__(self, dim: int, heads: int, depth: int, window: int, mlp_ratio: float) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(SwinBlock(dim, heads, window, i % 2 == 1, mlp_ratio) for i in range(depth))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for blk in self.blocks:
            x = blk(x)
        return x


class PatchMerging(nn.Module):
    """2x2 neighbours concatenated -> LayerNorm -> Linear(4C, C_out): halves H and W."""

    def __init__(self, dim: int, out_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(4 * dim)
        self.reduction = nn.Linear(4 * dim, out_dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, H, W, C = x.shape
        x = x.view(B, H // 2, 2, W // 2, 2, C).permute(0, 1, 3, 2, 4, 5).reshape(B, H // 2, W // 2, 4 * C)
        return self.reduction(self.norm(x))


class PatchUpsample(nn.Module):
    """A.2.1: Linear to 2x2 upsampled features (a deconvolution) -> LayerNorm -> Linear reducing
    the feature size. Doubles H and W."""

    def __init__(self, dim: int, out_dim: int) -> None:
        super().__init__()
        self.expand = nn.Linear(dim, 4 * dim, bias=False)
        self.norm = nn.LayerNorm(dim)
        self.reduction = nn.Linear(dim, out_dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, H, W, C = x.shape
        x = self.expand(x).view(B, H, W, 2, 2, C).permute(0, 1, 3, 2, 4, 5).reshape(B, 2 * H, 2 * W, C)
        return self.reduction(self.norm(x))


def sincos_2d(h: int, w: int, dim: int, device=None) -> torch.Tensor:
    """ViT-style fixed 2-D sine-cosine absolute positional encoding, (h, w, dim)."""
    assert dim % 4 == 0, "positional encoding needs a feature size divisible by 4"
    q = dim // 4
    omega = 1.0 / (10000 ** (torch.arange(q, dtype=torch.float32, device=device) / q))
    ys = torch.arange(h, dtype=torch.float32, device=device)[:, None] * omega
    xs = torch.arange(w, dtype=torch.float32, device=device)[:, None] * omega
    pe_y = torch.cat([ys.sin(), ys.cos()], dim=1)[:, None, :].expand(h, w, 2 * q)
    pe_x = torch.cat([xs.sin(), xs.cos()], dim=1)[None, :, :].expand(h, w, 2 * q)
    return torch.cat([pe_y, pe_x], dim=-1)


def init_transformer_(module: nn.Module, residual_layers: int) -> None:
    """A.3 init: weights ~ N(0, 1/(3 * fan_in)); Linear layers feeding a residual (attn.proj,
    fc2) scaled by sqrt(1 / L), L = 2 x blocks on that stage; biases zero; LayerNorm 1/0."""
    for name, m in module.named_modules():
        if isinstance(m, nn.Linear):
            std = math.sqrt(1.0 / (3.0 * m.in_features))
            if name.endswith("attn.proj") or name.endswith("fc2"):
                std *= math.sqrt(1.0 / max(residual_layers, 1))
            nn.init.normal_(m.weight, 0.0, std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.LayerNorm):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
