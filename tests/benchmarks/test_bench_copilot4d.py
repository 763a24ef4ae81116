"""Speed of Copilot4D inference rendering: one decoded token map of the ``tiny`` tokenizer
rendered along one sweep's rays by the numba marcher (``render_codes``'s CPU path) and by the
differentiable torch functions that training uses (``torch_path=True``), on the same input; and
of one world-model training step, against the way a step computed its loss until 2026-12-03.

With ``PCFBENCH_BENCH_FULL=1`` the rays are a 64-beam, 1800-step toy LiDAR (115,200 rays);
otherwise 16 x 360 keeps the default (disabled, run-once) pass quick. Run with

    PCFBENCH_BENCH_FULL=1 .venv/bin/python -m pytest tests/benchmarks/test_bench_copilot4d.py --benchmark-enable

The tokenizer is the ``tiny`` configuration with its initial weights and a coarse bias that
predicts about a tenth of the coarse voxels occupied (a trained checkpoint is not part of a
fresh clone); extra_info reports ``rays_per_s``.
"""

from __future__ import annotations

import itertools
import math
import os

import numpy as np
import pytest
import torch

from pcfbench.methods.copilot4d.config import TINY
from pcfbench.methods.copilot4d.evaluate import decode, render_codes, tokenize_sweep
from pcfbench.methods.copilot4d.model import Tokenizer

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"


@pytest.fixture(scope="module")
def scene():
    from pcfbench.testing import toy_world_sweeps

    kw = dict(beams=64, azimuths=1800) if FULL else dict(beams=16, azimuths=360)
    pts, _, _ = toy_world_sweeps(1, **kw)
    torch.manual_seed(0)
    model = Tokenizer(TINY).eval()
    with torch.no_grad():
        model.decoder.coarse_linear.bias.fill_(-2.0)
    codes = tokenize_sweep(model, pts[0])
    p = pts[0][np.linalg.norm(pts[0], axis=1) > 1.0]
    dirs = (p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
    return model, codes, decode(model, codes), dirs


@pytest.mark.parametrize("path", ["numba", "torch"])
def test_render_codes(benchmark, scene, path):
    model, codes, decoded, dirs = scene
    torch.set_num_threads(1)
    kw = dict(origin=np.array([2.0, -1.0, 0.0]), decoded=decoded, threshold=0.02, noise=False, readout="median",
              torch_path=path == "torch")
    render_codes(model, codes, dirs[:100], **kw)  # compile outside the timing
    depths = benchmark(render_codes, model, codes, dirs, **kw)
    assert depths.shape == (len(dirs),) and np.all(np.isfinite(depths))
    if benchmark.stats is not None:
        benchmark.extra_info["rays"] = len(dirs)
        benchmark.extra_info["rays_per_s"] = len(dirs) / benchmark.stats.stats.median


# --------------------------------------------------------------------------- a world-model training step
def _indexed_loss(model, x0, poses, n_past, variant, generator, objective):
    """The baseline: how a training step computed its loss until 2026-12-03 (boolean-indexed
    scored logits, then PyTorch's cross entropy, and again per token for the measurements)."""
    import torch.nn.functional as F

    from pcfbench.methods.copilot4d import diffusion as D

    c = D.corrupt(x0, n_past, model.mask_token, variant, generator, objective)
    logits = model(c.tokens, poses, c.temporal_mask)
    picked = logits[c.loss_mask].float()
    target = c.targets[c.loss_mask]
    loss = F.cross_entropy(picked, target, label_smoothing=0.1)
    with torch.no_grad():
        F.cross_entropy(picked, target, label_smoothing=0.1, reduction="none")
        picked.argmax(-1)
    return loss


@pytest.mark.parametrize("path", ["indexed", "current"])
def test_world_training_step(benchmark, path):
    """One optimiser step of the world model on one window (each objective of the mixture in
    turn), the loss as training computes it against the baseline's. Full: the shipped
    `tiny-window` network (10 frames of 64 x 64 tokens, 512 codes), both threads; otherwise a
    32 x 32-token version of it. extra_info: steps_per_s."""
    import dataclasses

    from pcfbench.methods.copilot4d import diffusion as D
    from pcfbench.methods.copilot4d.world import WorldModel
    from pcfbench.methods.copilot4d.world_config import get_world_config

    cfg = get_world_config("tiny-window")
    if not FULL:
        cfg = dataclasses.replace(cfg, token_grid=32, codebook_size=64)
    torch.set_num_threads(2 if FULL else 1)
    torch.manual_seed(0)
    model = WorldModel(cfg)
    opt = D.make_optimizer(model, cfg)
    gen = torch.Generator().manual_seed(0)
    x0 = torch.randint(0, cfg.codebook_size, (1, cfg.n_frames, cfg.token_grid, cfg.token_grid), generator=gen)
    poses = torch.eye(4).expand(1, cfg.n_frames, 4, 4).clone()
    turn = itertools.count()

    def step():
        obj = torch.tensor([next(turn) % 3])
        if path == "current":
            loss, _ = D.training_loss(model, x0, poses, cfg.n_past, D.COPILOT4D, 0.1, gen, obj)
        else:
            loss = _indexed_loss(model, x0, poses, cfg.n_past, D.COPILOT4D, gen, obj)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return float(loss.detach())

    step()  # the first step allocates the optimiser's state
    loss = benchmark.pedantic(step, rounds=9 if FULL else 3, iterations=1)
    assert math.isfinite(loss)
    if benchmark.stats is not None:
        benchmark.extra_info["steps_per_s"] = 1.0 / benchmark.stats.stats.median
