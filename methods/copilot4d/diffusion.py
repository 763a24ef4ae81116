"""Absorbing-uniform discrete diffusion for the world model (paper 4.2-4.3, A.5-A.6):
Algorithm 1 (training with a mixture of objectives), Algorithm 2 (sampling one frame, with
classifier-free guidance by equation 2 in one forward pass) and the MaskGIT variant.

Token maps are ``(B, T, H, W)`` integer codes in 0..|V|-1; the mask token is |V|
(``model.mask_token``). A frame has N = H * W tokens. gamma(u) = cos(u pi / 2).

Any module with the :class:`~pcfbench.methods.copilot4d.world.WorldModel` call signature
``model(tokens, T_ref_sensor, temporal_mask, frame_index) -> logits (B, T, H, W, |V|)`` and
attributes ``mask_token`` can be trained and sampled here.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.copilot4d.world import causal_mask, guidance_mask, identity_mask
from pcfbench.methods.copilot4d.world_config import WorldModelConfig

#: Objectives of section 4.3, in this order: condition on the clean past and denoise the
#: future (causal mask); denoise past and future jointly (causal mask); denoise each frame
#: alone (identity mask: the unconditional model that guidance needs).
OBJECTIVES = ("future", "joint", "individual")
OBJECTIVE_PROBS = (0.5, 0.4, 0.1)


@dataclass(frozen=True)
class Variant:
    """What distinguishes Copilot4D's discrete diffusion from MaskGIT (Algorithms 1 and 2).

    eta: percent; up to eta % of the tokens left unmasked are replaced by uniform codes.
    masked_only_loss: cross entropy on masked tokens only (MaskGIT) instead of on all tokens.
    revise: decoded tokens are re-sampled at every later step (never re-masked); if False
    they are frozen once decoded (MaskGIT).
    """

    name: str
    eta: float
    masked_only_loss: bool
    revise: bool


COPILOT4D = Variant("copilot4d", eta=20.0, masked_only_loss=False, revise=True)
MASKGIT = Variant("maskgit", eta=0.0, masked_only_loss=True, revise=False)
VARIANTS = {v.name: v for v in (COPILOT4D, MASKGIT)}

#: Algorithm 2 defaults (A.6, Table 3/4): K steps, guidance weight w, top-k sampling of x0.
DEFAULT_STEPS = 10
DEFAULT_GUIDANCE = 2.0
DEFAULT_TOP_K = 3


def get_variant(name: str) -> Variant:
    from pcfbench.errors import unknown_name

    if name not in VARIANTS:
        raise unknown_name("diffusion variant", name, VARIANTS)
    return VARIANTS[name]


def gamma(u):
    """The mask schedule gamma(u) = cos(u pi / 2) (a float or a tensor)."""
    if isinstance(u, torch.Tensor):
        return torch.cos(u * (math.pi / 2))
    return math.cos(u * math.pi / 2)


def _ceil(x):
    # ceil of a product like gamma * N that is an integer in exact arithmetic must not gain a
    # token from float error (cos(pi / 3) * N = N / 2 + 1e-16 N); 1e-9 is far below 1 / N.
    if isinstance(x, torch.Tensor):
        return torch.ceil(x - 1e-9).long()
    return math.ceil(x - 1e-9)


def decoded_count(k: int, K: int, N: int) -> int:
    """Algorithm 2 line 6: M = ceil(gamma(k / K) N) tokens are non-mask in x_k (the top-M of
    the confidence l_k); the other N - M stay masked. M grows from about N pi / (2K) at
    k = K - 1 to N at k = 0."""
    return _ceil(gamma(k / K) * N)


# --------------------------------------------------------------------------- Algorithm 1
@dataclass(frozen=True)
class Corruption:
    """One training input built from clean tokens ``targets`` (B, T, H, W).

    tokens: the masked-and-noised input x_k. masked / noised: (B, T, H, W) bool, disjoint.
    loss_mask: (B, T, H, W) bool, where the cross entropy applies. temporal_mask: (B, T, T).
    objective: (B,) index into OBJECTIVES. u0, u1: (B, T) float64, the draws of Algorithm 1
    (NaN for frames left clean). denoised: (B, T) bool, the frames corrupted and scored.
    """

    tokens: torch.Tensor
    targets: torch.Tensor
    masked: torch.Tensor
    noised: torch.Tensor
    loss_mask: torch.Tensor
    temporal_mask: torch.Tensor
    objective: torch.Tensor
    denoised: torch.Tensor
    u0: torch.Tensor
    u1: torch.Tensor


def corrupt(x0: torch.Tensor, n_past: int, codebook_size: int, variant: Variant = COPILOT4D,
            generator: torch.Generator | None = None, objective: torch.Tensor | None = None) -> Corruption:
    """Algorithm 1 lines 3-7 under the mixture of objectives, for each sequence independently.

    Each sequence draws its objective (probabilities OBJECTIVE_PROBS) unless ``objective``
    (B,) is given. Every frame to denoise draws its own u0, u1 ~ U(0, 1) (the per-frame
    diffusion steps k_1..k_T of section 4.3): exactly ceil(gamma(u0) N) of its tokens, chosen
    uniformly, become the mask token, then exactly floor(u1 eta / 100 (N - masked)) of the
    rest, chosen uniformly, become codes drawn uniformly from all |V| (so a noised token keeps
    its value with probability 1 / |V|, as in uniform diffusion, A.5). Frames of the past
    under the "future" objective stay clean and are not scored.
    """
    if x0.dim() != 4:
        raise ValueError(f"x0 has shape {tuple(x0.shape)}; expected (B, T, H, W) token codes")
    B, T, H, W = x0.shape
    if not 1 <= n_past < T:
        raise ValueError(f"n_past={n_past} must leave at least one future frame in {T} frames")
    lo, hi = int(x0.min()), int(x0.max())
    if lo < 0 or hi >= codebook_size:
        raise ValueError(f"clean token codes span {lo}..{hi}; expected 0..{codebook_size - 1}")
    dev, N = x0.device, H * W

    def rand(*shape, dtype=torch.float32):
        return torch.rand(*shape, generator=generator, device=dev, dtype=dtype)

    if objective is None:
        probs = torch.tensor(OBJECTIVE_PROBS, dtype=torch.float64, device=dev)
        objective = torch.searchsorted(probs.cumsum(0), rand(B, dtype=torch.float64), right=True).clamp_(max=2)
    objective = objective.to(dev)
    if objective.shape != (B,) or int(objective.min()) < 0 or int(objective.max()) > 2:
        raise ValueError(f"objective must be ({B},) indices into {OBJECTIVES}, got {objective.tolist()}")
    denoised = torch.ones(B, T, dtype=torch.bool, device=dev)
    denoised[objective == 0, :n_past] = False

    u0, u1 = rand(B, T, dtype=torch.float64), rand(B, T, dtype=torch.float64)
    n_mask = torch.where(denoised, _ceil(gamma(u0) * N), 0)
    n_noise = torch.where(denoised, torch.floor(u1 * (variant.eta / 100.0) * (N - n_mask)).long(), 0)
    # one uniform random order per frame: its first n_mask positions are masked, the next
    # n_noise noised (a uniform subset of the unmasked ones)
    rank = rand(B, T, N).argsort(-1).argsort(-1)
    masked = rank < n_mask[..., None]
    noised = (rank >= n_mask[..., None]) & (rank < (n_mask + n_noise)[..., None])
    codes = torch.randint(0, codebook_size, (B, T, N), generator=generator, device=dev)
    flat = x0.reshape(B, T, N)
    tokens = torch.where(masked, codebook_size, torch.where(noised, codes, flat))

    scored = masked if variant.masked_only_loss else denoised[..., None].expand(B, T, N)
    tmask = torch.where((objective == 2)[:, None, None], identity_mask(T, dev), causal_mask(T, dev))
    nan = torch.full_like(u0, float("nan"))
    return Corruption(
        tokens=tokens.view(B, T, H, W), targets=x0, masked=masked.view(B, T, H, W), noised=noised.view(B, T, H, W),
        loss_mask=scored.reshape(B, T, H, W), temporal_mask=tmask, objective=objective, denoised=denoised,
        u0=torch.where(denoised, u0, nan), u1=torch.where(denoised, u1, nan),
    )


def training_loss(model: nn.Module, x0: torch.Tensor, T_ref_sensor: torch.Tensor, n_past: int,
                  variant: Variant = COPILOT4D, label_smoothing: float = 0.1,
                  generator: torch.Generator | None = None, objective: torch.Tensor | None = None,
                  extra=None) -> tuple[torch.Tensor, dict]:
    """Algorithm 1 line 8: cross entropy (label smoothing) of the clean tokens given the
    corrupted sequence, averaged over the scored tokens of the batch. Returns the loss and
    {"loss", "accuracy" (argmax on scored tokens), "masked_accuracy"} as floats, and apart for
    the masked future tokens that differ from the last past frame's token at their place
    ("changed_*") and those that do not ("unchanged_*"): cross entropy (``*_loss``) and
    argmax accuracy (``*_accuracy``), with the share of changed tokens among the future's
    ("changed_share"): a model that only copies scores well on the unchanged ones alone.
    Measuring them draws no random number and changes no gradient. ``objective``: as
    :func:`corrupt`'s (None: each sequence draws one from the mixture). ``extra(logits,
    targets, masked)``: a term added to the loss (the render stage's,
    :class:`~pcfbench.methods.copilot4d.render_stage.RenderTerm`), returning it and its own
    measurements; "loss" stays the cross entropy."""
    seen = {}
    loss, sums = _loss_and_sums(model, x0, T_ref_sensor, n_past, variant, label_smoothing, generator, objective,
                                keep=seen if extra is not None else None)
    stats = {"loss": float(loss.detach()), **objective_ratios(sums)}
    if extra is not None:
        term, more = extra(seen["logits"], seen["corruption"].targets, seen["corruption"].masked)
        loss = loss + term
        stats.update(more)
    return loss, stats


#: the upper edges of the bins of a frame's masked share (the last bin ends at 1) in which
#: ``changed_r<i>``/``changed_hits_r<i>`` count the changed tokens and the right ones: how the
#: model does on what changed when little of its frame is visible, as Algorithm 2's first steps see
#: it; ``first_*`` the same on the first future frame alone (whose context, under the "future"
#: objective, is the clean past: the later ones see the true tokens of the future frames before them)
MASK_RATE_EDGES = (0.5, 0.8, 0.95, 0.99)
#: what :func:`objective_sums` adds up over a batch: counts of tokens, hits (arg max right) and
#: summed cross entropies; ``changed``/``unchanged``: masked future tokens that differ / do not
#: differ from the last past frame's token at their place; then the mask-rate bins
OBJECTIVE_SUMS = ("scored", "hits", "masked", "masked_hits", "future", "future_changed",
                  "changed", "changed_hits", "changed_ce", "unchanged", "unchanged_hits", "unchanged_ce",
                  *(f"{k}_r{i}" for i in range(len(MASK_RATE_EDGES) + 1) for k in ("changed", "changed_hits")),
                  *(f"first_{k}_r{i}" for i in range(len(MASK_RATE_EDGES) + 1) for k in ("changed", "changed_hits")))


def objective_ratios(sums: dict) -> dict[str, float]:
    """:func:`training_loss`'s measurements (less the loss) from sums and counts (NaN where a
    denominator is 0)."""
    div = lambda a, b: a / b if b else float("nan")  # noqa: E731
    stats = {"accuracy": div(sums["hits"], sums["scored"]), "masked_accuracy": div(sums["masked_hits"], sums["masked"]),
             "changed_share": div(sums["future_changed"], sums["future"])}
    for name in ("changed", "unchanged"):
        stats[f"{name}_loss"] = div(sums[f"{name}_ce"], sums[name])
        stats[f"{name}_accuracy"] = div(sums[f"{name}_hits"], sums[name])
    return stats


@torch.no_grad()
def objective_sums(model: nn.Module, x0: torch.Tensor, T_ref_sensor: torch.Tensor, n_past: int,
                   variant: Variant = COPILOT4D, label_smoothing: float = 0.1,
                   generator: torch.Generator | None = None, objective: torch.Tensor | None = None) -> dict:
    """:func:`training_loss`'s measurements as sums and counts (:data:`OBJECTIVE_SUMS`, the
    mask-rate bins included), so that batches add up exactly: the training objective on windows
    the model did not learn from."""
    return _loss_and_sums(model, x0, T_ref_sensor, n_past, variant, label_smoothing, generator, objective,
                          bins=True)[1]


def _cross_entropies(logits: torch.Tensor, target: torch.Tensor, smoothing) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross entropy of ``logits`` (n, |V|) against ``target`` (n,) under label smoothing
    ``smoothing``: a float (PyTorch's, towards the uniform distribution), or a (|V|, |V|) tensor
    whose row v is the target distribution of true code v (:func:`neighbour_targets`). Returns
    the mean (differentiable: the loss) and each row's (without autograd: the measurements), both
    from one log-softmax, which is a tenth of a training step's time on the CPU. With a float
    ``smoothing`` they equal ``F.cross_entropy(..., label_smoothing=smoothing)`` with reduction
    "mean" and "none" bit for bit, gradient included: the same operations as ATen's
    ``cross_entropy_loss_label_smoothing`` (mean NLL of the log-softmax, (1 - s) of it plus s / |V|
    times the mean negated row sum)."""
    logp = logits.log_softmax(-1)
    if isinstance(smoothing, torch.Tensor):
        rows = -(smoothing[target] * logp).sum(-1)
        return rows.mean(), rows.detach()
    nll = F.nll_loss(logp, target)
    smooth = -logp.sum(-1)
    mean = (1 - smoothing) * nll + smooth.sum() / target.numel() * (smoothing / logits.shape[-1])
    with torch.no_grad():
        each = (1 - smoothing) * -logp.detach().gather(-1, target[:, None]).squeeze(-1) \
            + smooth.detach() * (smoothing / logits.shape[-1])
    return mean, each


