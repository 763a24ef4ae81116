"""Training the world model through its rendering (**not the paper's**; docs/copilot4d.md,
"Near misses"; measured harmful at weight 1, so off by default): with ``render_weight`` > 0,
each training step adds to Algorithm 1's cross entropy that weight times the L1 depth error
(m) of one future frame of the window,
rendered through the frozen tokenizer's decoder along the true future sweep's rays from the
future sensor's origin, as ``copilot4d`` renders its forecast.

The frame rendered is the corrupted sequence's: its visible tokens are the true codes, its
masked ones the world model's arg max codes, with the straight-through gradient of the
softmax (the rendered map is the one a decoding would keep; the gradient reaches every code's
probability through the codebook). The cross entropy asks for the exact code of a token, and
most of a future map's changed codes appear nowhere in its context (measured: 70-85 % of them
are no context frame's code at their place, docs/copilot4d.md); the depth term tells the model
which wrong codes cost depth and which do not, as the tokenizer itself was trained.

Each step also renders the same frame with the last past frame's codes on the masked tokens
(no gradient): ``render_l1_copy``, the copy's error on the same rays, so the curve says whether
the model's masked tokens render better than copying them.

The rays: :class:`pcfbench.methods.bevworld.render_loss.WindowRays`, BEVWorld's render stage's
(the same windows, ``build_windows``'s).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

#: rays rendered per step (one future frame of the window)
RENDER_RAYS = 512
#: returns kept per future sweep to draw the rays from (drawn once, seeded)
RENDER_PER_SWEEP = 4096


def frame_embeddings(codebook: torch.Tensor, logits: torch.Tensor, targets: torch.Tensor,
                     masked: torch.Tensor) -> torch.Tensor:
    """(H, W, D) code embeddings of one frame: the true code's where ``masked`` is False, the
    arg max of ``logits`` (H, W, |V|) where it is True, with the gradient of the softmax
    (straight through: the forward value is the arg max code's embedding exactly)."""
    probs = logits.float().softmax(-1)
    hard = F.one_hot(probs.argmax(-1), probs.shape[-1]).to(probs.dtype)
    pick = hard + probs - probs.detach()
    predicted = pick @ codebook.float()
    true = F.embedding(targets, codebook).float()
    return torch.where(masked[..., None], predicted, true)


def render_l1(tokenizer, embeddings: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
              depths: torch.Tensor) -> torch.Tensor:
    """Mean L1 (m) between ``depths`` and the expected depths (equation 4) of the rays
    (``origins``, unit ``dirs``) through the frozen ``tokenizer``'s decoding of the (H, W, D)
    ``embeddings``: spatial skipping on its coarse voxels (threshold 0.5, no noise), the
    tokenizer's samples per ray at their strata's centres plus its uniform ones."""
    from pcfbench.methods.copilot4d.render import logistic_noise_mask, render_depth, sample_along_rays

    cfg = tokenizer.cfg
    nfg, coarse = tokenizer.decoder(embeddings[None].to(next(tokenizer.parameters()).dtype))
    batch = torch.zeros(len(dirs), dtype=torch.long, device=dirs.device)
    with torch.no_grad():
        mask = logistic_noise_mask(cfg, coarse.float(), noise=False)
        h = sample_along_rays(cfg, origins, dirs, batch, mask, cfg.samples_per_ray, jitter=False,
                              extra_uniform=cfg.train_uniform_samples)
    depth, _ = render_depth(tokenizer.decoder, nfg, cfg, origins, dirs, batch, h)
    return (depth - depths).abs().mean()


class RenderTerm:
    """The depth term of one training step: ``draw`` picks the future frame and its rays (from
    the loop's numpy stream, so a resumed run draws the same), ``__call__`` renders it."""

    def __init__(self, tokenizer, rays, n_past: int, n_future: int, own: bool, weight: float) -> None:
        self.tokenizer = tokenizer.eval().requires_grad_(False)
        self.rays, self.n_past, self.n_future, self.own, self.weight = rays, n_past, n_future, own, weight

    def draw(self, window: int, rng: np.random.Generator):
        """(frame, origins, dirs, depths) of a future frame of ``window``, or None when that
        sweep has no return inside the grid."""
        frame = self.n_past + int(rng.integers(0, self.n_future))
        got = self.rays.rays(self.tokenizer.cfg, window, frame, self.own, RENDER_RAYS, rng)
        return None if got is None else (frame, *got)

    def __call__(self, logits: torch.Tensor, targets: torch.Tensor, masked: torch.Tensor, drawn: list):
        """(weight x the mean rendered L1 with its graph, {"render_l1", "render_l1_copy"}) over the
        batch's sequences, ``drawn[b]`` sequence b's :meth:`draw`; sequences with nothing drawn
        or no masked token in the drawn frame add nothing ((0, NaNs) when none is left)."""
        terms, copies = [], []
        cb = self.tokenizer.vq.codebook
        for b, got in enumerate(drawn):
            if got is None or not bool(masked[b, got[0]].any()):
                continue
            frame, o, d, depth = got
            on = masked[b, frame]
            o, d, depth = (torch.from_numpy(np.ascontiguousarray(a)).to(logits.device) for a in (o, d, depth))
            terms.append(render_l1(self.tokenizer, frame_embeddings(cb, logits[b, frame], targets[b, frame], on),
                                   o, d, depth))
            with torch.no_grad():
                copy = torch.where(on, targets[b, self.n_past - 1], targets[b, frame])
                copies.append(float(render_l1(self.tokenizer, F.embedding(copy, cb).float(), o, d, depth)))
        if not terms:
            return logits.new_zeros(()), {"render_l1": float("nan"), "render_l1_copy": float("nan")}
        l1 = torch.stack(terms).mean()
        return self.weight * l1, {"render_l1": float(l1.detach()), "render_l1_copy": float(np.mean(copies))}
