"""The Copilot4D world model (paper 4.4, A.2.2): a U-Net spatio-temporal Transformer over BEV
token maps that outputs, for every frame and token, logits over the tokenizer's codebook.

Shapes: ``B`` sequences of ``T`` frames of ``H x W`` tokens; feature maps are channels-last
``(B, T, H, W, C)``. Spatial attention is Swin window attention inside each frame (the blocks
of :mod:`pcfbench.methods.copilot4d.swin`); temporal attention is a GPT-2 block over the ``T``
frames at one feature-map location, under a boolean ``(T, T)`` or ``(B, T, T)`` mask where
``mask[i, j]`` is True when frame i may attend to frame j (see :func:`causal_mask`,
:func:`identity_mask`, :func:`guidance_mask`).

Actions are the ego poses ``T_ref_sensor`` (B, T, 4, 4): frame k's sensor pose in the
reference sensor frame (t = 0, the last past frame), i.e. the transform mapping points of
sweep k's sensor frame into the reference frame, as in :class:`pcfbench.data.Sample`
(``past_T_ref_sensor`` then ``future_T_ref_sensor``). The reference frame's own pose is the
identity.

Past frames can be cached: under a causal mask a frame's features never depend on later
frames, so a pass over the context with ``return_kv=True`` yields, for every temporal block,
the keys and values of those frames, and later passes over new frames only (``past_kv``)
attend to them unchanged (Figure 10: "for all past timesteps, we only need cached keys and
values from the temporal blocks").

The network holds no device or dtype of its own beyond its parameters: inputs decide, so it
runs on CUDA under ``torch.autocast("cuda", dtype=torch.bfloat16)`` unchanged.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.copilot4d.swin import (PatchMerging, PatchUpsample, SwinBlock, attention, init_transformer_,
                                              sincos_2d)
from pcfbench.methods.copilot4d.world_config import WorldModelConfig


# --------------------------------------------------------------------------- temporal masks
def causal_mask(T: int, device=None) -> torch.Tensor:
    """(T, T) bool: frame i attends to frames 0..i (objectives 1 and 2, and sampling)."""
    return torch.ones(T, T, dtype=torch.bool, device=device).tril()


def identity_mask(T: int, device=None) -> torch.Tensor:
    """(T, T) bool: each frame attends to itself only (objective 3: the unconditional model)."""
    return torch.eye(T, dtype=torch.bool, device=device)


def guidance_mask(T: int, device=None) -> torch.Tensor:
    """(T + 1, T + 1) bool for classifier-free guidance in one pass (Figure 10): causal over the
    first T frames (past and the frame being decoded), and an appended copy of frame T-1 that
    attends only to itself and is attended by no other frame."""
    m = torch.zeros(T + 1, T + 1, dtype=torch.bool, device=device)
    m[:T, :T] = causal_mask(T, device)
    m[T, T] = True
    return m


def check_temporal_mask(mask: torch.Tensor, B: int, T: int, past: int = 0) -> torch.Tensor:
    """Validate a temporal mask and return it as (B or 1, T, past + T) bool: rows are the T
    input frames, columns the ``past`` cached frames then the T input frames."""
    if mask.dtype != torch.bool:
        raise ValueError(f"temporal mask must be bool (True = may attend), got {mask.dtype}")
    given = tuple(mask.shape)
    if mask.dim() == 2:
        mask = mask.unsqueeze(0)
    S = past + T
    if mask.dim() != 3 or mask.shape[-2:] != (T, S) or mask.shape[0] not in (1, B):
        raise ValueError(f"temporal mask has shape {given}; expected ({T}, {S}) or ({B}, {T}, {S})")
    if not bool(mask[..., past:].diagonal(dim1=-2, dim2=-1).all()):
        raise ValueError("temporal mask must let every frame attend to itself (its diagonal must be True)")
    return mask


# --------------------------------------------------------------------------- blocks
class TemporalBlock(nn.Module):
    """GPT-2 pre-norm block over time at each location: x + Attn(LN(x)); x + MLP(LN(x)).
    Bias-free Linear layers (A.2.2)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(dim)
        self.attn = nn.Module()
        self.attn.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.attn.proj = nn.Linear(dim, dim, bias=False)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.fc1 = nn.Linear(dim, hidden, bias=False)
        self.fc2 = nn.Linear(hidden, dim, bias=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor, kv: "_KV | None" = None) -> torch.Tensor:
        """x (B, T, H, W, C); mask (B or 1, T, past + T) bool; kv supplies the cached keys
        and values of the past frames and/or collects those of all frames."""
        B, T, H, W, C = x.shape
        h = self.heads
        y = self.norm1(x).permute(0, 2, 3, 1, 4).reshape(B * H * W, T, C)
        q, k, v = self.attn.qkv(y).view(B * H * W, T, 3, h, C // h).permute(2, 0, 3, 1, 4)
        if kv is not None:
            k, v = kv.extend(k, v)
        S = k.shape[-2]
        if kv is not None and kv.collect and S > T:
            q, k, mask = _as_whole_pass(q, k, mask)
        if mask.shape[0] == 1:
            attn_mask = mask  # (1, T, S) broadcasts over sequences and heads
        else:
            attn_mask = mask[:, None].expand(B, H * W, q.shape[-2], S).reshape(B * H * W, 1, q.shape[-2], S)
        y = attention(q, k, v, attn_mask)[:, :, S - T:] if q.shape[-2] > T else attention(q, k, v, attn_mask)
        y = self.attn.proj(y.transpose(1, 2).reshape(B * H * W, T, C))
        x = x + y.view(B, H, W, T, C).permute(0, 3, 1, 2, 4)
        return x + self.fc2(F.gelu(self.fc1(self.norm2(x))))


def _as_whole_pass(q: torch.Tensor, k: torch.Tensor, mask: torch.Tensor):
    """Query rows, keys and mask of a pass over all S frames for the T = q.shape[-2] new frames
    of a pass extending a cache (their rows last; the S - T earlier rows copies of the first
    new one, under causal rows, to be dropped), the keys laid out as such a pass's projection
    leaves them. Attention kernels round differently with the number of query rows and the
    keys' layout; in this shape the new frames' outputs, and so the extended cache, are bit
    for bit those of one pass over the whole sequence."""
    n, h, T, d = q.shape
    S = k.shape[-2]
    q = torch.cat([q[:, :, :1].expand(n, h, S - T, d), q], dim=2)
    k = k.new_empty(n, S, h, d).permute(0, 2, 1, 3).copy_(k)
    rows = causal_mask(S, mask.device)[: S - T].expand(mask.shape[0], S - T, S)
    return q, k, torch.cat([rows, mask], dim=1)


def _spatial_block(dim: int, heads: int, window: int, shift: bool, mlp_ratio: float) -> SwinBlock:
    blk = SwinBlock(dim, heads, window, shift, mlp_ratio)
    # A.2.2 removes every Linear bias except the Swin query/key/value projection.
    blk.fc1 = nn.Linear(blk.fc1.in_features, blk.fc1.out_features, bias=False)
    return blk


class Group(nn.Module):
    """``n_spatial`` Swin blocks on each frame (alternately shifted), then one temporal block."""

    def __init__(self, dim: int, heads: int, window: int, n_spatial: int, mlp_ratio: float) -> None:
        super().__init__()
        self.spatial = nn.ModuleList(_spatial_block(dim, heads, window, i % 2 == 1, mlp_ratio) for i in range(n_spatial))
        self.temporal = TemporalBlock(dim, heads, mlp_ratio)

    def forward(self, x: torch.Tensor, mask: torch.Tensor, kv: "_KV | None" = None) -> torch.Tensor:
        B, T, H, W, C = x.shape
        y = x.reshape(B * T, H, W, C)
        for blk in self.spatial:
            y = blk(y)
        return self.temporal(y.view(B, T, H, W, C), mask, kv)


class Stage(nn.Module):
    def __init__(self, n_groups: int, dim: int, heads: int, window: int, n_spatial: int, mlp_ratio: float) -> None:
        super().__init__()
        self.groups = nn.ModuleList(Group(dim, heads, window, n_spatial, mlp_ratio) for _ in range(n_groups))

    def forward(self, x: torch.Tensor, mask: torch.Tensor, kv: "_KV | None" = None) -> torch.Tensor:
        for g in self.groups:
            x = g(x, mask, kv)
        return x


class _KV:
    """Keys and values of the temporal blocks, in the order the blocks run: ``past`` (a list
    from an earlier pass, or None) is prepended to each block's own; with ``collect`` the
    concatenation is kept, for a later pass to extend. With ``room`` (the past's buffers hold
    ``room`` more frames after its ``frames``: :meth:`PastKV.with_room`), this pass's keys and
    values are written there instead: the same tensor as the concatenation, without copying the
    past again."""

    def __init__(self, past: list | None, collect: bool, frames: int = 0, room: int = 0) -> None:
        self.past, self.collect, self.out, self.i = past, collect, [], 0
        self.frames, self.room = frames, room

    def extend(self, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.past is not None:
            pk, pv = self.past[self.i]
            if self.room:
                pk[:, :, self.frames:], pv[:, :, self.frames:] = k, v
                k, v = pk, pv
            else:
                k, v = torch.cat([pk, k], dim=-2), torch.cat([pv, v], dim=-2)
        self.i += 1
        if self.collect:
            self.out.append((k, v))
        return k, v


class LevelMerging(nn.Module):
    """A.2.2 Level Merging: the coarser map up-sampled 2x (swin.PatchUpsample: a Linear
    'deconvolution' to 2 x 2 features), concatenated with the finer map, LayerNorm, a Linear
    reducing to the finer width. The caller adds the result to the finer map (a residual)."""

    def __init__(self, coarse_dim: int, fine_dim: int) -> None:
        super().__init__()
        self.up = PatchUpsample(coarse_dim, fine_dim)
        self.norm = nn.LayerNorm(2 * fine_dim)
        self.reduction = nn.Linear(2 * fine_dim, fine_dim, bias=False)

    def forward(self, coarse: torch.Tensor, fine: torch.Tensor) -> torch.Tensor:
        B, T, h, w, C = coarse.shape
        up = self.up(coarse.reshape(B * T, h, w, C)).view(B, T, 2 * h, 2 * w, -1)
        return self.reduction(self.norm(torch.cat([up, fine], dim=-1)))


def view_features(T_ref_sensor: torch.Tensor, grid: int, extent: float, freqs: int) -> torch.Tensor:
    """(B, T, grid, grid, 4 freqs + 2): where frame k's sensor sees every cell of a ``grid`` x
    ``grid`` map over [-extent, extent]^2 of the reference frame from (cell [i, j] centred at x =
    -extent + (i + 0.5) 2 extent / grid, y likewise with j, as the tokenizer's BEV grid).

    ``T_ref_sensor`` (B, T, 4, 4) maps frame k's sensor frame into the reference frame; the cell's
    centre, at the sensor's height, in the sensor frame is (lx, ly) = the first two rows of
    R^T (c - t). Features, with u = lx / extent, v = ly / extent: sin and cos of pi 2^f u and of
    pi 2^f v for f = 0 .. freqs-1, then the distance hypot(lx, ly) / extent and
    log(1 + distance in m) / log(1 + extent)."""
    poses = T_ref_sensor.float()
    c = -extent + (torch.arange(grid, device=poses.device, dtype=poses.dtype) + 0.5) * (2.0 * extent / grid)
    dx = c[None, None, :, None] - poses[..., 0, 3, None, None]  # (B, T, grid, 1): along x (rows i)
    dy = c[None, None, None, :] - poses[..., 1, 3, None, None]  # (B, T, 1, grid): along y (columns j)
    R = poses[..., :2, :2, None, None]  # (B, T, 2, 2, 1, 1)
    lx = R[:, :, 0, 0] * dx + R[:, :, 1, 0] * dy  # R^T (c - t), first row
    ly = R[:, :, 0, 1] * dx + R[:, :, 1, 1] * dy
    dist = torch.hypot(lx, ly)
    scale = math.pi * 2.0 ** torch.arange(freqs, device=poses.device, dtype=poses.dtype)
    u, v = (lx / extent)[..., None] * scale, (ly / extent)[..., None] * scale
    return torch.cat([u.sin(), u.cos(), v.sin(), v.cos(), (dist / extent)[..., None],
                      (torch.log1p(dist) / math.log1p(extent))[..., None]], -1)


def _lin_ln_lin(d_in: int, d: int) -> nn.Sequential:
    """Linear -> LayerNorm -> Linear: how every conditioning input enters (A.2.2)."""
    return nn.Sequential(nn.Linear(d_in, d, bias=False), nn.LayerNorm(d), nn.Linear(d, d, bias=False))


# --------------------------------------------------------------------------- the network
class WorldModel(nn.Module):
    """Logits (B, T, H, W, |V|) from tokens (B, T, H, W) in {0..|V|} (|V| = the mask token),
    ego poses ``T_ref_sensor`` (B, T, 4, 4) and a temporal mask.

    ``frame_index`` (T,) long gives each input frame's temporal position (default 0..T-1);
    the appended unconditional copy of guidance repeats the position of the frame it copies.
    Positions run 0 .. ``cfg.n_frames`` - 1 (the oldest past frame is 0).
    """

    def __init__(self, cfg: WorldModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d1, d2, d3 = cfg.dims
        (h1, h2, h3), (w1, w2, w3) = cfg.heads, cfg.windows
        V, S, r = cfg.codebook_size, cfg.spatial_per_group, cfg.mlp_ratio
        self.mask_token = V
        self.embed = nn.Embedding(V + 1, d1)  # row V: the learnable mask token; rows 0..V-1 tied to the output
        self.embed_proj = _lin_ln_lin(d1, d1)
        self.time_embed = nn.Parameter(torch.zeros(cfg.n_frames, d1))
        self.register_buffer("pos_embed", sincos_2d(cfg.token_grid, cfg.token_grid, d1), persistent=False)
        self.action = nn.ModuleList(_lin_ln_lin(16, d) for d in cfg.dims)  # added at each level's start
        if cfg.view_freqs:  # where each frame's sensor sees each token from, also at each level's start
            self.view = nn.ModuleList(_lin_ln_lin(4 * cfg.view_freqs + 2, d) for d in cfg.dims)
        self.down1 = Stage(cfg.groups_down[0], d1, h1, w1, S, r)
        self.merge12 = PatchMerging(d1, d2)
        self.down2 = Stage(cfg.groups_down[1], d2, h2, w2, S, r)
        self.merge23 = PatchMerging(d2, d3)
        self.down3 = Stage(cfg.groups_down[2], d3, h3, w3, S, r)
        self.up32 = LevelMerging(d3, d2)
        self.up2 = Stage(cfg.groups_up[1], d2, h2, w2, S, r)
        self.up21 = LevelMerging(d2, d1)
        self.up1 = Stage(cfg.groups_up[0], d1, h1, w1, S, r)
        self.out_norm = nn.LayerNorm(d1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """A.3: fan-in normal init N(0, 1/(3 fan_in)) everywhere; on each level the Linear layers
        feeding a residual are scaled by sqrt(1/L), L = 2 x the Transformer blocks of that level.
        The tied embedding is initialised as the output layer it also is (fan-in = width)."""
        cfg, S = self.cfg, self.cfg.spatial_per_group
        init_transformer_(self, 1)
        per_level = [
            ([self.down1, self.up1], cfg.groups_down[0] + cfg.groups_up[0]),
            ([self.down2, self.up2], cfg.groups_down[1] + cfg.groups_up[1]),
            ([self.down3], cfg.groups_down[2]),
        ]
        for stages, n_groups in per_level:
            for st in stages:
                init_transformer_(st, 2 * n_groups * (S + 1))
        nn.init.normal_(self.embed.weight, 0.0, math.sqrt(1.0 / (3.0 * cfg.dims[0])))
        nn.init.normal_(self.time_embed, 0.0, 0.02)

    def _action(self, level: int, poses: torch.Tensor, T: int) -> torch.Tensor:
        """What frame k's pose adds at the start of ``level`` for the last T frames of ``poses``
        (B, frames, 16): (B, T, 1, 1, C), or with ``view_freqs`` (B, T, H, W, C) (:func:`view_features`)."""
        out = self.action[level](poses)[:, -T:, None, None, :]
        if self.cfg.view_freqs:
            cfg = self.cfg
            feats = view_features(poses[:, -T:].reshape(poses.shape[0], T, 4, 4), cfg.token_grid >> level,
                                  cfg.bev_extent, cfg.view_freqs).to(poses.dtype)
            out = out + self.view[level](feats)
        return out

    def forward(self, tokens: torch.Tensor, T_ref_sensor: torch.Tensor, temporal_mask: torch.Tensor,
                frame_index: torch.Tensor | None = None, past_kv: "PastKV | None" = None,
                return_kv: bool = False):
        """Logits (B, T, H, W, |V|); with ``return_kv`` also the :class:`PastKV` of the
        ``past_kv`` frames and these T frames (meaningful when these frames attend causally).

        With ``past_kv`` (P cached frames), ``tokens``, ``T_ref_sensor`` and ``frame_index``
        describe the T new frames only and ``temporal_mask`` is (T, P + T) or (B, T, P + T).
        ``frame_index`` defaults to P .. P + T - 1.
        """
        cfg = self.cfg
        if tokens.dim() != 4 or tokens.shape[-2:] != (cfg.token_grid, cfg.token_grid):
            raise ValueError(f"tokens have shape {tuple(tokens.shape)}; expected (B, T, {cfg.token_grid}, {cfg.token_grid})")
        if tokens.dtype not in (torch.int64, torch.int32):
            raise ValueError(f"tokens must be integer codes, got {tokens.dtype}")
        B, T = tokens.shape[:2]
        if T_ref_sensor.shape != (B, T, 4, 4):
            raise ValueError(f"T_ref_sensor has shape {tuple(T_ref_sensor.shape)}; expected ({B}, {T}, 4, 4)")
        P = 0 if past_kv is None else past_kv.frames
        if past_kv is not None and past_kv.batch != B:
            raise ValueError(f"past_kv holds {past_kv.batch} sequences; tokens hold {B}")
        if past_kv is not None and past_kv.room and (past_kv.room != T or return_kv):
            raise ValueError(f"past_kv has room for {past_kv.room} new frames, not {T}"
                             + (" whose keys and values are returned (return_kv: they would be overwritten)"
                                if return_kv else ""))
        mask = check_temporal_mask(temporal_mask.to(tokens.device), B, T, P)
        if frame_index is None:
            frame_index = torch.arange(P, P + T, device=tokens.device)
        if frame_index.shape != (T,) or int(frame_index.min()) < 0 or int(frame_index.max()) >= cfg.n_frames:
            raise ValueError(f"frame_index {frame_index.tolist()} must hold {T} positions in 0..{cfg.n_frames - 1}")
        lo, hi = int(tokens.min()), int(tokens.max())
        if lo < 0 or hi > self.mask_token:
            raise ValueError(f"token codes span {lo}..{hi}; expected 0..{cfg.codebook_size} ({cfg.codebook_size} = mask)")

        poses = T_ref_sensor.reshape(B, T, 16).to(self.embed.weight.dtype)
        if past_kv is not None and return_kv and past_kv.poses is not None:
            # extending a cache: the actions of every frame, as one pass over them all computes
            # them (a small matrix product rounds differently with its number of rows)
            poses = torch.cat([past_kv.poses, poses], 1)
        x = self.embed_proj(self.embed(tokens))  # (B, T, H, W, C1)
        x = x + self.pos_embed + self.time_embed[frame_index][None, :, None, None, :] + self._action(0, poses, T)
        kv = (None if past_kv is None and not return_kv
              else _KV(None, True) if past_kv is None else _KV(past_kv.kv, return_kv, P, past_kv.room))
        x1 = self.down1(x, mask, kv)
        x = self._merge(self.merge12, x1) + self._action(1, poses, T)
        x2 = self.down2(x, mask, kv)
        x = self._merge(self.merge23, x2) + self._action(2, poses, T)
        x = self.down3(x, mask, kv)
        x = x2 + self.up32(x, x2)
        x = self.up2(x, mask, kv)
        x = x1 + self.up21(x, x1)
        x = self.up1(x, mask, kv)
        logits = F.linear(self.out_norm(x), self.embed.weight[: cfg.codebook_size])
        if return_kv:
            return logits, PastKV(kv.out, P + T, B, poses=poses if past_kv is None or past_kv.poses is not None else None)
        return logits

    @staticmethod
    def _merge(layer: PatchMerging, x: torch.Tensor) -> torch.Tensor:
        B, T, H, W, C = x.shape
        y = layer(x.reshape(B * T, H, W, C))
        return y.view(B, T, *y.shape[1:])


class PastKV:
    """Cached keys and values of ``frames`` frames for ``batch`` sequences: one (k, v) pair of
    (batch * H_l * W_l, heads, frames + room, head_dim) per temporal block, in the order they
    run; ``room`` (0 unless made by :meth:`with_room`) frames are left for a pass to fill;
    ``poses`` (batch, frames, 16), the frames' flattened poses (a pass extending the cache
    computes every frame's action, as one pass over them all would)."""

    def __init__(self, kv: list, frames: int, batch: int, room: int = 0, poses: torch.Tensor | None = None) -> None:
        self.kv, self.frames, self.batch, self.room, self.poses = kv, frames, batch, room, poses

    def with_room(self, T: int) -> "PastKV":
        """The same keys and values in new buffers with room for ``T`` more frames, for repeated
        passes over ``T`` new frames (Algorithm 2's steps): each pass writes its frames' keys
        and values into the room, and attends to exactly the tensors that concatenating them
        would build, without copying the past frames at every pass. The room is overwritten by
        the next pass, so such a cache cannot collect (``return_kv``)."""
        if self.room:
            raise ValueError("past_kv already has room for new frames")
        out = []
        for k, v in self.kv:
            n, h, P, d = k.shape
            bk, bv = k.new_empty(n, h, P + T, d), v.new_empty(n, h, P + T, d)
            bk[:, :, :P], bv[:, :, :P] = k, v
            out.append((bk, bv))
        return PastKV(out, self.frames, self.batch, T, self.poses)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


class WorldEnsemble(nn.Module):
    """World networks forecasting as one (not the paper's): the logits of a pass are the mean of
    the members' log-softmaxes (float32), a normalised product of their distributions. Each
    member keeps its own cache (:class:`EnsembleKV`); guidance, being linear in the logits,
    guides the mean as it would each member. The members must read the same codes and frames."""

    def __init__(self, members: list) -> None:
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs two networks or more, got {len(members)}")
        first = members[0].cfg
        for m in members[1:]:
            if (m.cfg.codebook_size, m.cfg.token_grid, m.cfg.n_frames) != (first.codebook_size, first.token_grid,
                                                                           first.n_frames):
                raise ValueError("ensemble members differ in codebook size, token grid or frames: "
                                 f"{first.name} and {m.cfg.name}")
        self.members = nn.ModuleList(members)
        self.cfg, self.mask_token = first, members[0].mask_token

    def forward(self, tokens: torch.Tensor, T_ref_sensor: torch.Tensor, temporal_mask: torch.Tensor,
                frame_index: torch.Tensor | None = None, past_kv: "EnsembleKV | None" = None,
                return_kv: bool = False):
        caches = [None] * len(self.members) if past_kv is None else past_kv.members
        outs = [m(tokens, T_ref_sensor, temporal_mask, frame_index, past_kv=kv, return_kv=return_kv)
                for m, kv in zip(self.members, caches)]
        logits = [o[0] if return_kv else o for o in outs]
        mean = torch.stack([x.float().log_softmax(-1) for x in logits]).mean(0)
        return (mean, EnsembleKV([o[1] for o in outs])) if return_kv else mean


class EnsembleKV:
    """The members' :class:`PastKV` of a :class:`WorldEnsemble` pass, one each."""

    def __init__(self, members: list) -> None:
        self.members = members
        self.frames, self.batch, self.room = members[0].frames, members[0].batch, members[0].room

    def with_room(self, T: int) -> "EnsembleKV":
        return EnsembleKV([m.with_room(T) for m in self.members])