def _scored_rows(logits: torch.Tensor, loss_mask: torch.Tensor) -> torch.Tensor:
    """``logits[loss_mask]`` ((n, |V|): the scored tokens' rows, in order) as a view of
    ``logits`` when they are one run of whole frames (every objective of the diffusion variant
    at batch 1: the future, or every frame), else by boolean indexing. The same rows either way;
    a view's backward adds no zero-filled copy of the whole logits (an eighth of a CPU step)."""
    B, T = loss_mask.shape[:2]
    frames = loss_mask.reshape(B * T, -1)
    whole = frames.all(-1)
    if logits.is_contiguous() and bool((whole == frames.any(-1)).all()):
        idx = whole.nonzero().flatten()
        if len(idx) and int(idx[-1] - idx[0]) + 1 == len(idx):
            flat = logits.view(B * T, -1, logits.shape[-1])
            return (flat if len(idx) == B * T else flat[int(idx[0]): int(idx[-1]) + 1]).view(-1, logits.shape[-1])
    return logits[loss_mask]


def neighbour_targets(codebook: torch.Tensor, k: int, share: float, label_smoothing: float) -> torch.Tensor:
    """(|V|, |V|) target distributions (not the paper's): true code v keeps 1 - ``share`` of its
    mass, its ``k`` nearest codes (Euclidean, in the codebook) share ``share`` equally, and
    ``label_smoothing`` of the whole is spread uniformly, as ``F.cross_entropy`` spreads it."""
    V = codebook.shape[0]
    if not 0 < k < V:
        raise ValueError(f"k={k} nearest codes: expected 1 to {V - 1} for a codebook of {V} codes")
    cb = codebook.detach().float()
    d = torch.cdist(cb, cb)
    d.fill_diagonal_(float("inf"))
    q = torch.eye(V, device=cb.device) * (1.0 - share)  # on the codebook's device: no copy per training step
    q.scatter_(1, d.topk(k, dim=1, largest=False).indices, share / k)
    return q * (1.0 - label_smoothing) + label_smoothing / V


