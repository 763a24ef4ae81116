"""Copilot4D world model: sizes, temporal masks, Algorithm 1 (corruption and loss),
Algorithm 2 (sampling, revision, guidance) and a short overfit run."""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.methods.copilot4d import config as tok_config
from pcfbench.methods.copilot4d import diffusion as D
from pcfbench.methods.copilot4d.world import (
    WorldEnsemble,
    WorldModel,
    causal_mask,
    count_parameters,
    guidance_mask,
    identity_mask,
    view_features,
)
from pcfbench.methods.copilot4d.world_config import PAPER, TINY, WIDE, WorldModelConfig, get_world_config

# the same architecture, small enough for unit tests: 8 x 8 tokens, 16 codes, 3 frames
MICRO = WorldModelConfig(
    name="micro", codebook_size=16, token_grid=8, n_past=2, n_future=1,
    dims=(32, 32, 32), heads=(2, 2, 2), windows=(4, 4, 2), groups_down=(1, 1, 1), groups_up=(1, 1),
    mlp_ratio=2.0, lr=3e-3, warmup=5, decay_steps=200,
)


def _eye_poses(B: int, T: int) -> torch.Tensor:
    return torch.eye(4, dtype=torch.float64).repeat(B, T, 1, 1)


def _random_poses(B: int, T: int, gen: torch.Generator) -> torch.Tensor:
    P = _eye_poses(B, T)
    P[..., :3, 3] = torch.randn(B, T, 3, generator=gen, dtype=torch.float64) * 5.0
    return P


@pytest.fixture(scope="module")
def micro_model():
    torch.manual_seed(0)
    m = WorldModel(MICRO).eval()
    with torch.no_grad():  # a non-trivial temporal mixing: zero-init would hide mask errors
        m.time_embed.normal_(0.0, 1.0)
    return m


# --------------------------------------------------------------------------- configs
def test_parameter_counts():
    # A.2: "the world model is a 39-Million parameter model"
    n_paper = count_parameters(WorldModel(PAPER))
    assert n_paper == 39_350_696
    assert abs(n_paper - 39e6) / 39e6 < 0.03
    assert count_parameters(WorldModel(TINY)) == 1_077_562
    assert count_parameters(WorldModel(WIDE)) == 39_219_624  # the paper's network, 512 codes instead of 1024


def test_wide_is_the_paper_network_on_the_tiny_tokenizer():
    """`wide`: what one GPU trains in minutes; its tokenizer is the tiny one, for the world model,
    its checkpoint's identity and the token-copy checkpoint it trains on."""
    from pcfbench.method import resolve_method
    from pcfbench.methods.copilot4d.world_config import tokenizer_config_name

    assert (WIDE.dims, WIDE.heads, WIDE.windows, WIDE.groups_down, WIDE.groups_up, WIDE.batch_size) == (
        PAPER.dims, PAPER.heads, PAPER.windows, PAPER.groups_down, PAPER.groups_up, PAPER.batch_size)
    assert (WIDE.token_grid, WIDE.codebook_size) == (tok_config.TINY.bev_tokens, tok_config.TINY.codebook_size)
    assert [tokenizer_config_name(n) for n in ("tiny", "paper", "wide", "tiny-window")] == ["tiny", "paper", "tiny",
                                                                                           "tiny-window"]
    with pytest.raises(UnknownNameError, match="did you mean 'wide'"):
        tokenizer_config_name("wdie")
    for name in ("copilot4d", "copilot4d-maskgit"):
        method = resolve_method((name, {"config": "wide"})).create()
        assert method.world_cfg == WIDE and method.tok_cfg == tok_config.TINY
        spec = method.tokenizer_spec()
        assert spec.name == "copilot4d-token-copy"
        assert spec.create().cfg == tok_config.TINY
        assert resolve_method((name, {"config": "paper"})).create().tokenizer_spec().create().cfg == tok_config.PAPER


