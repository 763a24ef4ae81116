"""OccWorld's spatio-temporal generative transformer (section 3.3), as the public
``PlanUAutoRegTransformer`` builds it, with ego-pose tokens that carry the given motion.

Inputs: the code vectors of T frames (B, T, C, h, w) (the tokenizer's codebook entries) and
one pose feature per frame (B, T, pose_dim). Output position t predicts frame t + 1: the
logits over the codebook of its tokens (B, T, N, h, w) and the next motion (B, T, pose_dim).

Each frame's tokens are the *keys* (position t gets temporal embedding t) and, shifted by one
embedding, the *queries* (embedding t + 1). Over ``len(channels) - 1`` scales the U-Net's
encoder side does, per scale: ego-pose attention (the pose query of frame t attends causally
to the pose tokens of frames <= t, then to all scene queries of frame t), an MLP on the pose
stream, ``temporal_layers`` layers of temporal attention (each spatial position's query of
frame t attends to the keys of frames <= t at that position: the causal mask), two residual
conv blocks ("UnetBlock": LayerNorm, 3x3 conv, ReLU, 3x3 conv, shortcut) on queries and keys
alike, and a 2x2 stride-2 convolution merging each 2 x 2 window. The middle has two blocks at
the coarsest scale; the decoder side up-samples (2x2 transposed convolution), concatenates the
encoder's output of that scale, and repeats temporal attention, pose attention and blocks. A
3x3 convolution gives the code logits, a linear layer and the pose decoder the motion. At
each scale the scene queries also get their frame's ego query (``ego``, below).

The pose of position t is the motion from frame t to frame t + 1 (``motion_features``): the
benchmark gives every future pose, so the prediction of frame t + 1 knows where the sensor
will be (``given`` poses, the default). With the pose predictor (option), the motions of
future positions are the model's own predictions instead, as the paper plans.

Parameter count of ``paper`` (``PAPER_PARAMETERS``; C = 128 codes, channels 128, 256, 512,
50 x 50 tokens, 6 temporal and 2 pose layers, 9 positions), with MHA(c) = 4c^2 + 4c, FFN(c) =
8c^2 + 5c, LN(n) = 2n, T(c) = MHA + LN + FFN + LN, P(c) = 2 MHA + 3 LN + FFN,
UB(s, i, o) = LN(s) + conv(3, i, o) + conv(3, o, o) [+ conv(1, i, o) if i != o], MLP(i, o) =
lin(i, o) + lin(o, o):

    embeddings     2 x 10 x 128                                                    =      2,560
    scale 1 (50^2) 6 T(128) + UB(50^2, 128, 128) x 2 + conv(2, 128, 128)
                   + 2 P(128) + MLP(128, 128) + lin(128, 128)                      =  2,434,320
    scale 2 (25^2) 6 T(128) + UB(25^2, 128, 256) + UB(25^2, 256, 256)
                   + conv(2, 256, 256) + 2 P(128) + MLP(128, 256) + lin(128, 128)  =  4,197,444
    middle (12^2)  UB((256, 12^2), 256, 512) + UB((512, 12^2), 512, 512) + MLP(256, 512)
                                                                                   =  9,006,592
    up 2 (25^2)    convT(512, 256) + 6 T(512) + UB((512, 25^2), 512, 256)
                   + UB((256, 25^2), 256, 256) + lin(512, 256) + 2 P(512) + MLP(512, 256)
                   + lin(512, 512)                                                 = 32,479,488
    up 1 (50^2)    convT(256, 128) + 6 T(256) + UB((256, 50^2), 256, 128)
                   + UB((128, 50^2), 128, 128) + lin(256, 128) + 2 P(256) + MLP(256, 128)
                   + lin(256, 256)                                                 =  9,815,424
    out            conv(3, 128, 512) + lin(128, 128)                               =    606,848
    pose encoder   lin(9, 128) + lin(128, 128)                                     =     17,792
    pose decoder   lin(128, 128) + lin(128, 9)                                     =     17,673
                                                                                     -----------
                                                                                     58,578,141

(the public model: 16 embedding rows, a 5-input pose encoder, a 3-mode, 2-D pose decoder, and
no ``lin`` from the ego token to the scene: see below).

**Ego to scene** (not in the public code). In the public transformer the ego queries attend to
the scene queries, but nothing flows back: its scene forecast does not depend on the poses at
all. The paper says the scene tokens are aggregated with the ego token and interact with it
(section 3.3). Here, at every scale, after the pose layers, each scene query of frame t gets
a linear map of frame t's ego query added (what a cross-attention to that single ego token
computes), so the forecast of frame t + 1 hears the motion into it; a test checks that it
does, and that it stays causal.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.occworld.config import WorldConfig

#: ``paper``'s parameter count, derived by hand in the module docstring
PAPER_PARAMETERS = 58_578_141


def causal_mask(n: int, device=None) -> torch.Tensor:
    """(n, n) bool, True where attention is blocked: position i sees positions 0..i."""
    return torch.ones(n, n, dtype=torch.bool, device=device).triu(1)


class FFN(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(c, 4 * c), nn.Linear(4 * c, c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class TemporalLayer(nn.Module):
    """Queries attend to the keys of the same spatial position, causally in time (post-norm)."""

    def __init__(self, c: int, heads: int) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(c, heads, batch_first=True)
        self.norm1, self.ffn, self.norm2 = nn.LayerNorm(c), FFN(c), nn.LayerNorm(c)

    def forward(self, q: torch.Tensor, kv: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        q = self.norm1(q + self.attn(q, kv, kv, attn_mask=mask, need_weights=False)[0])
        return self.norm2(q + self.ffn(q))


class PoseLayer(nn.Module):
    """The ego query of frame t: causal temporal attention to the pose keys, then attention to
    every scene query of frame t, then an FFN (post-norm)."""

    def __init__(self, c: int, heads: int) -> None:
        super().__init__()
        self.temporal = nn.MultiheadAttention(c, heads, batch_first=True)
        self.norm1 = nn.LayerNorm(c)
        self.spatial = nn.MultiheadAttention(c, heads, batch_first=True)
        self.norm2, self.ffn, self.norm3 = nn.LayerNorm(c), FFN(c), nn.LayerNorm(c)

    def forward(self, pq: torch.Tensor, pk: torch.Tensor, scene: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        B, T, C = pq.shape
        pq = self.norm1(pq + self.temporal(pq, pk, pk, attn_mask=mask, need_weights=False)[0])
        x = pq.reshape(B * T, 1, C)
        x = self.norm2(x + self.spatial(x, scene, scene, need_weights=False)[0])
        x = self.norm3(x + self.ffn(x))
        return x.view(B, T, C)


class UnetBlock(nn.Module):
    """LayerNorm over ``shape`` (the trailing dims), 3x3 conv, ReLU, 3x3 conv, shortcut, ReLU."""

    def __init__(self, shape: tuple[int, ...], cin: int, cout: int) -> None:
        super().__init__()
        self.ln = nn.LayerNorm(shape)
        self.conv1, self.conv2 = nn.Conv2d(cin, cout, 3, padding=1), nn.Conv2d(cout, cout, 3, padding=1)
        self.shortcut = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv2(F.relu(self.conv1(self.ln(x))))
        return F.relu(h + self.shortcut(x))


def _mlp(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, cout), nn.ReLU(), nn.Linear(cout, cout), nn.ReLU())


class WorldModel(nn.Module):
    def __init__(self, cfg: WorldConfig) -> None:
        super().__init__()
        self.cfg = cfg
        C, (H, W), L = cfg.code_dim, cfg.token_grid, cfg.positions
        self.time_embed = nn.Embedding(L + 1, C)
        self.pose_time_embed = nn.Embedding(L + 1, C)
        self.pose_encoder = nn.Sequential(nn.Linear(cfg.pose_dim, C), nn.ReLU(), nn.Linear(C, C))
        Hs, Ws = [H], [W]
        for _ in cfg.channels[1:]:
            Hs.append(Hs[-1] // 2)
            Ws.append(Ws[-1] // 2)
        self.enc_temporal, self.enc_blocks, self.downs = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        self.enc_pose, self.enc_pose_mlp, self.enc_ego = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        pre = C
        for ch, h, w in zip(cfg.channels[:-1], Hs[:-1], Ws[:-1]):
            self.enc_temporal.append(nn.ModuleList(TemporalLayer(pre, cfg.heads) for _ in range(cfg.temporal_layers)))
            self.enc_blocks.append(nn.Sequential(UnetBlock((h, w), pre, ch), UnetBlock((h, w), ch, ch)))
            self.downs.append(nn.Conv2d(ch, ch, 2, stride=2))
            self.enc_pose.append(nn.ModuleList(PoseLayer(pre, cfg.heads) for _ in range(cfg.pose_layers)))
            self.enc_pose_mlp.append(_mlp(pre, ch))
            self.enc_ego.append(nn.Linear(pre, pre))
            pre = ch
        ch = cfg.channels[-1]
        self.mid = nn.Sequential(UnetBlock((pre, Hs[-1], Ws[-1]), pre, ch), UnetBlock((ch, Hs[-1], Ws[-1]), ch, ch))
        self.pose_mid = _mlp(pre, ch)
        pre = ch
        self.ups, self.dec_temporal, self.dec_blocks = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        self.pose_up, self.dec_pose, self.dec_pose_mlp = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        self.dec_ego = nn.ModuleList()
        for ch, h, w in zip(cfg.channels[-2::-1], Hs[-2::-1], Ws[-2::-1]):
            agg = 2 * ch
            self.ups.append(nn.ConvTranspose2d(pre, ch, 2, stride=2))
            self.dec_temporal.append(nn.ModuleList(TemporalLayer(agg, cfg.heads) for _ in range(cfg.temporal_layers)))
            self.dec_blocks.append(nn.Sequential(UnetBlock((agg, h, w), agg, ch), UnetBlock((ch, h, w), ch, ch)))
            self.pose_up.append(nn.Linear(pre, ch))
            self.dec_pose.append(nn.ModuleList(PoseLayer(agg, cfg.heads) for _ in range(cfg.pose_layers)))
            self.dec_pose_mlp.append(_mlp(agg, ch))
            self.dec_ego.append(nn.Linear(agg, agg))
            pre = ch
        self.conv_out = nn.Conv2d(pre, cfg.codebook_size, 3, padding=1)
        self.pose_out = nn.Linear(pre, C)
        self.pose_decoder = nn.Sequential(nn.Linear(C, C), nn.ReLU(), nn.Linear(C, cfg.pose_dim))

    @staticmethod
    def _temporal(layers, q, k, B, mask):
        """Temporal attention at every spatial position: (B*Tq, c, h, w) queries attend to
        (B*T, c, h, w) keys."""
        _, c, h, w = q.shape
        Tq, T = q.shape[0] // B, k.shape[0] // B
        qs = q.view(B, Tq, c, h * w).permute(0, 3, 1, 2).reshape(B * h * w, Tq, c)
        ks = k.view(B, T, c, h * w).permute(0, 3, 1, 2).reshape(B * h * w, T, c)
        for layer in layers:
            qs = layer(qs, ks, mask)
        return qs.view(B, h * w, Tq, c).permute(0, 2, 3, 1).reshape(B * Tq, c, h, w)

    @staticmethod
    def _pose(layers, pq, pk, q, B, mask):
        _, c, h, w = q.shape
        scene = q.view(q.shape[0], c, h * w).transpose(1, 2)
        for layer in layers:
            pq = layer(pq, pk, scene, mask)
        return pq

    def forward(self, codes_vec: torch.Tensor, poses: torch.Tensor):
        """(B, T, C, h, w) code vectors and (B, T, pose_dim) motions -> (B, T, N, h, w) logits
        of the next frame's codes and (B, T, pose_dim) the next motion."""
        T = codes_vec.shape[1]
        if T > self.cfg.positions:
            raise ValueError(f"{T} frames: the model holds at most {self.cfg.positions}")
        return self.queries(codes_vec, poses, self.keys(codes_vec, poses), 0, causal_mask(T, codes_vec.device))

    def keys(self, codes_vec: torch.Tensor, poses: torch.Tensor, start: int = 0) -> list:
        """The key side of frames at positions start .. start + T - 1 ((B, T, C, h, w) code
        vectors, (B, T, pose_dim) motions): at each attention site, in order, the (pose keys
        (B, T, c), scene keys (B*T, c', h', w')) the queries attend to there. A frame's keys
        depend on that frame and its position alone, so the keys of a longer window are these
        frames' beside the others' (``cat_keys``): what an autoregressive forecast keeps."""
        B, T, C, H, W = codes_vec.shape
        k = codes_vec.reshape(B * T, C, H, W) + self.time_embed.weight[start:start + T].repeat(B, 1)[:, :, None, None]
        pk = self.pose_encoder(poses) + self.pose_time_embed.weight[None, start:start + T]
        sites, skips = [], []
        for blocks, down, pmlp in zip(self.enc_blocks, self.downs, self.enc_pose_mlp):
            sites.append((pk, k))
            pk, k = pmlp(pk), blocks(k)
            skips.append((k, pk))
            k = down(k)
        k, pk = self.mid(k), self.pose_mid(pk)
        for up, blocks, pup, pmlp, (sk, spk) in zip(self.ups, self.dec_blocks, self.pose_up, self.dec_pose_mlp,
                                                    skips[::-1]):
            k = torch.cat([self._fit(up(k), sk), sk], 1)
            pk = torch.cat([pup(pk), spk], -1)
            sites.append((pk, k))
            pk, k = pmlp(pk), blocks(k)
        return sites

    def queries(self, codes_vec: torch.Tensor, poses: torch.Tensor, sites: list, start: int, mask: torch.Tensor):
        """The logits (B, Tq, N, h, w) and next motions (B, Tq, pose_dim) of the frames at
        positions start .. start + Tq - 1 ((B, Tq, C, h, w) code vectors, (B, Tq, pose_dim)
        motions), their queries attending to the keys ``sites`` (:meth:`keys`) of T frames
        under ``mask`` (Tq, T) (True: blocked)."""
        B, Tq, C, H, W = codes_vec.shape
        q = codes_vec.reshape(B * Tq, C, H, W) + self.time_embed.weight[start + 1:start + Tq + 1].repeat(B, 1)[:, :, None,
                                                                                                               None]
        pq = self.pose_encoder(poses) + self.pose_time_embed.weight[None, start + 1:start + Tq + 1]
        n_enc, skips = len(self.enc_blocks), []
        for (pk, k), tl, blocks, down, pl, pmlp, ego in zip(sites, self.enc_temporal, self.enc_blocks, self.downs,
                                                             self.enc_pose, self.enc_pose_mlp, self.enc_ego):
            pq = self._pose(pl, pq, pk, q, B, mask)
            q = q + ego(pq).reshape(B * Tq, -1, 1, 1)  # every scene query of frame t hears its ego token
            pq = pmlp(pq)
            q = blocks(self._temporal(tl, q, k, B, mask))
            skips.append((q, pq))
            q = down(q)
        q, pq = self.mid(q), self.pose_mid(pq)
        for (pk, k), up, tl, blocks, pup, pl, pmlp, ego, (sq, spq) in zip(
                sites[n_enc:], self.ups, self.dec_temporal, self.dec_blocks, self.pose_up, self.dec_pose,
                self.dec_pose_mlp, self.dec_ego, skips[::-1]):
            q = torch.cat([self._fit(up(q), sq), sq], 1)
            q = self._temporal(tl, q, k, B, mask)
            pq = self._pose(pl, torch.cat([pup(pq), spq], -1), pk, q, B, mask)
            q = q + ego(pq).reshape(B * Tq, -1, 1, 1)
            pq = pmlp(pq)
            q = blocks(q)
        logits = self.conv_out(q).view(B, Tq, self.cfg.codebook_size, H, W)
        return logits, self.pose_decoder(self.pose_out(pq))

    @staticmethod
    def _fit(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Pad ``x`` to ``like``'s spatial size (odd sizes halve down; the up-sampling doubles)."""
        dh, dw = like.shape[-2] - x.shape[-2], like.shape[-1] - x.shape[-1]
        return F.pad(x, (dw // 2, dw - dw // 2, dh // 2, dh - dh // 2)) if dh or dw else x


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


# --------------------------------------------------------------------------- poses
def motion_features(T_a_b: np.ndarray | torch.Tensor):
    """(..., 4, 4) motions -> (..., 9): the translation and the first two columns of the rotation."""
    if isinstance(T_a_b, torch.Tensor):
        return torch.cat([T_a_b[..., :3, 3], T_a_b[..., :3, 0], T_a_b[..., :3, 1]], dim=-1)
    return np.concatenate([T_a_b[..., :3, 3], T_a_b[..., :3, 0], T_a_b[..., :3, 1]], axis=-1)


def window_motions(poses: torch.Tensor) -> torch.Tensor:
    """(B, T, 4, 4) sensor poses in one frame -> (B, T - 1, 9): position t's motion, frame t to t + 1."""
    rel = torch.linalg.inv(poses[:, :-1]) @ poses[:, 1:]
    return motion_features(rel)


def world_losses(model: WorldModel, codes: torch.Tensor, code_vectors: torch.Tensor, poses: torch.Tensor) -> dict:
    """One window batch's losses: (B, T) token maps ``codes`` (B, T, h, w), their vectors
    (B, T, C, h, w), the sensor poses (B, T, 4, 4) in one frame. Positions 0..T-2 predict frames
    1..T-1: cross entropy over the codebook + ``pose_weight`` x the mean squared error of the
    predicted next motion (positions 0..T-3, whose next motion the window holds)."""
    cfg = model.cfg
    motions = window_motions(poses)  # (B, T-1, 9)
    logits, pose_pred = model(code_vectors[:, :-1], motions)
    target = codes[:, 1:].long()
    ce = F.cross_entropy(logits.float().flatten(0, 1), target.flatten(0, 1))
    pose = (F.mse_loss(pose_pred[:, :-1].float(), motions[:, 1:]) if motions.shape[1] > 1
            else pose_pred.sum() * 0.0)
    with torch.no_grad():
        pred = logits.argmax(2)
        acc = (pred == target).float().mean()
        changed = target != codes[:, :-1]  # tokens that differ from the frame before
        ch_acc = (pred[changed] == target[changed]).float().mean() if changed.any() else acc.new_tensor(float("nan"))
    return {"loss": ce + cfg.pose_weight * pose, "ce": ce, "pose": pose, "accuracy": acc,
            "changed_accuracy": ch_acc, "changed_share": changed.float().mean()}


def cat_keys(a: list, b: list, B: int) -> list:
    """The keys (:meth:`WorldModel.keys`) of the frames of ``a`` followed by those of ``b``."""
    def cat(x, y):
        if x.dim() == 3:  # pose keys (B, T, c)
            return torch.cat([x, y], 1)
        return torch.cat([x.view(B, -1, *x.shape[1:]), y.view(B, -1, *y.shape[1:])], 1).flatten(0, 1)

    return [(cat(pa, pb), cat(ka, kb)) for (pa, ka), (pb, kb) in zip(a, b)]


@torch.no_grad()
def forecast_codes(model: WorldModel, embed, past_codes: torch.Tensor, poses: torch.Tensor, n_future: int, *,
                   predict_poses: bool = False, cached: bool = True) -> torch.Tensor:
    """Autoregressive forecast: (B, P, h, w) past codes, (B, P + n_future, 4, 4) every frame's
    sensor pose in one frame -> (B, n_future, h, w) codes (arg max, as the public inference).
    ``embed`` maps codes to their vectors (the tokenizer's codebook). With ``predict_poses``,
    the motions into future frames are the model's predictions instead of the given poses.
    The context holds the last ``positions`` frames.

    ``cached`` (with the given poses, and when the window never slides: P + n_future - 1 <=
    positions): each step computes the newest frame's keys and its queries alone, the earlier
    frames' keys kept (``WorldModel.keys``: causal, a frame's keys depend on it alone), instead
    of the whole window again; the same logits to float rounding (the tests compare the codes),
    0.2x the world model's time at the tiny configuration (docs/occworld.md)."""
    motions = window_motions(poses)  # (B, P + F - 1, 9)
    seq = past_codes
    B, P = past_codes.shape[:2]
    L = model.cfg.positions
    out = []
    if cached and not predict_poses and P + n_future - 1 <= L:
        sites = model.keys(embed(seq), motions[:, :P])
        for f in range(n_future):
            n = P + f  # frames so far; the newest, at position n - 1, predicts frame n
            logits = model.queries(embed(seq[:, n - 1:]), motions[:, n - 1:n], sites, n - 1,
                                   causal_mask(n, seq.device)[n - 1:])[0]
            nxt = logits[:, -1].argmax(1)
            out.append(nxt)
            seq = torch.cat([seq, nxt[:, None]], 1)
            if f < n_future - 1:
                sites = cat_keys(sites, model.keys(embed(nxt[:, None]), motions[:, n:n + 1], n), B)
        return torch.stack(out, 1)
    if predict_poses and P >= 2:  # the motion into the first future frame, from the last past position but one
        motions = motions.clone()
        motions[:, P - 1] = model(embed(seq[:, max(0, P - 1 - L):P - 1]), motions[:, max(0, P - 1 - L):P - 1])[1][:, -1]
    for f in range(n_future):
        n = seq.shape[1]
        lo = max(0, n - L)
        logits, pose_pred = model(embed(seq[:, lo:]), motions[:, lo:n])
        nxt = logits[:, -1].argmax(1)
        out.append(nxt)
        seq = torch.cat([seq, nxt[:, None]], 1)
        if predict_poses and P + f < motions.shape[1]:
            motions = motions.clone()
            motions[:, P + f] = pose_pred[:, -1].to(motions.dtype)
    return torch.stack(out, 1)