def _loss_and_sums(model, x0, T_ref_sensor, n_past, variant, label_smoothing, generator, objective, bins=False,
                   keep: dict | None = None):
    c = corrupt(x0, n_past, model.mask_token, variant, generator, objective)
    logits = model(c.tokens, T_ref_sensor, c.temporal_mask)
    if keep is not None:  # the caller's extra term needs them
        keep.update(logits=logits, corruption=c)
    sel = c.loss_mask
    picked = _scored_rows(logits, sel).float()
    target = c.targets[sel]
    loss, ce = _cross_entropies(picked, target, label_smoothing)
    with torch.no_grad():
        hit = picked.argmax(-1) == target
        on_masked = c.masked[sel]
        changed = x0 != x0[:, n_past - 1: n_past]  # (B, T, H, W): differs from the last past frame
        future = torch.zeros_like(changed)
        future[:, n_past:] = True
        sums = {"scored": int(hit.numel()), "hits": int(hit.sum()), "masked": int(on_masked.sum()),
                "masked_hits": int(hit[on_masked].sum()), "future": int(future.sum()),
                "future_changed": int(changed[future].sum())}
        for name, which in (("changed", changed[sel]), ("unchanged", ~changed[sel])):
            on = on_masked & future[sel] & which
            sums[name], sums[f"{name}_hits"] = int(on.sum()), int(hit[on].sum())
            sums[f"{name}_ce"] = float(ce[on].double().sum())
        if not bins:  # a training step does not need them
            return loss, sums
        rate = c.masked.flatten(2).float().mean(-1)  # (B, T): each frame's masked share
        rate_bin = torch.bucketize(rate, torch.tensor(MASK_RATE_EDGES, device=rate.device), right=True)
        rate_bin = rate_bin[..., None, None].expand_as(changed)[sel]
        first = torch.zeros_like(changed)  # the first future frame: its context is the clean past alone
        first[:, n_past] = True
        on = on_masked & future[sel] & changed[sel]
        for i in range(len(MASK_RATE_EDGES) + 1):
            for prefix, where in (("", on & (rate_bin == i)), ("first_", on & (rate_bin == i) & first[sel])):
                sums[f"{prefix}changed_r{i}"] = int(where.sum())
                sums[f"{prefix}changed_hits_r{i}"] = int(hit[where].sum())
    return loss, sums