def test_configs_match_their_tokenizers():
    assert (PAPER.token_grid, PAPER.codebook_size) == (128, 1024)
    assert (PAPER.token_grid, PAPER.codebook_size) == (tok_config.PAPER.bev_tokens, tok_config.PAPER.codebook_size)
    assert (TINY.token_grid, TINY.codebook_size) == (tok_config.TINY.bev_tokens, tok_config.TINY.codebook_size)
    assert PAPER.dims == (256, 384, 512) and PAPER.heads == (8, 12, 16) and PAPER.windows == (8, 8, 16)
    for cfg in (PAPER, TINY):
        assert all(d // h == 32 for d, h in zip(cfg.dims, cfg.heads))
        assert (cfg.n_past, cfg.n_future) == (5, 5)
    assert (PAPER.lr, PAPER.betas, PAPER.weight_decay, PAPER.warmup, PAPER.grad_clip, PAPER.batch_size) == (
        1e-3, (0.9, 0.95), 1e-4, 2000, 5.0, 8)


def test_config_errors():
    with pytest.raises(PcfbenchError, match="level 3 is 2 tokens wide, not a multiple of its window 8"):
        MICRO.with_overrides(windows=(4, 4, 8))
    with pytest.raises(UnknownNameError, match="did you mean 'tiny'"):
        get_world_config("tiyn")


# --------------------------------------------------------------------------- temporal masks
def test_temporal_masks_by_hand():
    t, f = True, False
    assert causal_mask(3).tolist() == [[t, f, f], [t, t, f], [t, t, t]]
    assert identity_mask(3).tolist() == [[t, f, f], [f, t, f], [f, f, t]]
    assert guidance_mask(3).tolist() == [
        [t, f, f, f],
        [t, t, f, f],
        [t, t, t, f],
        [f, f, f, t],  # the appended copy of frame 2 sees only itself
    ]


def test_temporal_masks_act_on_the_network(micro_model):
    gen = torch.Generator().manual_seed(3)
    x = torch.randint(0, 17, (1, 3, 8, 8), generator=gen)
    P = _random_poses(1, 3, gen)
    y = x.clone()
    y[:, 0] = (y[:, 0] + 1) % 16  # change the first frame only
    with torch.no_grad():
        causal_x, causal_y = micro_model(x, P, causal_mask(3)), micro_model(y, P, causal_mask(3))
        ident_x, ident_y = micro_model(x, P, identity_mask(3)), micro_model(y, P, identity_mask(3))
    assert not torch.allclose(causal_x[:, 1:], causal_y[:, 1:], atol=1e-4)  # later frames see frame 0
    assert torch.allclose(ident_x[:, 1:], ident_y[:, 1:], atol=1e-6)  # ... unless the mask is the identity
    z = x.clone()
    z[:, 2] = (z[:, 2] + 1) % 16  # change the last frame only: earlier frames cannot see it
    with torch.no_grad():
        causal_z = micro_model(z, P, causal_mask(3))
    assert torch.allclose(causal_x[:, :2], causal_z[:, :2], atol=1e-6)


def test_one_mask_per_sequence(micro_model):
    gen = torch.Generator().manual_seed(6)
    x = torch.randint(0, 17, (2, 3, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    with torch.no_grad():
        both = micro_model(x, P, torch.stack([causal_mask(3), identity_mask(3)]))
        first = micro_model(x[:1], P[:1], causal_mask(3))
        second = micro_model(x[1:], P[1:], identity_mask(3))
    assert torch.allclose(both[:1], first, atol=1e-5, rtol=0)
    assert torch.allclose(both[1:], second, atol=1e-5, rtol=0)


def test_bad_masks_and_inputs_are_refused(micro_model):
    x = torch.zeros(1, 3, 8, 8, dtype=torch.long)
    P = _eye_poses(1, 3)
    with pytest.raises(ValueError, match="must be bool"):
        micro_model(x, P, causal_mask(3).float())
    with pytest.raises(ValueError, match="diagonal must be True"):
        micro_model(x, P, ~identity_mask(3))
    with pytest.raises(ValueError, match=r"expected \(3, 3\)"):
        micro_model(x, P, causal_mask(4))
    bad = x.clone()
    bad[0, 1, 2, 3] = 17
    with pytest.raises(ValueError, match=r"token codes span 0..17; expected 0..16 \(16 = mask\)"):
        micro_model(bad, P, causal_mask(3))
    with pytest.raises(ValueError, match=r"T_ref_sensor has shape \(1, 2, 4, 4\)"):
        micro_model(x, P[:, :2], causal_mask(3))


def test_actions_are_each_frames_pose(micro_model):
    gen = torch.Generator().manual_seed(4)
    x = torch.randint(0, 16, (1, 3, 8, 8), generator=gen)
    P = _random_poses(1, 3, gen)
    Q = P.clone()
    Q[:, 2, 0, 3] += 1.0  # move the last frame's sensor 1 m along x of the reference frame
    with torch.no_grad():
        a, b = micro_model(x, P, identity_mask(3)), micro_model(x, Q, identity_mask(3))
    assert torch.allclose(a[:, :2], b[:, :2], atol=1e-6)
    assert not torch.allclose(a[:, 2], b[:, 2], atol=1e-4)


def test_bf16_autocast_runs_unchanged(micro_model):
    x = torch.randint(0, 16, (1, 3, 8, 8), generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        ref = micro_model(x, _eye_poses(1, 3), causal_mask(3))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = micro_model(x, _eye_poses(1, 3), causal_mask(3))
    assert low.dtype == torch.bfloat16
    assert (low.float().argmax(-1) == ref.argmax(-1)).float().mean() > 0.8


# --------------------------------------------------------------------------- Algorithm 1
def _exact_expectations(N: int, eta: float) -> tuple[float, float]:
    """E[masked] / N and E[noised] / N for one frame, by exact summation over the mask count
    m = ceil(cos(u0 pi / 2) N): P(m) is the length of the u0 interval giving m, and
    E[floor(u1 c)] = sum_{j=1..floor(c)} (1 - j / c) for u1 ~ U(0, 1)."""
    e_mask = e_noise = 0.0
    for m in range(1, N + 1):
        p = (math.acos((m - 1) / N) - math.acos(m / N)) * 2 / math.pi
        c = eta / 100 * (N - m)
        e_mask += p * m
        e_noise += p * sum(1 - j / c for j in range(1, math.floor(c) + 1))
    return e_mask / N, e_noise / N


@pytest.mark.parametrize("mask_batch", ["broadcast", "per_sequence"])
def test_attention_cut_into_batches_is_the_same(mask_batch):
    """The batch cut that keeps CUDA's fused attention below 2^16 sequences changes nothing:
    each piece, its own rows of the mask (or the broadcast one), concatenated in order."""
    from pcfbench.methods.copilot4d.swin import CUDA_SDPA_MAX_BATCH, attention

    assert CUDA_SDPA_MAX_BATCH < 2**16
    g = torch.Generator().manual_seed(0)
    n, h, L, d = 11, 2, 5, 4
    q, k, v = (torch.randn(n, h, L, d, generator=g) for _ in range(3))
    if mask_batch == "broadcast":
        mask = torch.ones(1, L, L, dtype=torch.bool).tril()
    else:
        mask = torch.rand(n, 1, L, L, generator=g) > 0.3
        mask[..., torch.arange(L), torch.arange(L)] = True  # every query sees itself
    whole = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    torch.testing.assert_close(attention(q, k, v, mask), whole, rtol=0, atol=0)  # CPU: one call
    for max_batch in (1, 3, 4, 10, 11):
        torch.testing.assert_close(attention(q, k, v, mask, max_batch=max_batch), whole, rtol=1e-6, atol=1e-6)
    if mask_batch == "per_sequence":  # a mask row applied to the wrong sequence would show
        shifted = attention(q, k, v, mask.roll(1, 0), max_batch=3)
        assert not torch.allclose(shifted, whole)


def test_corruption_counts_are_exact():
    gen = torch.Generator().manual_seed(11)
    V, B, T, H = 16, 64, 4, 6
    x0 = torch.randint(0, V, (B, T, H, H), generator=gen)
    c = D.corrupt(x0, n_past=2, codebook_size=V, generator=gen)
    N = H * H
    masked, noised = c.masked.view(B, T, N), c.noised.view(B, T, N)
    assert not (masked & noised).any()
    for b in range(B):
        obj = int(c.objective[b])
        assert c.temporal_mask[b].tolist() == (identity_mask(T) if obj == 2 else causal_mask(T)).tolist()
        for t in range(T):
            if obj == 0 and t < 2:  # the clean past of future prediction: untouched, not scored
                assert not c.denoised[b, t] and not masked[b, t].any() and not noised[b, t].any()
                assert not c.loss_mask[b, t].any() and torch.equal(c.tokens[b, t], x0[b, t])
                continue
            u0, u1 = float(c.u0[b, t]), float(c.u1[b, t])
            m = math.ceil(math.cos(u0 * math.pi / 2) * N)
            assert int(masked[b, t].sum()) == m
            assert int(noised[b, t].sum()) == math.floor(u1 * 0.20 * (N - m))
            assert c.loss_mask[b, t].all()  # Copilot4D: cross entropy on every token
    assert torch.equal(c.tokens[c.masked], torch.full_like(c.tokens[c.masked], V))
    keep = ~c.masked & ~c.noised
    assert torch.equal(c.tokens[keep], x0[keep])


def test_corruption_proportions_statistically():
    gen = torch.Generator().manual_seed(12)
    V, B, T, H = 16, 6000, 2, 8
    N = H * H
    x0 = torch.randint(0, V, (B, T, H, H), generator=gen)
    c = D.corrupt(x0, n_past=1, codebook_size=V, generator=gen)

    # objectives 50 / 40 / 10 %: each frequency within 4.5 binomial standard deviations
    for i, p in enumerate(D.OBJECTIVE_PROBS):
        freq = float((c.objective == i).float().mean())
        assert abs(freq - p) < 4.5 * math.sqrt(p * (1 - p) / B), (D.OBJECTIVES[i], freq)

    frames = c.denoised
    n = int(frames.sum())
    assert n == 2 * B - int((c.objective == 0).sum())
    mask_frac = c.masked.view(B, T, N).sum(-1)[frames].double() / N
    noise_frac = c.noised.view(B, T, N).sum(-1)[frames].double() / N
    e_mask, e_noise = _exact_expectations(N, 20.0)
    assert abs(e_mask - (2 / math.pi)) < 1.0 / N  # ceil adds less than one token on average
    for got, want in ((mask_frac, e_mask), (noise_frac, e_noise)):
        assert abs(float(got.mean()) - want) < 4.5 * float(got.std()) / math.sqrt(n)
    # gamma(u0) with u0 uniform: P(masked fraction <= 1/2) = P(u0 >= 2/3) = 1/3
    p_half = float((mask_frac <= 0.5).double().mean())
    assert abs(p_half - 1 / 3) < 4.5 * math.sqrt(2 / 9 / n)

    # masked and noised positions are uniform over the frame
    rate = c.masked.view(B, T, N)[frames].double().mean(0)
    assert float((rate - rate.mean()).abs().max()) < 4.5 * math.sqrt(0.25 / n)
    # noise codes are uniform over all |V| codes (chi-square, 15 dof, p = 1e-4 quantile 46.8)
    codes = c.tokens[c.noised]
    counts = torch.bincount(codes, minlength=V).double()
    chi2 = float(((counts - counts.mean()) ** 2 / counts.mean()).sum())
    assert chi2 < 46.8
    changed = float((codes != x0[c.noised]).double().mean())
    assert abs(changed - (1 - 1 / V)) < 4.5 * math.sqrt((1 / V) * (1 - 1 / V) / codes.numel())


def test_maskgit_variant_has_no_noise_and_scores_masked_tokens_only():
    gen = torch.Generator().manual_seed(13)
    x0 = torch.randint(0, 16, (200, 3, 4, 4), generator=gen)
    c = D.corrupt(x0, n_past=2, codebook_size=16, variant=D.MASKGIT, generator=gen)
    assert not c.noised.any()
    assert torch.equal(c.loss_mask, c.masked)
    assert torch.equal(c.tokens[~c.masked], x0[~c.masked])
    bad = x0.clone()
    bad[5, 1, 2, 3] = 16
    with pytest.raises(ValueError, match=r"clean token codes span 0..16; expected 0..15"):
        D.corrupt(bad, n_past=2, codebook_size=16)
    with pytest.raises(ValueError, match=r"objective must be \(200,\) indices"):
        D.corrupt(x0, n_past=2, codebook_size=16, objective=torch.full((200,), 3))
    with pytest.raises(UnknownNameError, match="did you mean 'maskgit'"):
        D.get_variant("maskgti")


class _CopyModel(nn.Module):
    """Logit `a` on the input code and 0 elsewhere; all zeros on mask tokens."""

    def __init__(self, V: int, a: float) -> None:
        super().__init__()
        self.mask_token, self.V, self.a = V, V, a

    def forward(self, tokens, T_ref_sensor, temporal_mask, frame_index=None):
        out = torch.zeros(*tokens.shape, self.V)
        seen = tokens != self.mask_token
        out[seen] = F.one_hot(tokens[seen], self.V).float() * self.a
        return out


def test_training_loss_by_hand():
    V, a, eps = 16, 3.0, 0.1
    model = _CopyModel(V, a)
    x0 = torch.randint(0, V, (8, 3, 4, 4), generator=torch.Generator().manual_seed(14))
    P = _eye_poses(8, 3)

    log_z = math.log(math.exp(a) + V - 1)
    ce_right = -((1 - eps + eps / V) * (a - log_z) + (V - 1) * (eps / V) * (0 - log_z))  # input = target
    ce_wrong = -((1 - eps + eps / V) * (0 - log_z) + (eps / V) * (a - log_z) + (V - 2) * (eps / V) * (0 - log_z))
    ce_mask = math.log(V)  # uniform logits: label smoothing cannot change log |V|

    # MaskGIT scores masked tokens only, where this model is uniform: the loss is log |V| exactly
    loss, _ = D.training_loss(model, x0, P, 2, D.MASKGIT, generator=torch.Generator().manual_seed(1))
    assert abs(float(loss) - ce_mask) < 1e-5

    loss, stats = D.training_loss(model, x0, P, 2, D.COPILOT4D, generator=torch.Generator().manual_seed(2))
    c = D.corrupt(x0, 2, V, D.COPILOT4D, generator=torch.Generator().manual_seed(2))  # the same draws
    sel = c.loss_mask
    n_mask = int((c.masked & sel).sum())
    n_right = int((~c.masked & sel & (c.tokens == x0)).sum())
    n_wrong = int((~c.masked & sel & (c.tokens != x0)).sum())
    assert n_wrong > 0 and n_mask > 0 and n_right > 0
    want = (n_mask * ce_mask + n_right * ce_right + n_wrong * ce_wrong) / (n_mask + n_right + n_wrong)
    assert abs(float(loss) - want) < 1e-5
    n_hit = n_right + int((c.masked & sel & (x0 == 0)).sum())  # argmax of uniform logits is code 0
    assert abs(stats["accuracy"] - n_hit / int(sel.sum())) < 1e-6



@pytest.mark.parametrize("smoothing", [0.1, 0.0])
def test_one_log_softmax_gives_pytorchs_cross_entropy_bit_for_bit(smoothing):
    """The loss and the per-token measurements come from one log-softmax: both equal
    F.cross_entropy (reduction mean and none) exactly, and so does the loss's gradient."""
    gen = torch.Generator().manual_seed(3)
    logits = (torch.randn(997, 64, generator=gen) * 4).requires_grad_()
    target = torch.randint(0, 64, (997,), generator=gen)
    mean, each = D._cross_entropies(logits, target, smoothing)
    (grad,) = torch.autograd.grad(mean, logits)
    ref = logits.detach().clone().requires_grad_()
    want = F.cross_entropy(ref, target, label_smoothing=smoothing)
    (want_grad,) = torch.autograd.grad(want, ref)
    assert torch.equal(mean.detach(), want.detach()) and torch.equal(grad, want_grad)
    assert torch.equal(each, F.cross_entropy(ref.detach(), target, label_smoothing=smoothing, reduction="none"))
    assert not each.requires_grad


def test_scored_rows_are_the_boolean_indexed_rows():
    """The scored tokens' rows: a view of the logits when they are one run of whole frames, the
    boolean-indexed rows otherwise; the same values in the same order, and the same gradient."""
    gen = torch.Generator().manual_seed(4)
    logits = torch.randn(2, 4, 3, 3, 5, generator=gen)
    whole = lambda *frames: torch.zeros(2, 4, 1, 1, dtype=torch.bool).index_fill_(1, torch.tensor(frames), True) \
        .expand(2, 4, 3, 3).clone()  # noqa: E731
    one = whole(2, 3)
    one[1] = False  # the future of the first sequence only: a run of frames 2..3
    tokens = torch.rand(2, 4, 3, 3, generator=gen) < 0.5  # MaskGIT: masked tokens only
    gap = whole(1, 3)  # two runs (frames 1 and 3 of each sequence, and the next sequence's)
    for mask, view in ((whole(0, 1, 2, 3), True), (whole(2, 3), False), (one, True), (tokens, False),
                       (gap, False), (torch.zeros(2, 4, 3, 3, dtype=torch.bool), False)):
        got = D._scored_rows(logits, mask)
        assert torch.equal(got, logits[mask]), mask
        assert (got._base is logits) == view, mask



@pytest.mark.parametrize("variant", [D.COPILOT4D, D.MASKGIT], ids=lambda v: v.name)
def test_a_training_steps_loss_and_gradient_are_the_indexed_cross_entropys(variant):
    """A training step's loss and every gradient equal, bit for bit, PyTorch's cross entropy of
    the boolean-indexed scored logits (how a step computed them until 2026-12-03, so the
    checkpoints trained before retrain to the same bits), for each objective and a batch of all three."""
    torch.manual_seed(5)
    model = WorldModel(MICRO)
    params = [p for p in model.parameters() if p.requires_grad]
    x0 = torch.randint(0, MICRO.codebook_size, (3, 3, 8, 8), generator=torch.Generator().manual_seed(6))
    P = _random_poses(3, 3, torch.Generator().manual_seed(7))
    for rows, objective in (([0], [0]), ([0], [1]), ([0], [2]), ([0, 1, 2], [0, 1, 2])):
        obj = torch.tensor(objective)
        loss, _ = D.training_loss(model, x0[rows], P[rows], 2, variant, 0.1,
                                  generator=torch.Generator().manual_seed(8), objective=obj)
        grads = torch.autograd.grad(loss, params)
        c = D.corrupt(x0[rows], 2, MICRO.codebook_size, variant, torch.Generator().manual_seed(8), obj)
        logits = model(c.tokens, P[rows], c.temporal_mask)
        want = F.cross_entropy(logits[c.loss_mask].float(), c.targets[c.loss_mask], label_smoothing=0.1)
        assert torch.equal(loss.detach(), want.detach()), objective
        assert all(torch.equal(a, b) for a, b in zip(grads, torch.autograd.grad(want, params))), objective


def test_optimizer_follows_a3(micro_model):
    opt = D.make_optimizer(micro_model, MICRO)
    decayed = {id(p) for g in opt.param_groups if g["weight_decay"] > 0 for p in g["params"]}
    assert id(micro_model.embed.weight) not in decayed  # tied embedding / un-embedding
    assert id(micro_model.time_embed) not in decayed
    assert id(micro_model.out_norm.weight) not in decayed
    assert id(micro_model.down1.groups[0].temporal.attn.qkv.weight) in decayed
    assert opt.defaults["betas"] == (0.9, 0.95)
    assert all(g["weight_decay"] in (0.0, 1e-4) for g in opt.param_groups)
    assert D.lr_at(PAPER, 0) == pytest.approx(1e-3 / 2000)
    assert D.lr_at(PAPER, 1999) == pytest.approx(1e-3)
    assert D.lr_at(PAPER, 750_000) == pytest.approx(1e-4)


# --------------------------------------------------------------------------- Algorithm 2
class _ToyModel(nn.Module):
    """The answer is `target`; but while more than half of the frame being decoded is masked
    it is confidently wrong ((target + 1) mod V). Context frames are ignored."""

    def __init__(self, target: torch.Tensor, V: int) -> None:
        super().__init__()
        self.target, self.mask_token, self.V = target, V, V  # target: (H, W)
        self.calls: list[tuple[int, list]] = []

    def forward(self, tokens, T_ref_sensor, temporal_mask, frame_index=None):
        self.calls.append((tokens.shape[1], temporal_mask.tolist()))
        B, T = tokens.shape[:2]
        frac = (tokens == self.mask_token).float().flatten(2).mean(-1)  # (B, T)
        code = torch.where(frac[..., None, None] > 0.5, (self.target + 1) % self.V, self.target)
        return F.one_hot(code, self.V).float() * 30.0


class _TokenLogits(nn.Module):
    """Each token's logits: a fixed function of its input code (a table, mask token included) plus
    a fixed vector of its place (H, W, |V|)."""

    def __init__(self, table: torch.Tensor, by_place: torch.Tensor | float = 0.0) -> None:
        super().__init__()
        self.table, self.by_place, self.mask_token = table, by_place, table.shape[0] - 1

    def forward(self, tokens, T_ref_sensor, temporal_mask, frame_index=None):
        return self.table[tokens] + self.by_place


def test_minimum_bayes_risk_chooses_the_code_of_least_expected_distance():
    """Hand-built: p = (0.4, 0.3, 0.3) at every token, codes 1 and 2 one apart and ten from code 0.
    Top-1 picks code 0; the expected distances are 6, 4.3 and 4.3, so the metric picks code 1 (the
    first of the least). Under the 0-1 metric the choice is the arg max: one step decodes every
    token, the same codes as top_k=1 on a model whose logits differ from token to token."""
    p = torch.tensor([0.4, 0.3, 0.3])
    model = _TokenLogits(p.log().expand(4, 3))
    ctx = torch.zeros(1, 1, 2, 2, dtype=torch.long)
    metric = torch.tensor([[0.0, 10.0, 10.0], [10.0, 0.0, 1.0], [10.0, 1.0, 0.0]])
    kw = dict(steps=3, guidance=0.0, cache=False, generator=torch.Generator().manual_seed(0))
    assert (D.sample_frame(model, ctx, _eye_poses(1, 2), top_k=1, **kw) == 0).all()
    kw["generator"] = torch.Generator().manual_seed(0)
    assert (D.sample_frame(model, ctx, _eye_poses(1, 2), metric=metric, **kw) == 1).all()
    V = 16
    gen = torch.Generator().manual_seed(3)
    model = _TokenLogits(torch.randn(V + 1, V, generator=gen), torch.randn(6, 6, V, generator=gen))
    ctx = torch.randint(0, V, (2, 2, 6, 6), generator=torch.Generator().manual_seed(4))
    for guidance in (0.0, 2.0):
        kw = dict(steps=1, guidance=guidance, cache=False)
        top1 = D.sample_frame(model, ctx, _eye_poses(2, 3), top_k=1, generator=torch.Generator().manual_seed(5), **kw)
        mbr = D.sample_frame(model, ctx, _eye_poses(2, 3), metric=1 - torch.eye(V),
                             generator=torch.Generator().manual_seed(5), **kw)
        assert torch.equal(top1, mbr) and len(top1.unique()) > 1


def test_final_logits_are_the_last_steps_guided_distribution():
    """``final_logits`` receives, once per frame, the guided logits of Algorithm 2's last step:
    with arg max sampling and revision every token takes their arg max at that step, so they
    give the returned codes, at one step and at three, guided or not; one entry per future frame."""
    V = 16
    gen = torch.Generator().manual_seed(3)
    model = _TokenLogits(torch.randn(V + 1, V, generator=gen), torch.randn(6, 6, V, generator=gen))
    ctx = torch.randint(0, V, (2, 2, 6, 6), generator=torch.Generator().manual_seed(4))
    for steps in (1, 3):
        for guidance in (0.0, 2.0):
            got: list = []
            x = D.sample_frame(model, ctx, _eye_poses(2, 3), steps=steps, guidance=guidance, top_k=1, cache=False,
                               generator=torch.Generator().manual_seed(5), final_logits=got)
            assert len(got) == 1 and got[0].shape == (2, 6, 6, V) and got[0].dtype == torch.float32
            assert torch.equal(got[0].argmax(-1), x)
    got = []
    out = D.forecast_sequence(model, ctx, _eye_poses(2, 5), 3, n_frames=5, n_past=2, steps=2, guidance=2.0, top_k=1,
                              cache=False, generator=torch.Generator().manual_seed(5), final_logits=got)
    assert len(got) == 3 and all(torch.equal(g.argmax(-1), o) for g, o in zip(got, out))


def test_change_confidence_changes_a_token_only_where_the_change_is_likelier_than_the_bar():
    """Hand-built: four tokens whose copy codes are 0, 1, 2, 0 and whose arg max is code 1 at
    p = 0.7, 0.5, 0.9, 0.4 (in that order). With the bar at 0.6 the first and third change (0.7
    and 0.9 > 0.6), the second keeps its copy code 1 (no change: its arg max is its copy) and the
    fourth keeps 0 (0.4 <= 0.6). At 0 the gate is off (the arg max everywhere); at 1 the frame is the
    copy, whatever the model says; without ``copy`` it is refused."""
    p = torch.tensor([[0.7, 0.2, 0.1], [0.5, 0.3, 0.2], [0.9, 0.05, 0.05], [0.4, 0.3, 0.3]])
    p = p[:, [1, 0, 2]]  # the likeliest code is 1 at every token
    model = _TokenLogits(torch.zeros(4, 3), p.log().view(2, 2, 3))
    ctx = torch.zeros(1, 1, 2, 2, dtype=torch.long)
    copy = torch.tensor([[[0, 1], [2, 0]]])
    kw = dict(guidance=0.0, top_k=1, cache=False, copy=copy)
    for steps in (1, 3):
        assert D.sample_frame(model, ctx, _eye_poses(1, 2), steps=steps, change_confidence=0.6, **kw).tolist() \
            == [[[1, 1], [1, 0]]]
        assert (D.sample_frame(model, ctx, _eye_poses(1, 2), steps=steps, **kw) == 1).all()
        assert torch.equal(D.sample_frame(model, ctx, _eye_poses(1, 2), steps=steps, change_confidence=1.0, **kw),
                           copy)
    with pytest.raises(ValueError, match="copy"):
        D.sample_frame(model, ctx, _eye_poses(1, 2), steps=1, guidance=0.0, change_confidence=0.5)
    # guided: the bar reads the guided distribution; the forecast keeps the last past frame's codes
    V = 16
    gen = torch.Generator().manual_seed(3)
    model = _TokenLogits(torch.randn(V + 1, V, generator=gen), torch.randn(6, 6, V, generator=gen))
    past = torch.randint(0, V, (2, 3, 6, 6), generator=torch.Generator().manual_seed(4))
    free = D.forecast_tokens(model, past, _eye_poses(2, 5), 2, steps=1, guidance=2.0, top_k=1, cache=False)
    gated = D.forecast_tokens(model, past, _eye_poses(2, 5), 2, steps=1, guidance=2.0, top_k=1, cache=False,
                              change_confidence=0.5)
    copy_all = D.forecast_tokens(model, past, _eye_poses(2, 5), 2, steps=1, guidance=2.0, top_k=1, cache=False,
                                 change_confidence=1.0)
    assert torch.equal(copy_all, past[:, -1:].expand(-1, 2, -1, -1))
    changed, kept = free != past[:, -1:], gated != past[:, -1:]
    assert (kept <= changed).all() and 0 < kept.sum() < changed.sum()  # some changes pass, not all
    assert torch.equal(gated[kept], free[kept])


@pytest.mark.parametrize("revise", [True, False])
def test_sampling_on_a_toy_model(revise):
    V, H, K = 8, 10, 10
    N = H * H
    target = torch.randint(0, V, (H, H), generator=torch.Generator().manual_seed(21))
    model = _ToyModel(target, V)
    context = target[None, None].clone()
    trace: list[torch.Tensor] = []
    out = D.sample_frame(model, context, _eye_poses(1, 2), steps=K, guidance=2.0, revise=revise,
                         generator=torch.Generator().manual_seed(0), cache=False, trace=trace)
    assert len(trace) == K and len(model.calls) == K
    # one pass per step, context + frame + its unconditional copy under the guidance mask
    assert all(T == 3 and m == guidance_mask(2).tolist() for T, m in model.calls)
    prev = torch.zeros(1, H, H, dtype=torch.bool)
    for step, x in enumerate(trace):
        k = K - 1 - step
        decoded = x != V
        assert int(decoded.sum()) == math.ceil(math.cos(k / K * math.pi / 2) * N - 1e-9)  # M = ceil(gamma(k/K) N)
        assert not (prev & ~decoded).any()  # decoded tokens are never masked again
        prev = decoded
    # the toy is wrong while more than half is masked: steps k = 9, 8, 7, 6 (masked 1, .84, .69, .55)
    wrong_until = math.ceil(math.cos(6 / K * math.pi / 2) * N)
    early = trace[3] != V
    assert int(early.sum()) == wrong_until
    assert torch.equal(trace[3][early], ((target + 1) % V).unsqueeze(0)[early])
    right = target.unsqueeze(0)
    if revise:  # Copilot4D revises the early tokens: everything ends right
        assert torch.equal(out, right)
        assert torch.equal(trace[4][early], right[early])
    else:  # MaskGIT freezes them: exactly the early tokens stay wrong
        assert int((out != right).sum()) == wrong_until
        assert torch.equal(out[early], ((right + 1) % V)[early])


def test_decoded_count_follows_gamma():
    assert [D.decoded_count(k, 10, 100) for k in range(9, -1, -1)] == [
        math.ceil(100 * math.cos(k * math.pi / 20) - 1e-9) for k in range(9, -1, -1)]
    assert D.decoded_count(0, 10, 16384) == 16384
    assert D.decoded_count(2, 3, 100) == 50  # cos(pi / 3) * 100 = 50.000000000000014


def test_guidance_zero_is_the_conditional_logits(micro_model):
    gen = torch.Generator().manual_seed(31)
    x = torch.randint(0, 17, (2, 3, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    with torch.no_grad():
        cond = micro_model(x, P, causal_mask(3))[:, -1]
        assert torch.equal(D.guided_logits(micro_model, x, P, 0.0), cond)


def test_guidance_copy_is_a_separate_unconditional_pass(micro_model):
    gen = torch.Generator().manual_seed(32)
    x = torch.randint(0, 17, (2, 3, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    with torch.no_grad():
        joint = micro_model(torch.cat([x, x[:, -1:]], 1), torch.cat([P, P[:, -1:]], 1), guidance_mask(3),
                            torch.tensor([0, 1, 2, 2]))
        cond = micro_model(x, P, causal_mask(3))[:, -1]
        uncond = micro_model(x[:, -1:], P[:, -1:], identity_mask(1), torch.tensor([2]))[:, 0]
        guided = D.guided_logits(micro_model, x, P, 2.0)
    assert not torch.allclose(cond, uncond, atol=1e-3)  # the context matters to this model
    assert torch.allclose(joint[:, 3], uncond, atol=1e-5, rtol=0)
    assert torch.allclose(joint[:, 2], cond, atol=1e-5, rtol=0)
    assert torch.allclose(guided, cond + 2.0 * (cond - uncond), atol=1e-4, rtol=0)


def test_cached_context_gives_the_same_logits_and_samples(micro_model):
    gen = torch.Generator().manual_seed(34)
    x = torch.randint(0, 17, (2, 3, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    with torch.no_grad():
        _, kv = micro_model(x[:, :2], P[:, :2], causal_mask(2), return_kv=True)
        assert kv.frames == 2 and kv.batch == 2 and len(kv.kv) == 5  # one temporal block per group
        for w in (0.0, 2.0):
            full = D.guided_logits(micro_model, x, P, w)
            cached = D.guided_logits(micro_model, x[:, 2:], P[:, 2:], w, past_kv=kv)
            assert torch.allclose(full, cached, atol=1e-5, rtol=0)
        with pytest.raises(ValueError, match=r"temporal mask has shape \(1, 1\); expected \(1, 3\)"):
            micro_model(x[:, 2:], P[:, 2:], causal_mask(1), past_kv=kv)
    ctx = x[:, :2].clamp(max=15)
    a = D.sample_frame(micro_model, ctx, P, steps=5, generator=torch.Generator().manual_seed(2), cache=True)
    b = D.sample_frame(micro_model, ctx, P, steps=5, generator=torch.Generator().manual_seed(2), cache=False)
    assert torch.equal(a, b)


def test_room_in_the_cache_gives_the_very_logits_of_concatenating(micro_model):
    """Algorithm 2's steps write their frames' keys and values into buffers made once per
    frame instead of concatenating the context's at every pass: bit for bit the same logits,
    pass after pass (each overwrites the last one's frames)."""
    gen = torch.Generator().manual_seed(35)
    ctx = torch.randint(0, 16, (2, 2, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    with torch.no_grad():
        _, kv = micro_model(ctx, P[:, :2], causal_mask(2), return_kv=True)
        roomy = kv.with_room(2)
        assert (roomy.frames, roomy.room) == (2, 2) and all(torch.equal(a[:, :, :2], b) for (a, _), (b, _)
                                                              in zip(roomy.kv, kv.kv))
        for _ in range(3):
            x = torch.randint(0, 17, (2, 1, 8, 8), generator=gen)
            for w in (2.0, 0.5):
                want = D.guided_logits(micro_model, x, P[:, 2:], w, past_kv=kv)
                assert torch.equal(D.guided_logits(micro_model, x, P[:, 2:], w, past_kv=roomy), want)
        with pytest.raises(ValueError, match="room for 2 new frames, not 1"):
            micro_model(x, P[:, 2:], causal_mask(3)[2:], past_kv=roomy)
        with pytest.raises(ValueError, match="return_kv: they would be overwritten"):
            micro_model(torch.cat([x, x], 1), P[:, 1:], guidance_mask(3)[2:], torch.tensor([2, 2]), past_kv=roomy,
                        return_kv=True)
        with pytest.raises(ValueError, match="already has room"):
            roomy.with_room(1)


def test_window_bias_is_kept_between_inference_passes_while_its_weights_stay():
    """Without autograd a Swin block keeps its relative position bias (plus the shifted
    windows' mask, repeated over the batch) for the next pass of the same shape, rebuilt when
    the bias parameter changes (an optimiser step, loading weights) or autograd is on; the
    block's output is the same either way."""
    from pcfbench.methods.copilot4d.swin import SwinBlock

    torch.manual_seed(4)
    blk = SwinBlock(16, 2, 4, True, 2.0)
    with torch.no_grad():
        blk.attn.rel_bias.normal_()
    x = torch.randn(3, 8, 8, 16)
    blk(x).sum().backward()  # autograd on: built, not kept
    assert getattr(blk.attn, "_bias_cache", None) is None

    def fresh():  # the same block with nothing kept
        with torch.no_grad():
            return copy.deepcopy(blk)(x)

    with torch.no_grad():
        want = fresh()
        assert torch.equal(blk(x), want)
        kept = blk.attn._bias_cache[1]
        assert kept.shape == (3 * 4, 2, 16, 16)
        assert torch.equal(blk(x), want) and blk.attn._bias_cache[1] is kept  # reused
        blk.attn.rel_bias.mul_(2.0)
        changed = blk(x)
        assert blk.attn._bias_cache[1] is not kept and not torch.allclose(changed, want)
        blk.attn._bias_cache = None
        assert torch.equal(changed, fresh())


class _FrameCounter(nn.Module):
    """Wraps a world model and counts the frames each pass sends through it."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model, self.mask_token, self.frames = model, model.mask_token, []

    def forward(self, tokens, *args, **kw):
        self.frames.append(tokens.shape[1])
        return self.model(tokens, *args, **kw)


@pytest.mark.parametrize("revise", [True, False])
def test_reusing_the_context_forecasts_the_same_tokens_with_less_work(revise):
    """Forecasting keeps the context's temporal keys and values from frame to frame and sends
    only the frame just decoded through the network to join them: the very tokens of
    recomputing the context for every frame (and of no cache at all), with the context passes'
    frames cut from 2 + 3 + 4 to 2 + 1 + 1 here; when the context slides (frame 4: 5 frames is
    the trained sequence), its positions change and it is recomputed."""
    torch.manual_seed(1)
    cfg = MICRO.with_overrides(n_future=3)  # 5 frames: 2 past, and the context slides at the 4th future frame
    model = WorldModel(cfg).eval()
    with torch.no_grad():
        model.time_embed.normal_(0.0, 1.0)
    gen = torch.Generator().manual_seed(36)
    past = torch.randint(0, 16, (2, 2, 8, 8), generator=gen)
    poses = _random_poses(2, 6, gen)
    runs = {}
    for name, kw in (("reuse", {}), ("recompute", {"reuse_context": False}), ("no cache", {"cache": False})):
        counter = _FrameCounter(model)
        out = D.forecast_sequence(counter, past, poses, 4, n_frames=cfg.n_frames, n_past=cfg.n_past, steps=4,
                                  revise=revise, generator=torch.Generator().manual_seed(3), **kw)
        runs[name] = (torch.stack(out, 1), counter.frames)
    assert torch.equal(runs["reuse"][0], runs["recompute"][0]) and torch.equal(runs["reuse"][0], runs["no cache"][0])
    steps = [2] * 4  # each step: the frame and its unconditional copy
    assert runs["recompute"][1] == [2, *steps, 3, *steps, 4, *steps, 4, *steps]
    assert runs["reuse"][1] == [2, *steps, 1, *steps, 1, *steps, 4, *steps]
    assert len(set(runs["reuse"][0].flatten().tolist())) > 4  # a real forecast, not a constant


@pytest.mark.parametrize("revise", [True, False])
def test_an_ensemble_forecasts_by_the_mean_of_its_members_log_probabilities(revise):
    """WorldEnsemble: a pass's logits are the mean of the members' log-softmaxes, with each
    member's own cache giving what whole passes give; guided, it is the mean of the members'
    guided log-probabilities (guidance is linear). A network with itself forecasts exactly as
    the network alone; two networks forecast differently from either; with reused context,
    recomputed context and no cache alike."""
    torch.manual_seed(3)
    cfg = MICRO.with_overrides(n_future=3)
    a, b = WorldModel(cfg).eval(), WorldModel(cfg).eval()
    with torch.no_grad():
        for m in (a, b):
            m.time_embed.normal_(0.0, 1.0)
    gen = torch.Generator().manual_seed(37)
    x = torch.randint(0, 17, (2, 3, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    both = WorldEnsemble([a, b])
    with torch.no_grad():
        mean = (a(x, P, causal_mask(3)).log_softmax(-1) + b(x, P, causal_mask(3)).log_softmax(-1)) / 2
        assert torch.allclose(both(x, P, causal_mask(3)), mean, atol=1e-6, rtol=0)
        _, kv = both(x[:, :2], P[:, :2], causal_mask(2), return_kv=True)
        assert (kv.frames, kv.batch) == (2, 2) and len(kv.members) == 2
        for w in (0.0, 2.0):
            want = (D.guided_logits(a, x, P, w).log_softmax(-1) + D.guided_logits(b, x, P, w).log_softmax(-1)) / 2
            for cache in (kv, kv.with_room(1 if w == 0 else 2)):
                got = D.guided_logits(both, x[:, 2:], P[:, 2:], w, past_kv=cache)
                assert torch.allclose(got.log_softmax(-1), want.log_softmax(-1), atol=1e-5, rtol=0)
    past, poses = x[:, :2].clamp(max=15), _random_poses(2, 6, gen)

    def forecast(model, **kw):
        return torch.stack(D.forecast_sequence(model, past, poses, 4, n_frames=cfg.n_frames, n_past=cfg.n_past,
                                               steps=3, top_k=1, revise=revise,
                                               generator=torch.Generator().manual_seed(4), **kw), 1)

    assert torch.equal(forecast(WorldEnsemble([a, a])), forecast(a))
    runs = [forecast(both, **kw) for kw in ({}, {"reuse_context": False}, {"cache": False})]
    assert all(torch.equal(runs[0], r) for r in runs[1:])
    assert not torch.equal(runs[0], forecast(a)) and not torch.equal(runs[0], forecast(b))
    with pytest.raises(ValueError, match="two networks or more"):
        WorldEnsemble([a])
    with pytest.raises(ValueError, match="differ in codebook size"):
        WorldEnsemble([a, WorldModel(cfg.with_overrides(codebook_size=32))])


def test_forecast_tokens_decodes_every_future_frame(micro_model):
    gen = torch.Generator().manual_seed(33)
    past = torch.randint(0, 16, (2, 2, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    a = D.forecast_tokens(micro_model, past, P, 1, steps=4, generator=torch.Generator().manual_seed(1))
    b = D.forecast_tokens(micro_model, past, P, 1, steps=4, generator=torch.Generator().manual_seed(1))
    assert a.shape == (2, 1, 8, 8) and torch.equal(a, b)
    assert int(a.min()) >= 0 and int(a.max()) < 16


@pytest.mark.parametrize("guidance", [0.0, 2.0])
def test_one_pass_decodes_each_future_frame_from_the_past_and_masks_alone(guidance):
    """``forecast_one_pass``: frame f's logits are the network's causal pass over the past and f + 1
    all-mask frames (a causal frame does not see later ones: the slow reference passes only those),
    guided by frame f alone (its own pass of one frame at its position: the unconditional model);
    the first future frame is Algorithm 2's at one step exactly so; the codes are the arg max."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(MICRO, n_future=3)
    model = WorldModel(cfg).eval()
    with torch.no_grad():
        model.time_embed.normal_(0.0, 1.0)
    gen = torch.Generator().manual_seed(8)
    past = torch.randint(0, 16, (2, 2, 8, 8), generator=gen)
    poses = _random_poses(2, 5, gen).float()
    got: list = []
    codes = D.forecast_one_pass(model, past, poses, 3, n_frames=cfg.n_frames, n_past=2, guidance=guidance,
                                final_logits=got)
    assert len(codes) == len(got) == 3
    x = torch.cat([past, torch.full((2, 3, 8, 8), model.mask_token)], 1)
    with torch.no_grad():
        for f in range(3):
            T = 3 + f
            cond = model(x[:, :T], poses[:, :T], causal_mask(T), torch.arange(T))[:, -1].float()
            alone = model(x[:, T - 1:T], poses[:, T - 1:T], torch.ones(1, 1, dtype=torch.bool),
                          torch.tensor([T - 1]))[:, 0].float()
            want = cond + guidance * (cond - alone)
            assert torch.allclose(got[f], want, atol=1e-4), f
            assert torch.equal(codes[f], got[f].argmax(-1))
        first: list = []
        D.forecast_sequence(model, past, poses[:, :3], 1, n_frames=cfg.n_frames, n_past=2, steps=1, guidance=guidance,
                            top_k=1, generator=torch.Generator().manual_seed(1), final_logits=first)
    assert torch.allclose(first[0], got[0], atol=1e-4)
    with pytest.raises(ValueError, match="outgrow the 5 frames"):
        D.forecast_one_pass(model, past, _random_poses(2, 6, gen).float(), 4, n_frames=cfg.n_frames, n_past=2)


def test_one_pass_is_refused_with_a_sampler_that_chooses_among_samples():
    from pcfbench.method import resolve_method

    for bad in ("one_pass=true", "one_pass=true,sampling_steps=1", "one_pass=true,sampling_steps=1,top_k=1,mbr=true"):
        with pytest.raises(PcfbenchError, match="one_pass=true takes each future token's guided arg max"):
            resolve_method(f"copilot4d:{bad}").create()
    resolve_method("copilot4d:one_pass=true,sampling_steps=1,top_k=1").create()


def test_one_pass_refuses_more_future_frames_than_the_network_was_trained_on_naming_the_sample():
    """A sample (or window) with more future frames than the network's window is one error naming
    it; as many as the window are decoded, one code map each (B, H, W)."""
    import types

    from pcfbench.methods.copilot4d.forecaster import Copilot4D

    torch.manual_seed(0)
    cfg = dataclasses.replace(MICRO, n_future=3)
    model = WorldModel(cfg).eval()
    method = types.SimpleNamespace(world_cfg=cfg, options=types.SimpleNamespace(one_pass=True),
                                   sampling_for=lambda world: (2.0, 0.0))
    gen = torch.Generator().manual_seed(8)
    past = torch.randint(0, 16, (1, 2, 8, 8), generator=gen)
    codes = Copilot4D.decode_future(method, model, past, _random_poses(1, 5, gen).float(), 3)
    assert [tuple(c.shape) for c in codes] == [(1, 8, 8)] * 3
    with pytest.raises(PcfbenchError, match="^sample 7: one_pass=true forecasts its 4 future frames in one pass; "
                                            "the network was trained on 3$"):
        Copilot4D.decode_future(method, model, past, _random_poses(1, 6, gen).float(), 4, name="sample 7")


# --------------------------------------------------------------------------- overfit
def test_overfit_a_tiny_sequence():
    """Algorithm 1 on one random 3-frame sequence: forecasting its last frame from the clean
    past (all of it masked, argmax) goes from chance (1/16) to above 90 %."""
    torch.manual_seed(0)
    model = WorldModel(MICRO)
    gen = torch.Generator().manual_seed(41)
    x0 = torch.randint(0, 16, (1, 3, 8, 8), generator=gen)
    P = _random_poses(1, 3, gen)
    opt = D.make_optimizer(model, MICRO)

    def forecast_accuracy() -> float:
        inp = x0.clone()
        inp[:, 2] = model.mask_token
        with torch.no_grad():
            pred = model(inp, P, causal_mask(3))[:, 2].argmax(-1)
        return float((pred == x0[:, 2]).float().mean())

    before = forecast_accuracy()
    assert before < 0.25
    for step in range(60):
        for g in opt.param_groups:
            g["lr"] = D.lr_at(MICRO, step)
        loss, _ = D.training_loss(model, x0.expand(2, -1, -1, -1), P.expand(2, -1, -1, -1), 2, generator=gen)
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), MICRO.grad_clip)
        opt.step()
        if step % 10 == 9 and forecast_accuracy() > 0.9:
            break
    assert forecast_accuracy() > 0.9


def test_training_loss_reports_changed_and_unchanged_tokens_apart():
    """A model that predicts, everywhere, the last past frame's token (a copier) is right on
    every future token that did not change and wrong on every one that did; the share of
    changed future tokens is counted by hand. The loss and its gradient are the plain ones."""
    V, n_past = 6, 2

    class Copier(nn.Module):
        mask_token = V

        def __init__(self, x0):
            super().__init__()
            self.x0, self.w = x0, nn.Parameter(torch.zeros(1))

        def forward(self, tokens, poses, mask):
            last = self.x0[:, n_past - 1: n_past].expand_as(self.x0)
            return F.one_hot(last, V).float() * 10 + self.w

    x0 = torch.zeros(1, 4, 2, 2, dtype=torch.long)
    x0[0, 1] = torch.tensor([[1, 2], [3, 4]])  # the last past frame
    x0[0, 2] = torch.tensor([[1, 2], [3, 5]])  # one token of four changed
    x0[0, 3] = torch.tensor([[0, 0], [3, 4]])  # two changed
    both = 0
    for seed in range(8):  # which tokens are masked is random: every seed, and at least one with both kinds
        gen = torch.Generator().manual_seed(seed)
        loss, stats = D.training_loss(Copier(x0), x0, torch.eye(4).expand(1, 4, 4, 4), n_past, generator=gen)
        assert stats["changed_share"] == pytest.approx(3 / 8)
        assert math.isnan(stats["changed_accuracy"]) or stats["changed_accuracy"] == 0.0
        assert math.isnan(stats["unchanged_accuracy"]) or stats["unchanged_accuracy"] == 1.0
        if not (math.isnan(stats["changed_loss"]) or math.isnan(stats["unchanged_loss"])):
            assert stats["changed_loss"] > stats["unchanged_loss"]
            both += 1
        # measuring draws nothing: the generator is where corrupt alone leaves it
        gen2 = torch.Generator().manual_seed(seed)
        D.corrupt(x0, n_past, V, D.COPILOT4D, gen2)
        assert torch.equal(gen.get_state(), gen2.get_state())
    assert both


# --------------------------------------------------------------------------- where each sensor sees a token from
def _view(x: float, y: float, extent: float, freqs: int) -> list[float]:
    """The features of a cell at (x, y) in a sensor's frame, written out."""
    out = []
    for c in (x, y):
        out += [math.sin(math.pi * 2 ** f * c / extent) for f in range(freqs)]
        out += [math.cos(math.pi * 2 ** f * c / extent) for f in range(freqs)]
    d = math.hypot(x, y)
    return out + [d / extent, math.log1p(d) / math.log1p(extent)]


def test_view_features_by_hand():
    # a 2 x 2 grid over [-10, 10]^2: cells centred at x, y = -5 and 5; cell [i, j] at (x_i, y_j)
    P = _eye_poses(1, 2)
    P[0, 0, :3, 3] = torch.tensor([5.0, -5.0, 1.7])  # frame 0's sensor on cell [1, 0], 1.7 m up
    P[0, 1, :2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])  # frame 1's sensor at the origin, its x along y
    f = view_features(P, 2, 10.0, 1)
    assert f.shape == (1, 2, 2, 2, 6)
    want = {(0, 1, 0): (0.0, 0.0), (0, 0, 1): (-10.0, 10.0), (0, 0, 0): (-10.0, 0.0), (0, 1, 1): (0.0, 10.0),
            # frame 1 turned 90 degrees: the cell at (x, y) = (-5, 5) of the reference lies 5 m ahead, 5 m to its left
            (1, 0, 1): (5.0, 5.0), (1, 1, 1): (5.0, -5.0), (1, 0, 0): (-5.0, 5.0), (1, 1, 0): (-5.0, -5.0)}
    for (k, i, j), (x, y) in want.items():
        assert torch.allclose(f[0, k, i, j], torch.tensor(_view(x, y, 10.0, 1)), atol=1e-6), (k, i, j)


def test_view_features_against_a_slow_reference():
    gen = torch.Generator().manual_seed(3)
    P = _random_poses(2, 3, gen)
    for b in range(2):
        for k in range(3):
            yaw = float(torch.rand(1, generator=gen)) * 6.0
            P[b, k, :3, :3] = torch.tensor([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                                            [0, 0, 1]], dtype=torch.float64)
    grid, extent = 4, 20.0
    f = view_features(P, grid, extent, 3)
    for b in range(2):
        for k in range(3):
            T_sensor_ref = torch.linalg.inv(P[b, k])
            for i in range(grid):
                for j in range(grid):
                    c = torch.tensor([-extent + (i + 0.5) * 2 * extent / grid, -extent + (j + 0.5) * 2 * extent / grid,
                                      float(P[b, k, 2, 3]), 1.0], dtype=torch.float64)
                    x, y = (T_sensor_ref @ c)[:2].tolist()
                    assert torch.allclose(f[b, k, i, j], torch.tensor(_view(x, y, extent, 3)), atol=1e-5)


MICRO_VIEW = MICRO.with_overrides(name="micro-view", view_freqs=2, bev_extent=10.0)


def test_a_view_field_model_tells_each_token_where_its_sensor_is():
    torch.manual_seed(0)
    m = WorldModel(MICRO_VIEW).eval()
    assert count_parameters(m) - count_parameters(WorldModel(MICRO)) == sum(10 * d + 2 * d + d * d for d in MICRO.dims)
    gen = torch.Generator().manual_seed(5)
    x = torch.randint(0, 16, (2, 3, 8, 8), generator=gen)
    P = _random_poses(2, 3, gen)
    with torch.no_grad():
        _, kv = m(x[:, :2], P[:, :2], causal_mask(2), return_kv=True)
        for w in (0.0, 2.0):  # a cached context is the same as the whole sequence
            assert torch.allclose(D.guided_logits(m, x, P, w), D.guided_logits(m, x[:, 2:], P[:, 2:], w, past_kv=kv),
                                  atol=1e-5, rtol=0)
        # the sensor turned about its own position: the action alone cannot say where each token is seen
        # from, so the turn changes that frame's logits, and not the others' (identity mask)
        Q = P.clone()
        Q[:, 2, :2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=torch.float64)
        a, b = m(x, P, identity_mask(3)), m(x, Q, identity_mask(3))
    assert torch.allclose(a[:, :2], b[:, :2], atol=1e-6) and not torch.allclose(a[:, 2], b[:, 2], atol=1e-4)


def test_a_view_field_world_model_takes_its_tokenizers_extent():
    from pcfbench.methods.copilot4d.forecaster import world_config_for
    from pcfbench.methods.copilot4d.world_config import TINY_WINDOW, TINY_WINDOW_VIEW, tokenizer_config_name

    tok = tok_config.get_config(tokenizer_config_name("tiny-window-view"))
    assert tok.name == "tiny-window" and TINY_WINDOW_VIEW.with_overrides(name="tiny-window", view_freqs=0) == TINY_WINDOW
    fitted = world_config_for(TINY_WINDOW_VIEW.with_overrides(bev_extent=1.0), tok)
    assert fitted.bev_extent == 80.0 == tok.x_range[1] and fitted.view_freqs == 6
    assert world_config_for(TINY_WINDOW.with_overrides(bev_extent=1.0), tok).bev_extent == 1.0  # unused, untouched
    with pytest.raises(PcfbenchError, match="square grid centred on the sensor"):
        world_config_for(TINY_WINDOW_VIEW, dataclasses.replace(tok, x_range=(-60.0, 100.0)))
    with pytest.raises(PcfbenchError, match="view_freqs=-1 must be at least 0"):
        MICRO.with_overrides(view_freqs=-1)