def make_optimizer(model: nn.Module, cfg: WorldModelConfig) -> torch.optim.Optimizer:
    """A.3 AdamW: lr, betas (0.9, 0.95), weight decay 1e-4 on Linear weight matrices only
    (biases, the tied embedding / un-embedding, positional encodings and LayerNorm excluded).
    The schedule (linear warm-up, cosine decay to 10 %) is :func:`lr_at`; gradient clipping
    at ``cfg.grad_clip`` is the training loop's."""
    from pcfbench.training import adamw

    return adamw(model, cfg.lr, cfg.betas, cfg.weight_decay)


def lr_at(cfg: WorldModelConfig, step: int) -> float:
    """Learning rate at ``step``: linear warm-up over ``cfg.warmup`` steps, then cosine decay
    over ``cfg.decay_steps`` to ``cfg.min_lr_ratio * cfg.lr`` (the tokenizer's schedule)."""
    from pcfbench.training import warmup_cosine

    return warmup_cosine(step, cfg.lr, cfg.warmup, cfg.decay_steps, cfg.min_lr_ratio)


# --------------------------------------------------------------------------- Algorithm 2
def guided_logits(model: nn.Module, tokens: torch.Tensor, T_ref_sensor: torch.Tensor, guidance: float,
                  frame_index: torch.Tensor | None = None, past_kv=None) -> torch.Tensor:
    """Logits (B, H, W, |V|) in float32 for the last frame of ``tokens`` (B, T, H, W), the
    earlier frames (and the ``past_kv`` frames, if given) being its context c, by equation 2:
    logits_c + w (logits_c - logits_u).

    w = 0 returns the conditional logits of a causal pass, exactly. Otherwise one pass with
    the last frame appended again (same pose and temporal position) under
    :func:`guidance_mask`, so the copy sees only itself and gives the unconditional logits.
    With ``past_kv`` (P frames cached by ``model(..., return_kv=True)`` under a causal mask),
    ``tokens``, ``T_ref_sensor`` and ``frame_index`` hold the frames after those P only.
    """
    B, T = tokens.shape[:2]
    dev = tokens.device
    P = 0 if past_kv is None else past_kv.frames
    if frame_index is None:
        frame_index = torch.arange(P, P + T, device=dev)
    kw = {} if past_kv is None else {"past_kv": past_kv}  # models without a cache need not take it
    if guidance == 0:
        return model(tokens, T_ref_sensor, causal_mask(P + T, dev)[P:], frame_index, **kw)[:, -1].float()
    out = model(torch.cat([tokens, tokens[:, -1:]], 1), torch.cat([T_ref_sensor, T_ref_sensor[:, -1:]], 1),
                guidance_mask(P + T, dev)[P:], torch.cat([frame_index, frame_index[-1:]]), **kw)
    cond, uncond = out[:, T - 1].float(), out[:, T].float()
    # cond + w (cond - uncond), in one buffer (the same floats: addition commutes exactly)
    return (cond - uncond).mul_(guidance).add_(cond)


def _gumbel(shape, generator, device) -> torch.Tensor:
    u = torch.rand(shape, generator=generator, device=device).clamp_(1e-20, 1.0 - 1e-7)
    return -torch.log(-torch.log(u))


@torch.no_grad()
def sample_frame(model: nn.Module, context: torch.Tensor, T_ref_sensor: torch.Tensor, *,
                 steps: int = DEFAULT_STEPS, guidance: float = DEFAULT_GUIDANCE, top_k: int = DEFAULT_TOP_K,
                 revise: bool = True, generator: torch.Generator | None = None,
                 cache: bool = True, trace: list | None = None, first_position: int = 0,
                 context_kv=None, metric: torch.Tensor | None = None, copy: torch.Tensor | None = None,
                 change_confidence: float = 0.0, final_logits: list | None = None) -> torch.Tensor:
    """Algorithm 2: decode the frame after ``context`` (B, Tc, H, W) clean codes, given the
    poses ``T_ref_sensor`` (B, Tc + 1, 4, 4) of the context frames and of the new frame.

    From all-mask x_K, for k = K-1 .. 0: x~0 is sampled among the top-k guided logits;
    l_k = log p(x~0) (the guided distribution over all codes) + Gumbel * k / K, +inf where
    x_{k+1} is already decoded; x_k takes x~0 on the top ceil(gamma(k/K) N) of l_k and is
    masked elsewhere. Decoded tokens are therefore never re-masked; with ``revise`` they take
    the new x~0 (re-sampled), without it (MaskGIT) they keep their value. Returns (B, H, W)
    codes; ``trace``, if a list, receives x_k (B, H, W) after each step.

    The context frames take temporal positions ``first_position`` .. ``first_position`` + Tc - 1
    and the new frame the next one (a context shorter than training's keeps the new frame at
    the position it had in training). With ``cache`` they run through the
    network once and each step passes only the new frame (and its unconditional copy),
    attending to their cached temporal keys and values: the same logits, ~(Tc + 2) / 2 times
    less work per step. ``context_kv``: that pass already made (a :class:`~.world.PastKV` of
    the Tc context frames at these positions, as :func:`forecast_sequence` keeps it from frame
    to frame); the steps write their frames' keys and values into one buffer per temporal
    block (:meth:`~.world.PastKV.with_room`) instead of concatenating the context's again.

    ``metric`` (|V|, |V|), a distance between codes (not the paper's): x~0 is instead, at every
    token, the code of least expected distance under the guided distribution, argmin_c sum_v
    p(v) metric[v, c] (minimum Bayes risk; no sampling, ``top_k`` unused), and l_k its log p.
    With the codebook's own distances a code near the true one renders nearly as the true one
    does (docs/copilot4d.md, "Near misses"), so the choice weighs a spread of similar codes
    against a single likely one by what they render.

    ``change_confidence`` c > 0 with ``copy`` (B, H, W) codes (not the paper's): x~0 keeps a code
    other than ``copy``'s only where its guided probability is more than c, and takes ``copy``'s
    code elsewhere (l_k then that code's log p): the frame changes only where the model is sure
    of the change. c = 1 returns ``copy`` whatever the model says.

    ``final_logits``, if a list, receives the guided logits (B, H, W, |V|) float32 of the last
    step: every token's distribution given the frame as decoded before it.
    """
    if steps < 1:
        raise ValueError(f"steps={steps}: Algorithm 2 needs at least one step")
    B, Tc, H, W = context.shape
    if change_confidence > 0 and (copy is None or copy.shape != (B, H, W)):
        raise ValueError(f"change_confidence={change_confidence} needs the codes to keep, copy=(B, H, W) = "
                         f"({B}, {H}, {W}); got {None if copy is None else tuple(copy.shape)}")
    if T_ref_sensor.shape[:2] != (B, Tc + 1):
        raise ValueError(f"T_ref_sensor has shape {tuple(T_ref_sensor.shape)}; expected ({B}, {Tc + 1}, 4, 4): "
                         "the context frames' poses and the new frame's")
    dev, N, mask_id = context.device, H * W, model.mask_token
    x = torch.full((B, N), mask_id, dtype=torch.long, device=dev)
    positions = torch.arange(first_position, first_position + Tc + 1, device=dev)
    past_kv = None
    if cache:
        if context_kv is None:
            _, context_kv = model(context, T_ref_sensor[:, :Tc], causal_mask(Tc, dev), positions[:Tc], return_kv=True)
        elif context_kv.frames != Tc or context_kv.batch != B:
            raise ValueError(f"context_kv holds {context_kv.frames} frames of {context_kv.batch} sequences; "
                             f"the context is {Tc} frames of {B}")
        past_kv = context_kv.with_room(1 if guidance == 0 else 2) if hasattr(context_kv, "with_room") else context_kv
    for k in range(steps - 1, -1, -1):
        if cache:
            logits = guided_logits(model, x.view(B, 1, H, W), T_ref_sensor[:, Tc:], guidance, positions[Tc:],
                                   past_kv=past_kv)
        else:
            seq = torch.cat([context, x.view(B, 1, H, W)], 1)
            logits = guided_logits(model, seq, T_ref_sensor, guidance, positions)
        if k == 0 and final_logits is not None:
            final_logits.append(logits.reshape(B, H, W, -1))
        logits = logits.reshape(B, N, -1)
        if metric is None:
            top_val, top_idx = logits.topk(min(top_k, logits.shape[-1]), dim=-1)
            pick = (top_val + _gumbel(top_val.shape, generator, dev)).argmax(-1, keepdim=True)
            x0 = top_idx.gather(-1, pick).squeeze(-1)
        else:
            x0 = (logits.softmax(-1) @ metric.to(logits.dtype)).argmin(-1)
        log_p = logits.log_softmax(-1)
        logp = log_p.gather(-1, x0[..., None]).squeeze(-1)
        if change_confidence > 0:
            keep_copy = copy.reshape(B, N)
            x0 = torch.where((x0 == keep_copy) | (logp.exp() > change_confidence), x0, keep_copy)
            logp = log_p.gather(-1, x0[..., None]).squeeze(-1)
        conf = logp + _gumbel(logp.shape, generator, dev) * (k / steps)
        decoded = x != mask_id
        conf = conf.masked_fill(decoded, float("inf"))
        keep = torch.zeros_like(decoded)
        keep.scatter_(1, conf.topk(decoded_count(k, steps, N), dim=-1).indices, True)
        new = torch.where(keep, x0, mask_id)
        x = new if revise else torch.where(decoded, x, new)
        if trace is not None:
            trace.append(x.view(B, H, W).clone())
    return x.view(B, H, W)


@torch.no_grad()
def forecast_sequence(model: nn.Module, past: torch.Tensor, T_ref_sensor: torch.Tensor, n_future: int, *,
                      n_frames: int, n_past: int, steps: int = DEFAULT_STEPS, guidance: float = DEFAULT_GUIDANCE,
                      top_k: int = DEFAULT_TOP_K, revise: bool = True, generator: torch.Generator | None = None,
                      cache: bool = True, reuse_context: bool = True,
                      context=contextlib.nullcontext, metric: torch.Tensor | None = None,
                      change_confidence: float = 0.0, final_logits: list | None = None) -> list[torch.Tensor]:
    """Algorithm 2 autoregressively, as the Copilot4D methods forecast: ``n_future`` frames
    (B, H, W) after ``past`` (B, P, H, W), oldest first, with poses ``T_ref_sensor``
    (B, P + n_future, 4, 4).

    The context of each new frame is every frame so far at the temporal positions of training
    (t=0 at ``n_past`` - 1 of a ``n_frames`` sequence), sliding once past and future outgrow the
    trained sequence (the newest ``n_frames`` - 1 frames from position 0).

    With ``reuse_context`` the context's temporal keys and values are kept from one frame to
    the next while its frames keep their positions: a causal frame's keys and values do not
    depend on later frames, so only the frame just decoded passes through the network (once)
    to join them, instead of the whole context again. ``False`` recomputes the context for
    every frame (the reference); ``cache=False`` computes every step over the whole sequence
    (:func:`sample_frame`). ``context``: a context manager each network pass runs in (autocast).
    ``metric``: :func:`sample_frame`'s; ``change_confidence``: its, the codes to keep those of
    the last past frame (t=0); ``final_logits``: its, one entry per future frame."""
    P = past.shape[1]
    if T_ref_sensor.shape[1] != P + n_future:
        raise ValueError(f"T_ref_sensor holds {T_ref_sensor.shape[1]} poses; expected {P} past + {n_future} future")
    dev = past.device
    reuse_context = reuse_context and cache
    seq, out = past, []
    kv, kv_at = None, None  # the cached context's keys and values; (its first frame in seq, its first position)
    for f in range(n_future):
        n_ctx = min(P + f, n_frames - 1)
        first = max(0, n_past - P) if P + f < n_frames else 0
        first = min(first, n_frames - 1 - n_ctx)
        start = P + f - n_ctx  # the context: seq[:, start:], at positions first .. first + n_ctx - 1
        pose = T_ref_sensor[:, start: P + f + 1]
        positions = torch.arange(first, first + n_ctx + 1, device=dev)
        with context():
            if reuse_context and kv is not None and kv_at == (start, first) and kv.frames == n_ctx - 1:
                # the same frames at the same positions, and the frame just decoded after them
                _, kv = model(seq[:, -1:], pose[:, n_ctx - 1: n_ctx], causal_mask(n_ctx, dev)[n_ctx - 1:],
                              positions[n_ctx - 1: n_ctx], past_kv=kv, return_kv=True)
            elif reuse_context:
                _, kv = model(seq[:, start:], pose[:, :n_ctx], causal_mask(n_ctx, dev), positions[:n_ctx],
                              return_kv=True)
            kv_at = (start, first)
            nxt = sample_frame(model, seq[:, start:], pose, steps=steps, guidance=guidance, top_k=top_k,
                               revise=revise, generator=generator, first_position=first, cache=cache,
                               context_kv=kv if reuse_context else None, metric=metric, copy=past[:, -1],
                               change_confidence=change_confidence, final_logits=final_logits)
        seq = torch.cat([seq, nxt[:, None]], 1)
        out.append(nxt)
    return out


@torch.no_grad()
def forecast_one_pass(model: nn.Module, past: torch.Tensor, T_ref_sensor: torch.Tensor, n_future: int, *,
                      n_frames: int, n_past: int, guidance: float = DEFAULT_GUIDANCE,
                      context=contextlib.nullcontext, final_logits: list | None = None) -> list[torch.Tensor]:
    """Every future frame at once (not the paper's sampler, which decodes them one at a time):
    ``past`` (B, P, H, W) followed by ``n_future`` frames of mask tokens, with poses
    ``T_ref_sensor`` (B, P + n_future, 4, 4), in one causal network pass at the temporal positions
    of training (t=0 at ``n_past`` - 1), each future token its guided arg max. This is the input
    Algorithm 1's future-prediction objective trains on, at a full mask. Guidance (equation 2)
    takes the unconditional logits from a second pass in which every frame sees only itself, as
    the third objective trains the model. ``final_logits``, if a list, receives the guided logits
    (B, H, W, |V|) float32 of each future frame. Returns ``n_future`` (B, H, W) code maps."""
    B, P = past.shape[:2]
    T = P + n_future
    first = max(0, n_past - P)
    if first + T > n_frames:
        raise ValueError(f"{P} past and {n_future} future frames from position {first} outgrow the {n_frames} frames "
                         "the network was trained on: one pass cannot slide")
    if T_ref_sensor.shape[1] != T:
        raise ValueError(f"T_ref_sensor holds {T_ref_sensor.shape[1]} poses; expected {P} past + {n_future} future")
    dev = past.device
    masked = torch.full((B, n_future, *past.shape[2:]), model.mask_token, dtype=past.dtype, device=dev)
    x = torch.cat([past, masked], 1)
    positions = torch.arange(first, first + T, device=dev)
    with context():
        logits = model(x, T_ref_sensor, causal_mask(T, dev), positions)[:, P:].float()
        if guidance:
            uncond = model(x, T_ref_sensor, identity_mask(T, dev), positions)[:, P:].float()
            logits = (logits - uncond).mul_(guidance).add_(logits)
    if final_logits is not None:
        final_logits.extend(logits[:, f] for f in range(n_future))
    return [logits[:, f].argmax(-1) for f in range(n_future)]


@torch.no_grad()
def forecast_tokens(model: nn.Module, past: torch.Tensor, T_ref_sensor: torch.Tensor, n_future: int, *,
                    steps: int = DEFAULT_STEPS, guidance: float = DEFAULT_GUIDANCE, top_k: int = DEFAULT_TOP_K,
                    revise: bool = True, generator: torch.Generator | None = None, cache: bool = True,
                    metric: torch.Tensor | None = None, change_confidence: float = 0.0) -> torch.Tensor:
    """Autoregressive forecast (section 4.3): future frames one at a time with
    :func:`sample_frame`, each decoded frame joining the context of the next.

    past: (B, P, H, W) codes, oldest first; T_ref_sensor: (B, P + n_future, 4, 4), past then
    future poses in the reference frame. Returns (B, n_future, H, W) codes.
    """
    P = past.shape[1]
    out = forecast_sequence(model, past, T_ref_sensor, n_future, n_frames=P + n_future, n_past=P, steps=steps,
                            guidance=guidance, top_k=top_k, revise=revise, generator=generator, cache=cache,
                            metric=metric, change_confidence=change_confidence)
    return torch.stack(out, 1)
